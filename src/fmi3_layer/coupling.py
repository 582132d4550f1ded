"""Sizes two of the project's FMUs must agree on to connect as they are, written once.

Each FMU package links this file as ``_coupling.py`` (an FMU carries only its own package), so
the Catheter's centerline and the Contact's tool points, and the Contact's compliance patch and
the Tissue's, start equal. A scene that changes one sets the other (``validate`` names both).
"""

#: Catheter centerline points (its segments + 1): the tool points the Contact renders by default.
TOOL_POINTS = 31
#: The most surface nodes the Contact names for the wall's compliance: the patch the Tissue solves.
PATCH_NODES = 16

"""The package's exceptions: one base class, :class:`TissueError` (a ``ValueError``).

Every error the tissue package raises for bad input or a failed step is a TissueError, so a
caller (the FMU, a study) catches one class; the subclasses say where the problem was found.
Each message names the problem and the fix.
"""

from __future__ import annotations

__all__ = ["TissueError", "StabilityError", "MeshError", "MaterialError", "ForceFieldError"]


class TissueError(ValueError):
    """Invalid tissue input or a failed tissue step; the message names the problem and the fix."""


class StabilityError(TissueError):
    """The explicit step is larger than its critical time step."""


class MeshError(TissueError):
    """Invalid mesh input; the message names the problem, the offending ids and the fix."""


class MaterialError(TissueError):
    """Invalid material parameter; the message names the parameter, the value and the fix."""


class ForceFieldError(TissueError):
    """Invalid force-field input (shape, law, mask); the message names the problem and the fix."""

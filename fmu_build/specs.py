"""The table of the project's FMUs: the one place that says which FMUs there are."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .paths import SRC


@dataclass(frozen=True)
class FmuSpec:
    """One FMU: its model identifier, the package it carries and the declaration in that package."""

    model_identifier: str
    package: str
    #: ``module:attribute`` of the FmuDeclaration inside the package
    declaration: str = "fmu:DECLARATION"
    #: folder that holds the package (default: ``src/``); test FMUs live elsewhere
    source_root: Path = SRC
    #: modules beyond the project's FMU packages whose imports the FMU's Python runtime must carry
    #: (the scene FMU's orchestrator); its runtime is then one of its own
    runtime_imports: tuple[str, ...] = ()


FMU_SPECS: dict[str, FmuSpec] = {
    "Tissue": FmuSpec("Tissue", "tissue_fmu"),
    "Contact": FmuSpec("Contact", "haptic_fmu"),
    "Catheter": FmuSpec("Catheter", "catheter_fmu"),
}


def available_fmus() -> list[str]:
    """FMUs whose package has an FMU declaration in this checkout."""
    return [name for name, spec in FMU_SPECS.items() if (SRC / spec.package / "fmu.py").exists()]

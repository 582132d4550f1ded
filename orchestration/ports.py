"""What an FMU offers: its ports (variables) with causality, type, size and unit.

Read from ``modelDescription.xml`` (through FMPy) without loading the FMU's binary, so a scene can
be checked before anything runs. Array sizes that depend on structural parameters are resolved
with the values the scene sets (or the start values).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

#: Causalities a connection may read from and write to.
READABLE = ("output", "calculatedParameter")
WRITABLE = ("input", "parameter", "structuralParameter")
#: FMI types the master moves through connections (as float64 arrays; integers and booleans exactly).
NUMERIC_TYPES = ("Float64", "Float32", "Int32", "UInt32", "Int64", "UInt64", "Int16", "UInt16", "Int8", "UInt8",
                 "Boolean")


@dataclass(frozen=True)
class PortInfo:
    """One variable of a component: ``size`` values (1 for scalars), ``shape`` as declared."""

    name: str
    causality: str
    type: str
    variability: str = "continuous"
    unit: str | None = None
    shape: tuple[int, ...] = ()
    value_reference: int = -1
    start: object = None
    description: str = ""

    @property
    def size(self) -> int:
        return int(math.prod(self.shape)) if self.shape else 1

    @property
    def is_array(self) -> bool:
        return bool(self.shape)

    def describe(self) -> str:
        dims = "x".join(str(d) for d in self.shape) if self.shape else "scalar"
        unit = f" [{self.unit}]" if self.unit else ""
        return f"{self.causality} {self.type} {dims}{unit}"


@dataclass
class FmuDescription:
    """The parts of a model description the master needs."""

    path: Path
    model_identifier: str
    instantiation_token: str
    default_step: float | None
    ports: dict[str, PortInfo] = field(default_factory=dict)
    model_description: object = None


def _start_value(variable):
    start = variable.start
    if isinstance(start, str) and variable.type != "String":
        parts = start.split()
        if variable.type == "Boolean":
            values = [p.lower() in ("true", "1") for p in parts]
        elif variable.type.startswith("Float"):
            values = [float(p) for p in parts]
        else:
            values = [int(p) for p in parts]
        return values[0] if len(values) == 1 else values
    return start


def read_fmu(path: Path | str, parameters: dict | None = None) -> FmuDescription:
    """Describe the FMU at ``path``; structural parameters in ``parameters`` override start values.

    Raises ``FileNotFoundError`` or ``ValueError`` with a readable message when the file is not
    an FMI 3.0 Co-Simulation FMU.
    """
    from fmpy import read_model_description

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist")
    try:
        md = read_model_description(str(path))
    except Exception as exc:  # fmpy raises many kinds on a bad archive
        raise ValueError(f"{path} is not a readable FMU: {exc}") from None
    if not md.fmiVersion.startswith("3") or md.coSimulation is None:
        raise ValueError(f"{path} is not an FMI 3.0 Co-Simulation FMU (fmiVersion {md.fmiVersion})")
    parameters = parameters or {}
    by_reference = {v.valueReference: v for v in md.modelVariables}

    def structural_value(variable) -> int:
        if variable.name in parameters:
            return int(parameters[variable.name])
        return int(_start_value(variable))

    ports: dict[str, PortInfo] = {}
    for v in md.modelVariables:
        shape: tuple[int, ...] = ()
        if v.dimensions:
            dims = []
            for d in v.dimensions:
                if d.start is not None:
                    dims.append(int(d.start))
                else:
                    dims.append(structural_value(by_reference[d.valueReference]))
            shape = tuple(dims)
        ports[v.name] = PortInfo(
            name=v.name, causality=v.causality, type=v.type, variability=v.variability,
            unit=v.unit or None,
            shape=shape, value_reference=v.valueReference, start=_start_value(v),
            description=v.description or "",
        )
    step = md.defaultExperiment.stepSize if md.defaultExperiment else None
    return FmuDescription(path=path, model_identifier=md.coSimulation.modelIdentifier,
                          instantiation_token=md.guid, default_step=float(step) if step else None,
                          ports=ports, model_description=md)

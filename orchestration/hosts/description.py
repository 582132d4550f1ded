"""What an FMU offers: its ports (variables) with causality, type, size and unit, and its capabilities.

Read from ``modelDescription.xml`` (through FMPy) without loading the FMU's binary, so a scene can
be checked before anything runs. Array sizes that depend on structural parameters are resolved
with the values the scene sets (or the start values). A variable without a unit of its own has
the unit of its declared type (``TypeDefinitions``).

Which connections are exact (:func:`conversion_problem`): the master moves values as float64, so
a connection is allowed where every value of the producer's type is a value of the consumer's
type: the same type; Float32 -> Float64; an integer type into a wider one or into a float type
that holds all its values (Int32 -> Float64, Int8 -> Float32; not Int64 -> Float64); an
enumeration into the same enumeration or into Int64 (FMI 3.0 enumerations are Int64 values), an
integer type into an enumeration (the FMU checks the value is an item). Boolean connects only to
Boolean. String, Binary and Clock variables are not moved through connections.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

#: Causalities a connection may read from and write to.
READABLE = ("output", "calculatedParameter")
WRITABLE = ("input", "parameter", "structuralParameter")
#: FMI types the master moves through connections and records (as float64; integers, Booleans and
#: enumeration values exactly).
NUMERIC_TYPES = ("Float64", "Float32", "Int32", "UInt32", "Int64", "UInt64", "Int16", "UInt16", "Int8", "UInt8",
                 "Boolean", "Enumeration")
#: Value ranges of the integer types (enumerations are Int64 values).
INTEGER_RANGES = {
    "Int8": (-2**7, 2**7 - 1), "UInt8": (0, 2**8 - 1), "Int16": (-2**15, 2**15 - 1), "UInt16": (0, 2**16 - 1),
    "Int32": (-2**31, 2**31 - 1), "UInt32": (0, 2**32 - 1), "Int64": (-2**63, 2**63 - 1), "UInt64": (0, 2**64 - 1),
    "Enumeration": (-2**63, 2**63 - 1),
}
#: The most values one port may hold (an array sized by structural parameters or a block's options).
#: The AAA wall has 2688 surface nodes (8064 coordinates); a port of more than a million values is a
#: typo and would exhaust memory when the FMU or block allocates it.
MAX_PORT_VALUES = 1_000_000
#: Largest magnitude below which every integer is exact in each float type.
_FLOAT_EXACT = {"Float32": 2**24, "Float64": 2**53}


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
    declared_type: str | None = None            # the TypeDefinitions entry it is declared with
    items: tuple[tuple[str, int], ...] = ()     # an Enumeration's items (name, value)
    minimum: float | None = None                # the declared min and max (numbers only), None if not declared
    maximum: float | None = None

    @property
    def size(self) -> int:
        return int(math.prod(self.shape)) if self.shape else 1

    @property
    def is_array(self) -> bool:
        return bool(self.shape)

    def describe(self) -> str:
        dims = "x".join(str(d) for d in self.shape) if self.shape else "scalar"
        unit = f" [{self.unit}]" if self.unit else ""
        kind = f"{self.type} {self.declared_type}" if self.type == "Enumeration" and self.declared_type else self.type
        return f"{self.causality} {kind} {dims}{unit}"

    def item_value(self, name: str) -> int | None:
        """The value of the Enumeration item ``name`` (None if it has no such item)."""
        return next((value for item, value in self.items if item == name), None)


def conversion_problem(source: PortInfo, target: PortInfo) -> str | None:
    """Why values of ``source`` cannot be moved exactly into ``target`` (None: they can)."""
    a, b = source.type, target.type
    for port in (source, target):
        if port.type not in NUMERIC_TYPES:
            return (f"{port.type} variables are not moved through connections (only numbers, Booleans and "
                    "enumerations are); set a String or Binary value as a parameter of the scene")
    if a == "Enumeration" or b == "Enumeration":
        if a == b:
            if set(source.items) != set(target.items):
                return (f"the enumerations differ ({source.declared_type} -> {target.declared_type}); "
                        "an enumeration connects only to the same enumeration or to an integer")
            return None
        other = b if a == "Enumeration" else a
        if other not in INTEGER_RANGES:
            return f"an enumeration connects only to the same enumeration or to an integer, not {other}"
        if a == "Enumeration":  # into an integer: every item value must fit
            lo, hi = INTEGER_RANGES[b]
            values = [v for _, v in source.items] or [INTEGER_RANGES["Int64"][0], INTEGER_RANGES["Int64"][1]]
            if not all(lo <= v <= hi for v in values):
                return f"{b} cannot hold every value of the enumeration {source.declared_type}; connect it to an Int64"
            return None
        if a == "UInt64":
            return "UInt64 values beyond 2**63 are not enumeration (Int64) values"
        return None
    if a == b:
        return None
    if a == "Boolean" or b == "Boolean":
        return "a Boolean connects only to a Boolean"
    if a.startswith("Float"):
        if a == "Float32" and b == "Float64":
            return None
        return f"{a} -> {b} is not exact (it would round{' or truncate' if not b.startswith('Float') else ''})"
    lo, hi = INTEGER_RANGES[a]
    if b.startswith("Float"):
        if max(-lo, hi) <= _FLOAT_EXACT[b]:
            return None
        return f"{a} -> {b} is not exact ({b} holds integers exactly only up to 2**{_FLOAT_EXACT[b].bit_length() - 1})"
    tlo, thi = INTEGER_RANGES[b]
    if tlo <= lo and hi <= thi:
        return None
    return f"{a} -> {b} is not exact ({b} cannot hold every {a} value)"


@dataclass
class FmuDescription:
    """The parts of a model description the master needs."""

    path: Path
    model_identifier: str
    instantiation_token: str
    default_step: float | None
    ports: dict[str, PortInfo] = field(default_factory=dict)
    model_description: object = None
    #: FMI 3.0 Co-Simulation capabilities: steps of any size between calls, and the FMU's fixed
    #: internal step (communication steps must then be whole multiples of it), exact
    can_handle_variable_step: bool = False
    fixed_internal_step: Fraction | None = None


def parse_binary(text: str) -> bytes:
    """A Binary value written in hexadecimal ("0a1B", "0x0a1b", "0a 1b"); ValueError if it is not."""
    digits = "".join(str(text).split())
    if digits[:2].lower() == "0x":
        digits = digits[2:]
    return bytes.fromhex(digits)


def _start_value(variable):
    start = variable.start
    if variable.type == "Binary" and isinstance(start, str):
        return parse_binary(start)
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


def _bound(variable, which: str) -> float | None:
    """A numeric variable's declared ``min``/``max`` (its own, else its declared type's), or None."""
    value = getattr(variable, which, None)
    if value is None and variable.declaredType is not None:
        value = getattr(variable.declaredType, which, None)
    if value is None or variable.type not in NUMERIC_TYPES or variable.type == "Boolean":
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


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
        declared = v.declaredType
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
            unit=v.unit or (declared.unit if declared is not None else None) or None,
            shape=shape, value_reference=v.valueReference, start=_start_value(v),
            description=v.description or "",
            declared_type=declared.name if declared is not None else None,
            items=tuple((item.name, int(item.value)) for item in declared.items) if declared is not None else (),
            minimum=_bound(v, "min"), maximum=_bound(v, "max"),
        )
    step = md.defaultExperiment.stepSize if md.defaultExperiment else None
    cs = md.coSimulation
    fixed = getattr(cs, "fixedInternalStepSize", None)
    try:
        fixed_step = Fraction(str(fixed).strip()) if fixed not in (None, "") else None
    except (ValueError, ZeroDivisionError):
        raise ValueError(f"{path}: fixedInternalStepSize {fixed!r} is not a number") from None
    if fixed_step is not None and fixed_step <= 0:
        raise ValueError(f"{path}: fixedInternalStepSize {fixed!r} is not positive")
    return FmuDescription(path=path, model_identifier=cs.modelIdentifier,
                          instantiation_token=md.guid, default_step=float(step) if step else None,
                          ports=ports, model_description=md,
                          can_handle_variable_step=bool(cs.canHandleVariableCommunicationStepSize),
                          fixed_internal_step=fixed_step)

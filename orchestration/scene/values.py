"""Parameter values against the ports an FMU declares: type, size, range."""
from __future__ import annotations

import numpy as np

from orchestration.checks import is_finite_number
from orchestration.hosts.description import INTEGER_RANGES, MAX_PORT_VALUES, PortInfo, parse_binary
from orchestration.scene.tables import short_text


def _type_matches(port: PortInfo, value) -> bool:
    values = np.ravel(np.asarray(value, dtype=object)) if isinstance(value, list) else [value]
    if port.type == "String":
        return all(isinstance(v, str) for v in values)
    if port.type == "Binary":
        return all(isinstance(v, str) and _is_hex(v) for v in values)
    if port.type == "Enumeration":
        return all((isinstance(v, int) and not isinstance(v, bool)) or (isinstance(v, str) and port.item_value(v) is not None)
                   for v in values)
    if port.type == "Boolean":
        return all(isinstance(v, bool) for v in values)
    if port.type.startswith("Float"):
        return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
    return all(isinstance(v, int) and not isinstance(v, bool) for v in values)


def _is_hex(text: str) -> bool:
    try:
        parse_binary(text)
    except ValueError:
        return False
    return True


def _expected(port: PortInfo) -> str:
    """What a parameter of ``port``'s type is written as in a scene."""
    if port.type == "Binary":
        return "Binary values, written in hexadecimal (\"0a1bff\")"
    if port.type == "Enumeration":
        items = ", ".join(f"{name!r} ({value})" for name, value in port.items)
        return f"Enumeration values: an item name or its value ({items})" if items else "Enumeration values (integers)"
    return f"{port.type} values"


def _size_of(value) -> int:
    return int(np.asarray(value, dtype=object).size) if isinstance(value, list) else 1


def type_of(port: PortInfo) -> str:
    """"Int32", or "Enumeration Mode" for an enumeration with its declared type."""
    if port.type == "Enumeration" and port.declared_type:
        return f"Enumeration {port.declared_type}"
    return port.type


def check_parameters(where: str, parameters: dict, ports: dict[str, PortInfo], problems: list[str]) -> None:
    settable = ("parameter", "structuralParameter", "input")
    for key, value in parameters.items():
        port = ports.get(key)
        if port is None:
            names = sorted(n for n, p in ports.items() if p.causality in settable)
            problems.append(f"{where} parameters.{key}: no such parameter or input; settable: {', '.join(names)}")
            continue
        if port.causality not in settable:
            problems.append(f"{where} parameters.{key}: is a {port.causality}, not settable")
            continue
        if not _type_matches(port, value):
            problems.append(f"{where} parameters.{key}: expects {_expected(port)} (got {short_text(value)})")
            continue
        problem = _value_problem(port, value)
        if problem:
            problems.append(f"{where} parameters.{key}: {problem}")
            continue
        if port.is_array and _size_of(value) not in (port.size, 1):
            problems.append(f"{where} parameters.{key}: expects {port.size} values ({'x'.join(map(str, port.shape))}), "
                            f"got {_size_of(value)}")


def flat_values(value) -> list:
    """The scalars of a value or of a nested list of values."""
    if isinstance(value, list):
        return [v for item in value for v in flat_values(item)]
    return [value]


def _value_problem(port: PortInfo, value) -> str | None:
    """Why a value of the right type cannot be set: not finite, out of the type's range, or an array
    size beyond MAX_PORT_VALUES (a structural parameter); None if it can."""
    values = flat_values(value)
    numbers = [v for v in values if isinstance(v, (int, float)) and not isinstance(v, bool)]
    if port.type.startswith("Float"):
        bad = [v for v in values if not is_finite_number(v)]
        if bad:
            return f"{short_text(bad[0])} is not a finite number; the FMU computes with it (give a finite value)"
    elif port.type in INTEGER_RANGES and port.type != "Enumeration":
        low, high = INTEGER_RANGES[port.type]
        bad = [v for v in values if isinstance(v, int) and not low <= v <= high]
        if bad:
            return f"{bad[0]} is outside the range of {port.type} ({low}..{high})"
        if port.causality == "structuralParameter" and any(isinstance(v, int) and v > MAX_PORT_VALUES for v in values):
            return (f"{max(values)} is more than {MAX_PORT_VALUES}: a structural parameter sizes arrays, and one this "
                    "large is far beyond any mesh this project runs (the AAA wall has 2688 surface nodes)")
    elif port.type == "Enumeration":
        numbers = [v for v in values if isinstance(v, int)]
        known = {item for _, item in port.items}
        bad = [v for v in numbers if known and v not in known]
        if bad:
            return f"{bad[0]} is not a value of {type_of(port)}: {_expected(port)}"
    # Last: the FMU's own plausible range (min/max in its modelDescription.xml), once the value is
    # a finite number of its type at all.
    below = [v for v in numbers if port.minimum is not None and v < port.minimum]
    above = [v for v in numbers if port.maximum is not None and v > port.maximum]
    if below or above:
        low = "-inf" if port.minimum is None else f"{port.minimum:g}"
        high = "inf" if port.maximum is None else f"{port.maximum:g}"
        return f"{short_text((below or above)[0])} is outside the range the FMU declares for it, {low} to {high}"
    return None

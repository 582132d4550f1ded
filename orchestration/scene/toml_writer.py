"""Writing a scene's data as TOML (the standard library reads TOML but does not write it).

Covers what scenes hold: tables, arrays of tables, inline tables, strings, booleans, integers,
finite floats and arrays of them. ``tomllib.loads(dumps(data)) == data`` for such data. Small
tables nested in a table are written inline (``outputs = { insertion = [...] }``) as the shipped
scenes write them; larger ones as ``[a.b]`` sections.
"""
from __future__ import annotations

import json
import math
import re

#: A nested table shorter than this is written inline.
INLINE_WIDTH = 100
_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(name: str) -> str:
    return name if _BARE_KEY.match(name) else json.dumps(name)


def _value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"TOML scenes hold finite numbers only (got {value!r})")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)   # JSON's escapes are TOML basic-string escapes
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items()) + " }" if value else "{}"
    raise TypeError(f"cannot write {type(value).__name__} {value!r} as TOML")


def _is_table_array(value) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def _section(path: list[str], table: dict, lines: list[str], header: str | None) -> None:
    simple, nested = [], []
    for key, value in table.items():
        if isinstance(value, dict) and len(_value(value)) + len(key) > INLINE_WIDTH:
            nested.append((key, value))
        elif _is_table_array(value):
            nested.append((key, value))
        else:
            simple.append((key, value))
    if header is not None and (simple or not nested):
        lines.append(header)
    lines.extend(f"{_key(k)} = {_value(v)}" for k, v in simple)
    for key, value in nested:
        sub = path + [key]
        dotted = ".".join(_key(p) for p in sub)
        if isinstance(value, dict):
            lines.append("")
            _section(sub, value, lines, f"[{dotted}]")
        else:
            for item in value:
                lines.append("")
                _section(sub, item, lines, f"[[{dotted}]]")


def dumps(data: dict, comment: str = "") -> str:
    """``data`` as TOML text, after ``comment`` (each of its lines written as a ``#`` line)."""
    lines = [f"# {line}".rstrip() for line in comment.splitlines()]
    if lines:
        lines.append("")
    _section([], data, lines, None)
    return "\n".join(line for i, line in enumerate(lines) if line or (i and lines[i - 1])).strip("\n") + "\n"

"""Reading the parsed TOML: tables, lists and strings where they are expected, unknown keys, each
problem named with where it is."""
from __future__ import annotations


def unknown_keys(table: dict, allowed: set, where: str, problems: list[str]) -> None:
    for key in table:
        if key not in allowed:
            problems.append(f"{where}: unknown key {key!r}; valid keys: {', '.join(sorted(allowed))}")


def expect_table(value, where: str, problems: list[str], fix: str) -> dict:
    """``value`` if it is a table; else a problem and an empty table (so checking goes on)."""
    if isinstance(value, dict):
        return value
    problems.append(f"{where}: must be a table ({fix}), got {type(value).__name__} {short_text(value)}")
    return {}


def expect_list(value, where: str, problems: list[str], fix: str) -> list:
    if isinstance(value, list):
        return value
    problems.append(f"{where}: must be a list ({fix}), got {type(value).__name__} {short_text(value)}")
    return []


def expect_tables(items: list, where: str, keys, problems: list[str], shape: str):
    """``(where[i], item)`` for each table in ``items``; a problem for each item that is not a
    table (it is skipped) and for each unknown key."""
    for i, item in enumerate(items):
        at = f"{where}[{i}]"
        if not isinstance(item, dict):
            problems.append(f"{at}: must be a table {shape}")
            continue
        unknown_keys(item, keys, at, problems)
        yield at, item


def short_text(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def expect_strings(values: list, where: str, problems: list[str], what: str) -> list[str]:
    """The strings of ``values``; a problem for each item that is not one."""
    good = []
    for i, item in enumerate(values):
        if isinstance(item, str):
            good.append(item)
        else:
            problems.append(f"{where}[{i}]: {short_text(item)} is not {what} (write it in quotes)")
    return good

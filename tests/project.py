"""What the project has: the one place the tests learn it from.

- Its FMUs: the build's FMU table (``FMU_SPECS``, name -> model identifier, package, declaration),
  in the table's order. The ports of an FMU are read from its model description once it is built
  (``orchestration.hosts.description.read_fmu``, ``fuzz_hosts.ports``), not listed in a test.
- Its shipped scenes: the ``scenes/*.toml`` files, by name.

Tests and fuzzers take their lists of FMUs and scenes from here, never from lists of their own. A
test that keeps a table of per-FMU or per-scene settings (inputs that make a run do something, an
expected value) looks its entries up with :func:`entry`, which fails naming the table when an FMU
or a scene has none, or gives the table's default.
"""
from __future__ import annotations

import tomllib
from pathlib import Path

# The build's FMU table: the only import of it in the tests (when it moves, only this line changes).
from fmu_build.specs import FMU_SPECS

REPO = Path(__file__).resolve().parent.parent
SCENE_DIR = REPO / "scenes"

#: The project's FMUs, in the order of the build's table.
FMU_NAMES: tuple[str, ...] = tuple(FMU_SPECS)

_NO_DEFAULT = object()


def fmu_spec(name: str):
    """The build's spec of the FMU ``name``: model identifier, package, declaration, source root."""
    return FMU_SPECS[name]


def fmu_file_name(name: str) -> str:
    """The file the build writes for the FMU ``name`` (``<model identifier>.fmu``)."""
    return f"{FMU_SPECS[name].model_identifier}.fmu"


def shipped_scenes() -> list[str]:
    """The names of the shipped scenes (``scenes/*.toml``), sorted."""
    return sorted(path.stem for path in SCENE_DIR.glob("*.toml"))


def scene_path(name: str) -> Path:
    return SCENE_DIR / f"{name}.toml"


def scene_data(name: str) -> dict:
    """A shipped scene's TOML, parsed."""
    return tomllib.loads(scene_path(name).read_text())


def scene_fmus(name: str) -> set[str]:
    """The FMUs of the table a shipped scene runs (its ``[fmu.*] path`` by file name); a file the
    table does not make is given by its file name."""
    by_file = {fmu_file_name(fmu): fmu for fmu in FMU_NAMES}
    files = [Path(table["path"]).name for table in scene_data(name).get("fmu", {}).values()
             if isinstance(table, dict) and "path" in table]
    return {by_file.get(file, file) for file in files}


def entry(table: dict, key: str, where: str, default=_NO_DEFAULT):
    """``table[key]`` for the FMU or shipped scene ``key``; when it has no entry, ``default`` if one
    is given, else the test fails saying which table lacks which entry (a new FMU or scene must be
    given its settings, not be skipped)."""
    if key in table:
        return table[key]
    if default is not _NO_DEFAULT:
        return default
    import pytest

    pytest.fail(f"{key!r}, an FMU or a shipped scene of the project (tests/project.py), has no entry in {where}: "
                f"add its settings there", pytrace=False)

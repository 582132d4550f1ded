"""Fuzzing scene files (issue 14): whatever a scene file holds, ``load_scene`` and ``validate``
either accept a scene that is sound or refuse it with ``SceneError`` / exit code 2, naming where
the problem is; never another exception, never a traceback.

Two generators: *structure* (random TOML trees built from the scene vocabulary: wrong types,
missing and extra keys, nested tables, huge, negative and non-finite numbers, names with path
characters, and files that are not UTF-8) and *values* (one value of a shipped scene replaced,
deleted or joined by an extra key). Cases run in process (``scene_from_dict`` / ``load_scene``)
and, for a few, through ``python -m orchestration validate`` in a subprocess.

The number of cases is the hypothesis profile's (tests/conftest.py): 25 per test in CI, 1000 with
``--hypothesis-profile=long``.
"""
from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import tempfile
import tomllib
from fractions import Fraction
from pathlib import Path

import pytest
from hypothesis import given, note
from hypothesis import strategies as st

from orchestration.app import cli
from orchestration.scene.text import _COMPONENT_NAME, FILE_NAME, _SCENE_NAME
from orchestration.scene.model import MAX_RUN_STEPS, MAX_STEP, MIN_STEP, Scene, SceneError
from fmu_build.paths import SCENE_DIR
from orchestration.scene.loading import load_scene, scene_from_dict
from project import shipped_scenes

REPO = Path(__file__).resolve().parent.parent
SHIPPED = shipped_scenes()

# The shipped scenes name their FMUs by file name, looked up in fmus/ (tests/conftest.py builds them).
pytestmark = pytest.mark.usefixtures("fmus_in_repo")


# -- writing TOML (no writer in the standard library) ----------------------------------------------
def toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string: JSON's escapes are TOML's
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(type(value))


def toml_text(data: dict) -> str:
    return "".join(f"{json.dumps(k)} = {toml_value(v)}\n" for k, v in data.items())


# -- strategies ---------------------------------------------------------------------------------------
KEYS = ["scene", "fmu", "source", "block", "connection", "record", "summary", "name", "description", "duration",
        "hosting", "realtime", "start_time", "path", "step", "parameters", "kind", "from", "to", "transition",
        "ordering", "surfaces", "plots", "peaks", "energy", "warnings", "component", "positions", "triangles",
        "every", "point_data", "file", "panels", "series", "stream", "column", "times", "outputs", "units",
        "contact", "tissue", "catheter", "device", "operator", "stiffness", "internal_step", "mass",
        "n_surface_nodes", "tool"]
PATHLIKE = ["../escape", "/tmp/abs", "..", ".", "a/b", "C:\\x", "~", "", " ", "a\x00b", "Tissue.fmu",
            "../fmus/Contact.fmu", "contact.tool_force", "catheter.tip_force", "hold", "jacobi", "in-process",
            "1/30", "0.001", "nan", "é", "x" * 300]
text = st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=12)
numbers = st.one_of(
    st.integers(min_value=-2**64, max_value=2**64),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, 1, 1e9, 1e-9, 1e300, -0.0, 2**63, 0.001, 1 / 30, 4.0, 1e-7, 10**400, -10**400]),
)
scalars = st.one_of(numbers, st.booleans(), text, st.sampled_from(PATHLIKE))
keys = st.one_of(st.sampled_from(KEYS), st.sampled_from([p for p in PATHLIKE if p]), text.filter(bool))
trees = st.recursive(scalars, lambda children: st.one_of(st.lists(children, max_size=4),
                                                          st.dictionaries(keys, children, max_size=4)),
                     max_leaves=12)
documents = st.dictionaries(st.one_of(st.sampled_from(KEYS[:7]), keys), trees, max_size=6)


def shipped_data(name: str) -> dict:
    return tomllib.loads((SCENE_DIR / f"{name}.toml").read_text())


def leaf_paths(node, prefix=()):
    """Every path (tuple of keys and indices) into a parsed TOML tree, tables and lists included."""
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from leaf_paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from leaf_paths(v, prefix + (i,))


@st.composite
def mutated_scenes(draw):
    """A shipped scene with one value replaced, one key deleted or one extra key added."""
    name = draw(st.sampled_from(SHIPPED))
    data = shipped_data(name)
    paths = [p for p in leaf_paths(data) if p]
    path = draw(st.sampled_from(paths))
    parent = data
    for part in path[:-1]:
        parent = parent[part]
    action = draw(st.sampled_from(["replace", "replace", "replace", "delete", "add"]))
    old = parent[path[-1]]
    if action == "replace":
        if isinstance(old, (int, float)) and not isinstance(old, bool) and draw(st.booleans()):
            # a plausible-looking change of a number: scaled, negated or made non-finite
            factor = draw(st.sampled_from([-1, 0, 0.5, 2, 10, 1e3, 1e9, 1e-9, math.nan, math.inf, 10**400]))
            if factor == 10**400:  # an integer no float holds (TOML integers have no size limit)
                new = int(old) * factor
            else:
                new = old * factor if not math.isnan(factor) else math.nan
                new = int(new) if isinstance(old, int) and math.isfinite(new) else new
        else:
            new = draw(trees)
        parent[path[-1]] = new
    elif action == "delete":
        del parent[path[-1]]
    else:  # add: an item to a list, or a new key to a table (the one at path, else the one holding it)
        target = parent[path[-1]] if isinstance(parent[path[-1]], (dict, list)) else parent
        if isinstance(target, list):
            target.append(draw(trees))
        else:
            target[draw(keys.filter(lambda k: k not in target))] = draw(trees)
    note(f"{name}: {action} at {path}")
    # what a message may name for this change: the keys on the path, and those of a removed table
    # (deleting [source] makes "operator" unknown)
    names = [p for p in path if isinstance(p, str)]
    if action != "add" and isinstance(old, dict):
        names += list(old)
    return name, data, names


# -- what an accepted scene must be (anything else would be "silently wrong") -------------------------
def assert_sound(scene: Scene) -> None:
    assert isinstance(scene, Scene)
    assert _SCENE_NAME.fullmatch(scene.name), scene.name  # a name, never a path
    assert isinstance(scene.duration, Fraction) and scene.duration > 0
    steps = [c.step for c in scene.components.values() if c.step is not None]
    assert all(MIN_STEP <= s <= MAX_STEP for s in steps)
    assert sum(scene.duration / s for s in steps) <= MAX_RUN_STEPS
    for c in scene.components.values():
        assert _COMPONENT_NAME.fullmatch(c.name)
        assert (scene.duration / c.step).denominator == 1 if c.step is not None else True
    for component, ports in scene.record.items():
        assert len(ports) == len(set(ports)), ports
        assert all(p in scene.components[component].ports for p in ports)
    for surface in scene.surfaces:
        assert FILE_NAME.fullmatch(surface.name)
    for figure in scene.plots:
        assert FILE_NAME.fullmatch(figure["file"]) and figure["file"].endswith(".png")


LOCATED = re.compile(r"\[|connection|override|top level|the scene has no|algebraic loop|(fmu|source|block): "
                     r"|TOML syntax error|not UTF-8|scene file not found|cannot read the file"
                     r"|\S+: tables or lists nested")


def assert_refusal(exc: SceneError) -> None:
    assert exc.problems, "a SceneError must list its problems"
    for problem in exc.problems:
        assert isinstance(problem, str) and problem.strip()
        assert "Traceback" not in problem
        # every problem starts by saying where: "[scene] duration: ...", "connection 3 ...", ...
        assert LOCATED.match(problem), problem


def check_in_process(data: dict, base_dir: Path = SCENE_DIR, path: Path | None = None) -> SceneError | None:
    """Accept a sound scene or refuse with SceneError; any other exception fails the test."""
    try:
        scene = scene_from_dict(data, base_dir, path)
    except SceneError as exc:
        assert_refusal(exc)
        return exc
    assert_sound(scene)
    return None


def check_validate_subprocess(path: Path) -> None:
    result = subprocess.run([sys.executable, "-m", "orchestration", "validate", str(path)], cwd=REPO,
                            capture_output=True, text=True, timeout=120)
    assert "Traceback" not in result.stderr, result.stderr
    assert result.returncode in (0, 2), (result.returncode, result.stderr)
    if result.returncode == 2:
        assert result.stderr.startswith("error: "), result.stderr
    else:
        assert result.stdout.rstrip().splitlines()[0].endswith(": OK")


def write_bytes(data: bytes) -> Path:
    handle, name = tempfile.mkstemp(suffix=".toml", prefix="fuzz_scene_")
    with os.fdopen(handle, "wb") as f:
        f.write(data)
    return Path(name)


# -- structure ---------------------------------------------------------------------------------------
@given(documents)
def test_random_trees_are_refused_with_a_located_message_or_sound(data):
    check_in_process(data)


@given(documents)
def test_random_trees_through_a_file_and_load_scene(data):
    path = write_bytes(toml_text(data).encode())
    try:
        scene = load_scene(path)
    except SceneError as exc:
        assert_refusal(exc)
    else:  # rare: e.g. {"block": {"d": {"kind": "device_plant"}}} is a whole scene (all defaults)
        assert_sound(scene)
    finally:
        path.unlink()


@given(st.sampled_from(SHIPPED), st.binary(min_size=1, max_size=8), st.integers(min_value=0))
def test_bytes_that_are_not_utf8_name_the_file_and_the_offset(name, junk, where):
    text = (SCENE_DIR / f"{name}.toml").read_bytes()
    at = where % len(text)
    data = text[:at] + b"\xff" + junk + text[at:]  # 0xff never occurs in UTF-8
    path = write_bytes(data)
    try:
        with pytest.raises(SceneError) as info:
            load_scene(path)
        assert len(info.value.problems) == 1
        assert "not UTF-8" in info.value.problems[0] and "offset" in info.value.problems[0]
        assert str(path) in str(info.value)
    finally:
        path.unlink()


@given(documents)
def test_validate_in_a_subprocess_exits_2_with_an_error_line_never_a_traceback(data):
    path = write_bytes(toml_text(data).encode())
    try:
        check_validate_subprocess(path)
    finally:
        path.unlink()


# -- values: mutations of the shipped scenes ----------------------------------------------------------
@given(mutated_scenes())
def test_mutated_shipped_scenes_are_refused_naming_the_key_or_its_table_or_sound(case):
    name, data, names = case
    exc = check_in_process(data, SCENE_DIR, SCENE_DIR / f"{name}.toml")
    if exc is None:
        return
    # The message names the changed key, or (for a value whose consequences show elsewhere, e.g. a
    # structural parameter that resizes an array) the table or component it is in.
    assert any(n in problem for n in names for problem in exc.problems), (names, exc.problems)


@given(case=mutated_scenes())
def test_mutated_shipped_scenes_through_validate_in_a_subprocess(case):
    name, data, _ = case
    path = write_bytes(toml_text(data).encode())
    try:
        check_validate_subprocess(path)
    finally:
        path.unlink()


@given(case=mutated_scenes())
def test_mutated_shipped_scenes_through_the_cli_in_process(capsys, case):
    name, data, _ = case
    path = write_bytes(toml_text(data).encode())
    try:
        code = cli.main(["validate", str(path)])
    finally:
        path.unlink()
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    assert code in (cli.EXIT_OK, cli.EXIT_USAGE)
    if code == cli.EXIT_USAGE:
        assert err.startswith("error: ") and str(path) in err
    else:
        assert out.splitlines()[0].endswith(": OK")


@given(st.integers(min_value=0, max_value=3000), st.sampled_from(["[", "{a = ", "dotted", "[table"]),
       st.sampled_from(KEYS[:7] + ["x"]))
def test_nesting_of_any_depth_is_accepted_or_refused_never_a_recursion_error(depth, opener, key):
    """Brackets, inline tables, dotted keys (`x.x.x = 1`: tomllib's memory grows with the square of
    their depth) and dotted table headers, at any depth."""
    if opener == "dotted":
        text = ".".join([json.dumps(key)] * (depth + 1)) + " = 1\n"
    elif opener == "[table":
        text = "[" + ".".join([json.dumps(key)] * (depth + 1)) + "]\nx = 1\n"
    else:
        closer = "]" if opener == "[" else "}"
        inner = "1" if opener != "[" else ""
        text = f"{json.dumps(key)} = {opener * depth}{inner}{closer * depth}\n"
    path = write_bytes(text.encode())
    try:
        load_scene(path)
    except SceneError as exc:
        assert_refusal(exc)
    finally:
        path.unlink()

"""The block kinds a scene may name, their options, and ``make_block``, which builds one from its TOML table."""
from __future__ import annotations

from pathlib import Path

from orchestration.blocks.csv_source import CsvSource, check_columns, read_csv
from orchestration.blocks.options import BlockConfigError, check_choice, check_units
from orchestration.blocks.plant import DevicePlant, check_plant
from orchestration.blocks.sources import INTERPOLATIONS, PiecewiseLinearSource, check_outputs, check_times
from orchestration.blocks.surfaces import PLANE_DEFAULTS, RigidSurfaceSource, TUBE_DEFAULTS, check_surface


# ---------------------------------------------------------------------------------- factory
REQUIRED = type("Required", (), {"__repr__": lambda self: "required"})()

BLOCK_KINDS: dict[str, str] = {
    "piecewise_linear": "scripted signal: values at knot times, linear or held between them (e.g. insertion ramp)",
    "csv": "recorded signal: columns of a CSV file played back against its time column",
    "rigid_surface": "constant rigid plane or tube (positions, velocities, triangles) for the Contact FMU",
    "device_plant": "haptic device: damped mass driven by operator and wall forces, exact over each step",
}

_OPTIONS: dict[str, list[tuple[str, object, str]]] = {
    "piecewise_linear": [
        ("times", REQUIRED, "knot times in s, strictly increasing, e.g. [0.0, 1.0, 3.0]"),
        ("outputs", REQUIRED, "table output -> one value per knot (number, or list for a vector), "
                              "e.g. { insertion = [0.0, 0.0, 0.05] }"),
        ("interpolation", "linear", "'linear' between knots, or 'hold' the last knot's value"),
        ("units", None, "table output -> unit string, e.g. { insertion = \"m\" }"),
    ],
    "csv": [
        ("path", REQUIRED, "CSV file with a header row (relative to the scene file)"),
        ("columns", REQUIRED, "table output -> column name (scalar) or list of column names (vector)"),
        ("time_column", "time", "name of the time column (s, strictly increasing)"),
        ("interpolation", "linear", "'linear' between rows, or 'hold' the last row's value"),
        ("units", None, "table output -> unit string"),
    ],
    "rigid_surface": [
        ("shape", "plane", "'plane' or 'tube'"),
        ("center", list(PLANE_DEFAULTS["center"]), "plane: centre in m"),
        ("normal", list(PLANE_DEFAULTS["normal"]), "plane: normal, pointing to the side where the tool is allowed"),
        ("size", PLANE_DEFAULTS["size"], "plane: side length in m, or [length_u, length_v]"),
        ("divisions", PLANE_DEFAULTS["divisions"], "plane: cells per side, or [n_u, n_v] (2 triangles per cell)"),
        ("start", list(TUBE_DEFAULTS["start"]), "tube: first axis point in m"),
        ("end", list(TUBE_DEFAULTS["end"]), "tube: last axis point in m"),
        ("radius", TUBE_DEFAULTS["radius"], "tube: radius in m (normals point to the axis: tool inside)"),
        ("n_circumferential", TUBE_DEFAULTS["n_circumferential"], "tube: nodes around each ring (>= 3)"),
        ("n_axial", TUBE_DEFAULTS["n_axial"], "tube: segments along the axis (>= 1)"),
    ],
    "device_plant": [
        ("mass", 0.1, "moving mass of the device in kg (> 0)"),
        ("damping", 1.0, "physical damping b_dev in N s/m (>= 0)"),
        ("step", 0.001, "haptic step in s; must equal the step the scene gives the plant"),
        ("initial_position", [0.0, 0.0, 0.0], "position at the start in m"),
        ("initial_velocity", [0.0, 0.0, 0.0], "velocity at the start in m/s"),
    ],
}


def block_options(kind: str) -> list[tuple[str, object, str]]:
    """The options of a block kind as (name, default, meaning); default ``REQUIRED`` when required."""
    if kind not in _OPTIONS:
        raise KeyError(f"unknown block kind {kind!r}: kinds are {list(BLOCK_KINDS)}")
    return list(_OPTIONS[kind])


def _collect(kind, opts, base_dir) -> list[str]:
    """Every value problem of the present options (missing required keys are reported elsewhere)."""
    problems: list[str] = []
    if kind == "piecewise_linear":
        times = check_times(problems, opts["times"]) if "times" in opts else None
        if "outputs" in opts:
            check_outputs(problems, opts["outputs"], None if times is None else len(times))
        check_choice(problems, "interpolation", opts.get("interpolation", "linear"), INTERPOLATIONS)
        if isinstance(opts.get("outputs"), dict):
            check_units(problems, "units", opts.get("units"), list(opts["outputs"]))
    elif kind == "csv":
        check_choice(problems, "interpolation", opts.get("interpolation", "linear"), INTERPOLATIONS)
        time_column = opts.get("time_column", "time")
        if not isinstance(time_column, str):
            problems.append(f"time_column must be a column name (got {time_column!r})")
        columns_ok = "columns" in opts and check_columns(problems, opts["columns"])
        if columns_ok:
            check_units(problems, "units", opts.get("units"), list(opts["columns"]))
        if "path" in opts and not isinstance(opts["path"], str):
            problems.append(f"path must be a file path string (got {opts['path']!r})")
        elif "path" in opts and columns_ok and isinstance(time_column, str):
            read_csv(problems, _resolve(opts["path"], base_dir), opts["columns"], time_column)
    elif kind == "rigid_surface":
        check_surface(problems, opts.get("shape", "plane"), {k: v for k, v in opts.items() if k != "shape"})
    elif kind == "device_plant":
        check_plant(problems, opts)
    return problems


def _resolve(path, base_dir) -> Path:
    p = Path(path)
    return p if p.is_absolute() else Path(base_dir) / p


def make_block(name: str, table: dict, base_dir: Path):
    """Build the block described by a scene's TOML table (``kind`` plus the kind's options).

    Raises ``BlockConfigError`` listing every problem at once (unknown, missing or invalid keys).
    """
    kind = table.get("kind")
    if not isinstance(kind, str) or kind not in BLOCK_KINDS:
        got = "no 'kind' key" if "kind" not in table else f"kind = {kind!r}"
        raise BlockConfigError([f"kind must be one of {list(BLOCK_KINDS)} ({got})"], name)
    opts = {k: v for k, v in table.items() if k != "kind"}
    valid = [o[0] for o in _OPTIONS[kind]]
    problems = [f"unknown key {k!r} for kind = {kind!r}: valid keys are {valid}" for k in opts if k not in valid]
    problems += [f"missing required key {o[0]!r}: {o[2]}" for o in _OPTIONS[kind]
                 if o[1] is REQUIRED and o[0] not in opts]
    known = {k: v for k, v in opts.items() if k in valid}
    problems += _collect(kind, known, base_dir)
    if problems:
        raise BlockConfigError(problems, name)
    if kind == "piecewise_linear":
        return PiecewiseLinearSource(name, **known)
    if kind == "csv":
        known["path"] = _resolve(known["path"], base_dir)
        return CsvSource(name, **known)
    if kind == "rigid_surface":
        return RigidSurfaceSource(name, **known)
    return DevicePlant(name, **known)

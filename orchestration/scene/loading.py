"""Scene files: what a simulation couples, at which rates, and what it records.

A scene is a TOML file (the format: ``docs/scenes.md``)::

    [scene]                      name, description, duration (s), hosting, realtime
    [fmu.<instance>]             path (to an .fmu), step (s: number or "1/30"), parameters (table)
    [source.<name>]              kind = "piecewise_linear" | "csv" | "rigid_surface" (continuous, no step)
    [block.<name>]               kind = "device_plant" (stepped built-in component), step, options
    [[connection]]               from = "a.port", to = "b.port", transition, ordering
    [record]                     <component> = [ports], surfaces, plots
    [summary]                    peaks, energy, warnings, deadlines

``load_scene`` parses and checks everything it can *before anything runs* and raises
``SceneError`` holding every problem found, each with where it is and how to fix it; nothing a
user writes in a scene produces a traceback. Times are exact rationals (``fractions.Fraction``):
a step given as ``0.001`` is 1/1000, ``"1/30"`` is 1/30.
"""
from __future__ import annotations

import tomllib
from pathlib import Path

from fmu_build.paths import DEFAULT_FMU_DIR as FMU_DIR
from fmu_build.paths import SCENE_DIR
from orchestration.checks import is_finite_number
from orchestration.hosts.description import MAX_PORT_VALUES, NUMERIC_TYPES, read_fmu
from orchestration.hosts.fmi3 import fmu_binary_problem
from orchestration.scene.connections import check_algebraic_loops, load_connections, parse_endpoint
from orchestration.scene.model import DEFAULT_HOSTING, ComponentSpec, HOSTINGS, MAX_NESTING, Scene, SceneError
from orchestration.scene.record import load_record
from orchestration.scene.tables import expect_list, expect_table, short_text, unknown_keys
from orchestration.scene.text import (
    component_name_problem, control_character_problems, nesting_problem, scene_name_problem, too_deep)
from orchestration.scene.timing import duration_problem, format_time, parse_time, run_size_problem, step_problem
from orchestration.scene.values import check_parameters


_SCENE_KEYS = {"name", "description", "duration", "hosting", "realtime", "start_time", "worker_timeout"}
_FMU_KEYS = {"path", "step", "parameters", "hosting"}
_SUMMARY_KEYS = {"peaks", "energy", "warnings", "deadlines"}


def resolve_fmu_path(value, scene_dir: Path) -> tuple[Path | None, list[Path]]:
    """An FMU path relative to the scene folder, else to ``fmus/``; returns (path or None, tried)."""
    raw = Path(str(value))
    tried = [raw] if raw.is_absolute() else [scene_dir / raw, FMU_DIR / raw]
    for candidate in tried:
        if candidate.is_file():
            return candidate.resolve(), tried
    return None, tried


# -- loading -------------------------------------------------------------------------------------
def load_scene(path: Path | str, overrides: dict | None = None) -> Scene:
    """Read and check a scene; raise ``SceneError`` listing every problem.

    ``path`` is a TOML file, an SSP package (``.ssp``: orchestration/scene/ssp/), or the bare name
    of a shipped scene (``scenes/<name>.toml``).
    ``overrides`` maps ``"component.parameter"`` (``"component.step"`` for the step,
    ``"scene.duration"`` or ``"duration"``) to values that replace the file's, as studies, ``--set``
    and ``--duration`` do.
    """
    try:
        path = Path(path)
        # Only a bare name means a shipped scene: "x/virtual_wall" is a path, not that scene.
        if not path.suffix and len(path.parts) == 1 and not path.exists():
            candidate = SCENE_DIR / f"{path.name}.toml"
            if candidate.is_file():
                path = candidate
        found = path.is_file()
    except (TypeError, ValueError, OSError) as exc:  # a NUL byte, a name too long for the file system
        raise SceneError(None, [f"scene {str(path)!r}: not a usable file name ({exc})"]) from None
    if not found:
        shipped = ", ".join(sorted(p.stem for p in SCENE_DIR.glob("*.toml")))
        raise SceneError(path, [f"scene file not found; shipped scenes: {shipped} (or give a path to a .toml file)"])
    if path.suffix.lower() == ".ssp":  # an SSP package (orchestration/scene/ssp/): its SSD as a scene dict
        from orchestration.scene.ssp import read_package

        package = read_package(path)
        scene = scene_from_dict(package.data, package.base_dir, path, overrides)
        package.check(scene)  # what the SSD declares is what the FMUs have
        return scene
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SceneError(path, [f"not UTF-8 text (byte {exc.object[exc.start]:#04x} at offset {exc.start}): "
                                "TOML files are UTF-8; save the file as UTF-8"]) from None
    except OSError as exc:
        raise SceneError(path, [f"cannot read the file: {exc.strerror or exc}"]) from None
    deep = nesting_problem(text)  # before the parser, which deep nesting makes recurse or grow as n**2
    if deep is not None:
        raise SceneError(path, [deep])
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(path, [f"TOML syntax error: {exc}"]) from None
    except RecursionError:
        raise SceneError(path, [f"TOML syntax error: tables or lists nested too deeply to parse; a scene nests at most "
                                f"{MAX_NESTING} levels"]) from None
    return scene_from_dict(data, path.parent, path, overrides)


def scene_from_dict(data: dict, base_dir: Path, path: Path | None = None, overrides: dict | None = None) -> Scene:
    """Build and check a scene from parsed TOML (``base_dir`` resolves relative paths)."""
    problems: list[str] = []
    deep = too_deep(data)
    if deep is not None:
        raise SceneError(path, [f"{deep}: tables or lists nested more than {MAX_NESTING} levels deep; a scene "
                                "nests at most 5 (see docs/scenes.md)"])
    problems += control_character_problems(data, overrides)
    allowed_top = {"scene", "fmu", "source", "block", "connection", "record", "summary"}
    unknown_keys(data, allowed_top, "top level", problems)
    overrides = _component_overrides(overrides, problems)
    head = _load_head(data, path, overrides, problems)
    components, declared = _load_components(data, base_dir, overrides, problems)
    duration, duration_where = head["duration"], head["duration_where"]
    if duration is not None:
        problem = duration_problem(components.values(), duration) or run_size_problem(components.values(), duration)
        if problem:
            problems.append(f"{duration_where}: {problem}")
    connections = load_connections(data.get("connection", []), components, problems, declared)
    check_algebraic_loops(connections, components, problems)
    record, surfaces, plots = load_record(expect_table(data.get("record", {}), "[record]", problems,
                                                  "<component> = [ports], surfaces, plots"), components, problems,
                                           declared)
    summary = _load_summary(data, components, declared, problems)
    if problems:
        raise SceneError(path, problems)
    worker_timeout = head["worker_timeout"]
    return Scene(path=path, name=head["name"], description=head["description"], duration=duration,
                 components=components, connections=connections, record=record, surfaces=surfaces, plots=plots,
                 summary=summary, hosting=head["hosting"], realtime=head["realtime"],
                 worker_timeout=None if worker_timeout is None else float(worker_timeout))


def _component_overrides(overrides: dict | None, problems: list[str]) -> dict:
    """The overrides (``--set``, studies) with the malformed keys reported and left out."""
    overrides = dict(overrides or {})
    for key in list(overrides):
        if not isinstance(key, str) or (key != "duration" and (key.count(".") != 1 or not all(key.split(".")))):
            problems.append(f"override {key!r}: write component.parameter (e.g. contact.stiffness) or scene.duration")
            overrides.pop(key)
    return overrides


def _load_head(data: dict, path: Path | None, overrides: dict, problems: list[str]) -> dict:
    """``[scene]`` with its overrides (taken out of ``overrides``): name, description, duration and
    where it was given, hosting, realtime, worker_timeout."""
    head = expect_table(data.get("scene", {}), "[scene]", problems, "name, description, duration, ...")
    unknown_keys(head, _SCENE_KEYS, "[scene]", problems)
    duration_where = "[scene] duration"
    for key in [k for k in overrides if k.startswith("scene.")]:
        field_name = key.split(".", 1)[1]
        if field_name not in _SCENE_KEYS:
            problems.append(f"override {key!r}: [scene] has no key {field_name!r}; valid keys: "
                            f"{', '.join(sorted(_SCENE_KEYS))}")
        elif field_name == "duration":
            duration_where = "scene.duration (override)"
        head = {**head, field_name: overrides.pop(key)}
    if "duration" in overrides:  # after scene.duration: `run --duration` wins over `--set scene.duration=`
        head = {**head, "duration": overrides.pop("duration")}
        duration_where = "duration (from the command line or a study)"
    name = head.get("name", path.stem if path else "scene")
    problem = scene_name_problem(name)
    if problem:
        where = "[scene] name" if "name" in head else f"[scene] name (taken from the file name {path.name!r})"
        problems.append(f"{where}: {problem}")
    description = head.get("description", "")
    if not isinstance(description, str):
        problems.append(f"[scene] description: must be a string (got {short_text(description)})")
    duration = parse_time(head.get("duration", 1.0), duration_where, problems)
    if head.get("start_time", 0) not in (0, 0.0) or isinstance(head.get("start_time"), bool):
        problems.append("[scene] start_time: only 0 is supported; shift your sources instead")
    hosting = head.get("hosting", DEFAULT_HOSTING)
    if hosting not in HOSTINGS:
        problems.append(f"[scene] hosting: {short_text(hosting)} is not one of {', '.join(HOSTINGS)}")
    realtime = head.get("realtime", False)
    if not isinstance(realtime, bool):
        problems.append(f"[scene] realtime: must be true or false (got {short_text(realtime)})")
    # How long a worker may take to answer one call; None: derived from its recent replies (worker.py).
    # A day bounds it: a longer wait is a hang, and 10**400 would not even convert to seconds.
    worker_timeout = head.get("worker_timeout")
    if worker_timeout is not None and (isinstance(worker_timeout, bool) or not isinstance(worker_timeout, (int, float))
                                       or not 0 < worker_timeout <= 86400):
        problems.append(f"[scene] worker_timeout: seconds a worker may take to answer, a number in (0, 86400] "
                        f"(got {short_text(worker_timeout)}); leave it out for the automatic max(10 s, 100 x slowest reply)")
        worker_timeout = None
    return {"name": name, "description": description, "duration": duration, "duration_where": duration_where,
            "hosting": hosting, "realtime": realtime, "worker_timeout": worker_timeout}


def _load_components(data: dict, base_dir: Path, overrides: dict, problems: list[str]) -> tuple[dict, set]:
    """The FMUs, sources and blocks (their overrides taken out of ``overrides``; any left is a
    problem), and the names declared, loaded or not."""
    components: dict[str, ComponentSpec] = {}
    sections = {section: expect_table(data.get(section, {}), section, problems, f"one [{section}.<name>] table each")
                for section in ("fmu", "source", "block")}
    declared = {name for table in sections.values() for name in table}
    for section, table in sections.items():
        for component in table:
            problem = component_name_problem(section, component)
            if problem:
                problems.append(problem)
    _load_fmus(sections["fmu"], base_dir, components, overrides, problems)
    _load_blocks(sections["source"], "source", base_dir, components, overrides, problems)
    _load_blocks(sections["block"], "block", base_dir, components, overrides, problems)
    for key in overrides:
        problems.append(f"override {key!r}: no such component parameter in the scene")
    if not components and not declared:
        problems.append("the scene has no [fmu.<name>] or [block.<name>]: nothing to simulate")
    return components, declared


def _load_summary(data: dict, components: dict, declared: set, problems: list[str]) -> dict:
    """``[summary]``: the ports whose peaks, energies and warnings a run's summary reports."""
    summary = expect_table(data.get("summary", {}), "[summary]", problems, "peaks, energy, warnings")
    unknown_keys(summary, _SUMMARY_KEYS, "[summary]", problems)
    for key in ("peaks", "energy", "warnings"):
        items = expect_list(summary.get(key, []), f"[summary] {key}", problems, 'of "component.port"')
        for i, item in enumerate(items):
            ref = parse_endpoint(item, f"[summary] {key}[{i}]", problems)
            if ref and (ref[0] not in components or ref[1] not in components[ref[0]].ports):
                if ref[0] not in declared or ref[0] in components:  # else: that component's problem is reported
                    problems.append(f"[summary] {key}[{i}]: {item!r} is not a port of the scene")
            elif ref and components[ref[0]].ports[ref[1]].type not in NUMERIC_TYPES:
                problems.append(f"[summary] {key}[{i}]: {item!r} is a {components[ref[0]].ports[ref[1]].type} variable; "
                                "the summary takes numbers, Booleans and enumerations")
    return summary


def _apply_overrides(name: str, parameters: dict, overrides: dict) -> dict:
    parameters = dict(parameters)
    for key in [k for k in overrides if k.split(".", 1)[0] == name]:
        parameters[key.split(".", 1)[1]] = overrides.pop(key)
    return parameters


def _load_fmus(tables: dict, base_dir: Path, components: dict, overrides: dict, problems: list[str]) -> None:
    for name, table in tables.items():
        where = f"[fmu.{name}]"
        if not isinstance(table, dict):
            problems.append(f"{where}: must be a table with path, step and parameters")
            continue
        unknown_keys(table, _FMU_KEYS, where, problems)
        if f"{name}.step" in overrides:  # "tissue.step" overrides the step, not a parameter
            table = {**table, "step": overrides.pop(f"{name}.step")}
        parameters = _apply_overrides(name, expect_table(table.get("parameters", {}), f"{where} parameters", problems,
                                                   f"[fmu.{name}.parameters] with name = value lines"), overrides)
        if "path" not in table:
            problems.append(f"{where}: no path; add path = \"Tissue.fmu\" (looked up next to the scene, then in fmus/)")
            continue
        if not isinstance(table["path"], str) or not table["path"].strip():
            problems.append(f"{where} path: must be the file name of an .fmu in quotes, e.g. path = \"Tissue.fmu\" "
                            f"(got {short_text(table['path'])})")
            continue
        try:
            fmu_path, tried = resolve_fmu_path(table["path"], base_dir)
        except (ValueError, OSError) as exc:  # a NUL byte, a name too long for the file system
            problems.append(f"{where} path: {short_text(table['path'])} is not a usable file name ({exc})")
            continue
        if fmu_path is None:
            problems.append(f"{where} path: {table['path']!r} not found (looked in {', '.join(str(t.parent) for t in tried)}); "
                            "build the FMUs with `python -m orchestration build`")
            continue
        # Array sizes follow the structural parameters: only plausible sizes go into the description
        # (a wrong one is reported by check_parameters, and must not make read_fmu build huge shapes).
        sizes = {k: v for k, v in parameters.items()
                 if isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= MAX_PORT_VALUES}
        try:
            description = read_fmu(fmu_path, sizes)
        except (OSError, ValueError) as exc:
            problems.append(f"{where} path: {exc}")
            continue
        # what a run loads into a process: a truncated binary passes the description and kills it
        binary = fmu_binary_problem(fmu_path, description.model_identifier, description.ports)
        if binary:
            problems.append(f"{where} path: {binary}")
            continue
        fixed = description.fixed_internal_step
        notes: list[str] = []
        step_value = table.get("step", description.default_step)
        if step_value is None and fixed is not None:
            step_value = format_time(fixed).strip('"')
        if step_value is None:
            problems.append(f"{where}: no step and the FMU declares no default step; add step = 0.001")
            continue
        step = parse_time(step_value, f"{where} step", problems)
        if step is not None and step_problem(step):
            problems.append(f"{where} step: {step_problem(step)}")
            step = None
        ports = description.ports
        for port in ports.values():
            if port.size > MAX_PORT_VALUES:
                problems.append(f"{where}: {port.name} would hold {port.size} values "
                                f"({'x'.join(map(str, port.shape))}), more than {MAX_PORT_VALUES} (a mesh far larger "
                                "than any this project runs): check the structural parameters that size it")
        if step is not None and "internal_step" in ports:
            # the project's FMUs: the scene's step is the model's own rate
            given = parameters.get("internal_step")
            number = isinstance(given, (int, float)) and not isinstance(given, bool) and is_finite_number(given)
            if given is not None and (not number or abs(float(given) - float(step)) > 1e-12 * float(step)):
                problems.append(f"{where} parameters.internal_step = {short_text(given)} differs from step = {step_value}; "
                                "remove the parameter (the master sets it from step)")
            parameters["internal_step"] = float(step)
        elif step is not None and fixed is not None and step % fixed != 0:
            # FMI 3.0 leaves such a step to the FMU (the standard's open issue 2156): it is passed on,
            # and the FMU accepts it (covering it as it can) or refuses it, which ends the run with its message
            below = step // fixed * fixed
            fixes = " or ".join(f"step = {format_time(s)}" for s in (below, below + fixed) if s > 0)
            internal = format_time(fixed).strip('"')
            notes.append(f"{where} step: {step_value} s is not a whole multiple of this FMU's fixed internal step "
                         f"{internal} s (fixedInternalStepSize); FMI 3.0 leaves such a step to the FMU, so it is "
                         f"passed on as it is: the FMU may cover it as it can or refuse it (then use {fixes})")
        parameters = _resolve_files(where, parameters, base_dir, problems)
        check_parameters(where, parameters, ports, problems)
        hosting = table.get("hosting")
        if hosting is not None and hosting not in HOSTINGS:
            problems.append(f"{where} hosting: {hosting!r} is not one of {', '.join(HOSTINGS)}")
        components[name] = ComponentSpec(name=name, kind="fmu", step=step, parameters=parameters, path=fmu_path,
                                         ports=ports, description=description, hosting=hosting, notes=notes)


def _resolve_files(where: str, parameters: dict, base_dir: Path, problems: list[str]) -> dict:
    """``name = { file = "wall.vtu" }``: a file beside the scene, passed to the FMU as its absolute path
    (an FMU resolves a relative path from the process's folder, which is not the scene's)."""
    resolved = dict(parameters)
    for key, value in parameters.items():
        if not isinstance(value, dict):
            continue
        if set(value) != {"file"} or not isinstance(value["file"], str) or not value["file"].strip():
            problems.append(f"{where} parameters.{key}: a table value names a file, {{ file = \"wall.vtu\" }} "
                            f"(relative to the scene's folder); got {short_text(value)}")
            continue
        path = (base_dir / value["file"]).resolve()
        if not path.is_file():
            problems.append(f"{where} parameters.{key}: the file {value['file']!r} is not in the scene's folder "
                            f"({base_dir}): write it there or give its path relative to the scene")
            continue
        resolved[key] = str(path)
    return resolved


def _load_blocks(tables: dict, section: str, base_dir: Path, components: dict, overrides: dict,
                 problems: list[str]) -> None:
    from orchestration.blocks.options import BlockConfigError
    from orchestration.blocks.registry import make_block

    for name, table in tables.items():
        where = f"[{section}.{name}]"
        if name in components:
            problems.append(f"{where}: the name {name!r} is used twice; component names must be unique")
            continue
        if not isinstance(table, dict):
            problems.append(f"{where}: must be a table with kind = ...")
            continue
        table = _apply_overrides(name, table, overrides)
        step = None
        if "step" in table:  # exact here; the block gets the float the master will step it with
            step = parse_time(table["step"], f"{where} step", problems)
            if step is not None and step_problem(step):
                problems.append(f"{where} step: {step_problem(step)}")
                step = None
            table = {**table, "step": float(step) if step is not None else 0.001}
        try:
            block = make_block(name, table, base_dir)
        except BlockConfigError as exc:
            problems.extend(f"{where} {p}" for p in exc.problems)
            continue
        continuous = not hasattr(block, "start_step")
        if section == "source" and not continuous:
            problems.append(f"{where}: kind {table.get('kind')!r} is stepped; declare it as [block.{name}]")
            continue
        if section == "block" and continuous:
            problems.append(f"{where}: kind {table.get('kind')!r} is a continuous source; declare it as [source.{name}]")
            continue
        if not continuous and step is None:
            if "step" in table:  # given and refused above
                continue
            step = parse_time(getattr(block, "step", None), f"{where} step", problems)
        components[name] = ComponentSpec(name=name, kind=str(table.get("kind")), step=step, table=table,
                                         ports=dict(block.ports), base_dir=base_dir)

"""Export a scene as one FMI 3.0 Co-Simulation FMU with scalar ports (``export SCENE --fmu OUT.fmu``).

For masters that cannot compose the project's FMUs themselves (no FMI 3 arrays, no Configuration
Mode, no multirate coupling: Ecos, the fmu-manipulation-toolbox's containers): the scene's
orchestrator runs inside the FMU (``src/scene_fmu``), exact. The FMU carries

- the scene (``scene.json``, the scene file as data) and its FMUs (``fmus/``, each without its own
  Python runtime: they run in the scene FMU's interpreter, which carries what they import);
- the orchestrator (``vendor/orchestration``, with the ``fmu_build`` paths it imports) and a Python
  runtime that carries what it imports (``fmpy`` among them) besides what the FMUs import;
- ``scene_fmu.json``: the ports. Each output of the scene's sources becomes a Float64 input (the
  operator's insertion and rotation, a probe's position: ``operator_insertion``, ``probe_position_0``
  ...); each port the scene records (or those ``outputs`` names) becomes scalar outputs
  (``contact_tool_force_0`` ...). The FMU's step is the scene's fastest.
"""
from __future__ import annotations

import json
import logging
import math
import os
import re
import secrets
import shutil
import tempfile
import tomllib
import zipfile
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

from fmu_build.errors import BuildError
from fmu_build.package import build_fmu_from_spec
from fmu_build.paths import REPO_ROOT, SRC
from fmu_build.specs import FmuSpec
from orchestration.scene.model import Scene

logger = logging.getLogger(__name__)

PACKAGE = "scene_fmu"
#: what the scene FMU's Python runtime must carry beyond the FMUs' packages: the orchestrator's imports
#: (and those FMPy makes inside its functions: lxml reads a model description)
RUNTIME_IMPORTS = ("fmpy", "fmpy.model_description", "lxml.etree", "orchestration.run.algorithm",
                   "orchestration.hosts.in_process", "orchestration.scene.loading", "orchestration.blocks.registry")
#: an array port with more values than this is no scalar output (a surface is not a signal)
MAX_PORT_VALUES = 64
#: simulated seconds a scene FMU may run by default (its importer's stop time must not pass it)
DEFAULT_HORIZON = Fraction(1800)
#: FMI types the scalar outputs take, by the type of the port they come from (others: Float64)
_OUTPUT_TYPES = {"Boolean": "Boolean", "Int8": "Int32", "UInt8": "Int32", "Int16": "Int32", "UInt16": "Int32",
                 "Int32": "Int32"}


class SceneFmuError(ValueError):
    """The scene cannot be exported as one FMU as asked; the message says why and the fix."""


@dataclass(frozen=True)
class Port:
    """One scalar port of the scene FMU and where its value comes from or goes."""

    name: str
    causality: str
    type: str
    unit: str | None
    description: str
    origin: str      # the source or component
    port: str        # its port
    index: int       # the value's index in the port's flat array
    start: float = 0.0

    def as_json(self) -> dict:
        entry = {"name": self.name, "causality": self.causality, "type": self.type, "unit": self.unit,
                 "description": self.description, "port": self.port, "index": self.index}
        entry["source" if self.causality == "input" else "component"] = self.origin
        if self.causality == "input":
            entry["start"] = self.start
        return entry


def _identifier(text: str) -> str:
    """``text`` as a variable name: letters, digits and underscores, not starting with a digit."""
    name = re.sub(r"\W", "_", text)
    return name if name and not name[0].isdigit() else f"_{name}"


def _scalar_names(base: str, size: int) -> list[str]:
    return [base] if size == 1 else [f"{base}_{i}" for i in range(size)]


def scene_inputs(scene: Scene) -> list[Port]:
    """A Float64 input per value of every output of the scene's sources (their start: the value at 0)."""
    ports = []
    for spec in scene.components.values():
        if not spec.is_continuous:
            continue
        block = spec.new_block()
        for name, info in block.ports.items():
            start = block.evaluate(0.0)[name]
            flat = [float(x) for x in (start.ravel() if hasattr(start, "ravel") else [start])]
            for i, scalar in enumerate(_scalar_names(_identifier(f"{spec.name}_{name}"), info.size)):
                where = f"{spec.name}.{name}" + (f"[{i}]" if info.size > 1 else "")
                ports.append(Port(scalar, "input", "Float64", info.unit,
                                  f"{where}: set before the step [t, t + h] to its value at t + h", spec.name, name,
                                  i, flat[i]))
    return ports


def scene_outputs(scene: Scene, names: list[str] | None = None) -> list[Port]:
    """Scalar outputs for ``names`` (``component.port``), by default every port the scene records."""
    chosen = names if names else [f"{c}.{p}" for c, ports in scene.record.items() for p in ports]
    if not chosen:
        raise SceneFmuError(f"{scene.name} records no port and no --outputs were given: name the outputs, e.g. "
                            "--outputs contact.tool_force,catheter.effort_warning")
    ports, problems = [], []
    for item in chosen:
        component, _, port = item.partition(".")
        spec = scene.components.get(component)
        info = spec.ports.get(port) if spec is not None and spec.is_fmu else None
        if info is None or info.causality not in ("output", "calculatedParameter"):
            fmus = ", ".join(c.name for c in scene.components.values() if c.is_fmu)
            problems.append(f"{item}: no output of an FMU of the scene (its FMUs: {fmus}); name it component.port")
            continue
        if info.size > MAX_PORT_VALUES:
            problems.append(f"{item} holds {info.size} values, more than the {MAX_PORT_VALUES} a scalar interface "
                            "carries: leave it out (--outputs) and record it with `python -m orchestration run`")
            continue
        kind = _OUTPUT_TYPES.get(info.type, "Float64")
        for i, scalar in enumerate(_scalar_names(_identifier(f"{component}_{port}"), info.size)):
            where = f"{item}" + (f"[{i}]" if info.size > 1 else "")
            text = f"{where}: {info.description}" if info.description else where
            ports.append(Port(scalar, "output", kind, info.unit, text, component, port, i))
    if problems:
        raise SceneFmuError("; ".join(problems))
    return ports


def _hyperperiod(scene: Scene) -> Fraction:
    """The least time that is a whole number of steps of every stepped component."""
    steps = [c.step for c in scene.components.values() if c.step is not None]
    numerator = math.lcm(*(s.numerator for s in steps))
    denominator = math.gcd(*(s.denominator for s in steps))
    return Fraction(numerator, denominator)


def _scene_data(scene: Scene) -> tuple[dict, Path]:
    """The scene file as data (what ``scene_from_dict`` reads), from its TOML or SSP package, and the
    folder its relative paths start from."""
    if scene.path is None:
        raise SceneFmuError("the scene has no file to export: load it from a .toml or .ssp file")
    if scene.path.suffix.lower() == ".ssp":
        from orchestration.scene.ssp import read_package

        package = read_package(scene.path)
        return package.data, package.base_dir
    return tomllib.loads(scene.path.read_text(encoding="utf-8")), scene.path.parent


def _carry_block_files(data: dict, base_dir: Path, package: Path) -> None:
    """Copy the files the scene's blocks read (a CSV source's ``path``) into ``files/`` of the package
    and point the scene at the copies (the scene FMU loads the scene relative to its package)."""
    for section in ("source", "block"):
        for name, table in data.get(section, {}).items():
            if isinstance(table, dict) and isinstance(table.get("path"), str):
                source = Path(table["path"]) if Path(table["path"]).is_absolute() else base_dir / table["path"]
                copy = Path("files") / f"{name}_{source.name}"
                (package / "files").mkdir(exist_ok=True)
                shutil.copyfile(source, package / copy)
                table["path"] = copy.as_posix()


def _without_runtime(fmu: Path, dest: Path) -> None:
    """A copy of ``fmu`` without its Python runtime: in the scene FMU it runs in that FMU's interpreter."""
    with zipfile.ZipFile(fmu) as source, zipfile.ZipFile(dest, "w", zipfile.ZIP_DEFLATED) as out:
        for item in source.infolist():
            if item.filename in ("resources/runtime.zip", "resources/runtime.id"):
                continue
            out.writestr(item, source.read(item.filename))


def export_scene_fmu(scene: Scene, out: Path | str, *, outputs: list[str] | None = None,
                     horizon: Fraction | None = None, overrides: dict | None = None, force: bool = False) -> Path:
    """Write ``scene`` as the FMU ``out`` (see the module documentation) and return its path.

    ``horizon``: the simulated seconds the FMU may run (default 30 minutes, or the scene's duration
    if longer), rounded up to a whole number of every component's steps. ``overrides``: the
    ``--set``/``--duration`` values the scene was loaded with, applied again inside the FMU.
    """
    out = Path(out)
    if out.suffix.lower() != ".fmu":
        raise SceneFmuError(f"{out}: an FMU's file name ends in .fmu; give e.g. {out.with_suffix('.fmu').name}")
    if not out.parent.is_dir():
        raise SceneFmuError(f"{out}: the folder {out.parent} does not exist; create it or write elsewhere")
    if out.exists() and not force:
        raise SceneFmuError(f"{out}: exists; give --force to replace it, or another file name")
    stepped = [c for c in scene.components.values() if c.step is not None]
    if not stepped:
        raise SceneFmuError(f"{scene.name} has no stepped component: nothing to run in an FMU")
    step = min(c.step for c in stepped)
    inputs, scalar_outputs = scene_inputs(scene), scene_outputs(scene, outputs)
    hyper = _hyperperiod(scene)
    wanted = Fraction(horizon) if horizon is not None else max(DEFAULT_HORIZON, scene.duration)
    horizon = math.ceil(wanted / hyper) * hyper
    names = [p.name for p in inputs + scalar_outputs]
    clash = sorted({n for n in names if names.count(n) > 1})
    if clash:
        raise SceneFmuError(f"two ports of the scene give the same scalar name {clash}: rename a component or port")
    model_identifier = _identifier(scene.name)
    with tempfile.TemporaryDirectory(prefix="scene_fmu_") as tmp:
        root = Path(tmp) / "source"
        package = root / PACKAGE
        shutil.copytree(SRC / PACKAGE, package, symlinks=False,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "scene_fmu.json", "fmus", "vendor"))
        for vendored in ("orchestration", "fmu_build"):  # the orchestrator imports the build's paths
            shutil.copytree(REPO_ROOT / vendored, package / "vendor" / vendored,
                            ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.so", "*.o"))
        (package / "fmus").mkdir()
        fmu_files = {}
        for spec in scene.components.values():
            if spec.is_fmu:
                fmu_files[spec.name] = f"{spec.name}.fmu"
                _without_runtime(spec.path, package / "fmus" / fmu_files[spec.name])
        data, base_dir = _scene_data(scene)
        _carry_block_files(data, base_dir, package)
        try:
            (package / "scene.json").write_text(json.dumps(data))
        except TypeError as exc:  # TOML dates and times: no scene value is one
            raise SceneFmuError(f"{scene.path}: a value the scene FMU cannot carry ({exc}); scenes hold numbers, "
                                "text, lists and tables") from None
        (package / "scene_fmu.json").write_text(json.dumps({
            "model_name": scene.name,
            "description": f"{scene.description} (the scene {scene.name} as one FMU: its orchestrator and FMUs "
                           "inside, scalar ports)",
            "step": str(step), "horizon": str(horizon), "stop_time": float(scene.duration),
            "overrides": {k: (str(v) if isinstance(v, Fraction) else v) for k, v in (overrides or {}).items()},
            "fmus": fmu_files,
            "inputs": [p.as_json() for p in inputs],
            "outputs": [p.as_json() for p in scalar_outputs],
        }, indent=1))
        spec = FmuSpec(model_identifier, PACKAGE, source_root=root, runtime_imports=RUNTIME_IMPORTS)
        built = build_fmu_from_spec(spec, Path(tmp) / "built")
        temporary = out.parent / f".{out.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"
        try:
            shutil.copyfile(built, temporary)
            temporary.replace(out)
        except OSError as exc:
            raise BuildError(f"{out}: cannot write the FMU ({exc.strerror or exc}); check the folder is writable "
                             "and has room") from None
        finally:
            temporary.unlink(missing_ok=True)
    logger.info("wrote %s: %d inputs, %d outputs, step %s s", out, len(inputs), len(scalar_outputs), step)
    return out

"""Run one FMI 3.0 Co-Simulation FMU in Ecos (https://github.com/Ecos-platform/ecos, ``ecospy`` 0.7.2),
an independent C++ FMI importer, and return what it saw: for tests that compare our numbers with
another master's.

    from ecos_host import ecos_available, run_in_ecos
    reason = ecos_available()            # None when usable, else why not (pytest.skip(reason))
    result = run_in_ecos(fmu, step=0.002, stop_time=0.1, parameters={"a": 3.0},
                         inputs={"u": lambda t: 2 * t}, outputs=["x", "steps"])
    result["time"], result["x"], result["steps"]   # numpy arrays, one sample per communication point
    result.log, result.fmu_messages              # Ecos's log text, the FMU's own log messages

How a run goes (``ecospy``'s calls, in a child process of its own):

- ``EcosSimulationStructure().add_model(instance, fmu, step_size_hint)`` then
  ``EcosSimulation(structure=ss, step_size=step)``: Ecos's fixed-step algorithm with the global step
  ``step``. ``component_step`` (Ecos's per-component ``step_size_hint``) makes Ecos step the FMU only
  every ``ceil(component_step / step)``-th global step, over that many global steps at once, from the
  *start* of its period: between its steps the FMU's outputs are those at the end of its current
  step, i.e. ahead of the global time (Ecos warns when ``component_step`` is not a whole multiple).
- Parameters and the inputs' first values (at t = 0) are set with ``set_real`` / ``set_integer`` /
  ``set_bool`` / ``set_string`` before ``sim.init()``: Ecos caches every set and passes it to the FMU
  in Initialization Mode (``fmi3EnterInitializationMode(start 0, no tolerance, no stop time)``).
- Samples: ``time`` = 0 and each output right after ``init()``, then after each ``sim.step()`` the
  time Ecos returns (its own sum of steps: ``t + step`` added up, so not exactly ``k * step``) and
  each output.
- Inputs are open loop: before the step k that goes from t_k = k * step (computed as that product,
  here) to t_k + step, each input is set to its value **at t_k** (a callable is called with t_k; a
  table of ``(time, value)`` rows gives the value of the last row with time <= t_k, a zero-order
  hold). Ecos passes the set to the FMU right before that ``fmi3DoStep`` (with ``component_step``:
  the FMU's ``fmi3DoStep`` from t_k sees the value at t_k; those set at the global steps where the
  FMU does not step reach it at the end of the global step, and are overwritten before its next).
- ``sim.terminate()`` (``fmi3Terminate``), then the simulation and structure are freed
  (``fmi3FreeInstance``).

What Ecos 0.7.2 does not do, hence what this harness refuses or checks itself:

- It ignores the fmi3Status of ``fmi3DoStep``/``fmi3Get*``/``fmi3Set*`` (an FMU that returns
  fmi3Error or fmi3Discard is stepped on, its outputs stale). The only trace is the FMU's own log
  message, which Ecos prints at its debug level as ``[instance] <Status> <message>``: a run whose FMU
  logged an Error or Fatal message raises :class:`EcosError`; the others are in ``fmu_messages``.
- It reads/writes all of an FMU's integer (resp. real) variables in one fmi3Get/Set call of the
  *first* one's type, into 32-bit int (resp. double) buffers: only Float64, Int32 and Boolean
  variables (and String parameters) come through intact, so only those are accepted. No arrays
  (``<Dimension>``), no Enumeration (skipped by Ecos), no Configuration Mode (no structural
  parameters), no event mode, no clocks.
- It runs the FMU in its own process (fmi4c, ``dlopen``) and unzips the FMU with the ``unzip``
  program into ``$TMPDIR`` (without ``unzip``: "Failed to unzip", then a segmentation fault). Ecos
  can run an FMU in a ``proxyfmu`` process instead (``proxyfmu://localhost?file=...``); not offered
  here: the wheel installs that executable without its execute bit, and that process drops the
  FMU's log messages, the only sign of an FMU error under Ecos.

Ecos is run in a child process (``python tests/ecos_host.py <spec.json>``): Ecos logs to the
process's stdout (spdlog), throws C++ exceptions through its C API on some errors (an abort) and
crashes on an FMU it failed to unpack; the child's output is the log, and any failure raises
:class:`EcosError` with that text. Nothing is pickled: the spec and the result are JSON files.
"""
from __future__ import annotations

import functools
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time as _time
import zipfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from xml.etree import ElementTree as ET

import numpy as np

__all__ = ["EcosError", "EcosResult", "ecos_available", "run_in_ecos"]

ECOS_VERSION = "0.7.2"
_KINDS = {"Float64": "real", "Int32": "integer", "Boolean": "bool", "String": "string"}
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
# Ecos's FMI 3 logger: log::debug("[" + instance + "] " + status + " " + message)
_FMU_LINE = re.compile(r"^\[[^\]]*\] \[ecos\] \[debug\] \[(?P<instance>[^\]]+)\] "
                       r"(?P<status>OK|Warning|Discard|Error|Fatal|Unknown) (?P<message>.*)$")
_ECOS_ERROR = re.compile(r"^\[[^\]]*\] \[ecos\] \[(error|critical)\] (?P<message>.*)$")


class EcosError(RuntimeError):
    """Ecos could not run the FMU, or the FMU reported an error; ``log`` holds Ecos's output."""

    def __init__(self, message: str, log: str = ""):
        super().__init__(f"{message}\n--- Ecos log ---\n{log.rstrip() or '(empty)'}" if log else message)
        self.log = log


class EcosResult(dict):
    """``time`` and each output (numpy arrays, sample 0 after initialization, then one per step);
    ``log``: Ecos's output; ``fmu_messages``: the FMU's log messages as (status, message);
    ``wall_time``: seconds the child process took; ``ecos_version``: e.g. ``"v0.7.2"``."""

    log: str
    fmu_messages: list[tuple[str, str]]
    wall_time: float
    ecos_version: str


@functools.lru_cache(maxsize=1)
def ecos_available() -> str | None:
    """None when Ecos can run here, else the reason (for ``pytest.skip``)."""
    import importlib.util
    if importlib.util.find_spec("ecospy") is None:
        return f"ecospy is not installed (pip install ecospy=={ECOS_VERSION}, or the `test` extra)"
    if not sys.platform.startswith("linux"):
        return f"this harness runs ecospy's Linux binaries only (platform {sys.platform})"
    if shutil.which("unzip") is None:
        return "Ecos unpacks FMUs with the `unzip` program, not found on PATH (apt-get install unzip)"
    # Load its library in a throwaway process (it links libtbb.so.12, from Debian's libtbb12).
    try:
        probe = subprocess.run([sys.executable, "-c", "import ecospy; print(ecospy.EcosLib.version())"],
                               capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        return "importing ecospy took more than 60 s"
    if probe.returncode != 0:
        text = (probe.stderr.strip().splitlines() or ["(no output)"])[-1]
        if "libtbb" in probe.stderr:
            return f"Ecos's library needs libtbb.so.12 (apt-get install libtbb12): {text}"
        return f"ecospy does not load: {text}"
    return None


# ---------------------------------------------------------------- the parent: checks and results

def _variables(fmu: Path) -> dict[str, dict]:
    """name -> {"type", "causality", "variability", "array"} from the FMU's modelDescription.xml."""
    try:
        with zipfile.ZipFile(fmu) as archive:
            root = ET.fromstring(archive.read("modelDescription.xml"))
    except (OSError, KeyError, zipfile.BadZipFile, ET.ParseError) as exc:
        raise EcosError(f"{fmu}: not a readable FMU ({exc})") from exc
    version = root.get("fmiVersion", "")
    if not version.startswith("3."):
        raise EcosError(f"{fmu}: fmiVersion {version!r}; this harness takes FMI 3.0 FMUs")
    if root.find("CoSimulation") is None:
        raise EcosError(f"{fmu}: no <CoSimulation> element; Ecos runs Co-Simulation FMUs only")
    found = {}
    model_variables = root.find("ModelVariables")
    for v in (model_variables if model_variables is not None else []):
        found[v.get("name")] = {"type": v.tag, "causality": v.get("causality", "local"),
                                "variability": v.get("variability", ""), "array": v.find("Dimension") is not None}
    return found


def _kind(fmu: Path, variables: dict, name: str, role: str) -> str:
    if name not in variables:
        raise EcosError(f"{fmu.name}: no variable named {name!r} (the {role})")
    v = variables[name]
    if role == "parameter" and v["causality"] == "structuralParameter":
        raise EcosError(f"{fmu.name}: {name!r} is a structural parameter; Ecos has no Configuration Mode")
    if v["array"]:
        raise EcosError(f"{fmu.name}: {name!r} is an array; Ecos 0.7.2 handles scalar variables only")
    kind = _KINDS.get(v["type"])
    if kind is None or (kind == "string" and role != "parameter"):
        article = "an" if v["type"][0] in "AEIOU" else "a"
        raise EcosError(f"{fmu.name}: {name!r} is {article} {v['type']}; through Ecos 0.7.2 only Float64, Int32 and "
                        "Boolean variables (and String parameters) come through intact")
    if role == "input" and v["causality"] != "input":
        raise EcosError(f"{fmu.name}: {name!r} has causality {v['causality']!r}, not an input")
    if role == "parameter":
        if v["causality"] in ("output", "independent", "calculatedParameter") or v["variability"] == "constant":
            raise EcosError(f"{fmu.name}: {name!r} ({v['causality']}, {v['variability'] or 'no variability'}) "
                            "cannot be set")
    return kind


def _coerce(kind: str, name: str, value):
    if kind == "real":
        return float(value)
    if kind == "bool":
        return bool(value)
    if kind == "string":
        return str(value)
    number = float(value) if not isinstance(value, (int, np.integer)) else int(value)
    if number != int(number) or not -2**31 <= int(number) < 2**31:
        raise EcosError(f"{name!r} is an Int32: {value!r} is not one")
    return int(number)


def _input_values(name: str, kind: str, source, times: list[float], step: float) -> list:
    if callable(source):
        return [_coerce(kind, name, source(t)) for t in times]
    rows = [(float(t), v) for t, v in source]
    if not rows or any(b[0] < a[0] for a, b in zip(rows, rows[1:])):
        raise EcosError(f"input {name!r}: a table needs (time, value) rows in increasing time")
    values, i = [], -1
    slack = 1e-9 * step
    for t in times:
        while i + 1 < len(rows) and rows[i + 1][0] <= t + slack:
            i += 1
        if i < 0:
            raise EcosError(f"input {name!r}: no row at or before t = {t}")
        values.append(_coerce(kind, name, rows[i][1]))
    return values


def run_in_ecos(fmu_path: str | os.PathLike, *, step: float, stop_time: float,
                outputs: Sequence[str],
                parameters: Mapping[str, float | int | bool | str] | None = None,
                inputs: Mapping[str, Callable[[float], float] | Sequence[tuple[float, float]]] | None = None,
                component_step: float | None = None, instance: str = "model", timeout: float = 300.0) -> EcosResult:
    """Run ``fmu_path`` in Ecos from 0 to ``stop_time`` in global steps of ``step`` (``stop_time`` must
    be a whole number of steps) and return ``time`` and each of ``outputs`` sampled after
    initialization and after each step (``round(stop_time / step) + 1`` samples).

    ``parameters``: variable name -> value, set before initialization. ``inputs``: input name ->
    a callable of time, or a table of ``(time, value)`` rows (zero-order hold); the value set before
    the step from t_k = k * step is the input's value at t_k (at t = 0 also before initialization).
    ``component_step``: Ecos's per-component step (``step_size_hint``). ``instance``: the name Ecos
    gives the FMU instance. Raises :class:`EcosError` naming the problem (with Ecos's log)."""
    fmu = Path(fmu_path).resolve()
    if not fmu.is_file():
        raise EcosError(f"no FMU at {fmu}")
    reason = ecos_available()
    if reason is not None:
        raise EcosError(f"Ecos is not usable here: {reason}")
    if not (step > 0 and math.isfinite(step) and stop_time > 0 and math.isfinite(stop_time)):
        raise EcosError(f"need step > 0 and stop_time > 0 (got step={step}, stop_time={stop_time})")
    n_steps = round(stop_time / step)
    if n_steps < 1 or abs(n_steps * step - stop_time) > 1e-9 * stop_time:
        raise EcosError(f"stop_time {stop_time} is not a whole number of steps of {step}")
    if component_step is not None and not (component_step > 0 and math.isfinite(component_step)):
        raise EcosError(f"component_step must be > 0 (got {component_step})")
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", instance):
        raise EcosError(f"instance name {instance!r}: letters, digits and underscores only")

    variables = _variables(fmu)
    params = [[name, kind, _coerce(kind, name, value)]
              for name, value in (parameters or {}).items()
              for kind in [_kind(fmu, variables, name, "parameter")]]
    times = [k * step for k in range(n_steps)]
    ins = [[name, kind, _input_values(name, kind, source, times, step)]
           for name, source in (inputs or {}).items()
           for kind in [_kind(fmu, variables, name, "input")]]
    outs = [[name, _kind(fmu, variables, name, "output")] for name in outputs]
    if not outs:
        raise EcosError("no outputs asked for")
    if "time" in outputs:
        raise EcosError("an output named 'time' would hide the result's sample times (result['time'], Ecos's)")

    with tempfile.TemporaryDirectory(prefix="ecos_run_") as tmp:
        folder = Path(tmp)
        spec = {"fmu": str(fmu), "instance": instance, "step": step, "n_steps": n_steps,
                "component_step": component_step, "parameters": params,
                "inputs": ins, "outputs": outs, "result": str(folder / "result.json")}
        (folder / "spec.json").write_text(json.dumps(spec))
        env = dict(os.environ, TMPDIR=str(folder), PYTHONUNBUFFERED="1")
        started = _time.perf_counter()
        try:
            child = subprocess.run([sys.executable, str(Path(__file__).resolve()), str(folder / "spec.json")],
                                   cwd=folder, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                   stdin=subprocess.DEVNULL, timeout=timeout)
        except subprocess.TimeoutExpired as exc:
            log = _text(exc.output)
            raise EcosError(f"Ecos did not finish {fmu.name} within {timeout} s (killed)", log) from None
        wall = _time.perf_counter() - started
        log = _text(child.stdout)
        if child.returncode != 0:
            how = (f"was killed by {signal.Signals(-child.returncode).name}" if child.returncode < 0
                   else f"exited with code {child.returncode}")
            raise EcosError(f"Ecos running {fmu.name} {how}", log)
        result_file = folder / "result.json"
        if not result_file.is_file():
            raise EcosError(f"Ecos running {fmu.name} wrote no result", log)
        data = json.loads(result_file.read_text())

    messages = [(m["status"], m["message"]) for line in log.splitlines()
                if (m := _FMU_LINE.match(line)) and m["instance"] == instance]
    failures = [f"{status} {message}" for status, message in messages if status in ("Error", "Fatal")]
    failures += [m["message"] for line in log.splitlines() if (m := _ECOS_ERROR.match(line))]
    if failures:
        raise EcosError(f"{fmu.name} in Ecos: " + "; ".join(failures), log)

    result = EcosResult(time=np.array(data["time"], dtype=np.float64))
    dtypes = {"real": np.float64, "integer": np.int64, "bool": np.bool_}
    for name, kind in outs:
        result[name] = np.array(data["outputs"][name], dtype=dtypes[kind])
    result.log = log
    result.fmu_messages = messages
    result.wall_time = wall
    result.ecos_version = data["version"]
    return result


def _text(raw: bytes | str | None) -> str:
    if raw is None:
        return ""
    text = raw.decode(errors="replace") if isinstance(raw, bytes) else raw
    return _ANSI.sub("", text)


# ---------------------------------------------------------------- the child: ecospy's calls

def _child(spec_path: str) -> None:
    from ecospy import EcosLib, EcosSimulation, EcosSimulationStructure

    spec = json.loads(Path(spec_path).read_text())
    EcosLib.set_log_level("debug")  # the FMU's log messages are Ecos debug lines
    name = spec["instance"]

    structure = EcosSimulationStructure()
    structure.add_model(name, spec["fmu"], spec["component_step"])
    sim = EcosSimulation(structure=structure, step_size=spec["step"])
    setters = {"real": sim.set_real, "integer": sim.set_integer, "bool": sim.set_bool, "string": sim.set_string}
    getters = {"real": sim.get_real, "integer": sim.get_integer, "bool": sim.get_bool}

    for variable, kind, value in spec["parameters"]:
        setters[kind](f"{name}::{variable}", value)
    for variable, kind, values in spec["inputs"]:
        setters[kind](f"{name}::{variable}", values[0])
    if not sim.init(0.0):
        raise RuntimeError(f"init failed: {EcosLib.get_last_error()}")

    times = [sim.get_time()]
    samples = {variable: [getters[kind](f"{name}::{variable}")] for variable, kind in spec["outputs"]}
    for k in range(spec["n_steps"]):
        for variable, kind, values in spec["inputs"]:
            setters[kind](f"{name}::{variable}", values[k])
        times.append(sim.step())
        for variable, kind in spec["outputs"]:
            samples[variable].append(getters[kind](f"{name}::{variable}"))
    sim.terminate()
    sim.free()
    structure.free()
    Path(spec["result"]).write_text(json.dumps({"time": times, "outputs": samples,
                                                "version": repr(EcosLib.version())}))


if __name__ == "__main__":
    _child(sys.argv[1])

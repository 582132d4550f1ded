"""Scripted FMI call sequences in fresh host processes, for the fuzzers (tests/test_fuzz_*.py).

Two hosts speak one line protocol (documented in tests/c_host/fmu_host.c, ``--serve``): the C
importer (no Python in it) and this file run as a script, which makes the same calls through
FMPy's low-level API (its ctypes functions, statuses as they are). :class:`ScriptHost` keeps one
such process per FMU and host and sends it one case (a list of commands) at a time; each case
makes and frees its own instance. A process that dies by a signal or hangs is reported with the
case and the command it died in (:class:`HostCrashed`), and the next case starts a fresh process;
every ``cases_per_process`` cases a fresh process starts anyway, so an effect of one case on the
next stays bounded.

    python tests/fuzz_hosts.py FMU WORKDIR      # the FMPy host, commands on stdin
"""
from __future__ import annotations

import ctypes
import os
import select
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote, unquote

HOST_SOURCE = Path(__file__).resolve().parent / "c_host" / "fmu_host.c"
INCLUDE = Path(__file__).resolve().parent.parent / "src" / "fmi3_layer" / "include"

OK, WARNING, DISCARD, ERROR, FATAL = range(5)


def encode_string(text: str) -> str:
    """A String value as one protocol token ("%" alone is the empty string)."""
    return quote(text, safe="-_.~/") or "%"


def decode_string(token: str) -> str:
    return "" if token == "%" else unquote(token)


def compile_c_host(dest: Path) -> Path:
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        raise RuntimeError("no C compiler on PATH: the C host is compiled at test time (apt-get install gcc)")
    binary = Path(dest) / "fmu_host"
    subprocess.run([compiler, "-O1", "-Wall", f"-I{INCLUDE}", str(HOST_SOURCE), "-o", str(binary), "-ldl", "-lz"],
                   check=True, capture_output=True, text=True)
    return binary


@dataclass
class Answer:
    """One call's outcome: the status it returned, its values (a get) and what the FMU logged during it."""

    command: str
    status: int
    values: list = field(default_factory=list)
    logs: list = field(default_factory=list)  # (status, message)

    def __repr__(self):  # commands carry thousands of values: keep failure reports readable
        command = self.command if len(self.command) < 160 else self.command[:160] + "..."
        return f"Answer({command!r}, status={self.status}, values={self.values[:6]}, logs={self.logs})"


class HostCrashed(AssertionError):
    """The host process died by a signal, exited early or hung during a case."""


#: The suffix of a host kind whose FMU runs its model in the FMU's helper process ("c-helper"),
#: not in the host's own process (src/fmi3_layer/remote.h).
HELPER = "-helper"


class ScriptHost:
    """One FMU in a host process ("fmpy" or "c"; "fmpy-helper", "c-helper": the model in the FMU's
    helper process) that runs cases of commands."""

    def __init__(self, kind: str, fmu: Path, work: Path, c_host: Path | None = None, cases_per_process: int = 10,
                 call_timeout: float = 120.0):
        self.kind, self.fmu, self.work, self.c_host = kind, Path(fmu), Path(work), c_host
        self.cases_per_process, self.call_timeout = cases_per_process, call_timeout
        self.process: subprocess.Popen | None = None
        self.cases_in_process = 0
        self.processes_started = 0
        self.cases_run = 0

    def _start(self) -> None:
        self.work.mkdir(parents=True, exist_ok=True)
        folder = self.folder = self.work / f"{self.kind}{self.processes_started}"
        if self.kind.removesuffix(HELPER) == "c":
            command = [str(self.c_host), "--serve", str(self.fmu), str(folder)]
            env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "LD_PRELOAD")}
        else:
            command = [sys.executable, str(Path(__file__).resolve()), str(self.fmu), str(folder)]
            env = dict(os.environ)
        env["AAA_COSIM_MODEL_PROCESS"] = "helper" if self.kind.endswith(HELPER) else "importer"
        self.stderr_path = self.work / f"{self.kind}{self.processes_started}.stderr"
        self.process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        stderr=open(self.stderr_path, "wb"), env=env, bufsize=0)
        self.processes_started += 1
        self.cases_in_process = 0

    def _readline(self, deadline: float) -> bytes:
        out = self.process.stdout
        while True:
            ready, _, _ = select.select([out], [], [], max(0.0, deadline - time.monotonic()))
            if not ready:
                return b""
            return out.readline()

    def run(self, commands: list[str]) -> list[Answer]:
        if self.process is None or self.process.poll() is not None or self.cases_in_process >= self.cases_per_process:
            self.close()
            self._start()
        self.cases_in_process += 1
        self.cases_run += 1
        answers = []
        for command in commands:
            self.process.stdin.write((command + "\n").encode())
            logs = []
            deadline = time.monotonic() + self.call_timeout
            while True:
                line = self._readline(deadline).decode(errors="replace").rstrip("\n")
                if not line:
                    self._fail(commands, command, answers)
                if line.startswith("L "):
                    status, _, message = line[2:].partition(" ")
                    logs.append((int(status), message))
                    continue
                if line.startswith("R "):
                    tokens = line[2:].split(" ")
                    answers.append(Answer(command, int(tokens[0]), tokens[1:], logs))
                    break
        return answers

    def _fail(self, commands, command, answers):
        """The process is gone or silent: report how, with the case, and start afresh next time."""
        process, self.process = self.process, None
        try:
            code = process.wait(timeout=2)
            how = f"killed by signal {-code}" if code < 0 else f"exited with status {code}"
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
            how = f"hung for more than {self.call_timeout:g} s"
        stderr = self.stderr_path.read_text(errors="replace")[-3000:]
        short = [c if len(c) < 160 else c[:160] + "..." for c in commands]
        raise HostCrashed(f"the {self.kind} host {how} in {short[len(answers)]!r} (call {len(answers) + 1} of the "
                          f"case)\ncase: {short}\nstderr: {stderr}")

    def close(self) -> None:
        if self.process is not None:
            process, self.process = self.process, None
            try:
                process.stdin.write(b"quit\n")
                process.stdin.close()
                code = process.wait(timeout=60)
            except (BrokenPipeError, subprocess.TimeoutExpired):
                process.kill()
                code = process.wait()
            # the extracted FMU (the size of the FMU: its runtime is in it) is not needed any more
            shutil.rmtree(self.folder, ignore_errors=True)
            if code != 0:
                raise HostCrashed(f"the {self.kind} host exited with {code} at the end of its cases: "
                                  f"{self.stderr_path.read_text(errors='replace')[-2000:]}")


# ---- the FMPy host (this file run as a script) --------------------------------------------------------
def serve_fmpy(fmu_path: str, work: str) -> None:
    from fmpy import extract, read_model_description
    from fmpy.fmi3 import (FMU3Slave, fmi3Boolean, fmi3Byte, fmi3Float64, fmi3FMUState, fmi3Int32, fmi3String,
                           fmi3UInt64, fmi3ValueReference)

    md = read_model_description(fmu_path)
    unzipdir = extract(fmu_path, work)
    slave = FMU3Slave(guid=md.guid, unzipDirectory=unzipdir, modelIdentifier=md.coSimulation.modelIdentifier,
                      instanceName="fuzz")
    raw = slave._functions  # FMPy's ctypes functions: the statuses as returned, no exceptions
    out = sys.stdout

    def log(env, status, category, message):
        text = message.decode(errors="replace") if isinstance(message, bytes) else str(message)
        out.write(f"L {int(status)} {' '.join(text.splitlines())}\n")

    types = {"f64": fmi3Float64, "i32": fmi3Int32, "u64": fmi3UInt64, "bool": fmi3Boolean, "str": fmi3String}
    names = {"f64": "Float64", "i32": "Int32", "u64": "UInt64", "bool": "Boolean", "str": "String"}
    parse = {"f64": float, "i32": int, "u64": int, "bool": lambda x: bool(int(x)),
             "str": lambda x: decode_string(x).encode()}
    live = False
    state = fmi3FMUState()
    for line in sys.stdin:
        tokens = line.split()
        if not tokens:
            continue
        command, args = tokens[0], tokens[1:]
        if command == "quit":
            break
        values = []
        if command == "instantiate":
            if not live:
                try:
                    slave.instantiate(loggingOn=True, logMessage=log)
                    live = True
                except Exception:
                    live = False
            status = OK if live else ERROR
        elif not live:
            out.write("R -1 no instance\n")
            out.flush()
            continue
        elif command == "free":
            if state:
                raw["fmi3FreeFMUState"](slave.component, ctypes.byref(state))
            raw["fmi3FreeInstance"](slave.component)
            live, status = False, OK
        elif command == "enter_init":
            status = raw["fmi3EnterInitializationMode"](slave.component, False, 0.0, 0.0, False, 0.0)
        elif command in ("exit_init", "enter_config", "exit_config", "terminate", "reset"):
            function = {"exit_init": "fmi3ExitInitializationMode", "enter_config": "fmi3EnterConfigurationMode",
                        "exit_config": "fmi3ExitConfigurationMode", "terminate": "fmi3Terminate",
                        "reset": "fmi3Reset"}[command]
            status = raw[function](slave.component)
        elif command == "step":
            flags = [fmi3Boolean(), fmi3Boolean(), fmi3Boolean()]
            last = fmi3Float64(-1.0)
            status = raw["fmi3DoStep"](slave.component, float(args[0]), float(args[1]), True,
                                       *[ctypes.byref(f) for f in flags], ctypes.byref(last))
            values = [repr(last.value)]
        elif command == "get_state":
            status = raw["fmi3GetFMUState"](slave.component, ctypes.byref(state))
        elif command == "set_state":
            status = raw["fmi3SetFMUState"](slave.component, state)  # NULL when none is saved: refused
        elif command == "free_state":
            status = raw["fmi3FreeFMUState"](slave.component, ctypes.byref(state))
        elif command == "roundtrip_state":
            size = ctypes.c_size_t()
            status = raw["fmi3SerializedFMUStateSize"](slave.component, state, ctypes.byref(size))
            if status == OK:
                data = (fmi3Byte * size.value)()
                status = raw["fmi3SerializeFMUState"](slave.component, state, data, size.value)
                if status == OK:
                    status = raw["fmi3FreeFMUState"](slave.component, ctypes.byref(state))
                if status == OK:
                    status = raw["fmi3DeserializeFMUState"](slave.component, data, size.value, ctypes.byref(state))
        elif command == "stale_state":  # a copied handle used after its state was freed: refused alike
            fresh = fmi3FMUState()
            status = raw["fmi3GetFMUState"](slave.component, ctypes.byref(fresh))
            copy = fmi3FMUState(fresh.value)
            if status == OK:
                status = raw["fmi3FreeFMUState"](slave.component, ctypes.byref(fresh))
            if status == OK:
                refused = raw["fmi3SetFMUState"](slave.component, copy)
                status = refused if refused == raw["fmi3FreeFMUState"](slave.component, ctypes.byref(copy)) else 99
        elif command == "damaged_state":  # serialized bytes with one bit flipped: refused
            fresh, restored, size = fmi3FMUState(), fmi3FMUState(), ctypes.c_size_t()
            status = raw["fmi3GetFMUState"](slave.component, ctypes.byref(fresh))
            if status == OK:
                status = raw["fmi3SerializedFMUStateSize"](slave.component, fresh, ctypes.byref(size))
            if status == OK:
                data = (fmi3Byte * size.value)()
                status = raw["fmi3SerializeFMUState"](slave.component, fresh, data, size.value)
                if status == OK:
                    data[size.value // 2] ^= 0x10
                    status = raw["fmi3DeserializeFMUState"](slave.component, data, size.value, ctypes.byref(restored))
                    if restored:
                        raw["fmi3FreeFMUState"](slave.component, ctypes.byref(restored))
            if fresh:
                raw["fmi3FreeFMUState"](slave.component, ctypes.byref(fresh))
        elif command in ("set", "get"):
            kind, n, refs = args[0], int(args[1]), [int(r) for r in args[2].split(",")] if len(args) > 2 else []
            vrs = (fmi3ValueReference * len(refs))(*refs)
            buffer = (types[kind] * max(n, 1))()
            if command == "set":
                for k, token in enumerate(args[3:3 + max(n, 1)]):
                    buffer[k] = parse[kind](token)
                if kind == "str":
                    for k in range(len(args[3:]), max(n, 1)):
                        buffer[k] = b""  # never a NULL pointer
            function = raw[f"fmi3{'Set' if command == 'set' else 'Get'}{names[kind]}"]
            status = function(slave.component, vrs, len(refs), buffer, n)
            if command == "get" and status <= WARNING:
                if kind == "str":
                    values = [encode_string((buffer[k] or b"").decode(errors="replace")) for k in range(n)]
                elif kind == "f64":
                    values = [repr(float(buffer[k])) for k in range(n)]
                else:
                    values = [str(int(buffer[k])) for k in range(n)]
        else:
            raise SystemExit(f"unknown command {command!r}")
        out.write(" ".join(["R", str(status), *values]) + "\n")
        out.flush()
    if live:
        if state:
            raw["fmi3FreeFMUState"](slave.component, ctypes.byref(state))
        raw["fmi3FreeInstance"](slave.component)
    slave.freeLibrary()


if __name__ == "__main__":
    serve_fmpy(sys.argv[1], sys.argv[2])


# ---- the FMUs as the fuzzers drive them ------------------------------------------------------------------
@dataclass(frozen=True)
class Port:
    name: str
    vr: int
    type: str  # f64, i32, u64, bool, str
    causality: str
    variability: str
    size: int
    minimum: float | None
    maximum: float | None
    start: str | None  # as the model description gives it


PROTOCOL_TYPES = {"Float64": "f64", "Int32": "i32", "UInt64": "u64", "Boolean": "bool", "String": "str"}


def ports(fmu: Path, structural: dict | None = None) -> dict[str, Port]:
    """Every variable of ``fmu`` with its value reference, protocol type and size (the dimensions'
    start values, or the values in ``structural``)."""
    from fmpy import read_model_description

    md = read_model_description(str(fmu))
    by_name = {v.name: v for v in md.modelVariables}
    sizes = {name: int(v.start) for name, v in by_name.items() if v.causality == "structuralParameter"}
    sizes.update(structural or {})
    result = {}
    for v in md.modelVariables:
        size = 1
        for d in v.dimensions:
            size *= int(d.start) if d.start is not None else sizes[d.variable.name]
        result[v.name] = Port(v.name, v.valueReference, PROTOCOL_TYPES[v.type], v.causality, v.variability, size,
                              float(v.min) if v.min is not None else None,
                              float(v.max) if v.max is not None else None, v.start)
    return result


def set_command(port: Port, values) -> str:
    values = list(values) if isinstance(values, (list, tuple)) else [values] * port.size
    tokens = [encode_string(str(x)) if port.type == "str" else repr(x) if port.type == "f64" else str(int(x))
              for x in values]
    return f"set {port.type} {len(tokens)} {port.vr} {' '.join(tokens)}"


def get_command(port: Port) -> str:
    return f"get {port.type} {port.size} {port.vr}"


#: A coarse AAA wall for the Tissue cases (192 tets: a case costs milliseconds, not seconds); the
#: structural sizes it needs are set in Configuration Mode, as the standard asks.
TISSUE_COARSE = {"n_circumferential": 8, "n_axial": 4, "n_radial": 1}
TISSUE_COARSE_SIZES = {"n_surface_nodes": 80, "n_surface_triangles": 160}


@dataclass(frozen=True)
class PlainRun:
    """A legal run of one FMU: configuration and parameters, then steps under inputs, then outputs."""

    step: float
    steps: int
    structural: dict  # name -> value, set in Configuration Mode
    parameters: dict  # name -> value, set in Instantiated
    inputs: dict  # name -> value per element (scaled by 1 + k/100 at step k)
    outputs: tuple

    def configure(self, p: dict[str, Port]) -> list[str]:
        if not self.structural:
            return []
        return (["enter_config"] + [set_command(p[n], v) for n, v in self.structural.items()] + ["exit_config"])

    def setup(self, p: dict[str, Port]) -> list[str]:
        return [set_command(p[n], v) for n, v in self.parameters.items()]

    def step_commands(self, p: dict[str, Port], k: int) -> list[str]:
        scale = 1 + k / 100
        commands = [set_command(p[n], [x * scale for x in v] if isinstance(v, (list, tuple)) else v * scale)
                    for n, v in self.inputs.items()]
        return commands + [f"step {k * self.step!r} {self.step!r}"]

    def read(self, p: dict[str, Port]) -> list[str]:
        return [get_command(p[n]) for n in self.outputs]


#: The legal runs the fuzzers build their cases on, per FMU: what makes a run of it do something
#: (a contact, a bent tip, a deformed wall). An FMU without one gets :func:`default_plain_run`.
PLAIN_RUNS = {
    "Catheter": PlainRun(0.001, 6, {}, {"controller_mode": "regulate"}, {"insertion": 0.01, "tip_force": 0.2},
                         ("tip_position", "bend_angle", "total_bend", "actuator_command", "tip_force_magnitude")),
    # a probe point pressed into the default wall's sac (as tests/test_fmi_layer.py's state cases)
    "Contact": PlainRun(0.001, 5, {"n_tool_points": 1}, {"tool": "probe", "tool_radius": 0.0},
                        {"tool_positions": [0.0252, 0.0, 0.065]}, ("tool_force", "tip_force", "penetration_depth",
                                                     "contact_energy")),
    "Tissue": PlainRun(1.0 / 30.0, 2, TISSUE_COARSE_SIZES, TISSUE_COARSE, {"contact_force": 2e-3},
                       ("strain_energy", "kinetic_energy", "max_strain", "surface_positions")),
}


def default_plain_run(fmu: Path) -> PlainRun:
    """A legal run of any FMU, made from what its model description declares: three steps of its
    fixed internal step (else its default experiment's step), its start values (no parameter, no
    structural parameter and no input set) and every Float64 output read at the end."""
    from fmpy import read_model_description

    md = read_model_description(str(fmu))
    step = md.coSimulation.fixedInternalStepSize or (md.defaultExperiment and md.defaultExperiment.stepSize)
    if step is None:
        raise ValueError(f"{fmu} declares no fixed internal step and no default step: give it a PlainRun")
    outputs = tuple(q.name for q in ports(fmu).values() if q.causality == "output" and q.type == "f64")
    return PlainRun(float(step), 3, {}, {}, {}, outputs)


def plain_run(name: str, fmu: Path) -> PlainRun:
    """The plain run of the FMU ``name`` (the .fmu at ``fmu``): PLAIN_RUNS's, else the default one."""
    return PLAIN_RUNS[name] if name in PLAIN_RUNS else default_plain_run(fmu)

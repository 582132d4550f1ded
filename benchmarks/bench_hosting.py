"""Per-step cost of hosting an FMU: raw in-process ctypes vs worker process vs FMPy's list API.

Scenario "Contact": the 1 kHz haptic step of the real Contact FMU with a moving catheter piece
(31 points) that touches the default AAA wall about half of the time. Per step the host sets
``tool_positions`` (93 values), calls fmi3DoStep and reads every output the master would
observe (``tissue_contact_force`` is 8064 values, plus the tool/tip forces and 4 scalars).

* ``InProcessFmu``: raw ctypes calls with preallocated buffers (orchestration/hosting.py);
* ``WorkerFmu``: the same in a worker process, pipe + shared memory (orchestration/worker.py);
* ``FMPy lists``: FMPy's ``setFloat64``/``doStep``/``getFloat64``/``getInt32``, which build lists.

Scenario "Signal": a trivial FMU (a polynomial of time, 4 outputs), so the worker's per-step
round-trip overhead (pipe + wake-ups + shared memory copies) stands out: it is the difference
between the worker and the in-process medians.

The variants run interleaved in rounds, so a busy shared machine slows them alike.
Run: .venv/bin/python benchmarks/bench_hosting.py
"""
from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from fmu_build.specs import FmuSpec
from fmu_build.package import build_fmu, build_fmu_from_spec
from orchestration.hosts.in_process import InProcessFmu
from orchestration.hosts.description import read_fmu
from orchestration.hosts.worker import WorkerFmu

REPO = Path(__file__).resolve().parent.parent
CONTACT_OUTPUTS = ["tool_force", "tip_force", "tissue_contact_force", "penetration_depth", "contact_energy",
                   "passivity_energy", "contact_count"]
DT = 0.001
ROUNDS = 5
STEPS_PER_ROUND = 400


def tool(k: int, n: int = 31) -> np.ndarray:
    x = 0.016 + 0.010 * np.sin(np.pi * (k % 400) / 200)  # in and out of the sac wall
    z = np.linspace(0.060, 0.070, n)
    return np.column_stack([np.full(n, x), np.zeros(n), z]).ravel()


class FmpyListHost:
    """The plain FMPy way: list-building setters and getters."""

    def __init__(self, path: Path):
        from fmpy import extract
        from fmpy.fmi3 import FMU3Slave

        self.desc = read_fmu(path)
        self.dir = extract(str(path), tempfile.mkdtemp(prefix="bench_fmpy_"))
        self.slave = FMU3Slave(guid=self.desc.instantiation_token, unzipDirectory=self.dir,
                               modelIdentifier=self.desc.model_identifier, instanceName="fmpy")
        self.slave.instantiate(loggingOn=False, logMessage=lambda *a: None)
        self.slave.enterInitializationMode()
        self.slave.exitInitializationMode()

    def step(self, t: float, inputs: dict[str, np.ndarray], observed: list[str]) -> dict[str, np.ndarray]:
        ports = self.desc.ports
        for name, value in inputs.items():
            self.slave.setFloat64([ports[name].value_reference], value.tolist())
        self.slave.doStep(t, DT)
        out = {}
        for name in observed:
            port = ports[name]
            getter = self.slave.getInt32 if port.type == "Int32" else self.slave.getFloat64
            out[name] = np.array(getter([port.value_reference], nValues=port.size), dtype=np.float64)
        return out

    def close(self) -> None:
        self.slave.terminate()
        self.slave.freeInstance()
        shutil.rmtree(self.dir, ignore_errors=True)


def start_host(host, inputs, observed, initial, values):
    host.instantiate()
    host.set_values(values)
    host.enter_initialization(0.0)
    host.configure(inputs, observed)
    if initial:
        host.set_inputs(initial)
    host.exit_initialization()
    return host


def time_steps(step, first: int, count: int) -> np.ndarray:
    times = np.empty(count)
    for i in range(count):
        k = first + i
        t0 = time.perf_counter()
        step(k)
        times[i] = time.perf_counter() - t0
    return times


def run(fmu: Path, inputs_of, observed: list[str], with_fmpy: bool, values: dict | None = None
        ) -> dict[str, np.ndarray]:
    desc = read_fmu(fmu)
    input_names = list(inputs_of(0))
    hosts = {
        "InProcessFmu": start_host(InProcessFmu("bench", desc), input_names, observed, inputs_of(0), values or {}),
        "WorkerFmu": start_host(WorkerFmu("bench", desc), input_names, observed, inputs_of(0), values or {}),
    }
    steppers = {}
    for label, host in hosts.items():
        def step(k, host=host):
            host.start_step(k * DT, DT, inputs_of(k))
            return host.finish_step()
        steppers[label] = step
    fmpy_host = None
    if with_fmpy:
        fmpy_host = FmpyListHost(fmu)
        steppers["FMPy lists"] = lambda k: fmpy_host.step(k * DT, inputs_of(k), observed)
    samples = {label: [] for label in steppers}
    try:
        for label, step in steppers.items():  # warm-up (numba caches, first contacts)
            time_steps(step, 0, 20)
        for r in range(ROUNDS):
            for label, step in steppers.items():
                samples[label].append(time_steps(step, 20 + r * STEPS_PER_ROUND, STEPS_PER_ROUND))
    finally:
        for host in hosts.values():
            host.terminate()
        if fmpy_host is not None:
            fmpy_host.close()
    return {label: np.concatenate(s) for label, s in samples.items()}


def report(title: str, samples: dict[str, np.ndarray]) -> float:
    print(f"\n{title}: per-step wall time over {ROUNDS * STEPS_PER_ROUND} steps (us)")
    base = float(np.median(samples["InProcessFmu"]))
    print(f"  {'host':<14}{'median':>10}{'p99':>10}{'vs InProcessFmu':>18}")
    for label, t in samples.items():
        median, p99 = np.median(t) * 1e6, np.percentile(t, 99) * 1e6
        print(f"  {label:<14}{median:10.1f}{p99:10.1f}{median / (base * 1e6):17.2f}x")
    return (float(np.median(samples["WorkerFmu"])) - base) * 1e6


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="bench_hosting_") as tmp:
        contact = build_fmu("Contact", Path(tmp))
        signal = build_fmu_from_spec(FmuSpec("Signal", "synthetic_fmu", "fmu:SIGNAL",
                                             source_root=REPO / "tests" / "synthetic"), Path(tmp))
        contact_samples = run(contact, lambda k: {"tool_positions": tool(k)}, CONTACT_OUTPUTS, with_fmpy=True)
        signal_samples = run(signal, lambda k: {}, ["y", "y3", "count", "odd"], with_fmpy=False,
                             values={"internal_step": DT})
    overhead_contact = report("Contact (93 inputs, 8073 observed values)", contact_samples)
    overhead_signal = report("Signal (trivial FMU, 6 observed values)", signal_samples)
    print(f"\nworker round-trip overhead per step (worker median - in-process median): "
          f"{overhead_signal:.1f} us (Signal), {overhead_contact:.1f} us (Contact)")
    fmpy = np.median(contact_samples["FMPy lists"]) / np.median(contact_samples["InProcessFmu"])
    print(f"FMPy list API / raw InProcessFmu on Contact: {fmpy:.2f}x")


if __name__ == "__main__":
    main()

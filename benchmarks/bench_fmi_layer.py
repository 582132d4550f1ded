"""Cost of the FMI layer per 1 kHz component step: the FMU's step minus the same model step called directly.

Contact: one FMU step as the orchestrator makes it: set the Contact inputs (the 31-point catheter
centerline, 93 values), ``fmi3DoStep``, get the observed outputs (tool and tip force, penetration,
energies: 9 Float64 values, plus the 8064-value tissue contact force and the Int32 contact
count). The direct loop calls ``ContactModel.step`` with the same inputs and copies the same
outputs. Both run the same catheter path (pressing the tip into the default AAA wall).

Catheter: set insertion, rotation and the tip force (5 values), ``fmi3DoStep``, get the Float64
outputs (centerline 93 values, tip position, bend angle, command, advice, force magnitude, total
bend: 101 values) and the Boolean warning; the direct loop calls ``CatheterModel.step`` and copies
the same outputs. Both push the catheter in while a tip force swings.

Each FMU runs twice: with its model in this process (the importer's, as the orchestrator and
FMPy in the project's environment run it) and in the FMU's helper process (as any importer whose
Python lacks the model's packages runs it: src/fmi3_layer/remote.h; each FMI call a round trip
over shared memory).

The FMUs are called through their raw C functions (FMPy's ctypes bindings, the importer's own
cost included) on preallocated numpy buffers; the two FMU instances and the direct steps alternate
in blocks in one process so that machine noise hits all alike, and each reports the median of its
steps. The FMI cost is the difference of the medians; the last step's outputs must agree to the bit.

Targets: FMI cost <= 10 us per step with the model in the importer's process, <= 20 us per Contact
step through the helper process.

Run: .venv/bin/python benchmarks/bench_fmi_layer.py
"""
from __future__ import annotations

import ctypes
import os
import tempfile
import time

import numpy as np

# imported first: the host's own copies (the FMUs import theirs under other names)
from catheter_fmu.model import CatheterModel, CatheterParameters
from haptic_fmu.model import ContactModel, ContactParameters
from fmu_build.paths import DEFAULT_FMU_DIR
from fmu_build.package import build_fmu, fmu_is_stale
from tissue_fmu.mesh import aaa_mesh

DT = 1e-3
BLOCK = 500
BLOCKS = 12
CLOCK = time.perf_counter_ns


def catheter_path(k: int) -> np.ndarray:
    """31 points up the aorta; the tip bends into the sac wall and presses in and out."""
    s = np.linspace(0.0, 1.0, 31)
    t = k * DT
    z = 0.02 + s * 0.045
    x = (0.0236 + 0.0008 * np.sin(2 * np.pi * 0.5 * t)) * np.clip((s - 0.6) / 0.4, 0, None) ** 2
    return np.stack([x, np.zeros_like(s), z], axis=1)


def catheter_inputs(k: int) -> np.ndarray:
    """insertion (m), rotation (rad), tip force (N): pushed in while the tip force swings."""
    t = k * DT
    return np.array([0.07 + 0.002 * t, 0.2 * np.sin(t), 0.4 * np.sin(3 * t), 0.1, 0.05 * np.cos(2 * t)])


#: where the model of each benchmarked instance runs (AAA_COSIM_MODEL_PROCESS, remote.h)
PROCESSES = ("importer", "helper")


class Fmu:
    """One FMU instance in Step Mode and its raw C functions (FMPy's ctypes bindings), its model in
    ``process`` (one of PROCESSES)."""

    def __init__(self, name: str, process: str):
        if fmu_is_stale(name):
            build_fmu(name)
        from fmpy import extract, read_model_description
        from fmpy.fmi3 import FMU3Slave, fmi3Boolean, fmi3Float64, fmi3ValueReference

        path = DEFAULT_FMU_DIR / f"{name}.fmu"
        md = read_model_description(str(path))
        self.refs = {v.name: v.valueReference for v in md.modelVariables}
        self._vr_type = fmi3ValueReference
        self.slave = FMU3Slave(guid=md.guid, unzipDirectory=extract(str(path), tempfile.mkdtemp()),
                               modelIdentifier=name, instanceName="bench")
        chosen = os.environ.get("AAA_COSIM_MODEL_PROCESS")
        os.environ["AAA_COSIM_MODEL_PROCESS"] = process
        try:
            self.slave.instantiate(loggingOn=False)
        finally:
            if chosen is None:
                os.environ.pop("AAA_COSIM_MODEL_PROCESS")
            else:
                os.environ["AAA_COSIM_MODEL_PROCESS"] = chosen
        self.slave.enterInitializationMode()
        self.slave.exitInitializationMode()
        self.f = self.slave._functions
        self.c = self.slave.component
        self._flags = [fmi3Boolean() for _ in range(3)]
        self._last = fmi3Float64()
        self.step_refs = [ctypes.byref(x) for x in self._flags] + [ctypes.byref(self._last)]

    def vrs(self, names):
        return (self._vr_type * len(names))(*[self.refs[n] for n in names])

    def close(self) -> None:
        self.slave.terminate()
        self.slave.freeInstance()


def pointer(array: np.ndarray):
    ctype = {np.float64: ctypes.c_double, np.int32: ctypes.c_int32, np.bool_: ctypes.c_bool}[array.dtype.type]
    return array.ctypes.data_as(ctypes.POINTER(ctype))


def alternate(*steps) -> list[np.ndarray]:
    """Times (us) of BLOCKS * BLOCK steps of each of ``steps`` (functions of the step number), in
    blocks taking turns."""
    times = [[] for _ in steps]
    for block in range(BLOCKS * len(steps)):
        which = block % len(steps)
        start = len(times[which])
        for k in range(start, start + BLOCK):
            times[which].append(steps[which](k))
    return [np.array(t) / 1e3 for t in times]


def report(title: str, fmu_us: dict[str, np.ndarray], direct_us: np.ndarray, targets: dict[str, float]) -> dict:
    print(title)
    print(f"  direct model step (+ output copies)            median {np.median(direct_us):7.1f} us   p99 "
          f"{np.percentile(direct_us, 99):7.1f} us")
    costs = {}
    for process, times in fmu_us.items():
        print(f"  FMU step, model in the {process + ' process':16s}  median {np.median(times):7.1f} us   p99 "
              f"{np.percentile(times, 99):7.1f} us")
        costs[process] = float(np.median(times) - np.median(direct_us))
    for process, cost in costs.items():
        target = f" (target <= {targets[process]:g} us)" if process in targets else ""
        print(f"  FMI cost per step, model in the {process} process (difference of the medians): {cost:.1f} us; "
              f"FMU / direct = {np.median(fmu_us[process]) / np.median(direct_us):.2f}{target}")
    return costs


def contact_fmu_step(process: str, paths: list[np.ndarray]):
    """The FMU instance with its model in ``process``, its step function and its last outputs."""
    fmu = Fmu("Contact", process)
    f, c = fmu.f, fmu.c
    set_f64, get_f64, get_i32, do_step = f["fmi3SetFloat64"], f["fmi3GetFloat64"], f["fmi3GetInt32"], f["fmi3DoStep"]
    scalar_names = ["tool_force", "tip_force", "penetration_depth", "contact_energy", "passivity_energy"]
    in_vr, out_vr = fmu.vrs(["tool_positions"]), fmu.vrs(scalar_names)
    force_vr, count_vr = fmu.vrs(["tissue_contact_force"]), fmu.vrs(["contact_count"])
    tool, outputs, tissue_force, count = np.zeros(93), np.zeros(9), np.zeros(8064), np.zeros(1, np.int32)
    p_tool, p_out, p_force, p_count = pointer(tool), pointer(outputs), pointer(tissue_force), pointer(count)
    refs = fmu.step_refs
    contacts = [0]

    def fmu_step(k):
        tool[:] = paths[k].ravel()
        t0 = CLOCK()
        set_f64(c, in_vr, 1, p_tool, 93)
        status = do_step(c, k * DT, DT, True, *refs)
        get_f64(c, out_vr, 5, p_out, 9)
        get_f64(c, force_vr, 1, p_force, 8064)
        get_i32(c, count_vr, 1, p_count, 1)
        elapsed = CLOCK() - t0
        if status != 0:
            raise SystemExit(f"Contact ({process} process): fmi3DoStep returned {status}")
        contacts[0] += int(count[0] > 0)
        return elapsed

    return fmu, fmu_step, (outputs, tissue_force), contacts


def contact() -> dict:

    mesh = aaa_mesh()
    nodes, triangles = mesh.surface()
    model = ContactModel(triangles, len(nodes), 31, ContactParameters())
    model.set_tissue_frame(0.0, mesh.points[nodes], np.zeros((len(nodes), 3)))
    direct_out = np.zeros(9)
    direct_force = np.zeros(8064)
    paths = [catheter_path(k) for k in range(BLOCK * BLOCKS)]
    instances = {process: contact_fmu_step(process, paths) for process in PROCESSES}

    def direct_step(k):
        positions = paths[k]
        t0 = CLOCK()
        out = model.step(k * DT, DT, positions)
        direct_out[0:3], direct_out[3:6] = out.tool_force, out.tip_force
        direct_out[6:9] = out.penetration_depth, out.contact_energy, out.passivity_energy
        direct_force[:] = out.tissue_contact_force.ravel()
        return CLOCK() - t0

    *fmu_us, direct_us = alternate(*(instances[p][1] for p in PROCESSES), direct_step)
    for process, (fmu, _, (outputs, tissue_force), contacts) in instances.items():
        if not (np.array_equal(outputs, direct_out) and np.array_equal(tissue_force, direct_force)):
            raise SystemExit(f"Contact: the FMU ({process} process) and the direct model disagree on the last step")
        fmu.close()
    contacts = instances["importer"][3][0]
    return report(f"Contact step, {BLOCK * BLOCKS} steps each, alternating blocks of {BLOCK}; steps with contact: "
                  f"{contacts / len(direct_us):.0%}", dict(zip(PROCESSES, fmu_us)), direct_us,
                  {"importer": 10.0, "helper": 20.0})


def catheter_fmu_step(process: str, drive: list[np.ndarray]):
    """The FMU instance with its model in ``process``, its step function and its last outputs."""
    fmu = Fmu("Catheter", process)
    f, c = fmu.f, fmu.c
    set_f64, get_f64, get_bool, do_step = f["fmi3SetFloat64"], f["fmi3GetFloat64"], f["fmi3GetBoolean"], \
        f["fmi3DoStep"]
    in_vr = fmu.vrs(["insertion", "rotation", "tip_force"])
    float_names = ["centerline_positions", "tip_position", "bend_angle", "actuator_command",
                   "advised_insertion_scale", "tip_force_magnitude", "total_bend"]
    out_vr, warning_vr = fmu.vrs(float_names), fmu.vrs(["effort_warning"])
    inputs, outputs, warning = np.zeros(5), np.zeros(101), np.zeros(1, np.bool_)
    p_in, p_out, p_warning = pointer(inputs), pointer(outputs), pointer(warning)
    refs = fmu.step_refs

    def fmu_step(k):
        inputs[:] = drive[k]
        t0 = CLOCK()
        set_f64(c, in_vr, 3, p_in, 5)
        status = do_step(c, k * DT, DT, True, *refs)
        get_f64(c, out_vr, 7, p_out, 101)
        get_bool(c, warning_vr, 1, p_warning, 1)
        elapsed = CLOCK() - t0
        if status != 0:
            raise SystemExit(f"Catheter ({process} process): fmi3DoStep returned {status}")
        return elapsed

    return fmu, fmu_step, (outputs, warning)


def catheter() -> dict:
    model = CatheterModel(CatheterParameters(), dt=DT)
    direct_out = np.zeros(101)
    direct_warning = [False]
    drive = [catheter_inputs(k) for k in range(BLOCK * BLOCKS)]
    tip_forces = [d[2:5].copy() for d in drive]
    instances = {process: catheter_fmu_step(process, drive) for process in PROCESSES}

    def direct_step(k):
        insertion, rotation = drive[k][0], drive[k][1]
        tip_force = tip_forces[k]
        t0 = CLOCK()
        out = model.step(k * DT, DT, insertion, rotation, tip_force)
        direct_out[0:93], direct_out[93:96] = out.centerline_positions, out.tip_position
        direct_out[96:101] = (out.bend_angle, out.actuator_command, out.advised_insertion_scale,
                              out.tip_force_magnitude, out.total_bend)
        direct_warning[0] = out.effort_warning
        return CLOCK() - t0

    *fmu_us, direct_us = alternate(*(instances[p][1] for p in PROCESSES), direct_step)
    for process, (fmu, _, (outputs, warning)) in instances.items():
        if not (np.array_equal(outputs, direct_out) and bool(warning[0]) == bool(direct_warning[0])):
            raise SystemExit(f"Catheter: the FMU ({process} process) and the direct model disagree on the last step")
        fmu.close()
    return report(f"Catheter step, {BLOCK * BLOCKS} steps each, alternating blocks of {BLOCK}",
                  dict(zip(PROCESSES, fmu_us)), direct_us, {"importer": 10.0})


def main() -> None:
    contact()
    catheter()


if __name__ == "__main__":
    main()

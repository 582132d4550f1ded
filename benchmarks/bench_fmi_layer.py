"""Cost of the FMI layer per 1 kHz component step: Contact.fmu step minus the same model step called directly.

One FMU step as the orchestrator makes it: set the Contact inputs (the 31-point catheter
centerline, 93 values), ``fmi3DoStep``, get the observed outputs (tool and tip force, penetration,
energies: 9 Float64 values, plus the 8064-value tissue contact force and the Int32 contact
count). The FMU is called through its raw C functions on preallocated numpy buffers (as the
in-process host does); the direct loop calls ``ContactModel.step`` with the same inputs and copies
the same outputs. Both run the same catheter path (pressing the tip into the default AAA wall),
alternating in blocks in one process so that machine noise hits both alike.

Target (issue: the project's own FMI layer): FMI cost <= 10 us per step, from about 120 us with
pythonfmu3 (the figure measured on this machine before the layer was replaced).

Run: .venv/bin/python benchmarks/bench_fmi_layer.py
"""
from __future__ import annotations

import ctypes
import tempfile
import time

import numpy as np

from haptic_fmu.model import ContactModel, ContactParameters  # imported first: the host's own copy
from orchestration.build import DEFAULT_FMU_DIR, build_fmu, fmu_is_stale
from tissue_fmu.mesh import aaa_mesh

DT = 1e-3
BLOCK = 500
BLOCKS = 12


def catheter_path(k: int) -> np.ndarray:
    """31 points up the aorta; the tip bends into the sac wall and presses in and out."""
    s = np.linspace(0.0, 1.0, 31)
    t = k * DT
    z = 0.02 + s * 0.045
    x = (0.0236 + 0.0008 * np.sin(2 * np.pi * 0.5 * t)) * np.clip((s - 0.6) / 0.4, 0, None) ** 2
    return np.stack([x, np.zeros_like(s), z], axis=1)


def main() -> None:
    if fmu_is_stale("Contact"):
        build_fmu("Contact")
    from fmpy import extract, read_model_description
    from fmpy.fmi3 import FMU3Slave, fmi3Boolean, fmi3Float64, fmi3ValueReference

    fmu_path = DEFAULT_FMU_DIR / "Contact.fmu"
    md = read_model_description(str(fmu_path))
    refs = {v.name: v.valueReference for v in md.modelVariables}
    slave = FMU3Slave(guid=md.guid, unzipDirectory=extract(str(fmu_path), tempfile.mkdtemp()),
                      modelIdentifier="Contact", instanceName="bench")
    slave.instantiate(loggingOn=False)
    slave.enterInitializationMode()
    slave.exitInitializationMode()
    f = slave._functions
    set_f64, get_f64, get_i32, do_step = f["fmi3SetFloat64"], f["fmi3GetFloat64"], f["fmi3GetInt32"], f["fmi3DoStep"]
    c = slave.component

    def vrs(names):
        return (fmi3ValueReference * len(names))(*[refs[n] for n in names])

    scalar_names = ["tool_force", "tip_force", "penetration_depth", "contact_energy", "passivity_energy"]
    in_vr, out_vr, force_vr, count_vr = vrs(["tool_positions"]), vrs(scalar_names), vrs(["tissue_contact_force"]), \
        vrs(["contact_count"])
    tool = np.zeros(93)
    outputs = np.zeros(9)
    tissue_force = np.zeros(8064)
    count = np.zeros(1, np.int32)
    flags = [fmi3Boolean() for _ in range(3)]
    last = fmi3Float64()
    refs_out = [ctypes.byref(x) for x in flags] + [ctypes.byref(last)]
    p_tool, p_out = tool.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), outputs.ctypes.data_as(ctypes.POINTER(ctypes.c_double))
    p_force, p_count = tissue_force.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), count.ctypes.data_as(ctypes.POINTER(ctypes.c_int32))

    mesh = aaa_mesh()
    nodes, triangles = mesh.surface()
    model = ContactModel(triangles, len(nodes), 31, ContactParameters())
    model.set_tissue_frame(0.0, mesh.points[nodes], np.zeros((len(nodes), 3)))
    direct_out = np.zeros(9)
    direct_force = np.zeros(8064)
    paths = [catheter_path(k) for k in range(BLOCK * BLOCKS)]

    fmu_times, direct_times, contacts = [], [], 0
    k_fmu = k_direct = 0
    clock = time.perf_counter_ns
    for block in range(2 * BLOCKS):
        if block % 2 == 0:
            for _ in range(BLOCK):
                tool[:] = paths[k_fmu].ravel()
                t0 = clock()
                set_f64(c, in_vr, 1, p_tool, 93)
                status = do_step(c, k_fmu * DT, DT, True, *refs_out)
                get_f64(c, out_vr, 5, p_out, 9)
                get_f64(c, force_vr, 1, p_force, 8064)
                get_i32(c, count_vr, 1, p_count, 1)
                fmu_times.append(clock() - t0)
                if status != 0:
                    raise SystemExit(f"fmi3DoStep returned {status}")
                contacts += int(count[0] > 0)
                k_fmu += 1
        else:
            for _ in range(BLOCK):
                positions = paths[k_direct]
                t0 = clock()
                out = model.step(k_direct * DT, DT, positions)
                direct_out[0:3], direct_out[3:6] = out.tool_force, out.tip_force
                direct_out[6:9] = out.penetration_depth, out.contact_energy, out.passivity_energy
                direct_force[:] = out.tissue_contact_force.ravel()
                direct_times.append(clock() - t0)
                k_direct += 1
    if not (np.array_equal(outputs, direct_out) and np.array_equal(tissue_force, direct_force)):
        raise SystemExit("the FMU and the direct model disagree on the last step")
    fmu_us, direct_us = np.array(fmu_times) / 1e3, np.array(direct_times) / 1e3
    print(f"Contact step, {BLOCK * BLOCKS} steps each, alternating blocks of {BLOCK}; steps with contact: "
          f"{contacts / len(fmu_times):.0%}")
    print(f"  direct model step (+ output copies)   median {np.median(direct_us):7.1f} us   p99 "
          f"{np.percentile(direct_us, 99):7.1f} us")
    print(f"  FMU step (set, fmi3DoStep, get)       median {np.median(fmu_us):7.1f} us   p99 "
          f"{np.percentile(fmu_us, 99):7.1f} us")
    cost = np.median(fmu_us) - np.median(direct_us)
    print(f"  FMI layer cost per step (difference of the medians): {cost:.1f} us "
          f"(target <= 10 us; pythonfmu3 cost about 120 us here)")
    slave.terminate()
    slave.freeInstance()


if __name__ == "__main__":
    main()

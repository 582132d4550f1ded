"""Orchestrator cost on the default AAA scene, measured side by side in one run.

1. Overhead: the same three models (TissueModel at 30 Hz with its compliance W, CatheterModel
   and ContactModel at 1 kHz, forces averaged over each tissue step, tissue frames held, the tip
   force and stiffness one step late) stepped by a plain Python loop, against the orchestrated
   in-process run of ``aaa_endovascular`` (FMI calls through the FMUs, the master's transitions,
   recording). Both compute the same run (the peak haptic force is printed for both).
   Overhead = (orchestrated - direct) / orchestrated; target <= 10 % of the total wall time. The
   pair is run three times, alternating, and the median taken: one pair moves by 5 points on this
   host (the three are printed).
2. Hosting: the scene all in-process, every FMU in a worker process of its own, and the scene's
   own choice (the 30 Hz tissue in a worker, stepping concurrently with the 1 kHz loop in this
   process); real-time factors and ratios. Targets: the scene's hosting at least as fast as the
   direct serial loop, real-time factor >= 5.
3. The compiled loop (orchestration/compiled_loop.py): the in-process and the scene's hosting
   runs again with every step made from Python (``compiled_loop=False``), the same results.

Run: ``.venv/bin/python benchmarks/bench_orchestrator.py [--duration 4]``. The machine is noisy:
compare the ratios, not the absolute times.
"""
from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np

#: Direct and in-process runs alternate this many times; the overhead is the median pair's
OVERHEAD_PAIRS = 3


def direct_loop(duration: float) -> float:
    """The scene's models stepped directly in Python (no FMI, no master); returns (wall seconds, peak
    haptic force), the peak to check that both sides computed the same run.

    The same data flow as the scene's connections: the tissue steps with the contact forces
    averaged over its step and publishes, with each frame, its compliance W at the patch Contact
    named at the step's start; Contact takes positions, velocities and W together when the frame
    is published (jacobi, hold); the catheter gets the tip force and tip stiffness of the last
    step (jacobi).
    """
    from catheter_fmu.model import CatheterModel, CatheterParameters
    from haptic_fmu.model import ContactModel, ContactParameters
    from tissue_fmu.mesh import aaa_mesh
    from tissue_fmu.model import TissueModel, TissueParameters

    from orchestration.scene.loading import load_scene

    # The scene's own settings, so that both sides do the same work.
    scene = load_scene("aaa_endovascular").components
    tp, cp, kp = (scene[n].parameters for n in ("tissue", "catheter", "contact"))
    operator = scene["operator"].new_block()

    def operator_insertion(t: float) -> float:
        return float(operator.evaluate(t)["insertion"][0])

    tissue = TissueModel(aaa_mesh(), TissueParameters(
        law=tp["law"], integrator=tp["integrator"], viscosity=tp["viscosity"],
        active_region=(*tp["active_center"], tp["active_radius"])))
    centerline = np.array(cp["centerline_points"], dtype=float).reshape(-1, 3)
    params = CatheterParameters(n_segments=30, centerline=centerline, controller_mode=cp["controller_mode"],
                                force_threshold=cp["force_threshold"])
    catheter = CatheterModel(params, dt=0.001)
    catheter.reset(operator_insertion(0.0), 0.0)
    contact = ContactModel(tissue.surface_triangles, tissue.n_surface, 31,
                           ContactParameters(tool=kp["tool"], stiffness=kp["stiffness"], damping=kp["damping"],
                                             local_model=kp["local_model"]))
    contact.set_tissue_frame(0.0, tissue.surface_positions(), tissue.surface_velocities())
    tolerance = scene["tissue"].description.ports["compliance_tolerance"].start
    n_fast = int(round(duration * 1000))
    tip_force, tip_stiffness, tip_gap = np.zeros(3), np.zeros((3, 3)), np.zeros(3)
    # Contact samples are averaged over (t_f - 1/30, t_f] for the tissue step starting at t_f = f / 30;
    # a sample ending after t_f (t_f is rarely a whole millisecond) belongs to the next window.
    force_sum, next_sum = np.zeros((tissue.n_surface, 3)), np.zeros((tissue.n_surface, 3))
    samples = next_samples = 0
    patch = contact.patch_nodes().copy()  # the contact's patch at the latest sample <= t_f
    frame = 0
    pending = None  # the tissue step's result, published at the next frame
    peak = 0.0
    start = time.perf_counter()
    for k in range(n_fast):
        t = k / 1000
        if k * 30 >= frame * 1000:  # a tissue step starts at frame / 30 s
            if frame:  # the previous step's result becomes the contact's frame now (jacobi, hold)
                positions, velocities, w, nodes = pending
                if nodes.size:
                    contact.set_tissue_frame(frame / 30, positions, velocities, compliance=w, compliance_nodes=nodes)
                else:
                    contact.set_tissue_frame(frame / 30, positions, velocities)
            if samples:
                tissue.set_contact_force(force_sum / samples)
            ids = patch[patch >= 0]
            tissue.step(frame / 30, 1 / 30)
            w = tissue.compliance(ids, 1 / 30, tolerance=tolerance) if ids.size else None
            if w is not None:
                w = 0.5 * (w + w.T)
            pending = (tissue.surface_positions().copy(), tissue.surface_velocities().copy(), w, ids)
            force_sum, next_sum = next_sum, force_sum
            next_sum[:] = 0.0
            samples, next_samples = next_samples, 0
            frame += 1
        out = catheter.step(t, 0.001, operator_insertion((k + 1) / 1000), 0.0, tip_force, tip_stiffness=tip_stiffness,
                            tip_gap=tip_gap)
        contact_out = contact.step(t, 0.001, out.centerline_positions.reshape(-1, 3))
        tip_force = contact_out.tip_force.copy()
        tip_stiffness = contact_out.tip_stiffness.copy()
        tip_gap = contact_out.tip_gap.copy()
        if (k + 1) * 30 <= frame * 1000:  # ends by the next tissue step's start
            force_sum += contact_out.tissue_contact_force
            samples += 1
            patch = contact.patch_nodes().copy()
        else:
            next_sum += contact_out.tissue_contact_force
            next_samples += 1
        peak = max(peak, math.hypot(*contact_out.tool_force.tolist()))  # as the summary computes it
    return time.perf_counter() - start, peak


def orchestrated(duration: float, hosting: str, compiled_loop: bool = True) -> dict:
    from orchestration.run.simulation import run_scene
    from orchestration.scene.loading import load_scene

    scene = load_scene("aaa_endovascular", {"duration": duration})
    with tempfile.TemporaryDirectory() as tmp:
        summary, _ = run_scene(scene, Path(tmp), hosting=hosting, progress=False, plots=False, vtu=False,
                               compiled_loop=compiled_loop)
    if summary["status"] != "completed":
        raise SystemExit(f"{hosting} run failed: {summary['error']}")
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--duration", type=float, default=4.0, help="simulated seconds per run (default 4)")
    args = parser.parse_args()
    # The models are imported before any FMU is loaded: an FMU's resources folder on sys.path
    # would otherwise shadow the packages.
    import catheter_fmu.model  # noqa: F401
    import haptic_fmu.model  # noqa: F401
    import tissue_fmu.model  # noqa: F401
    from orchestration.app.warmup import ensure_fmus_built

    ensure_fmus_built(quiet=True)
    orchestrated(0.1, "in-process")  # the FMU extraction path, imports
    # The direct loop's kernels are the source tree's, not the FMUs': loaded from the numba cache, or
    # compiled after a change (the non-linear ones only once the wall strains, past 1.5 s), in a run
    # of their own rather than in the first pair's time
    direct_loop(args.duration)
    pairs = []
    for _ in range(OVERHEAD_PAIRS):
        direct_wall, direct_peak = direct_loop(args.duration)
        run = orchestrated(args.duration, "in-process")
        pairs.append(((run["wall_time_s"] - direct_wall) / run["wall_time_s"], direct_wall, run))
    overhead, direct, inproc = sorted(pairs, key=lambda pair: pair[0])[len(pairs) // 2]
    outproc = orchestrated(args.duration, "out-of-process")
    mixed = orchestrated(args.duration, None)
    inproc_python = orchestrated(args.duration, "in-process", compiled_loop=False)
    mixed_python = orchestrated(args.duration, None, compiled_loop=False)
    peak = inproc["peaks"]["contact.tool_force"]["value"]
    same = all(run["peaks"] == inproc["peaks"]
               for run in (*(pair[2] for pair in pairs), outproc, mixed, inproc_python, mixed_python))
    print(f"default scene, {args.duration:g} s simulated (peak haptic force: direct {direct_peak:.6g} N, "
          f"orchestrated {peak:.6g} N: {'the same run' if direct_peak == peak else 'DIFFERENT RUNS'})")
    print(f"  direct model loop (no FMI, no master)   wall {direct:7.2f} s   real-time factor {args.duration / direct:5.2f}")
    print(f"  orchestrated in-process                 wall {inproc['wall_time_s']:7.2f} s   real-time factor "
          f"{inproc['real_time_factor']:5.2f}")
    print(f"  orchestrated out-of-process             wall {outproc['wall_time_s']:7.2f} s   real-time factor "
          f"{outproc['real_time_factor']:5.2f}")
    print(f"  orchestrated, the scene's hosting       wall {mixed['wall_time_s']:7.2f} s   real-time factor "
          f"{mixed['real_time_factor']:5.2f}   [{mixed['hosting']}] (target >= 5)")
    print(f"  orchestration overhead (FMI + master) = {100 * overhead:5.1f} % of the in-process wall time (target <= 10 %; "
          f"the median of {', '.join(f'{100 * pair[0]:.1f}' for pair in pairs)} %, direct and in-process "
          f"alternating; the walls above are its pair's)")
    # In process, a component is "busy" while the master is inside one of its calls (set inputs,
    # fmi3DoStep, get outputs; timed in C within a compiled stretch): the rest of the wall time is
    # the master's own work. The direct loop is the models plus its own Python around them, so
    # the second share can come out below zero when the FMUs' layer costs less than that Python.
    busy = sum(c["busy_wall_s"] for c in inproc["components"].values())
    steps = sum(c["steps"] for c in inproc["components"].values())
    print(f"    of which the master itself (scheduling, routing, histories, recording) = "
          f"{100 * (inproc['wall_time_s'] - busy) / inproc['wall_time_s']:5.1f} % "
          f"({1e6 * (inproc['wall_time_s'] - busy) / steps:.0f} us per component step)")
    print(f"    and the FMI calls beyond the direct loop's time = "
          f"{100 * (busy - direct) / inproc['wall_time_s']:5.1f} % ({1e6 * (busy - direct) / steps:.0f} us per component step)")
    print(f"  every FMU in a worker / in-process     = {inproc['wall_time_s'] / outproc['wall_time_s']:5.2f}x speed")
    print(f"  the scene's hosting / in-process       = {inproc['wall_time_s'] / mixed['wall_time_s']:5.2f}x speed")
    print(f"  the scene's hosting / direct serial    = {direct / mixed['wall_time_s']:5.2f}x speed (target >= 1)")
    print(f"  the compiled loop: in-process {inproc_python['wall_time_s'] / inproc['wall_time_s']:5.2f}x, the scene's "
          f"hosting {mixed_python['wall_time_s'] / mixed['wall_time_s']:5.2f}x the speed of every step from Python "
          f"(wall {inproc_python['wall_time_s']:.2f} and {mixed_python['wall_time_s']:.2f} s; "
          f"{'the same peaks in every run' if same else 'PEAKS DIFFER BETWEEN RUNS'})")
    for label, run in (("all workers", outproc), ("scene hosting", mixed)):
        for name, comp in run["components"].items():
            print(f"    {label:13s} {name:9s} {comp['hosting']:15s} busy {comp['busy_wall_s']:6.2f} s "
                  f"over {comp['steps']} steps")

if __name__ == "__main__":
    main()

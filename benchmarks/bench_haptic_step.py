"""Timing of ContactModel.step (the 1 kHz haptic update) on an AAA-like surface.

Surface: a thick-walled tube (inner and outer wall, 48 x 32 nodes each, 3072 surface nodes,
5952 triangles) with a fusiform aneurysm bulge (radius 10 mm -> 25 mm over 60 mm). Tissue frames
arrive every 33 haptic steps (30 Hz vs 1 kHz) with a smooth breathing deformation. Scenarios:
a 30-point catheter centerline (capsules of 1 mm) moving in and out and pressing its tip into
the aneurysm wall, and a single probe point pressed in and out while sliding along the wall.

Local models: "hold" and "extrapolate" (frozen facets) and "compliance" (the default: the wall
yields at 1 kHz through the compliance W of the patch the contact names; here W is a
synthetic wall compliance of the named nodes, c exp(-|xi - xj|^2 / l^2) per axis with
c = 1/70 m/N (about the AAA wall's point compliance, 0.23 N -> 3 mm) and l = 5 mm, sent with each
frame for the ids named at the frame before, as the Tissue FMU will; the breathing frames are free
motion, so the applied force sent with them is zero).

Targets: step median <= 100 us (compliance: <= 50 us), p99 <= 250 us. Prints median / p99 / max per
scenario in wall time and in thread CPU time (the CPU time excludes preemption by other processes: on a shared
machine the wall-time tail is the scheduler's, in multiples of its 4 ms tick), the mean number
of contacts, and set_tissue_frame timings (not part of the 1 kHz budget).

Run: .venv/bin/python benchmarks/bench_haptic_step.py
"""
import time

import numpy as np

from haptic_fmu.model import ContactModel, ContactParameters

DT = 1e-3
FRAME_EVERY = 33
N_STEPS = 6000


def aaa_surface(n_around=48, n_along=32, length=0.15, thickness=0.0015):
    z = np.linspace(0.0, length, n_along)
    radius = 0.010 + 0.015 * np.exp(-((z - 0.075) / 0.025) ** 2)   # bulge of 25 mm radius, ~60 mm long
    theta = np.arange(n_around) * 2 * np.pi / n_around
    points, tris, offset = [], [], 0
    for wall, extra in (("inner", 0.0), ("outer", thickness)):
        r = (radius + extra)[None, :]
        th = theta[:, None]
        pts = np.stack([r * np.cos(th), r * np.sin(th), np.broadcast_to(z, (n_around, n_along))], axis=-1)
        points.append(pts.reshape(-1, 3))
        for i in range(n_around):
            for j in range(n_along - 1):
                a = offset + i * n_along + j
                b = offset + ((i + 1) % n_around) * n_along + j
                c, d = b + 1, a + 1
                tris += [[a, d, c], [a, c, b]] if wall == "inner" else [[a, b, c], [a, c, d]]
        offset += n_around * n_along
    return np.concatenate(points), np.array(tris, np.int64), radius, z


def breathing(rest, t):
    """Smooth radial deformation (0.3 mm amplitude, 1.2 Hz) and its velocity."""
    rho = np.linalg.norm(rest[:, :2], axis=1, keepdims=True)
    radial = np.concatenate([rest[:, :2] / rho, np.zeros((rest.shape[0], 1))], axis=1)
    w = 2 * np.pi * 1.2
    amp = 3e-4 * np.sin(rest[:, 2:3] * 40.0)
    return rest + radial * amp * np.sin(w * t), radial * amp * w * np.cos(w * t)


def centerline_path(t, n=30):
    """30 points up the axis, the distal 40% bending toward the aneurysm wall (+x), tip pressing on it."""
    s = np.linspace(0.0, 1.0, n)
    insertion = 0.055 + 0.004 * np.sin(2 * np.pi * 0.25 * t)   # tip moving in and out near the bulge
    z = s * insertion + 0.02
    bend = (0.0235 + 0.0008 * np.sin(2 * np.pi * 2.0 * t)) * np.clip((s - 0.6) / 0.4, 0, 1) ** 2
    return np.stack([bend, 0.0005 * s, z], axis=1)


def probe_path(t, r_wall):
    """A probe pressed 0..1 mm into the aneurysm wall at 3 Hz, sliding 5 mm/s around it."""
    phi = 0.3 + 0.25 * t
    depth = 0.0005 * (1 - np.cos(2 * np.pi * 3.0 * t))
    r = r_wall + depth - 0.0002
    return np.array([[r * np.cos(phi), r * np.sin(phi), 0.075]])


WALL_COMPLIANCE = 1.0 / 70.0   # m/N
WALL_LENGTH = 0.005            # m


def synthetic_compliance(pos, ids):
    """W (3p x 3p) of the nodes ids: c exp(-|xi - xj|^2 / l^2) per axis (symmetric positive definite)."""
    x = pos[ids]
    d2 = ((x[:, None, :] - x[None, :, :]) ** 2).sum(axis=2)
    return np.kron(WALL_COMPLIANCE * np.exp(-d2 / WALL_LENGTH ** 2), np.eye(3))


def run(name, model, rest, tool_at):
    steps, cpu, frames, contacts = [], [], [], []
    t = 0.0
    compliance = model.params.local_model == "compliance"
    named = np.zeros(0, np.int64)
    for k in range(N_STEPS):
        if k % FRAME_EVERY == 0:
            pos, vel = breathing(rest, t)
            extra = {}
            if compliance and named.size:
                # the breathing frames are the wall's free motion (they do not contain the contact's
                # load), so the force the tissue applied is reported as zero
                extra = dict(compliance=synthetic_compliance(pos, named), compliance_nodes=named,
                             applied_force=np.zeros((named.size, 3)))
            t0 = time.perf_counter_ns()
            model.set_tissue_frame(t, pos, vel, **extra)
            frames.append(time.perf_counter_ns() - t0)
            named = model.patch_nodes()
            named = named[named >= 0]
        tool = tool_at(t + DT)
        c0 = time.thread_time_ns()
        t0 = time.perf_counter_ns()
        out = model.step(t, DT, tool)
        steps.append(time.perf_counter_ns() - t0)
        cpu.append(time.thread_time_ns() - c0)
        contacts.append(out.contact_count)
        t = (k + 1) * DT
    steps = np.array(steps[200:]) / 1e3          # drop the first steps (first local-model builds)
    cpu = np.array(cpu[200:]) / 1e3
    frames = np.array(frames[5:]) / 1e3
    med, p99 = np.median(steps), np.percentile(steps, 99)
    cpu_med, cpu_p99 = np.median(cpu), np.percentile(cpu, 99)
    target = 50.0 if compliance else 100.0
    print(f"{name:48s} wall: median {med:6.1f} us p99 {p99:7.1f} us max {steps.max():8.1f} us | "
          f"cpu: median {cpu_med:6.1f} us p99 {cpu_p99:6.1f} us | "
          f"contacts {np.mean(contacts):4.2f} | frame {np.median(frames):6.1f} us | "
          f"cpu median/{target:.0f}us {cpu_med / target:4.2f} cpu p99/250us {cpu_p99 / 250:5.2f}")
    if compliance:
        c = model.compliance
        print(f"{'':48s} compliance: W of {c.ids.size} nodes at the last frame, Newton iterations of the last "
              f"solve {c.iterations}, unconverged solves {c.unconverged}")
    return cpu_med, cpu_p99


def main():
    rest, tri, radius, z = aaa_surface()
    n_surface = rest.shape[0]
    r_wall = radius[np.argmin(abs(z - 0.075))] * np.cos(np.pi / 48)
    print(f"surface: {n_surface} nodes, {tri.shape[0]} triangles; {N_STEPS} steps of {DT * 1e3:.0f} ms, "
          f"a tissue frame every {FRAME_EVERY} steps")
    scenarios = []
    for detection in ("continuous", "discrete"):
        for policy in ("compliance", "hold", "extrapolate"):
            scenarios.append((f"centerline 30 pts, {detection}, {policy}",
                              ContactParameters(tool="centerline", detection=detection, local_model=policy),
                              30, centerline_path))
    scenarios.append(("centerline 50 pts, continuous, compliance", ContactParameters(), 50,
                      lambda t: centerline_path(t, 50)))
    scenarios.append(("centerline 30 pts, continuous, cubic, compliance",
                      ContactParameters(tool="centerline", interpolation="cubic"), 30, centerline_path))
    # The passivity controller is for a device probe only (the contact refuses it on a catheter).
    scenarios.append(("probe, continuous, passivity, compliance",
                      ContactParameters(tool="probe", passivity_controller=True), 1,
                      lambda t: probe_path(t, r_wall)))
    for detection in ("continuous", "discrete"):
        for policy in ("compliance", "hold"):
            scenarios.append((f"probe, {detection}, {policy}",
                              ContactParameters(tool="probe", detection=detection, local_model=policy), 1,
                              lambda t: probe_path(t, r_wall)))
    # compile everything once outside the timings
    warm = ContactModel(tri, n_surface, 30, ContactParameters())
    warm.set_tissue_frame(0.0, rest, np.zeros_like(rest))
    warm.step(0.0, DT, centerline_path(0.0))
    results = {}
    for name, params, n_tool, path in scenarios:
        results[name] = run(name, ContactModel(tri, n_surface, n_tool, params), rest, path)
    print("compliance / hold, CPU time median (p99), same run:")
    for name, (med, p99) in results.items():
        if name.endswith(", compliance") and name.replace(", compliance", ", hold") in results:
            ref_med, ref_p99 = results[name.replace(", compliance", ", hold")]
            print(f"  {name.replace(', compliance', ''):44s} {med / ref_med:4.2f} ({p99 / ref_p99:4.2f})")


if __name__ == "__main__":
    main()

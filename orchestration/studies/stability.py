"""Stability study (issue 6): the sampled virtual wall and the multirate tissue/haptic coupling.

Virtual wall (scene ``virtual_wall``: a device plant pushed into a penalty wall rendered with a
zero-order hold at period T). Colgate and Schenkel (1997): the wall plus the device damping b_dev
is passive iff ``b_dev > K T / 2 + |B|``. Passivity is a worst case over everything the operator
can do; the worst case is a device whose inertia does not matter within one period (m << b_dev T,
a light device or a stiff grip): then the sampled loop ``b (x[k+1]-x[k]) / T = F0 - K x[k] - B (x[k]
- x[k-1]) / T`` loses stability exactly at b = K T / 2 + B, in an oscillation at the Nyquist
frequency. The study measures, in the simulated scene (Contact FMU + device plant):

* ``hold`` points: the device rests against the wall under a constant operator force F0, started
  2 % off its equilibrium x* = F0 / K. The oscillation energy E = K (x - x*)^2 / 2 + m v^2 / 2 is
  compared between the first and the last window; its growth per step is the stability measure
  (> 0: the wall puts in more energy than the device dissipates, unstable). b_crit is bisected on
  b_dev (geometric, 14 halvings) and compared with the bound.
* ``contacts`` points: the scene's repeated pushes (3 presses of F0, released in between) on a
  grid of b_dev / bound. Energy metric: the net work the wall did on the device over all contacts
  (``device.wall_energy`` at the end, device free so the wall spring is empty: an ideal spring
  gives 0, a passive wall <= 0) and its share of what the device dissipated while in contact
  (-> 1 when the wall drives a limit cycle of chatter, ~0 when the contact settles).
* ``multirate`` points (scene ``tissue_indentation`` on a coarse mesh): tissue rate against
  haptic rate, local model hold/extrapolate, passivity controller off/on; force error against a
  single-rate reference, energy drift of the contact, oscillation of the force.
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from orchestration.studies.common import run_point, write_table
from orchestration.run.status import RunStatus

logger = logging.getLogger(__name__)

OPERATOR_FORCE = 2.0            # N, the scene's push
LIGHT_INERTIA = 1e-3            # m / (bound T) of the "light" device: inertia negligible over a period


def light_mass(K, B, T) -> float:
    """Mass (kg) of the light device for wall (K, B, T): m = 1e-3 bound T, the passivity worst case.

    A fixed light mass is not enough: with m = 1 mg, K = 500 N/m, T = 0.25 ms (m / (bound T) =
    0.064) the boundary is already 15 % below the bound, in the scene and in the exact model alike."""
    return LIGHT_INERTIA * wall_bound(K, B, T) * T


DEVICE_MASS = 0.1               # kg: the scene's desktop device, for the comparison rows
PERTURBATION = 0.02             # initial offset from equilibrium, fraction of x*
BISECTION_HALVINGS = 14
WINDOW = 40                     # steps per energy window of the hold experiment


# -- virtual wall: one run ---------------------------------------------------------------------
def _wall_overrides(K, B, b_dev, T, mass, times, forces, x0) -> dict:
    # the sampled wall itself is studied (the scene's energy_consistent = false): no device limit
    # shapes its force (a wall held to 7.9 N lets the operator push the device through it)
    return {
        "contact.max_force": 1000.0, "contact.max_force_rate": 1e7,
        "contact.stiffness": float(K), "contact.damping": float(B),
        "device.damping": float(b_dev), "device.mass": float(mass),
        "device.step": float(T), "contact.step": float(T),
        "device.initial_position": [float(x0), 0.0, 0.0],
        "operator.times": [float(t) for t in times],
        "operator.outputs": {"force": [[float(f), 0.0, 0.0] for f in forces]},
    }


def _device_series(simulation):
    from orchestration.observers.recorder import port_values

    time, cols = simulation.streams["device"]
    x = port_values(cols, "position")[:, 0]
    v = port_values(cols, "velocity")[:, 0]
    energies = {k: np.asarray(cols[k], float) for k in
                ("wall_energy", "operator_energy", "dissipated_energy", "kinetic_energy")}
    return np.asarray(time, float), x, v, energies


def hold_growth(K, B, b_dev, T, mass, n_steps) -> dict:
    """Device at rest against the wall under F0, started 2 % off equilibrium: growth of the
    oscillation energy per step (log ratio of the last to the first window, / steps / 2)."""
    x_eq = OPERATOR_FORCE / K
    duration = n_steps * T
    # the wall's output at t = 0 is zero (nothing sampled yet), so the first step moves the device
    # by F0 alone: start that far back so that the first sample is x* (1 + 2 %)
    tau = mass / b_dev
    first_step = OPERATOR_FORCE / b_dev * (T - tau * -math.expm1(-T / tau))
    overrides = _wall_overrides(K, B, b_dev, T, mass, [0.0, duration], [OPERATOR_FORCE] * 2,
                                x_eq * (1.0 + PERTURBATION) - first_step)
    summary, sim = run_point("virtual_wall", overrides, duration=duration)
    if summary.get("status") not in (None, RunStatus.COMPLETED):
        raise RuntimeError(f"virtual_wall run failed: {summary.get('error')}")
    _, x, v, _ = _device_series(sim)
    e = x - x_eq
    energy = 0.5 * K * e ** 2 + 0.5 * mass * v ** 2
    left_wall = bool(np.any(x[1:] <= 0.0))
    floor = 1e-24 * K * x_eq ** 2          # round-off floor of the energy
    first = energy[5:5 + WINDOW]
    last = energy[-WINDOW:]
    settled = np.nonzero(energy < floor)[0]
    if settled.size and settled[0] > 5 + WINDOW:
        # decayed to round-off: measure over the decay only
        k_end = int(settled[0])
        growth = math.log(max(energy[k_end - 1], floor) / np.mean(first)) / (k_end - 5) / 2.0
    else:
        growth = math.log(max(np.mean(last), floor) / np.mean(first)) / (len(energy) - WINDOW - 5) / 2.0
    return {"growth_per_step": float(growth), "left_wall": left_wall,
            "unstable": bool(left_wall or growth > 0.0)}


def wall_bound(K, B, T) -> float:
    """Colgate-Schenkel: the wall (K, B, period T) with device damping b is passive iff b > this."""
    return K * T / 2.0 + abs(B)


def critical_damping(K, B, T, mass, n_steps) -> dict:
    """b_crit by geometric bisection on b_dev in [bound / 64, 2 bound] with the hold experiment."""
    bound = wall_bound(K, B, T)
    lo, hi = bound / 64.0, 2.0 * bound
    if hold_growth(K, B, hi, T, mass, n_steps)["unstable"]:
        return {"b_crit": float("nan"), "b_crit_low": hi, "b_crit_high": float("nan"),
                "note": "unstable at 2 x bound"}
    if not hold_growth(K, B, lo, T, mass, n_steps)["unstable"]:
        return {"b_crit": lo, "b_crit_low": float("nan"), "b_crit_high": lo,
                "note": "stable down to bound / 64 (b_crit is an upper limit)"}
    for _ in range(BISECTION_HALVINGS):
        mid = math.sqrt(lo * hi)
        if hold_growth(K, B, mid, T, mass, n_steps)["unstable"]:
            lo = mid
        else:
            hi = mid
    return {"b_crit": math.sqrt(lo * hi), "b_crit_low": lo, "b_crit_high": hi, "note": ""}


def repeated_contacts(K, B, b_dev, T, mass, press_steps, release_steps, n_presses=3) -> dict:
    """The scene's repeated pushes: energy the wall put into the device over all contacts."""
    x_eq = OPERATOR_FORCE / K
    times, forces = [], []
    period = (press_steps + release_steps) * T
    for i in range(n_presses):
        times += [i * period, i * period + press_steps * T]
        forces += [OPERATOR_FORCE, 0.0]
    duration = n_presses * period
    overrides = _wall_overrides(K, B, b_dev, T, mass, times, forces, -0.5 * x_eq)
    overrides["operator.interpolation"] = "hold"
    summary, sim = run_point("virtual_wall", overrides, duration=duration)
    if summary.get("status") not in (None, RunStatus.COMPLETED):
        raise RuntimeError(f"virtual_wall run failed: {summary.get('error')}")
    _, x, v, en = _device_series(sim)
    wall = en["wall_energy"]
    dissipated = np.diff(en["dissipated_energy"], prepend=0.0)
    in_contact = np.concatenate([[False], x[:-1] > 0.0])   # wall force held over step k came from x[k-1]
    d_contact = float(np.sum(dissipated[in_contact]))
    onsets = int(np.sum((x[1:] > 0.0) & (x[:-1] <= 0.0)))
    # residual oscillation at the end of each press, relative to x*
    residual = []
    steps_per_period = press_steps + release_steps
    for i in range(n_presses):
        end = i * steps_per_period + press_steps
        seg = x[max(end - 20, 0):end]
        residual.append(float(np.sqrt(np.mean((seg - x_eq) ** 2)) / x_eq))
    return {"wall_energy_J": float(wall[-1]), "wall_energy_per_press_J": float(wall[-1]) / n_presses,
            "max_depth_over_equilibrium": float(np.max(x) / x_eq),
            # a held step can carry the device past the wall's detection margin: it passes through
            "tunnelled": bool(x[-1] > 2.0 * x_eq and wall[-1] == 0.0),
            "dissipated_in_contact_J": d_contact,
            "wall_share_of_dissipation": float(wall[-1] / d_contact) if d_contact > 0 else 0.0,
            "contact_onsets": onsets, "residual_oscillation": max(residual),
            "settled": bool(max(residual) < 1e-3)}


# -- multirate tissue/haptic coupling ------------------------------------------------------------
COARSE_MESH = {"n_circumferential": 16, "n_axial": 20, "n_radial": 1}
HOLD_PHASE = (1.3, 2.0)          # s: probe at rest, the reference force is nearly steady
#: Penalty stiffness of the convergence and passivity rows (the scenes' value when they were
#: measured); the stiffness map goes up to a device's maximum.
BASE_STIFFNESS = 200.0
MAP_STIFFNESSES = (200.0, 500.0, 1000.0, 2000.0, 3000.0, 5000.0)
LOCAL_MODELS = ("hold", "extrapolate", "compliance")
#: A run is stable when |F| varies by less than this fraction of its mean in the hold phase (the
#: single-rate references vary by less than 0.1 %; a limit cycle by tens of per cent).
STABLE_RIPPLE = 0.05


PROBE_TIMES = (0.0, 0.2, 1.2, 2.0)   # s, as the scene: wait, indent over 1 s, hold
PROBE_OFFSETS = (0.003, 0.003, -0.002, -0.002)   # m along the facet's outward normal


def _coarse_mesh_overrides() -> dict:
    """Coarse mesh sizes for Tissue and Contact, and the probe moved onto the centre of a facet.

    The scene's probe sits exactly on a surface node of the coarse mesh, where the contact normal
    (a facet normal) jumps between the six facets around the node: the lateral force component
    then flips sign between runs that differ by round-off, which swamps the multirate effects.
    The probe here travels along the outward normal through the centroid of the outer-surface
    facet nearest the scene's probe point, 3 mm outside to 2 mm inside, on the scene's timing.
    """
    from tissue_fmu.mesh import aaa_mesh

    mesh = aaa_mesh(**COARSE_MESH)
    nodes, triangles = mesh.surface()
    overrides = {f"tissue.{k}": v for k, v in COARSE_MESH.items()}
    for comp in ("tissue", "contact"):
        overrides[f"{comp}.n_surface_nodes"] = int(len(nodes))
        overrides[f"{comp}.n_surface_triangles"] = int(len(triangles))
    corners = np.asarray(mesh.points)[np.asarray(nodes)][np.asarray(triangles)]     # (n_tri, 3, 3)
    centroids = corners.mean(axis=1)
    scene_probe = np.array([0.0265, 0.0, 0.065])      # the scene's contact point on the outer wall
    k = int(np.argmin(np.linalg.norm(centroids - scene_probe, axis=1)))
    normal = np.cross(corners[k, 1] - corners[k, 0], corners[k, 2] - corners[k, 0])
    normal /= np.linalg.norm(normal)
    radial = np.array([centroids[k, 0], centroids[k, 1], 0.0])
    if normal @ radial < 0.0:                           # outward: away from the vessel axis
        normal = -normal
    overrides["probe.times"] = list(PROBE_TIMES)
    overrides["probe.outputs"] = {"position": [(centroids[k] + d * normal).tolist() for d in PROBE_OFFSETS]}
    return overrides


def _probe_path(times: np.ndarray, overrides: dict) -> np.ndarray:
    """The scripted probe (piecewise linear) at ``times``, (n, 3)."""
    knots = np.asarray(overrides["probe.outputs"]["position"], float)
    return np.stack([np.interp(times, PROBE_TIMES, knots[:, i]) for i in range(3)], axis=1)


def indentation_run(tissue_rate, haptic_rate, local_model, passivity, stiffness=BASE_STIFFNESS) -> dict:
    """tissue_indentation on the coarse mesh: time, tool force (n, 3), port energy (n,)."""
    from orchestration.observers.recorder import port_values

    overrides = _coarse_mesh_overrides()
    overrides.update({"tissue.step": f"1/{int(tissue_rate)}", "contact.step": f"1/{int(haptic_rate)}",
                      "contact.local_model": str(local_model), "contact.stiffness": float(stiffness),
                      "contact.passivity_controller": bool(passivity)})
    summary, sim = run_point("tissue_indentation", overrides)
    if summary.get("status") not in (None, RunStatus.COMPLETED):
        raise RuntimeError(f"tissue_indentation run failed: {summary.get('error')}")
    time, cols = sim.streams["contact"]
    time = np.asarray(time, float)
    force = port_values(cols, "tool_force")
    x = _probe_path(time, overrides)
    # work done BY the probe ON the environment, force sampled at t_k held over [t_k, t_k+1]
    port = np.concatenate([[0.0], -np.cumsum(np.sum(force[:-1] * np.diff(x, axis=0), axis=1))])
    return {"time": time, "force": force, "port_energy": port}


def force_oscillation(time, force) -> dict:
    """Ripple of |F| in the hold phase: peak-to-peak, and sign changes of d|F|/dt per second."""
    hold = (time >= HOLD_PHASE[0]) & (time <= HOLD_PHASE[1])
    mag = np.linalg.norm(force[hold], axis=1)
    slope = np.diff(mag)
    # ignore round-off wiggles: a step counts when |F| moves by more than 0.1 % of its peak
    slope = slope[np.abs(slope) > 1e-3 * max(float(np.max(mag)), 1e-12)]
    changes = int(np.sum(np.sign(slope[1:]) != np.sign(slope[:-1])))
    mean = float(np.mean(mag)) if mag.size else 0.0
    ripple = float(np.ptp(mag)) if mag.size else 0.0
    return {"ripple_N": ripple, "mean_hold_force_N": mean,
            "stable": bool(mag.size and mean > 0 and ripple < STABLE_RIPPLE * mean),
            "slope_sign_changes_per_s": changes / (HOLD_PHASE[1] - HOLD_PHASE[0])}


def compare_to_reference(run: dict, ref: dict) -> dict:
    """Force error of a run against the single-rate reference, on the reference's sample times."""
    t, f = run["time"], run["force"]
    f_on_ref = np.stack([np.interp(ref["time"], t, f[:, i]) for i in range(3)], axis=1)
    diff = np.linalg.norm(f_on_ref - ref["force"], axis=1)
    scale = float(np.max(np.linalg.norm(ref["force"], axis=1)))
    e_ref = float(ref["port_energy"][-1])
    return {"force_error_rms": float(np.sqrt(np.mean(diff ** 2)) / scale),
            "force_error_max": float(np.max(diff) / scale),
            "final_force_N": float(np.linalg.norm(f[-1])),
            "port_energy_J": float(run["port_energy"][-1]),
            "energy_drift": float((run["port_energy"][-1] - e_ref) / abs(e_ref)),
            "min_port_energy_J": float(np.min(run["port_energy"]))}


# -- sweep points --------------------------------------------------------------------------------
def _save_reference(path: Path, run: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, time=run["time"], force=run["force"], port_energy=run["port_energy"])
    tmp.replace(path)


def _load_reference(path: str) -> dict:
    with np.load(path) as data:
        return {k: data[k] for k in ("time", "force", "port_energy")}


def study_task(point: dict) -> dict:
    """One sweep point; ``point["kind"]`` is bcrit | contacts | reference | multirate."""
    kind = point["kind"]
    if kind == "bcrit":
        K, B, T, mass = point["K"], point["B"], point["T"], point["mass"]
        found = critical_damping(K, B, T, mass, int(point["n_steps"]))
        bound = wall_bound(K, B, T)
        return {**found, "bound": bound, "b_crit_over_bound": found["b_crit"] / bound,
                "b_crit_discrete_model": discrete_critical_damping(mass, K, B, T)}
    if kind == "contacts":
        bound = wall_bound(point["K"], point["B"], point["T"])
        b_dev = point["b_over_bound"] * bound
        out = repeated_contacts(point["K"], point["B"], b_dev, point["T"], point["mass"],
                                int(point["press_steps"]), int(point["release_steps"]))
        return {**out, "b_dev": b_dev, "bound": bound,
                "wall_energy_per_press_over_spring": out["wall_energy_per_press_J"]
                / (0.5 * OPERATOR_FORCE ** 2 / point["K"])}
    if kind == "reference":
        # the wall's compliance even at the single rate: a held wall with a one-step delay limit-cycles
        # from about 3000 N/m at 1 kHz, so it cannot be the reference there
        run = indentation_run(point["haptic_rate"], point["haptic_rate"], "compliance", False,
                              point.get("stiffness", BASE_STIFFNESS))
        _save_reference(Path(point["path"]), run)
        return {**force_oscillation(run["time"], run["force"]),
                "final_force_N": float(np.linalg.norm(run["force"][-1])),
                "port_energy_J": float(run["port_energy"][-1])}
    if kind == "multirate":
        run = indentation_run(point["tissue_rate"], point["haptic_rate"], point["local_model"],
                              bool(point["passivity"]), point.get("stiffness", BASE_STIFFNESS))
        ref = _load_reference(point["reference"])
        return {**compare_to_reference(run, ref), **force_oscillation(run["time"], run["force"])}
    raise ValueError(f"unknown point kind {kind!r}: use bcrit, contacts, reference or multirate")


def discrete_critical_damping(mass, K, B, T) -> float:
    """b_crit of the exact sampled-data model (mass-damper integrated exactly under a zero-order
    hold, wall force -K x[k] - B (x[k] - x[k-1]) / T): the known answer the simulation must hit."""
    def radius(b):
        tau = mass / b
        a = math.exp(-T / tau)
        c = np.array([-K - B / T, 0.0, B / T])
        A = np.zeros((3, 3))
        A[0] = np.array([1.0, tau * (1 - a), 0.0]) + c * (T - tau * (1 - a)) / b
        A[1] = np.array([0.0, a, 0.0]) + c * (1 - a) / b
        A[2, 0] = 1.0
        return float(np.max(np.abs(np.linalg.eigvals(A))))

    bound = wall_bound(K, B, T)
    lo, hi = bound / 64.0, 2.0 * bound
    if radius(lo) < 1.0:
        return lo
    for _ in range(50):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if radius(mid) >= 1.0 else (lo, mid)
    return math.sqrt(lo * hi)


def _grid(quick: bool, out: Path) -> tuple[list[dict], list[dict]]:
    """(first-phase points, multirate points); multirate points need the references."""
    if quick:
        lines = [(800.0, 0.0, 1e-3), (800.0, 0.5, 1e-3), (2000.0, 1.0, 4e-3), (500.0, 2.0, 2.5e-4)]
        heavy = []
        contacts = [(800.0, 0.0, 1e-3, r) for r in (0.8, 1.25)]
        tissue_rates, haptic_rates = (15, 30, 120), (1000,)
        variants = [("hold", False)]
        extra = [(30, 1000, "hold", True), (30, 1000, "extrapolate", False)]
        # the local models at three stiffnesses: error against the single-rate reference, stability
        stiff = [(30, 1000, lm, False, k) for lm in LOCAL_MODELS for k in (200.0, 1000.0, 3000.0)
                 if (lm, k) not in (("hold", BASE_STIFFNESS), ("extrapolate", BASE_STIFFNESS))]
    else:
        lines = [(K, B, T) for K in (500.0, 1000.0, 2000.0) for B in (0.0, 0.5, 2.0)
                 for T in (2.5e-4, 5e-4, 1e-3, 2e-3, 4e-3)]
        heavy = [(K, B, T) for K in (800.0, 2000.0) for B in (0.0, 0.5) for T in (1e-3, 4e-3)]
        contacts = [(K, B, T, r) for K in (500.0, 2000.0) for B in (0.0, 0.5) for T in (1e-3, 4e-3)
                    for r in (0.6, 0.8, 0.9, 0.95, 1.05, 1.1, 1.25, 1.5)]
        tissue_rates, haptic_rates = (15, 30, 60, 120), (250, 1000, 4000)
        variants = [(lm, pc) for lm in LOCAL_MODELS for pc in (False, True)]
        extra = []
        # the stability map: largest stable stiffness against tissue and haptic rate, per local model
        stiff = [(tr, h, lm, False, k) for h in haptic_rates for tr in tissue_rates for lm in LOCAL_MODELS
                 for k in MAP_STIFFNESSES if k != BASE_STIFFNESS]
    first = [{"kind": "bcrit", "K": K, "B": B, "T": T, "mass": light_mass(K, B, T), "n_steps": 400}
             for K, B, T in lines]
    first += [{"kind": "bcrit", "K": K, "B": B, "T": T, "mass": DEVICE_MASS, "n_steps": 3000}
              for K, B, T in heavy]
    first += [{"kind": "contacts", "K": K, "B": B, "T": T, "mass": light_mass(K, B, T), "b_over_bound": r,
               "press_steps": 300, "release_steps": 150} for K, B, T, r in contacts]
    stiffnesses = sorted({BASE_STIFFNESS} | {k for *_, k in stiff})
    refs = {(h, k): str(out / "references" / f"single_rate_{h}Hz_{k:g}Nm.npz")
            for h in haptic_rates for k in stiffnesses}
    first += [{"kind": "reference", "haptic_rate": h, "stiffness": k, "path": p} for (h, k), p in refs.items()]
    multirate = [{"kind": "multirate", "tissue_rate": tr, "haptic_rate": h, "local_model": lm,
                  "passivity": pc, "stiffness": BASE_STIFFNESS, "reference": refs[(h, BASE_STIFFNESS)]}
                 for h in haptic_rates for tr in tissue_rates for lm, pc in variants]
    multirate += [{"kind": "multirate", "tissue_rate": tr, "haptic_rate": h, "local_model": lm,
                   "passivity": pc, "stiffness": BASE_STIFFNESS, "reference": refs[(h, BASE_STIFFNESS)]}
                  for tr, h, lm, pc in extra]
    multirate += [{"kind": "multirate", "tissue_rate": tr, "haptic_rate": h, "local_model": lm,
                   "passivity": pc, "stiffness": k, "reference": refs[(h, k)]} for tr, h, lm, pc, k in stiff]
    return first, multirate


def run(out, quick: bool = False, workers=None, scheduler=None, progress: bool = True) -> Path:
    """Run the stability study into ``out``; returns the path of report.md."""
    from orchestration.studies.sweep import results_table, run_sweep

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    first, multirate = _grid(quick, out)
    results_path = out / "points.jsonl"
    # a reference whose file is gone (e.g. a copied points.jsonl) must be recomputed
    for point in first:
        if point["kind"] == "reference" and not Path(point["path"]).exists():
            _forget(results_path, point)
    results = run_sweep(study_task, first, results_path, workers=workers, scheduler=scheduler,
                        progress=progress, description="stability: wall and references", timeout_s=900)
    results += run_sweep(study_task, multirate, results_path, workers=workers, scheduler=scheduler,
                         progress=progress, description="stability: multirate", timeout_s=900)
    rows = results_table(results)
    write_table(out / "stability.csv", rows)
    for kind in ("bcrit", "contacts", "multirate"):
        write_table(out / f"stability_{kind}.csv", [r for r in rows if r.get("kind") == kind])
    failed = [r for r in results if r.status != "ok"]
    for r in failed:
        logger.warning("point %s failed: %s", r.point, r.error)
    figures = _figures(out, results)
    report = out / "report.md"
    report.write_text(_report(results, figures, quick))
    return report


def _forget(results_path: Path, point: dict) -> None:
    """Drop the ok line of ``point`` from the results file so that the sweep runs it again."""
    from orchestration.studies.sweep import point_key

    if not results_path.exists():
        return
    key = point_key(point)
    lines = results_path.read_text().splitlines()
    kept = [line for line in lines if not (line.strip() and _line_key(line) == key)]
    if len(kept) != len(lines):
        results_path.write_text("".join(line + "\n" for line in kept))


def _line_key(line: str):
    try:
        return json.loads(line).get("key")
    except json.JSONDecodeError:        # a line cut off by a kill: the sweep skips it too
        return None


def _ok(results, kind):
    return [r for r in results if r.status == "ok" and r.point["kind"] == kind]


# -- summaries, figures, report ----------------------------------------------------------------
def wall_agreement(results) -> dict:
    """Largest |b_crit / bound - 1| over the light-device lines (the passivity worst case)."""
    light = [r for r in _ok(results, "bcrit") if r.point["mass"] != DEVICE_MASS]
    dev = [abs(r.values["b_crit_over_bound"] - 1.0) for r in light]
    model = [abs(r.values["b_crit"] / r.values["b_crit_discrete_model"] - 1.0) for r in light]
    return {"n_lines": len(light), "max_rel_dev": max(dev) if dev else float("nan"),
            "mean_rel_dev": float(np.mean(dev)) if dev else float("nan"),
            "max_rel_dev_from_discrete_model": max(model) if model else float("nan")}


def multirate_findings(results) -> list[str]:
    """Convergence order in the tissue rate, extrapolate against hold, passivity on against off."""
    multi = _ok(results, "multirate")
    table = {(r.point["haptic_rate"], r.point["tissue_rate"], r.point["local_model"], r.point["passivity"]): r.values
             for r in multi if _stiffness(r) == BASE_STIFFNESS}
    found = []
    for (h, model) in sorted({(k[0], k[2]) for k in table}):
        rates = sorted(k[1] for k in table if k[0] == h and k[2] == model and not k[3])
        if len(rates) >= 2:
            lo, hi = rates[0], rates[-1]
            e_lo, e_hi = table[(h, lo, model, False)]["force_error_rms"], table[(h, hi, model, False)]["force_error_rms"]
            d_lo, d_hi = table[(h, lo, model, False)]["energy_drift"], table[(h, hi, model, False)]["energy_drift"]
            order = math.log(e_lo / e_hi) / math.log(hi / lo) if e_hi > 0 and e_lo > 0 else float("nan")
            found.append(f"haptic {h} Hz, {model}: force error {e_lo:.3g} at {lo} Hz -> {e_hi:.3g} at {hi} Hz "
                         f"(observed order {order:.2f}); energy drift {d_lo:.3g} -> {d_hi:.3g}")
    pairs = [(v, table[(k[0], k[1], "extrapolate", k[3])]) for k, v in table.items()
             if k[2] == "hold" and (k[0], k[1], "extrapolate", k[3]) in table]
    if pairs:
        ratio = [e["force_error_rms"] / h["force_error_rms"] for h, e in pairs if h["force_error_rms"] > 0]
        ripple = [(e["ripple_N"], h["ripple_N"]) for h, e in pairs]
        found.append(f"extrapolate / hold force error: min {min(ratio):.3f}, median {float(np.median(ratio)):.3f}, "
                     f"max {max(ratio):.3f} over {len(ratio)} pairs; extrapolate has the larger hold-phase ripple in "
                     f"{sum(a > b for a, b in ripple)} of {len(ripple)}")
    onoff = [(v, table[(k[0], k[1], k[2], True)]) for k, v in table.items() if not k[3] and (k[0], k[1], k[2], True) in table]
    if onoff:
        diff = max(abs(a["force_error_rms"] - b["force_error_rms"]) for a, b in onoff)
        min_e = min(a["min_port_energy_J"] for a, b in onoff)
        found.append(f"passivity controller on vs off: largest change of the force error {diff:.2e} over {len(onoff)} "
                     f"pairs; the smallest port energy seen is {min_e:.2e} J (the controller acts only when it is < 0)")
    by_stiffness = {}
    for r in multi:
        if not r.point["passivity"]:
            by_stiffness[(r.point["haptic_rate"], r.point["tissue_rate"], _stiffness(r), r.point["local_model"])] = r.values
    for (h, tr, k) in sorted({key[:3] for key in by_stiffness}):
        models = {m: by_stiffness[(h, tr, k, m)] for m in LOCAL_MODELS if (h, tr, k, m) in by_stiffness}
        if len(models) > 1:
            found.append(f"haptic {h} Hz, tissue {tr} Hz, {k:g} N/m: force error " + ", ".join(
                f"{m} {v['force_error_rms']:.3g}{'' if v['stable'] else ' (limit cycle)'}" for m, v in models.items()))
    for (h, tr, m), k in sorted(stability_map(results).items()):
        found.append(f"largest stable stiffness, haptic {h} Hz, tissue {tr} Hz, {m}: {k:g} N/m")
    return found


def _stiffness(result) -> float:
    return float(result.point.get("stiffness", BASE_STIFFNESS))


def stability_map(results) -> dict:
    """(haptic rate, tissue rate, local model) -> the largest stiffness of the grid below which every
    run is stable (0 when the smallest already limit-cycles), over the points without passivity
    control; only where at least two stiffnesses were run."""
    runs = {}
    for r in results:
        if r.point.get("kind") != "multirate" or r.point.get("passivity"):
            continue
        stable = r.status == "ok" and bool(r.values.get("stable"))
        runs.setdefault((r.point["haptic_rate"], r.point["tissue_rate"], r.point["local_model"]), []).append(
            (_stiffness(r), stable))
    found = {}
    for key, points in runs.items():
        if len(points) < 2:
            continue
        largest = 0.0
        for k, stable in sorted(points):
            if not stable:
                break
            largest = k
        found[key] = largest
    return found


def _figures(out: Path, results) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    bcrit = _ok(results, "bcrit")
    if bcrit:
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.5))
        for light, marker, label in ((True, "o", "light device (m = 1e-3 bound T)"),
                                     (False, "s", f"desktop device (m = {DEVICE_MASS:g} kg)")):
            rows = [r for r in bcrit if (r.point["mass"] != DEVICE_MASS) == light]
            if not rows:
                continue
            bound = np.array([r.values["bound"] for r in rows])
            crit = np.array([r.values["b_crit"] for r in rows])
            ax1.loglog(bound, crit, marker, mfc="none", label=label)
            T = np.array([r.point["T"] for r in rows]) * 1e3
            ax2.semilogx(T * (1 + 0.04 * np.array([r.point["B"] for r in rows])), crit / bound, marker,
                         mfc="none", label=label)
        span = np.array([1e-2, 10.0])
        ax1.loglog(span, span, "k-", lw=0.8, label="b = K T / 2 + |B|")
        ax1.fill_between(span, 0.9 * span, 1.1 * span, color="0.85", label="+-10 %")
        ax1.set_xlabel("Colgate-Schenkel bound K T/2 + |B| (N s/m)")
        ax1.set_ylabel("empirical b_crit (N s/m)")
        ax1.legend(fontsize=8)
        ax2.axhspan(0.9, 1.1, color="0.85")
        ax2.axhline(1.0, color="k", lw=0.8)
        ax2.set_xlabel("haptic period T (ms), points offset by B")
        ax2.set_ylabel("b_crit / bound")
        ax2.set_ylim(-0.05, 1.3)
        fig.suptitle("Virtual wall: empirical critical device damping against the passivity bound")
        fig.tight_layout()
        fig.savefig(out / "bcrit_vs_bound.png", dpi=110)
        plt.close(fig)
        files.append("bcrit_vs_bound.png")
    contacts = _ok(results, "contacts")
    if contacts:
        fig, ax = plt.subplots(figsize=(7, 4.5))
        groups = sorted({(r.point["K"], r.point["B"], r.point["T"]) for r in contacts})
        for K, B, T in groups:
            # a tunnelled run (the device jumped through the wall) has no contact energy to show
            rows = sorted((r for r in contacts if (r.point["K"], r.point["B"], r.point["T"]) == (K, B, T)
                           and not r.values.get("tunnelled")), key=lambda r: r.point["b_over_bound"])
            ax.semilogy([r.point["b_over_bound"] for r in rows],
                        [max(r.values["wall_energy_per_press_over_spring"], 1e-6) for r in rows], "o-",
                        label=f"K={K:g} B={B:g} T={T * 1e3:g} ms")
        ax.axvline(1.0, color="k", lw=0.8)
        ax.set_xlabel("b_dev / (K T / 2 + |B|)")
        ax.set_ylabel("wall work per press / (F0^2 / 2K)")
        ax.set_title("Energy the wall puts into the device over repeated contacts\n"
                     "(runs where the device tunnelled through the wall are left out)", fontsize=10)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "wall_energy.png", dpi=110)
        plt.close(fig)
        files.append("wall_energy.png")
    multi = [r for r in _ok(results, "multirate") if not r.point["passivity"] and _stiffness(r) == BASE_STIFFNESS]
    if multi:
        tissue = sorted({r.point["tissue_rate"] for r in multi})
        haptic = sorted({r.point["haptic_rate"] for r in multi})
        models = sorted({r.point["local_model"] for r in multi})
        metrics = (("force_error_rms", "force error (RMS / peak of reference)"),
                   ("energy_drift", "port energy drift (relative)"))
        fig, axes = plt.subplots(len(metrics), len(models), figsize=(4.5 * len(models), 7), squeeze=False)
        for j, model in enumerate(models):
            for i, (name, title) in enumerate(metrics):
                grid = np.full((len(haptic), len(tissue)), np.nan)
                for r in multi:
                    if r.point["local_model"] == model:
                        grid[haptic.index(r.point["haptic_rate"]), tissue.index(r.point["tissue_rate"])] = \
                            r.values[name]
                ax = axes[i, j]
                im = ax.imshow(grid, origin="lower", aspect="auto", cmap="viridis")
                for (a, b), v in np.ndenumerate(grid):
                    ax.text(b, a, f"{v:.3g}", ha="center", va="center", color="w", fontsize=8)
                ax.set_xticks(range(len(tissue)), [str(t) for t in tissue])
                ax.set_yticks(range(len(haptic)), [str(h) for h in haptic])
                ax.set_xlabel("tissue rate (Hz)")
                ax.set_ylabel("haptic rate (Hz)")
                ax.set_title(f"{title}\nlocal model: {model}", fontsize=9)
                fig.colorbar(im, ax=ax)
        fig.tight_layout()
        fig.savefig(out / "multirate_error.png", dpi=110)
        plt.close(fig)
        files.append("multirate_error.png")
    return files


def _fmt(value, digits=3) -> str:
    return "nan" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}g}"


def _report(results, figures, quick) -> str:
    lines = [f"# Stability study{' (quick)' if quick else ''}", ""]
    failed = [r for r in results if r.status != "ok"]
    lines += [f"Points: {len(results)} ({len(failed)} failed).", ""]
    agreement = wall_agreement(results)
    lines += ["## Virtual wall: b_crit against the Colgate-Schenkel bound b_dev > K T/2 + |B|", "",
              "Measurement: the device rests against the wall under a constant operator force "
              f"F0 = {OPERATOR_FORCE:g} N, started 2 % off its equilibrium; the oscillation energy "
              "K (x - x*)^2/2 + m v^2/2 is compared between the first and last 40 steps of 400 (growth > 0 "
              "or leaving the wall = unstable: the sampled wall puts in more energy per cycle than "
              "b_dev v^2 takes out). b_crit is bisected on b_dev (14 geometric halvings, bracket "
              "< 0.1 %). The passivity bound is a worst case over the operator; the worst case is a "
              f"device whose inertia is negligible over one period (m = {LIGHT_INERTIA:g} x bound x T; with a "
              "fixed 1 mg the K = 500 N/m, T = 0.25 ms line (m/(bound T) = 0.064) fell 15 % below the bound, "
              "as the exact model of that plant also does), "
              "where the loop loses stability exactly at the bound, at the Nyquist frequency.", "",
              f"Light-device lines: {agreement['n_lines']}; |b_crit/bound - 1|: max "
              f"{_fmt(100 * agreement['max_rel_dev'])} %, mean {_fmt(100 * agreement['mean_rel_dev'])} % "
              f"(target 10 %); largest deviation from the exact sampled-data model of the same plant: "
              f"{_fmt(100 * agreement['max_rel_dev_from_discrete_model'])} %.", "",
              "| mass (kg) | K (N/m) | B (N s/m) | T (ms) | bound | b_crit | b_crit/bound | exact discrete model | note |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(_ok(results, "bcrit"), key=lambda r: (r.point["mass"], r.point["K"], r.point["B"], r.point["T"])):
        p, v = r.point, r.values
        lines.append(f"| {p['mass']:g} | {p['K']:g} | {p['B']:g} | {p['T'] * 1e3:g} | {v['bound']:.4g} | "
                     f"{v['b_crit']:.4g} | {v['b_crit_over_bound']:.4f} | {v['b_crit_discrete_model']:.4g} | "
                     f"{v.get('note', '')} |")
    heavy = [r for r in _ok(results, "bcrit") if r.point["mass"] == DEVICE_MASS]
    if heavy:
        lines += ["", "The desktop device (0.1 kg) reaches the bound only for B = 0 (its oscillation is "
                  "slow, where the held spring's negative damping is K T/2); with B > 0 it is stable far "
                  "below the bound (at low frequency the differenced damper dissipates), so the bound is "
                  "conservative there: the |B| term is a Nyquist-frequency worst case."]
    contacts = _ok(results, "contacts")
    if contacts:
        lines += ["", "## Energy over repeated contacts", "",
                  "Three presses of F0 (300 steps each, 150 released). Energy metric: the net work of "
                  "the wall on the device over all presses (device.wall_energy at the end; the device is "
                  "then free, so an ideal spring would give 0 and anything > 0 was generated by the "
                  "sampled wall), per press and normalised by the spring energy F0^2/2K, and its share of "
                  "what b_dev dissipated while in contact (1 = the wall drives the motion).", "",
                  "| K | B | T (ms) | b/bound | wall work/press / (F0^2/2K) | share of in-contact dissipation | contact onsets | settled | max depth / x* |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in sorted(contacts, key=lambda r: (r.point["K"], r.point["B"], r.point["T"], r.point["b_over_bound"])):
            p, v = r.point, r.values
            lines.append(f"| {p['K']:g} | {p['B']:g} | {p['T'] * 1e3:g} | {p['b_over_bound']:g} | "
                         f"{v['wall_energy_per_press_over_spring']:.3g} | {v['wall_share_of_dissipation']:.3f} | "
                         f"{v['contact_onsets']} | {v['settled']}{' (tunnelled)' if v.get('tunnelled') else ''} | "
                         f"{v.get('max_depth_over_equilibrium', float('nan')):.3g} |")
        wrong = [r for r in contacts if r.values["settled"] != (r.point["b_over_bound"] > 1.0)]
        lines += ["", f"Settled iff b_dev > bound in {len(contacts) - len(wrong)} of {len(contacts)} points."]
    multi = _ok(results, "multirate")
    if multi:
        lines += ["", "## Multirate tissue/haptic coupling (tissue_indentation, coarse mesh 16x20x1)", "",
                  "Force error: RMS over time of |F - F_ref| / max |F_ref|, F_ref the single-rate run "
                  "(tissue rate = haptic rate, compliance local model) at the same haptic rate and stiffness. Energy drift: (E - E_ref) / "
                  "E_ref of the work the probe did on the environment (E = -sum F_k . dx_k, F held over the "
                  "haptic step). Oscillation: peak-to-peak of |F| and sign changes/s of d|F|/dt (steps > "
                  "0.1 % of peak) in the hold phase t in [1.3, 2] s. The probe travels along the normal of the "
                  "outer facet nearest the scene's probe point (3 mm outside to 2 mm inside, the scene's "
                  "timing): the scene's probe sits on a node of the coarse mesh, where the contact normal "
                  "jumps between facets and the lateral force flips sign between runs that differ by "
                  "round-off, which would swamp the multirate effects.", ""]
        for r in _ok(results, "reference"):
            lines.append(f"Reference {r.point['haptic_rate']} Hz, {_stiffness(r):g} N/m: final |F| {r.values['final_force_N']:.4g} N, "
                         f"ripple {r.values['ripple_N']:.3g} N, port energy {r.values['port_energy_J']:.4g} J.")
        lines += ["", f"Stable: |F| varies by less than {STABLE_RIPPLE:.0%} of its mean in the hold phase.", "",
                  "| haptic Hz | tissue Hz | stiffness N/m | local model | passivity | force err RMS | force err max | "
                  "energy drift | ripple (N) | stable | d|F| sign changes/s | min port energy (J) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in sorted(multi, key=lambda r: (r.point["haptic_rate"], _stiffness(r), r.point["local_model"],
                                              r.point["passivity"], r.point["tissue_rate"])):
            p, v = r.point, r.values
            lines.append(f"| {p['haptic_rate']} | {p['tissue_rate']} | {_stiffness(r):g} | {p['local_model']} | "
                         f"{p['passivity']} | {v['force_error_rms']:.3f} | {v['force_error_max']:.3f} | "
                         f"{v['energy_drift']:.4f} | {v['ripple_N']:.3f} | {v['stable']} | "
                         f"{v['slope_sign_changes_per_s']:.1f} | {v['min_port_energy_J']:.2e} |")
        found = stability_map(results)
        if found:
            lines += ["", "Largest stable stiffness (N/m) of the grid, by local model:", "",
                      "| haptic Hz | tissue Hz | " + " | ".join(LOCAL_MODELS) + " |",
                      "|---|---|" + "---|" * len(LOCAL_MODELS)]
            for h, tr in sorted({(a, b) for a, b, _ in found}):
                lines.append(f"| {h} | {tr} | " + " | ".join(
                    f"{found[(h, tr, m)]:g}" if (h, tr, m) in found else "" for m in LOCAL_MODELS) + " |")
    if multi:
        lines += ["", "Findings (computed from the rows above):", ""] + [f"- {f}" for f in multirate_findings(results)]
    if failed:
        lines += ["", "## Failed points", ""] + [f"- {r.point}: {r.error}" for r in failed]
    lines += ["", "Figures: " + ", ".join(figures), ""]
    return "\n".join(lines)

"""Numerical extremes (issue 6): one row per extreme, each ``stable``, ``detected`` or ``failing``.

Every row is a sweep point (``orchestration.studies.sweep.run_sweep`` over :func:`run_row`) that runs the
real FMUs through the orchestrator (in-process hosting); only the explicit-step rows use the
Tissue model once, before the run, to read the critical time step they need to pick ``substeps``.

Outcome rules (the same for every row, see :func:`classify`):

- ``stable``: the run completed, every recorded output is finite, and the row's physical bound
  holds (stated per row in the ``bound`` column: tissue surface displacement below the sac radius
  25 mm; haptic wall: the wall never returns more energy to the device than the operator put in).
- ``detected``: the run stopped (or logged a warning) with a message naming the problem; the
  message is copied into the table verbatim.
- ``failing``: anything else: a crash of the study code, NaN or a blow-up without a message, a
  bound broken silently.  A failing row is a finding, not a test failure to hide.
"""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np

from fmu_build.paths import DEFAULT_FMU_DIR
from orchestration.blocks.plant import PLANT_LIMITS
from orchestration.run.status import RunStatus
from orchestration.studies.common import run_point, write_table

logger = logging.getLogger(__name__)

# Physical bounds of the ``stable`` verdict.
MAX_TISSUE_DISPLACEMENT_M = 0.025  # the sac radius: a wall node moving farther has blown up
# A passive rebound carries at most the operator's work (~0.2 J here): v <= 2 m/s, and the device
# damping (1 N s/m, 0.1 kg) stops it within m v / b_dev = 0.2 m.
MAX_DEVICE_EXCURSION_M = 0.5

QUICK_MESH = {"n_circumferential": 16, "n_axial": 20, "n_radial": 1}
FULL_MESH = {"n_circumferential": 32, "n_axial": 40, "n_radial": 2}
# Extreme aspect ratio: 8 radial layers of 0.19 mm under 20 mm x 13 mm faces (about 100:1).
ASPECT_MESH = {"n_circumferential": 8, "n_axial": 10, "n_radial": 8}

# The probe of the tissue_indentation scene, along +x at the sac's widest section (z = 65 mm):
# outer wall at r = 26.5 mm, lumen wall at 25 mm.
PROBE_Z = 0.065
# The probe's contact these rows were measured with (the scene's before it moved to 1000 N/m with
# the compliance local model): stable against the 30 Hz wall; pinned so rows compare.
PROBE_STIFFNESS = 200.0
PROBE_LOCAL_MODEL = "extrapolate"


def _probe(times, radii):
    return {"probe.times": list(map(float, times)),
            "probe.outputs": {"position": [[float(r), 0.0, PROBE_Z] for r in radii]}}


# ------------------------------------------------------------------------------------------
# Rows
# ------------------------------------------------------------------------------------------

#: tissue rows also run with the frame-budgeted step (issue 35)
BUDGETED_TWINS = ("young_1000", "young_1e+08", "implicit_step_0.1", "extreme_indentation_etmm")


def rows(quick: bool) -> list[dict]:
    """Sweep points: scalars only (``row`` names it, ``kind`` says how it runs)."""
    tissue = []
    for nu in (0.49, 0.499, 0.4999):
        tissue.append({"row": f"poisson_{nu:g}", "kind": "tissue", "setting": f"poisson_ratio = {nu:g}, implicit",
                       "poisson_ratio": nu})
    for e in (1e3, 1e5, 1.044e6, 1e7, 1e8):
        tissue.append({"row": f"young_{e:g}", "kind": "tissue", "setting": f"young_modulus = {e:g} Pa, implicit",
                       "young_modulus": e})
    for m in (0.5, 1.0, 2.0):
        tissue.append({"row": f"explicit_{m:g}x", "kind": "tissue",
                       "setting": f"explicit, substep = {m:g} x critical_time_step", "critical_multiple": m})
    for step, label in (("1/30", "1/30"), (0.05, "0.05"), (0.1, "0.1")):
        tissue.append({"row": f"implicit_step_{label}", "kind": "tissue",
                       "setting": f"implicit, tissue step {label} s", "tissue_step": step})
    tissue.append({"row": "sliver_mesh_file", "kind": "tissue", "mesh": "sliver",
                   "setting": "mesh_file with a sliver tet (radius ratio ~4e-4) under the probe"})
    tissue.append({"row": "aspect_ratio_mesh", "kind": "tissue", "mesh": "aspect",
                   "setting": "AAA generator 8 x 10 x 8 (0.19 mm x 20 mm x 13 mm elements)"})
    for law in ("etmm", "linear", "hyperelastic"):
        tissue.append({"row": f"extreme_indentation_{law}", "kind": "tissue", "load": "extreme", "law": law,
                       "setting": f"law {law}: probe centre driven 16.5 mm past the outer wall, K = 5000 N/m"})
    for detection in ("continuous", "discrete"):
        tissue.append({"row": f"tool_10mps_wall_{detection}", "kind": "tissue", "load": "fast",
                       "detection": detection,
                       "setting": f"probe at 10 m/s through the 1.5 mm wall, {detection} detection"})
    # The frame-budgeted step (the shipped scenes' choice, 4 iterations) at the extremes of the
    # exact step's rows: soft and stiff walls, a long step, the deep indentation.
    tissue += [{**row, "row": f"{row['row']}_budgeted", "implicit_step": "budgeted",
                "setting": f"{row['setting']}, budgeted step (4 iterations)"}
               for row in list(tissue) if row["row"] in BUDGETED_TWINS]
    plane = [{"row": f"tool_10mps_plane_{d}", "kind": "plane", "detection": d,
              "setting": f"probe at 10 m/s 20 mm through a rigid plane, {d} detection"}
             for d in ("continuous", "discrete")]
    haptic = [{"row": f"haptic_K{k:g}_pc_{'on' if pc else 'off'}", "kind": "haptic", "stiffness": float(k),
               "passivity_controller": pc,
               "setting": f"virtual wall K = {k:g} N/m, passivity controller {'on' if pc else 'off'}"}
              for k, pc in ((800, False), (2000, False), (20000, False), (800, True), (5000, True), (20000, True))]
    nan = [{"row": "nan_source_runtime", "kind": "nan_runtime",
            "setting": "device plant mass 1e-10 kg pushed with 1e308 N: position overflows to Inf/NaN into Contact"},
           {"row": "nan_source_scene", "kind": "nan_scene",
            "setting": "piecewise source with a NaN knot value"}]
    points = tissue + plane + haptic + nan
    if quick:
        keep = {"poisson_0.499", "young_1e+08", "explicit_0.5x", "explicit_1x", "explicit_2x", "implicit_step_0.1",
                "young_1e+08_budgeted", "implicit_step_0.1_budgeted",
                "tool_10mps_wall_continuous", "extreme_indentation_hyperelastic",
                "sliver_mesh_file", "tool_10mps_plane_continuous", "tool_10mps_plane_discrete",
                "haptic_K800_pc_off", "haptic_K20000_pc_on", "nan_source_runtime", "nan_source_scene"}
        points = [p for p in points if p["row"] in keep]
    for p in points:
        p["quick"] = quick
    return points


# ------------------------------------------------------------------------------------------
# The sweep task (top level: pickled to the workers)
# ------------------------------------------------------------------------------------------

def run_row(point: dict) -> dict:
    """Run one extreme and classify it; never raises for a problem the run itself hits."""
    kind = point["kind"]
    start = time.perf_counter()
    try:
        runner = {"tissue": _run_tissue, "plane": _run_plane, "haptic": _run_haptic,
                  "nan_runtime": _run_nan_runtime, "nan_scene": _run_nan_scene}[kind]
        result = runner(point)
    except Exception as exc:  # a crash of the study or the orchestrator is itself the finding
        logger.exception("row %s crashed", point["row"])
        result = {"outcome": "failing", "message": f"crash: {type(exc).__name__}: {exc}", "bound": ""}
    result["run_wall_s"] = time.perf_counter() - start
    return _jsonable(result)


def classify(summary: dict, finite: bool, within_bound: bool) -> tuple[str, str]:
    """(outcome, message) from a run summary, whether all outputs were finite and the bound held."""
    messages = [f"{m.get('component', '?')} {m.get('status')}: {m.get('message', '')}"
                for m in summary.get("fmu_messages", [])
                if m.get("status") in ("warning", "error", "fatal", "discard")]
    if summary.get("status") != RunStatus.COMPLETED:
        return "detected" if summary.get("error") else "failing", summary.get("error") or "stopped without a message"
    if messages:
        return "detected", _summarise(messages)
    if finite and within_bound:
        return "stable", ""
    return "failing", ("non-finite outputs without a message" if not finite
                       else "bound exceeded without a message")


def _summarise(messages: list[str], keep: int = 2) -> str:
    """The first ``keep`` distinct messages (numbers aside) verbatim, and how many were logged."""
    import re

    seen, shown = set(), []
    for text in messages:
        shape = re.sub(r"[-+0-9.e]+", "#", text)
        if shape not in seen:
            seen.add(shape)
            shown.append(text)
    head = " | ".join(shown[:keep])
    return head if len(messages) <= keep else f"{head} | ({len(messages)} warnings logged in all)"


# -- tissue rows (tissue_indentation scene) --------------------------------------------------

def _mesh_sizes(point) -> dict:
    if point.get("mesh") == "aspect":
        return dict(ASPECT_MESH)
    if point.get("load") == "extreme":  # one radial layer: every node is a surface node, so the
        return {**(QUICK_MESH if point["quick"] else FULL_MESH), "n_radial": 1}  # tets can be checked
    return dict(QUICK_MESH if point["quick"] else FULL_MESH)


def _structural(overrides: dict, n_nodes: int, n_triangles: int) -> None:
    for comp in ("tissue", "contact"):
        overrides[f"{comp}.n_surface_nodes"] = int(n_nodes)
        overrides[f"{comp}.n_surface_triangles"] = int(n_triangles)


def _sliver_mesh(sizes: dict, path: Path) -> tuple[object, float]:
    """The AAA mesh with a sliver layer under the probe; returns (mesh, min radius ratio)."""
    from tissue_fmu.mesh import TetMesh, aaa_mesh, save_mesh

    mesh = aaa_mesh(**sizes)
    points = mesh.points.copy()
    outer = mesh.node_sets["outer"]
    k = outer[np.argmin(np.linalg.norm(points[outer] - [0.0265, 0.0, PROBE_Z], axis=1))]
    # The next node inward on the same radial line (the lumen node when n_radial = 1), moved 99.9 %
    # of the way to the outer node: the tets between the two layers there turn into slivers while the
    # outer wall the probe touches stays where it was.
    radial = np.flatnonzero((np.abs(points[:, 1] - points[k, 1]) < 1e-12) & (np.abs(points[:, 2] - points[k, 2]) < 1e-12)
                            & (points[:, 0] > 0.0) & (points[:, 0] < points[k, 0]))
    j = radial[np.argmax(points[radial, 0])]
    points[j] = points[j] + 0.999 * (points[k] - points[j])
    sliver = TetMesh(points, mesh.tets, mesh.node_sets, mesh.element_sets)
    save_mesh(sliver, path)
    return sliver, sliver.quality()["min_radius_ratio"]


def _critical_step(sizes: dict, overrides: dict) -> float:
    from tissue_fmu.mesh import aaa_mesh
    from tissue_fmu.model import TissueModel, TissueParameters

    params = TissueParameters(law="etmm", integrator="explicit", viscosity=50.0)
    return TissueModel(aaa_mesh(**sizes), params).critical_time_step


def _run_tissue(point: dict) -> dict:
    import tempfile

    from tissue_fmu.mesh import aaa_mesh

    quick = point["quick"]
    duration = 0.4 if quick else 1.0
    sizes = _mesh_sizes(point)
    # the exact step unless the row is a budgeted twin: the rows characterise the laws and meshes
    overrides: dict = {"tissue.integrator": "implicit", "contact.stiffness": PROBE_STIFFNESS,
                       "contact.local_model": PROBE_LOCAL_MODEL,
                       "tissue.implicit_step": point.get("implicit_step", "exact")}
    numbers: dict = {}
    with tempfile.TemporaryDirectory(prefix="extremes_mesh_") as tmp:
        if point.get("mesh") == "sliver":
            mesh, ratio = _sliver_mesh(sizes, Path(tmp) / "sliver.vtu")
            overrides["tissue.mesh_file"] = str(Path(tmp) / "sliver.vtu")
            numbers["min_radius_ratio"] = ratio
        else:
            mesh = aaa_mesh(**sizes)
            overrides.update({f"tissue.{k}": v for k, v in sizes.items()})
        rest_nodes, triangles = mesh.surface()
        rest = mesh.points[rest_nodes]
        _structural(overrides, len(rest_nodes), len(triangles))
        # Probe: its centre 1 mm off the outer wall (r = 26.5 mm) at rest, pressed to 1 mm
        # nominal indentation (less than the 1.5 mm wall) over 60 % of the run, then held (contact
        # is measured from the probe centre here: it starts when the centre reaches r = 26.5 mm).
        overrides.update(_probe([0.0, 0.02, 0.6 * duration, duration], [0.0275, 0.0275, 0.0255, 0.0255]))
        if "law" in point:
            overrides["tissue.law"] = point["law"]
        for key in ("poisson_ratio", "young_modulus"):
            if key in point:
                overrides[f"tissue.{key}"] = point[key]
        if "tissue_step" in point:
            overrides["tissue.step"] = point["tissue_step"]
        if "critical_multiple" in point:
            duration = 0.1  # about 50k (quick) to 100k substeps
            overrides.update(_probe([0.0, 0.01, 0.06, duration], [0.0270, 0.0270, 0.0258, 0.0258]))
            overrides["tissue.integrator"] = "explicit"
            overrides["tissue.step"] = 0.002  # 500 Hz: same substep cost, finer outputs
            critical = _critical_step(sizes, overrides)
            m = point["critical_multiple"]
            dt = 0.002
            substeps = math.ceil(dt / (m * critical)) if m <= 1.0 else max(1, math.floor(dt / (m * critical)))
            overrides["tissue.substeps"] = substeps
            numbers.update(critical_time_step_s=critical, substeps=substeps,
                           substep_over_critical=dt / substeps / critical)
        if point.get("load") == "extreme":
            overrides["contact.stiffness"] = 5000.0
            overrides.update(_probe([0.0, 0.02, 0.6 * duration, duration], [0.0295, 0.0295, 0.010, 0.010]))
        if point.get("load") == "fast":
            # 10 m/s: 10 mm per 1 ms haptic sample, the wall is 1.5 mm thick.
            t0 = 0.05
            overrides["contact.detection"] = point["detection"]
            overrides.update(_probe([0.0, t0, t0 + 0.002, duration], [0.0395, 0.0395, 0.0195, 0.0195]))
            numbers["tool_speed_mps"] = 10.0
        summary, sim = run_point("tissue_indentation", overrides, duration=duration,
                                 observe={"tissue": ["critical_time_step"], "contact": ["tool_force"]})
    numbers.update(_stream_numbers(sim))
    final = sim.final_outputs.get("tissue", {})
    finite = numbers.pop("_finite")
    displacement = math.nan
    if "surface_positions" in final and summary["simulated_time_s"] > 0:
        moved = final["surface_positions"].reshape(-1, 3) - rest
        displacement = float(np.abs(moved).max()) if np.isfinite(moved).all() else math.inf
        finite = finite and math.isfinite(displacement)
    numbers["final_max_displacement_m"] = displacement
    numbers["critical_time_step_s"] = numbers.get("critical_time_step_s",
                                                  float(final.get("critical_time_step", [math.nan])[0]))
    within = math.isfinite(displacement) and displacement < MAX_TISSUE_DISPLACEMENT_M
    if "surface_positions" in final and len(rest_nodes) == mesh.n_nodes and summary["simulated_time_s"] > 0:
        numbers.update(_inversion(mesh, rest_nodes, final["surface_positions"]))
    numbers["bound_held"] = bool(finite and within and numbers.get("inverted_tets", 0) == 0)
    outcome, message = classify(summary, finite, within)
    if outcome == "stable" and numbers.get("inverted_tets", 0) > 0:
        outcome, message = "failing", (f"{numbers['inverted_tets']} tets inverted (volume ratio down to "
                                       f"{numbers['min_volume_ratio']:.3g}) and nothing was logged")
    if point.get("load") == "fast":
        numbers["tunnelled"] = numbers.get("contact_samples", 0) == 0
        if outcome == "stable" and numbers["tunnelled"]:
            outcome, message = "failing", ("tool tunnelled through the 1.5 mm wall: no contact was ever reported "
                                           "and nothing was logged")
    return {"outcome": outcome, "message": message, "status": summary["status"],
            "simulated_time_s": summary["simulated_time_s"],
            "bound": f"finite; surface displacement < {MAX_TISSUE_DISPLACEMENT_M * 1e3:g} mm; no inverted tet (n_radial = 1 meshes)", **numbers}


def _inversion(mesh, surface_nodes, surface_positions) -> dict:
    """Signed tet volumes of the final state over rest volumes (every node is a surface node)."""
    points = mesh.points.copy()
    points[surface_nodes] = np.asarray(surface_positions, dtype=float).reshape(-1, 3)

    def volumes(p):
        a, b, c, d = (p[mesh.tets[:, i]] for i in range(4))
        return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6.0

    ratio = volumes(points) / volumes(mesh.points)
    return {"inverted_tets": int(np.count_nonzero(ratio <= 0.0)), "min_volume_ratio": float(ratio.min())}


def _stream_numbers(sim) -> dict:
    """Peaks of the recorded streams; ``_finite`` is False when any recorded value is NaN/Inf."""
    out: dict = {"_finite": True}
    for comp, (times, columns) in getattr(sim, "streams", {}).items():
        for name, values in columns.items():
            values = np.asarray(values, dtype=float)
            if values.size and not np.isfinite(values).all():
                out["_finite"] = False
        if comp == "tissue":
            for name in ("max_strain", "strain_energy", "solver_iterations"):
                if name in columns and len(columns[name]):
                    out[f"peak_{name}"] = float(np.nanmax(columns[name]))
        if comp == "contact":
            force = _norm(columns, "tool_force")
            if force is not None and force.size:
                out["peak_tool_force_N"] = float(np.nanmax(force))
                out["final_tool_force_N"] = float(force[-1])
            if "penetration_depth" in columns and len(columns["penetration_depth"]):
                out["peak_penetration_m"] = float(np.nanmax(columns["penetration_depth"]))
            if "contact_count" in columns:
                touching = np.flatnonzero(np.asarray(columns["contact_count"]) > 0)
                out["contact_samples"] = int(touching.size)
                if touching.size:
                    out["first_contact_s"] = float(times[touching[0]])
                    out["last_contact_s"] = float(times[touching[-1]])
    return out


def _norm(columns: dict, port: str):
    parts = [columns.get(f"{port}[{i}]") for i in range(3)]
    if any(p is None for p in parts):
        return None
    return np.sqrt(sum(np.asarray(p, dtype=float) ** 2 for p in parts))


# -- rigid plane at 10 m/s (a scene written here: Contact, a plane, a scripted probe) ------------

PLANE_SCENE = """
[scene]
name = "extremes_fast_tool"
description = "probe at 10 m/s through a rigid plane (extremes study)"
duration = {duration}
hosting = "in-process"

[source.wall]
kind = "rigid_surface"
shape = "plane"
center = [0.0, 0.0, 0.0]
normal = [-1.0, 0.0, 0.0]
size = 0.1
divisions = 1

[source.probe]
kind = "piecewise_linear"
times = [0.0, 0.0100, 0.0140, {duration}]
outputs = {{ position = [[-0.0205, 0.0, 0.0], [-0.0205, 0.0, 0.0], [0.0195, 0.0, 0.0], [0.0195, 0.0, 0.0]] }}
units = {{ position = "m" }}

[fmu.contact]
path = "{fmus}/Contact.fmu"
step = 0.001
[fmu.contact.parameters]
tool = "probe"
n_tool_points = 1
n_surface_nodes = 4
n_surface_triangles = 2
stiffness = 800.0
damping = 0.0
tool_radius = 0.0
margin = 0.01
detection = "{detection}"
local_model = "hold"
max_force = 1000.0              # the contact alone: no device limit (its 15.6 N is what the row measures)
max_force_rate = 1e7

[[connection]]
from = "wall.triangles"
to = "contact.surface_triangles"
[[connection]]
from = "wall.positions"
to = "contact.tissue_positions"
[[connection]]
from = "wall.velocities"
to = "contact.tissue_velocities"
[[connection]]
from = "probe.position"
to = "contact.tool_positions"

[record]
contact = ["tool_force", "penetration_depth", "contact_count"]
"""


def _fmus_dir() -> Path:
    return DEFAULT_FMU_DIR


def _run_plane(point: dict) -> dict:
    import tempfile

    duration = 0.05
    with tempfile.TemporaryDirectory(prefix="extremes_plane_") as tmp:
        scene = Path(tmp) / "fast_tool.toml"
        scene.write_text(PLANE_SCENE.format(duration=duration, detection=point["detection"], fmus=_fmus_dir()))
        summary, sim = run_point(str(scene), {}, duration=duration)
    numbers = _stream_numbers(sim)
    finite = numbers.pop("_finite")
    # The probe ends 19.5 mm behind the plane, at rest: a detector that keeps the contact reports
    # that depth and K * depth = 15.6 N; one that lost it (tunnelled) reports nothing.
    depth = numbers.get("peak_penetration_m", 0.0)
    numbers["final_depth_behind_plane_m"] = 0.0195
    numbers["tunnelled"] = bool(depth < 0.5 * 0.0195)
    numbers["bound_held"] = bool(finite and not numbers["tunnelled"])
    outcome, message = classify(summary, finite, True)
    if outcome == "stable" and numbers["tunnelled"]:
        outcome, message = "failing", "tool tunnelled through the wall: no contact reported, no message"
    return {"outcome": outcome, "message": message, "status": summary["status"],
            "simulated_time_s": summary["simulated_time_s"],
            "bound": "finite; contact kept after crossing (penetration >= half the true 19.5 mm)", **numbers}


# -- haptic virtual wall ------------------------------------------------------------------------

def _run_haptic(point: dict) -> dict:
    # The loop with the device's damping is judged (Colgate), not the contact alone: its sampled,
    # undamped wall creates about 5 % of each contact cycle's exchange, which the device's damping
    # takes out below the bound, so the per-cycle report is off; and the device limit is lifted
    # (the rows measure the wall, not the PHANTOM's 7.9 N).
    overrides = {"contact.stiffness": point["stiffness"], "contact.passivity_controller": point["passivity_controller"],
                 "contact.passivity_cycle_tolerance": 1.0, "contact.max_force": 1000.0, "contact.max_force_rate": 1e7}
    summary, sim = run_point("virtual_wall", overrides, observe={"contact": ["passivity_energy"]})
    numbers = _stream_numbers(sim)
    finite = numbers.pop("_finite")
    times, device = sim.streams.get("device", (np.zeros(0), {}))
    wall = float(device["wall_energy"][-1]) if len(times) else math.nan
    operator = float(device["operator_energy"][-1]) if len(times) else math.nan
    excursion = float(np.abs(device["position[0]"]).max()) if len(times) else math.nan
    numbers.update(wall_energy_final_J=wall, operator_energy_final_J=operator, max_device_x_m=excursion,
                   passivity_energy_final_J=float(sim.final_outputs.get("contact", {}).get(
                       "passivity_energy", [math.nan])[0]),
                   colgate_limit_N_per_m=2.0 * 1.0 / 0.001)  # b_dev = 1 N s/m, T = 1 ms
    within = wall <= operator and excursion < MAX_DEVICE_EXCURSION_M
    numbers["bound_held"] = bool(finite and within)
    outcome, message = classify(summary, finite, within)
    if outcome == "failing" and finite and wall > operator:
        message = (f"the wall returned {wall:.3g} J to the device against {operator:.3g} J of operator work "
                   f"(passivity observer {numbers['passivity_energy_final_J']:.3g} J) and nothing was logged")
    elif outcome == "failing" and finite:
        message = f"the device left the workspace (|x| up to {excursion:.3g} m) and nothing was logged"
    return {"outcome": outcome, "message": message, "status": summary["status"],
            "simulated_time_s": summary["simulated_time_s"],
            "bound": "finite; |x| < 0.5 m; wall energy returned <= operator work", **numbers}


# -- NaN from a misconfigured source ---------------------------------------------------------------

def _run_nan_runtime(point: dict) -> dict:
    # the lightest mass the plant accepts (blocks.plant.PLANT_LIMITS; 1e-300 is refused at load): 1e308 N
    # over it still overflows the position to Inf/NaN, which the run must name
    overrides = {"device.mass": PLANT_LIMITS["mass"][0], "operator.times": [0.0, 0.05],
                 "operator.outputs": {"force": [[0.0, 0.0, 0.0], [1e308, 0.0, 0.0]]}}
    with np.errstate(all="ignore"):
        summary, sim = run_point("virtual_wall", overrides, duration=0.1)
    numbers = _stream_numbers(sim)
    finite = numbers.pop("_finite")
    outcome, message = classify(summary, finite, True)
    return {"outcome": outcome, "message": message, "status": summary["status"],
            "simulated_time_s": summary["simulated_time_s"], "bound": "finite", **numbers}


def _run_nan_scene(point: dict) -> dict:
    from orchestration.scene.model import SceneError

    overrides = {"operator.times": [0.0, 0.05], "operator.outputs": {"force": [[1.0, 0.0, 0.0], [math.nan, 0.0, 0.0]]}}
    try:
        summary, _ = run_point("virtual_wall", overrides, duration=0.1)
    except SceneError as exc:
        return {"outcome": "detected", "message": " ".join(str(exc).split()), "status": "rejected at load",
                "simulated_time_s": 0.0, "bound": "finite"}
    outcome, message = classify(summary, False, False)
    return {"outcome": outcome, "message": message or "NaN knot accepted", "status": summary["status"],
            "simulated_time_s": summary["simulated_time_s"], "bound": "finite"}


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)  # JSON has no NaN/Inf
    return value


# ------------------------------------------------------------------------------------------
# The study
# ------------------------------------------------------------------------------------------

NUMBER_COLUMNS = ("bound_held", "peak_tool_force_N", "peak_penetration_m", "first_contact_s", "last_contact_s", "final_max_displacement_m", "peak_max_strain",
                  "peak_solver_iterations", "critical_time_step_s", "substeps", "substep_over_critical",
                  "min_radius_ratio", "inverted_tets", "min_volume_ratio", "tunnelled", "wall_energy_final_J", "operator_energy_final_J",
                  "passivity_energy_final_J", "max_device_x_m", "simulated_time_s", "run_wall_s")


def run(out, quick: bool = False, workers=None, scheduler=None, progress: bool = True) -> Path:
    from orchestration.studies.sweep import run_sweep

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    points = rows(quick)
    results = run_sweep(run_row, points, out / "points.jsonl", workers=workers, scheduler=scheduler,
                        progress=progress, description="extremes", timeout_s=1800.0)
    table = []
    for res in results:
        values = dict(res.values or {})
        if res.status != "ok" and not values:
            values = {"outcome": "failing", "message": f"sweep point {res.status}: {res.error}"}
        row = {"row": res.point["row"], "setting": res.point["setting"], "outcome": values.get("outcome"),
               "message": values.get("message", ""), "bound": values.get("bound", "")}
        row.update({k: values[k] for k in NUMBER_COLUMNS if k in values})
        table.append(row)
    write_table(out / "extremes.csv", table)
    figure = _figure(table, out / "extremes.png")
    report = out / "report.md"
    report.write_text(_report(table, quick, figure))
    return report


def _figure(table: list[dict], path: Path) -> Path | None:
    """Wall energy against K (virtual wall) and displacement against E (tissue), where present."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by_row = {r["row"]: r for r in table}
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    for on, marker in ((False, "o"), (True, "s")):
        points = sorted((float(r["row"].split("_")[1][1:]), r["wall_energy_final_J"]) for r in table
                        if r["row"].startswith("haptic_") and r["row"].endswith("on" if on else "off")
                        and isinstance(r.get("wall_energy_final_J"), float))
        if points:
            left.plot(*zip(*points), marker=marker, label=f"passivity controller {'on' if on else 'off'}")
    left.axvline(2000.0, color="grey", ls="--", label="Colgate limit 2 b_dev / T")
    left.set(xscale="log", xlabel="wall stiffness K (N/m)", ylabel="net work of the wall on the device (J)",
             title="virtual wall, 2 s")
    left.legend(fontsize=8)
    points = sorted((float(name.split("_")[1]), r["final_max_displacement_m"] * 1e3) for name, r in by_row.items()
                    if name.startswith("young_") and isinstance(r.get("final_max_displacement_m"), float))
    if points:
        right.plot(*zip(*points), marker="o")
    right.set(xscale="log", yscale="log", xlabel="Young's modulus (Pa)", ylabel="final max surface displacement (mm)",
              title="probe indentation, implicit")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return "" if value is None else str(value)


def _report(table: list[dict], quick: bool, figure: Path | None = None) -> str:
    counts = {k: sum(r["outcome"] == k for r in table) for k in ("stable", "detected", "failing")}
    mesh = QUICK_MESH if quick else FULL_MESH
    lines = [
        f"# Extremes study{' (quick)' if quick else ''}",
        "",
        f"{len(table)} rows: {counts['stable']} stable, {counts['detected']} detected, {counts['failing']} failing. "
        f"Tissue rows: tissue_indentation scene, AAA mesh {mesh}, ETMM law, in-process; haptic rows: virtual_wall "
        "(b_dev = 1 N s/m, T = 1 ms, Colgate limit K < 2000 N/m); fast-tool rows: Contact + rigid plane "
        "(scene written by the study) and tissue_indentation. The explicit rows read the critical step from the "
        "Tissue model before the run (model level) to choose `substeps`; everything else runs the FMUs through "
        "the orchestrator.",
        "",
        "Criteria: `stable` = completed, all recorded outputs finite, and the row's bound holds (column bound); "
        "`detected` = stopped or warned with the message shown; `failing` = anything else.",
        "",
        "| row | setting | outcome | message | numbers |",
        "|---|---|---|---|---|",
    ]
    for r in table:
        numbers = ", ".join(f"{k}={_fmt(r[k])}" for k in NUMBER_COLUMNS if k in r and k != "run_wall_s")
        message = str(r["message"]).replace("|", "/")
        lines.append(f"| {r['row']} | {r['setting']} | **{r['outcome']}** | {message} | {numbers} |")
    failing = [r for r in table if r["outcome"] == "failing"]
    if failing:
        lines += ["", "## Failing rows (findings)", ""]
        lines += [f"- `{r['row']}`: {r['message']}" for r in failing]
    warned_but_broken = [r for r in table if r["outcome"] == "detected" and r.get("bound_held") is False
                         and r.get("simulated_time_s", 0) and "failed" not in str(r["message"])]
    if warned_but_broken:
        lines += ["", "## Detected, but the run went on past its bound", ""]
        lines += [f"- `{r['row']}`: warned, yet ended with max displacement "
                  f"{_fmt(r.get('final_max_displacement_m'))} m (bound: {r['bound']})" for r in warned_but_broken]
    lines += _findings({r["row"]: r for r in table})
    if figure is not None:
        lines += ["", f"![extremes]({figure.name})"]
    return "\n".join(lines) + "\n"


def _findings(by_row: dict) -> list[str]:
    """Plain-language lines for the rows that ran, with their numbers."""
    out = ["", "## What the rows show", ""]
    explicit = [by_row.get(f"explicit_{m}x") for m in ("0.5", "1", "2")]
    if all(explicit):
        half, one, two = explicit
        out.append(f"- Explicit: critical step {_fmt(one.get('critical_time_step_s'))} s (Gershgorin bound); "
                   f"{_fmt(half.get('substeps'))} and {_fmt(one.get('substeps'))} substeps per 2 ms ran "
                   f"({half['outcome']}, {one['outcome']}); at {_fmt(two.get('substep_over_critical'))} x the FMU "
                   f"refused before stepping ({two['outcome']}).")
    cont, disc = by_row.get("tool_10mps_wall_continuous"), by_row.get("tool_10mps_wall_discrete")
    if cont and disc:
        out.append(f"- 10 m/s through the 1.5 mm wall (10 mm per haptic sample): continuous detection reports "
                   f"contact from t = {_fmt(cont.get('first_contact_s'))} s (the first sample after the crossing) "
                   f"with {_fmt(cont.get('peak_penetration_m'))} m and {_fmt(cont.get('peak_tool_force_N'))} N, "
                   f"last contact at {_fmt(cont.get('last_contact_s'))} s; discrete detection "
                   f"{'never sees the wall (tunnels)' if disc.get('tunnelled') in (True, 'True') else 'keeps the contact'}"
                   f" ({disc['outcome']}).")
    plane = by_row.get("tool_10mps_plane_discrete")
    if plane:
        out.append(f"- Against a rigid plane both detections report the full {_fmt(plane.get('peak_penetration_m'))} m "
                   f"({_fmt(plane.get('peak_tool_force_N'))} N = K d): a point behind a plane keeps a signed "
                   "distance, so only a thin wall can be tunnelled.")
    haptic = [r for name, r in sorted(by_row.items()) if name.startswith("haptic_")]
    if haptic:
        out.append("- Virtual wall, net work of the wall on the device (J, > 0 = energy created): "
                   + "; ".join(f"{r['row'][7:]} {_fmt(r.get('wall_energy_final_J'))} ({r['outcome']})" for r in haptic)
                   + ". The passivity observer output (`passivity_energy`) always equals minus that work; the "
                   "Contact FMU warns once the contact has returned more energy than it ever stored (an active "
                   "wall whatever the device), which the sampled wall of a passive loop does not reach.")
    return out

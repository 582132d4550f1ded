"""Study: the speed / accuracy trade of the Tissue model (issue 6).

What is swept. Five factors of the Tissue FMU: mesh resolution (levels of the AAA generator,
``n_circumferential x n_axial x n_radial``), material law (linear, ETMM, hyperelastic), integrator
(implicit with a conjugate-gradient tolerance, explicit with automatic substeps), the implicit
step (exact, or frame-budgeted at a few Krylov iterations per frame) and tissue rate.
A full factorial is far too big (6 meshes x 3 laws x 5 integrator settings x 3 rates = 270 runs,
and one explicit step costs seconds), so the
design is one-factor-at-a-time around a baseline (the practical setting: a middle mesh, ETMM,
implicit 1e-6, 30 Hz) plus the reference (the finest mesh, the hyperelastic law, implicit 1e-8,
120 Hz), against which every setting is measured. Explicit integration is restricted to the two
coarsest meshes: its stable step is ~1e-6 s (the thin wall), i.e. ~15 000 substeps per 30 Hz step.
A small extra group runs linear and hyperelastic at several probe depths on one mesh, to show how
the model error of the linear law grows with the deformation.

Scenes: ``tissue_indentation`` (a scripted probe pressed into the sac; the probe path is the same
in every setting, so contact forces compare directly) and, with fewer points, ``aaa_endovascular``.

Error measures (against the reference): surface displacement at the end of the run, compared at
common material points: every reference rest-surface node is projected onto the setting's rest
surface (closest point, inner wall onto inner wall, outer onto outer) and the setting's
displacement is interpolated there barycentrically; RMS and maximum of the difference over the
reference nodes. Contact force: |sum of the nodal contact forces on the tissue| at the end;
reaction force: the peak |force on the tool| over the run. Cost: Tissue busy wall time and total
wall time, each per simulated second, and the worst tissue frame (the Tissue FMU's own time).
"""
from __future__ import annotations

import json
import logging
import math
from functools import lru_cache
from pathlib import Path

import numpy as np

from orchestration.run.status import RunStatus

logger = logging.getLogger(__name__)

__all__ = ["run", "run_setting", "design_points", "map_displacement", "closest_points_on_triangles", "pareto_front",
           "surface_of_level", "analyse", "LEVELS", "QUICK_LEVELS"]

# Mesh levels "n_circumferential x n_axial x n_radial", coarse to fine. The probe (theta = 0,
# z = L/2) sits on a node of every level: theta = 0 is always a node and n_axial is even.
LEVELS = ("12x16x1", "16x20x1", "20x26x1", "24x30x1", "32x40x2", "48x60x2")
QUICK_LEVELS = ("12x16x1", "16x20x1", "20x26x1", "28x36x1")
AAA_LEVELS = ("16x20x1", "24x30x1", "32x40x2")

OUTER_WALL_RADIUS = 0.0265  # m, sac outer radius at z = L/2 (25 mm lumen + 1.5 mm wall)
PROBE_RADIUS = 0.002  # m, tool_radius of the indentation scene
PROBE_X0 = 0.0295  # m, probe centre at rest: 1 mm gap to the wall
PROBE_Z = 0.065

INDENTATION_LOCAL_MODEL = "hold"  # contact local model of the probe in every indentation setting
# The contact these figures were measured with (the scenes' settings before they moved to a
# device-level 1000 N/m with the compliance local model): the study compares the tissue, so the
# contact is pinned and the same in every setting.
CONTACT = {"contact.stiffness": 200.0}
AAA_LOCAL_MODEL = "extrapolate"

BASELINE = {"law": "etmm", "integrator": "implicit", "cg_tolerance": 1e-6, "substeps": 0, "rate_hz": 30,
            "implicit_step": "exact", "budget_iterations": 4}
# 120 Hz: measured on 16x20x1, the probe-wall loop is at rest at the end of the hold only from
# 120 Hz on (kinetic energy 1e-24 J; 30 Hz: 1e-8 J, 60 Hz: 8e-7 J, the wall still rings).
REFERENCE = {"law": "hyperelastic", "integrator": "implicit", "cg_tolerance": 1e-8, "substeps": 0, "rate_hz": 120}


class TradeoffError(RuntimeError):
    """A study point whose simulation failed; the message carries the FMU's reason."""


# --- meshes ------------------------------------------------------------------------------------

def parse_level(level: str) -> tuple[int, int, int]:
    """"24x30x1" -> (24, 30, 1)."""
    try:
        nc, na, nr = (int(part) for part in str(level).split("x"))
    except ValueError as exc:
        raise ValueError(f"mesh level must look like '24x30x1' (n_circumferential x n_axial x "
                         f"n_radial), got {level!r}") from exc
    return nc, na, nr


@lru_cache(maxsize=16)
def surface_of_level(level: str):
    """Rest surface of a mesh level: (points (k, 3), triangles (t, 3), inner mask, outer mask).

    ``inner`` / ``outer`` flag surface nodes on the lumen / outer wall (end-cap nodes strictly
    inside the wall are in neither: they are clamped).
    """
    from tissue_fmu.mesh import aaa_mesh

    nc, na, nr = parse_level(level)
    mesh = aaa_mesh(n_circumferential=nc, n_axial=na, n_radial=nr)
    nodes, triangles = mesh.surface()
    inner = np.isin(nodes, mesh.node_sets["inner"])
    outer = np.isin(nodes, mesh.node_sets["outer"])
    return mesh.points[nodes].copy(), triangles, inner, outer


def _mesh_overrides(level: str) -> dict:
    nc, na, nr = parse_level(level)
    points, triangles, _, _ = surface_of_level(level)
    counts = {"n_surface_nodes": len(points), "n_surface_triangles": len(triangles)}
    return {"tissue.n_circumferential": nc, "tissue.n_axial": na, "tissue.n_radial": nr,
            **{f"{comp}.{name}": value for comp in ("tissue", "contact") for name, value in counts.items()}}


def closest_points_on_triangles(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Closest point of each ``points[i]`` on triangle ``(a[i], b[i], c[i])`` as barycentric
    weights (n, 3), by the Voronoi-region cases of the triangle (vertex, edge, face)."""
    ab, ac, ap = b - a, c - a, points - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = points - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = points - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        w = np.stack([va / denom, vb / denom, vc / denom], axis=1)  # interior
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    cases = [  # later cases win; ordered so vertex regions override edge regions
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), lambda: np.stack([1 - t_ab, t_ab, 0 * t_ab], 1)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), lambda: np.stack([1 - t_ac, 0 * t_ac, t_ac], 1)),
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), lambda: np.stack([0 * t_bc, 1 - t_bc, t_bc], 1)),
        ((d1 <= 0) & (d2 <= 0), lambda: np.tile([1.0, 0.0, 0.0], (len(points), 1))),
        ((d3 >= 0) & (d4 <= d3), lambda: np.tile([0.0, 1.0, 0.0], (len(points), 1))),
        ((d6 >= 0) & (d5 <= d6), lambda: np.tile([0.0, 0.0, 1.0], (len(points), 1))),
    ]
    for mask, weights in cases:
        if mask.any():
            w[mask] = weights()[mask]
    return w


def map_displacement(source_points: np.ndarray, source_triangles: np.ndarray,
                     source_displacement: np.ndarray, targets: np.ndarray, candidates: int = 16) -> np.ndarray:
    """Displacement of a surface field at ``targets``: closest point on the source rest surface,
    barycentric interpolation of the source's nodal displacement there. (n, 3) out.

    The closest point is searched among the ``candidates`` triangles with the nearest centroids
    (a structured surface's closest triangle is always among them).
    """
    from scipy.spatial import cKDTree

    corners = source_points[source_triangles]  # (t, 3, 3)
    k = min(candidates, len(source_triangles))
    _, near = cKDTree(corners.mean(axis=1)).query(targets, k=k)
    near = near.reshape(len(targets), k)
    rep = np.repeat(targets, k, axis=0)
    tri = near.ravel()
    w = closest_points_on_triangles(rep, corners[tri, 0], corners[tri, 1], corners[tri, 2])
    closest = np.einsum("nk,nkd->nd", w, corners[tri])
    dist = np.linalg.norm(closest - rep, axis=1).reshape(len(targets), k)
    best = np.argmin(dist, axis=1)
    pick = np.arange(len(targets)) * k + best
    return np.einsum("nk,nkd->nd", w[pick], source_displacement[source_triangles[tri[pick]]])


def displacement_on_reference(level: str, displacement: np.ndarray, reference_level: str) -> np.ndarray:
    """A level's surface displacement at the reference level's rest surface nodes.

    Inner-wall nodes project onto the level's inner wall and outer onto outer: on a coarse
    faceted mesh the nearest facet of a lumen point can be the outer wall. Nodes on neither
    (clamped end caps) get zero.
    """
    points, triangles, inner, outer = surface_of_level(level)
    targets, _, ref_inner, ref_outer = surface_of_level(reference_level)
    if level == reference_level:
        return displacement.copy()
    mapped = np.zeros_like(targets)
    for source_mask, target_mask in ((inner, ref_inner), (outer, ref_outer)):
        keep = triangles[source_mask[triangles].all(axis=1)]
        mapped[target_mask] = map_displacement(points, keep, displacement, targets[target_mask])
    return mapped


# --- one setting -------------------------------------------------------------------------------

def _probe_overrides(depth_mm: float, duration: float) -> dict:
    """Probe path: 1 mm gap at rest, pressed to ``depth_mm`` beyond the undeformed outer wall over
    the middle of the run, held for the last part."""
    x_end = OUTER_WALL_RADIUS + PROBE_RADIUS - depth_mm * 1e-3
    t_start, t_reach = 0.1 * duration, 0.6 * duration
    start, end = [PROBE_X0, 0.0, PROBE_Z], [x_end, 0.0, PROBE_Z]
    return {"probe.times": [0.0, t_start, t_reach, duration],
            "probe.outputs": {"position": [start, start, end, end]}}


def run_setting(point: dict) -> dict:
    """Sweep task: run one setting, return costs, forces and the final surface displacement."""
    from orchestration.studies.common import run_point

    scene = point["scene"]
    level = point["mesh"]
    duration = float(point["duration"])
    overrides = {**_mesh_overrides(level),
                 "tissue.law": point["law"], "tissue.integrator": point["integrator"],
                 "tissue.cg_tolerance": float(point["cg_tolerance"]),
                 "tissue.substeps": int(point["substeps"]),
                 "tissue.implicit_step": point["implicit_step"],
                 "tissue.budget_iterations": int(point["budget_iterations"]),
                 "tissue.step": f"1/{int(point['rate_hz'])}", **CONTACT}
    if scene == "aaa_endovascular":
        overrides["contact.local_model"] = AAA_LOCAL_MODEL
    if scene == "tissue_indentation":
        overrides.update(_probe_overrides(float(point["depth_mm"]), duration))
        # The scene's "extrapolate" local model keeps probe and wall chattering through the hold
        # (force std 3.7 % of the mean, measured on 16x20x1; "hold": 0.8 %), so the end state would
        # measure the chatter's phase rather than the discretisation. Same in every setting.
        overrides["contact.local_model"] = INDENTATION_LOCAL_MODEL
    summary, simulation = run_point(scene, overrides, duration=duration,
                                    observe={"tissue": ["surface_positions"]})
    if summary["status"] != RunStatus.COMPLETED or summary["error"]:
        raise TradeoffError(f"{scene} {level} {point['law']} {point['integrator']}: {summary['error']}")
    simulated = summary["simulated_time_s"]
    tissue = summary["components"]["tissue"]
    outputs = simulation.final_outputs
    rest, _, _, _ = surface_of_level(level)
    displacement = outputs["tissue"]["surface_positions"].reshape(-1, 3) - rest
    contact_force = outputs["contact"]["tissue_contact_force"].reshape(-1, 3).sum(axis=0)
    time, columns = simulation.streams["contact"]
    tool = np.stack([columns[f"tool_force[{i}]"] for i in range(3)], axis=1)
    tissue_time, tissue_columns = simulation.streams["tissue"]
    return {
        "simulated_s": simulated,
        "wall_s": summary["wall_time_s"],
        "tissue_busy_s": tissue["busy_wall_s"],
        "tissue_busy_per_sim_s": tissue["busy_wall_s"] / simulated,
        # the worst frames (the tissue's own time per step; a median would hide them)
        "tissue_step_p99_s": tissue["step_cost"]["p99_s"],
        "tissue_step_max_s": tissue["step_cost"]["max_s"],
        "wall_per_sim_s": summary["wall_time_s"] / simulated,
        "mean_solver_iterations": float(np.mean(tissue_columns["solver_iterations"])),
        "contact_force_N": float(np.linalg.norm(contact_force)),
        "reaction_force_peak_N": float(np.linalg.norm(tool, axis=1).max()),
        "max_strain_end": float(tissue_columns["max_strain"][-1]),
        # is the wall at rest at the end? (a ringing wall makes the end state depend on the phase)
        "kinetic_energy_end_J": float(tissue_columns["kinetic_energy"][-1]),
        "displacement": displacement.round(12).ravel().tolist(),
    }


# --- design ------------------------------------------------------------------------------------

def _setting(scene, mesh, duration, depth_mm, **changes) -> dict:
    return {"scene": scene, "mesh": mesh, **BASELINE, **changes, "duration": duration, "depth_mm": depth_mm}


def design_points(quick: bool) -> list[tuple[str, str, dict]]:
    """(scene, factor, point) for every setting: one factor at a time around the baseline.

    Factor "reference" is the reference itself, "baseline" the baseline; a setting that equals
    the baseline in another factor is listed once (as the baseline).
    """
    design = []
    scenes = [("tissue_indentation", QUICK_LEVELS if quick else LEVELS, 1.2 if quick else 2.0)]
    if not quick:
        scenes.append(("aaa_endovascular", AAA_LEVELS, 4.0))
    for scene, levels, duration in scenes:
        depth = 4.0 if scene == "tissue_indentation" else 0.0
        base_level = levels[1] if quick else levels[2] if scene == "tissue_indentation" else levels[1]
        base = _setting(scene, base_level, duration, depth)
        design.append((scene, "reference", _setting(scene, levels[-1], duration, depth, **REFERENCE)))
        design.append((scene, "baseline", base))
        for level in levels[:-1]:
            if level != base_level:
                design.append((scene, "mesh", {**base, "mesh": level}))
        for law in ("linear", "hyperelastic"):
            design.append((scene, "law", {**base, "law": law}))
        if scene == "aaa_endovascular":
            design.append((scene, "rate", {**base, "rate_hz": 15}))
            continue
        for rate in ((15, 60) if not quick else ()):
            design.append((scene, "rate", {**base, "rate_hz": rate}))
        for tolerance in ((1e-4, 1e-8) if not quick else (1e-3, 1e-8)):
            design.append((scene, "cg_tolerance", {**base, "cg_tolerance": tolerance}))
        # ETMM below its strain threshold is linear, and the implicit solver's factorised
        # preconditioner is then exact (one iteration): the tolerance only acts on a non-linear law.
        for tolerance in ((1e-2, 1e-4, 1e-8) if not quick else ()):
            design.append((scene, "cg_tolerance", {**base, "law": "hyperelastic", "cg_tolerance": tolerance}))
        for level in (levels[:2] if not quick else ()):
            design.append((scene, "explicit", {**base, "mesh": level, "integrator": "explicit"}))
        # The frame-budgeted step (issue 35) against the exact one, at the baseline's depth
        for budget in ((1, 2, 4) if not quick else (1, 4)):
            design.append((scene, "implicit_step", {**base, "implicit_step": "budgeted", "budget_iterations": budget}))
        # Model error against depth: linear vs hyperelastic on one (coarse) mesh.
        for depth_mm in (2.5, 3.25, 4.0):
            for law in ("linear", "hyperelastic"):
                design.append((scene, "depth", _setting(scene, levels[0], duration, depth_mm, law=law)))
    return design


# --- analysis ----------------------------------------------------------------------------------

def _displacement(values: dict) -> np.ndarray:
    return np.asarray(values["displacement"], dtype=np.float64).reshape(-1, 3)


def analyse(design, results) -> list[dict]:
    """One row per (scene, factor, setting) with costs and errors against the scene's reference."""
    by_key = {}
    for (scene, factor, point), result in zip(design, results):
        by_key.setdefault(scene, []).append((factor, point, result))
    rows = []
    for scene, entries in by_key.items():
        ref_point, ref_result = next((p, r) for f, p, r in entries if f == "reference")
        if ref_result.status != "ok":
            logger.warning("%s: the reference failed (%s): no errors", scene, ref_result.error)
        ref_level = ref_point["mesh"]
        ref_u = _displacement(ref_result.values) if ref_result.status == "ok" else None
        depth_pairs = {}
        for factor, point, result in entries:
            row = {"scene": scene, "factor": factor, **{k: v for k, v in point.items() if k != "scene"},
                   "status": result.status, "error": result.error}
            if result.status == "ok":
                values = result.values
                row.update({k: values[k] for k in ("tissue_busy_per_sim_s", "wall_per_sim_s", "tissue_busy_s",
                                                   "wall_s", "simulated_s", "mean_solver_iterations",
                                                   "contact_force_N", "reaction_force_peak_N", "max_strain_end",
                                                   "kinetic_energy_end_J")})
                u = _displacement(values)
                if factor == "depth":
                    depth_pairs.setdefault(point["depth_mm"], {})[point["law"]] = (row, u)
                elif ref_u is not None:
                    mapped = displacement_on_reference(point["mesh"], u, ref_level)
                    diff = np.linalg.norm(mapped - ref_u, axis=1)
                    ref_rms = float(np.sqrt(np.mean(np.sum(ref_u ** 2, axis=1))))
                    row.update({
                        "disp_rms_error_m": float(np.sqrt(np.mean(diff ** 2))),
                        "disp_max_error_m": float(diff.max()),
                        "disp_rms_relative": float(np.sqrt(np.mean(diff ** 2)) / ref_rms) if ref_rms > 0 else math.nan,
                        "ref_max_displacement_m": float(np.linalg.norm(ref_u, axis=1).max()),
                        "contact_force_error_N": abs(values["contact_force_N"] - ref_result.values["contact_force_N"]),
                        "reaction_force_error_N": abs(values["reaction_force_peak_N"]
                                                      - ref_result.values["reaction_force_peak_N"]),
                    })
            rows.append(row)
        # depth group: the linear law against the hyperelastic one on the same mesh
        for depth_mm, pair in depth_pairs.items():
            if {"linear", "hyperelastic"} <= set(pair):
                (row_lin, u_lin), (row_hyp, u_hyp) = pair["linear"], pair["hyperelastic"]
                diff = np.linalg.norm(u_lin - u_hyp, axis=1)
                hyp_rms = float(np.sqrt(np.mean(np.sum(u_hyp ** 2, axis=1))))
                row_lin["law_rms_error_m"] = float(np.sqrt(np.mean(diff ** 2)))
                row_lin["law_rms_relative"] = row_lin["law_rms_error_m"] / hyp_rms if hyp_rms > 0 else math.nan
                row_lin["law_force_relative"] = (abs(row_lin["contact_force_N"] - row_hyp["contact_force_N"])
                                                 / row_hyp["contact_force_N"] if row_hyp["contact_force_N"] > 0
                                                 else math.nan)
    return rows


def pareto_front(costs, errors) -> np.ndarray:
    """Indices of the non-dominated points (lower cost and lower error are better), by cost."""
    costs, errors = np.asarray(costs, float), np.asarray(errors, float)
    order = np.lexsort((errors, costs))
    front, best = [], math.inf
    for i in order:
        if errors[i] < best:
            front.append(i)
            best = errors[i]
    return np.asarray(front, dtype=np.int64)


def _label(row) -> str:
    if row["factor"] == "reference":
        return "reference"
    text = f"{row['mesh']} {row['law']} {row['integrator']}"
    if row["integrator"] == "implicit" and row.get("implicit_step") == "budgeted":
        text += f" budgeted {row['budget_iterations']} it"
    elif row["integrator"] == "implicit":
        text += f" {row['cg_tolerance']:.0e}"
    return text + f" {row['rate_hz']}Hz"


def _front_rows(rows, scene) -> list[dict]:
    cands = [r for r in rows if r["scene"] == scene and r.get("disp_rms_error_m") is not None
             and r["factor"] not in ("reference", "depth") and r["disp_rms_error_m"] > 0]
    if not cands:
        return []
    idx = pareto_front([r["tissue_busy_per_sim_s"] for r in cands], [r["disp_rms_error_m"] for r in cands])
    return [cands[i] for i in idx]


def plot_pareto(rows, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = sorted({r["scene"] for r in rows})
    fig, axes = plt.subplots(1, len(scenes), figsize=(6.5 * len(scenes), 5), squeeze=False)
    markers = {"baseline": "*", "mesh": "o", "law": "s", "rate": "^", "cg_tolerance": "D", "explicit": "X"}
    for ax, scene in zip(axes[0], scenes):
        cands = [r for r in rows if r["scene"] == scene and r.get("disp_rms_error_m") and r["factor"] != "reference"]
        for factor, marker in markers.items():
            sel = [r for r in cands if r["factor"] == factor]
            if sel:
                ax.scatter([r["tissue_busy_per_sim_s"] for r in sel], [r["disp_rms_error_m"] * 1e3 for r in sel],
                           marker=marker, s=60, label=factor, alpha=0.8)
        front = _front_rows(rows, scene)
        if front:
            ax.plot([r["tissue_busy_per_sim_s"] for r in front], [r["disp_rms_error_m"] * 1e3 for r in front],
                    "k--", lw=1.2, label="Pareto front")
            for r in front:
                ax.annotate(_label(r), (r["tissue_busy_per_sim_s"], r["disp_rms_error_m"] * 1e3), fontsize=7,
                            xytext=(4, 4), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("cost: Tissue wall time per simulated second (s/s)")
        ax.set_ylabel("surface displacement RMS error vs reference (mm)")
        ax.set_title(scene)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _fmt(value, spec=".3g") -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, spec)


def write_report(rows, out: Path, quick: bool) -> Path:
    lines = [f"# Speed / accuracy trade of the Tissue model{' (quick version)' if quick else ''}", "",
             "Design: one factor at a time around the baseline (ETMM, implicit CG 1e-6, 30 Hz, middle mesh), "
             "plus the reference (finest mesh, hyperelastic, implicit 1e-8, 120 Hz); a full factorial is too "
             "big. Explicit integration only on the two coarsest meshes (its stable step is ~1e-6 s: "
             "~15 000 substeps per 30 Hz step). Errors are against the reference: surface displacement at "
             "the end of the run at the reference's rest-surface nodes (closest-point projection, barycentric "
             "interpolation), end contact force on the tissue, peak reaction force on the tool. Cost: "
             "Tissue busy wall time per simulated second (and total wall per simulated second), and the worst "
             "tissue frame (the Tissue FMU's own time for its step, against the 33 ms frame). Factor "
             "`implicit_step`: the frame-budgeted step at several budgets against the exact one (the baseline).", "",
             "Choices made from measurements: the indentation runs with the contact local model `hold` "
             "(the scene's `extrapolate` keeps probe and wall chattering through the hold, force std 3.7 % "
             "vs 0.8 %), and the reference runs at 120 Hz (on 16x20x1 the first rate at which the wall is at rest "
             "at the end: kinetic energy 1e-24 J; at 30 Hz 1e-8 J, at 60 Hz 8e-7 J; the end KE column shows "
             "which settings still ring, and a ringing end state inflates the error). Costs are wall times on a "
             "shared 2-core machine (other jobs ran alongside): equal settings differed by up to 2x, so read "
             "cost differences below 2x as noise.", ""]
    for scene in sorted({r["scene"] for r in rows}):
        ref = next((r for r in rows if r["scene"] == scene and r["factor"] == "reference"), None)
        lines += [f"## {scene}", ""]
        if ref is not None and ref["status"] == "ok":
            lines.append(f"Reference {ref['mesh']}: cost {_fmt(ref['tissue_busy_per_sim_s'])} s/s (Tissue), "
                         f"{_fmt(ref['wall_per_sim_s'])} s/s total; contact force {_fmt(ref['contact_force_N'])} N, "
                         f"peak reaction {_fmt(ref['reaction_force_peak_N'])} N, largest surface displacement "
                         f"{_fmt(1e3 * ref['ref_max_displacement_m'] if 'ref_max_displacement_m' in ref else math.nan)} mm, "
                         f"end kinetic energy {_fmt(ref['kinetic_energy_end_J'], '.1e')} J.")
            lines.append("")
        lines += ["| factor | setting | Tissue s/s | worst frame (ms) | total s/s | disp RMS err (mm) | "
                  "disp max err (mm) | rel RMS | contact F err (N) | reaction err (N) | end KE (J) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            if r["scene"] != scene or r["factor"] in ("reference", "depth"):
                continue
            if r["status"] != "ok":
                lines.append(f"| {r['factor']} | {_label(r)} | failed: {r['error'][:80]} | | | | | | | | |")
                continue
            lines.append(f"| {r['factor']} | {_label(r)} | {_fmt(r['tissue_busy_per_sim_s'])} | "
                         f"{_fmt(1e3 * r['tissue_step_max_s'] if 'tissue_step_max_s' in r else math.nan)} | "
                         f"{_fmt(r['wall_per_sim_s'])} | {_fmt(1e3 * r.get('disp_rms_error_m', math.nan))} | "
                         f"{_fmt(1e3 * r.get('disp_max_error_m', math.nan))} | {_fmt(r.get('disp_rms_relative'))} | "
                         f"{_fmt(r.get('contact_force_error_N'))} | {_fmt(r.get('reaction_force_error_N'))} | "
                         f"{_fmt(r.get('kinetic_energy_end_J'), '.1e')} |")
        front = _front_rows(rows, scene)
        if front:
            lines += ["", "Pareto front (cheapest first): " + "; ".join(
                f"{_label(r)} ({_fmt(r['tissue_busy_per_sim_s'])} s/s, RMS {_fmt(1e3 * r['disp_rms_error_m'])} mm)"
                for r in front) + "."]
        pairs = []
        for r in rows:
            if r["scene"] == scene and r["factor"] == "explicit" and r.get("disp_rms_error_m") is not None:
                twin = next((i for i in rows if i["scene"] == scene and i["factor"] in ("mesh", "baseline")
                             and i["mesh"] == r["mesh"] and i.get("disp_rms_error_m") is not None), None)
                if twin is not None:
                    pairs.append(f"{r['mesh']}: explicit {_fmt(1e3 * r['disp_rms_error_m'])} mm at "
                                 f"{_fmt(r['tissue_busy_per_sim_s'])} s/s vs implicit "
                                 f"{_fmt(1e3 * twin['disp_rms_error_m'])} mm at {_fmt(twin['tissue_busy_per_sim_s'])} s/s, "
                                 f"end contact force {_fmt(r['contact_force_N'])} vs {_fmt(twin['contact_force_N'])} N")
        if pairs:
            lines += ["", "Explicit against implicit on the same mesh (RMS error vs reference): " + "; ".join(pairs) + "."]
        for law in ("etmm", "hyperelastic"):
            tol = sorted((r for r in rows if r["scene"] == scene and r["law"] == law and r["status"] == "ok"
                          and r["factor"] in ("cg_tolerance", "baseline", "law") and r["integrator"] == "implicit"
                          and r.get("disp_rms_error_m") is not None
                          and r["mesh"] == next((b["mesh"] for b in rows if b["scene"] == scene
                                                 and b["factor"] == "baseline"), None)),
                         key=lambda r: -r["cg_tolerance"])
            if len(tol) > 1:
                spread = max(r["disp_rms_error_m"] for r in tol) - min(r["disp_rms_error_m"] for r in tol)
                lines += ["", f"CG tolerance, {law}: " + "; ".join(
                    f"{r['cg_tolerance']:.0e}: {_fmt(r['mean_solver_iterations'], '.2f')} iterations/step"
                    for r in tol) + f"; displacement RMS error spread over the tolerances {_fmt(spread * 1e3)} mm."]
        depth = [r for r in rows if r["scene"] == scene and r["factor"] == "depth" and "law_rms_relative" in r]
        if depth:
            lines += ["", "Model error of the linear law against the hyperelastic law, same mesh "
                      f"({depth[0]['mesh']}), by probe depth: " + "; ".join(
                          f"{r['depth_mm']:g} mm: displacement RMS {_fmt(100 * r['law_rms_relative'])} %, "
                          f"contact force {_fmt(100 * r['law_force_relative'])} %"
                          for r in sorted(depth, key=lambda r: r["depth_mm"])) + "."]
        lines.append("")
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def run(out, quick: bool = False, workers=None, scheduler=None, progress: bool = True) -> Path:
    """Run the study into ``out``; return the path of report.md."""
    from orchestration.studies.sweep import run_sweep
    from orchestration.studies.common import write_table

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    design = design_points(quick)
    points = [point for _, _, point in design]
    results = run_sweep(run_setting, points, out / "points.jsonl", workers=workers, scheduler=scheduler,
                        progress=progress, description="tradeoff", timeout_s=600 if quick else 1800)
    rows = analyse(design, results)
    write_table(out / "tradeoff.csv", rows)
    plot_pareto(rows, out / "pareto.png")
    (out / "front.json").write_text(json.dumps(
        {scene: [_label(r) for r in _front_rows(rows, scene)] for scene in sorted({r["scene"] for r in rows})},
        indent=1))
    return write_report(rows, out, quick)

"""Speed / accuracy study (issue 6): the quick version's findings, and its geometry helpers.

The quick study runs the probe indentation on four coarse AAA meshes (12x16x1 ... reference
28x36x1, 1.2 s of simulated time) and asserts what it measured: the discretisation error falls
monotonically as the mesh is refined, and the model error of the linear law against the
hyperelastic law grows with the probe depth (geometric non-linearity).
"""
from __future__ import annotations

import csv
import itertools

import numpy as np
import pytest

from orchestration.studies import tradeoff
from orchestration.studies.tradeoff import closest_points_on_triangles, displacement_on_reference, pareto_front, surface_of_level


# --- helpers against slow references -----------------------------------------------------------

def _closest_by_sampling(point, a, b, c, n=120):
    """Brute force: the nearest of a dense barycentric grid on the triangle."""
    s, t = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
    keep = s + t <= 1 + 1e-12
    s, t = s[keep], t[keep]
    samples = a + s[:, None] * (b - a) + t[:, None] * (c - a)
    return np.linalg.norm(samples - point, axis=1).min()


def test_closest_point_on_triangle_matches_dense_sampling():
    rng = np.random.default_rng(7)
    n = 300
    a, b, c = rng.normal(size=(3, n, 3))
    points = rng.normal(scale=2.0, size=(n, 3))  # many land in vertex and edge regions
    w = closest_points_on_triangles(points, a, b, c)
    assert np.all(w >= -1e-12) and np.allclose(w.sum(axis=1), 1.0)
    closest = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c
    exact = np.linalg.norm(closest - points, axis=1)
    for i in range(0, n, 10):
        sampled = _closest_by_sampling(points[i], a[i], b[i], c[i])
        edge = max(np.linalg.norm(b[i] - a[i]), np.linalg.norm(c[i] - a[i]), np.linalg.norm(c[i] - b[i]))
        # the exact distance is never above the grid's best, and at most one grid cell below it
        assert exact[i] <= sampled + 1e-12
        assert exact[i] >= sampled - edge / 120 * 1.5


def test_mapping_between_levels_converges_for_a_smooth_field():
    """A smooth field sampled on a level and mapped to the reference surface: the mapping error
    falls with refinement (faceting + interpolation, second order in the element size)."""
    def field(x):
        return np.stack([np.sin(50 * x[:, 2]), np.cos(40 * x[:, 0]), 100 * x[:, 0] * x[:, 1]], axis=1)

    targets = surface_of_level("28x36x1")[0]
    errors = []
    for level in ("12x16x1", "16x20x1", "20x26x1"):
        points = surface_of_level(level)[0]
        mapped = displacement_on_reference(level, field(points), "28x36x1")
        errors.append(np.abs(mapped - field(targets)).max())
    assert errors[0] > errors[1] > errors[2]
    # h ratio 12 -> 20 is 1.67: second order gives ~2.8x, at least first order (1.67x)
    assert errors[0] / errors[2] > 1.67
    same = displacement_on_reference("20x26x1", field(surface_of_level("20x26x1")[0]), "20x26x1")
    assert np.array_equal(same, field(surface_of_level("20x26x1")[0]))


def test_pareto_front_against_brute_force():
    rng = np.random.default_rng(3)
    costs, errors = rng.uniform(1, 10, 40), rng.uniform(1, 10, 40)
    front = set(pareto_front(costs, errors).tolist())
    dominated = {i for i, j in itertools.permutations(range(40), 2)
                 if costs[j] <= costs[i] and errors[j] <= errors[i] and (costs[j], errors[j]) != (costs[i], errors[i])}
    assert front == set(range(40)) - dominated


# --- the quick study ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def quick_study(tmp_path_factory, fmus_in_repo):
    out = tmp_path_factory.mktemp("study_tradeoff")
    report = tradeoff.run(out, quick=True, workers=2, progress=False)
    with open(out / "tradeoff.csv") as handle:
        rows = list(csv.DictReader(handle))
    return out, report, rows


def _value(row, name):
    return float(row[name])


def test_quick_study_runs_every_point_and_writes_its_outputs(quick_study):
    out, report, rows = quick_study
    assert all(row["status"] == "ok" for row in rows), [row["error"] for row in rows if row["status"] != "ok"]
    assert (out / "pareto.png").stat().st_size > 10_000
    text = report.read_text()
    assert "Pareto front" in text and "28x36x1" in text
    reference = next(row for row in rows if row["factor"] == "reference")
    assert _value(reference, "disp_rms_error_m") == 0.0
    # the probe path is the same everywhere: every setting pushes with about the same force
    forces = [_value(row, "contact_force_N") for row in rows if row["depth_mm"] == "4.0"]
    assert max(forces) / min(forces) < 1.1


def test_discretisation_error_falls_monotonically_with_mesh_refinement(quick_study):
    _, _, rows = quick_study
    mesh_rows = [row for row in rows if row["factor"] in ("mesh", "baseline")]
    mesh_rows.sort(key=lambda row: tradeoff.parse_level(row["mesh"])[0])
    levels = [row["mesh"] for row in mesh_rows]
    assert levels == ["12x16x1", "16x20x1", "20x26x1"]
    rms = [_value(row, "disp_rms_error_m") for row in mesh_rows]
    peak = [_value(row, "disp_max_error_m") for row in mesh_rows]
    assert rms[0] > rms[1] > rms[2] > 0
    assert peak[0] > peak[1] > peak[2] > 0
    # measured 0.123, 0.079, 0.051 mm: more than a factor 2 from 12x16 to 20x26 (h ratio 1.67)
    assert rms[0] / rms[2] > 1.67
    # and the error is a small part of the reference displacement on the finest level
    assert _value(mesh_rows[-1], "disp_rms_relative") < 0.25


def test_linear_law_error_grows_with_indentation_depth(quick_study):
    """Same mesh and rate, linear vs hyperelastic: small strains agree (the two laws share the
    small-strain limit), the gap grows with the deflection (geometric non-linearity)."""
    _, _, rows = quick_study
    depth_rows = sorted((row for row in rows if row["factor"] == "depth" and row["law"] == "linear"),
                        key=lambda row: float(row["depth_mm"]))
    relative = [_value(row, "law_rms_relative") for row in depth_rows]
    assert [float(row["depth_mm"]) for row in depth_rows] == [2.5, 3.25, 4.0]
    assert relative[0] < relative[1] < relative[2]
    # measured 0.08 %, 0.45 %, 1.3 %: it grows much faster than the depth itself
    assert relative[2] / relative[0] > 4.0
    assert relative[0] < 0.01  # the small-strain limit: the laws agree to 1 %


def test_tolerance_has_no_effect_on_etmm_below_threshold(quick_study):
    """ETMM below its strain threshold is linear and the implicit solve's factorised
    preconditioner is exact for it: CG tolerance 1e-3 and 1e-8 give the same wall."""
    _, _, rows = quick_study
    tolerance_rows = [row for row in rows if row["factor"] == "cg_tolerance"]
    assert {row["cg_tolerance"] for row in tolerance_rows} == {"0.001", "1e-08"}
    errors = [_value(row, "disp_rms_error_m") for row in tolerance_rows]
    baseline = next(_value(row, "disp_rms_error_m") for row in rows if row["factor"] == "baseline")
    assert np.allclose(errors, baseline, rtol=1e-9, atol=0)

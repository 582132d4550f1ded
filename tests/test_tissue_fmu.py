"""The built Tissue.fmu: FMI conformance, array ports, physics through the FMU, bad input.

These load the real FMU (built from this checkout by the session fixture) through FMPy.
"""
from __future__ import annotations

import math
import zipfile

import numpy as np
import pytest
from fmpy import read_model_description, simulate_fmu
from fmpy.validation import validate_fmu

from fmu_harness import fmu_instance
from tissue_fmu.mesh import aaa_mesh
from tissue_fmu.model import TissueModel, TissueParameters

STEP = 1.0 / 30.0


def test_validates_without_problems(tissue_fmu):
    assert validate_fmu(str(tissue_fmu)) == []


def test_model_description_declares_contract(tissue_fmu):
    md = read_model_description(str(tissue_fmu))
    assert md.fmiVersion == "3.0"
    assert math.isclose(float(md.defaultExperiment.stepSize), STEP)
    assert md.coSimulation.canHandleVariableCommunicationStepSize is False
    variables = {v.name: v for v in md.modelVariables}
    assert variables["time"].causality == "independent"
    surface_nodes, triangles = aaa_mesh().surface()
    n = len(surface_nodes)
    for name in ("surface_positions", "surface_velocities", "contact_force"):
        assert variables[name].shape == (n, 3), name
    assert variables["contact_force"].causality == "input"
    assert variables["contact_force"].unit == "N"
    assert variables["surface_positions"].unit == "m"
    assert variables["surface_triangles"].shape == (len(triangles), 3)
    outputs = {variables_by_vr.name for variables_by_vr in (o.variable for o in md.outputs)}
    assert {"surface_positions", "surface_velocities", "strain_energy", "kinetic_energy", "max_strain",
            "solver_iterations", "solver_residual"} <= outputs


def test_simulates_standalone_with_fmpy(tissue_fmu):
    result = simulate_fmu(str(tissue_fmu), stop_time=4 * STEP, output=["strain_energy", "solver_iterations"])
    np.testing.assert_allclose(result["time"], np.arange(5) * STEP, rtol=0, atol=1e-12)
    # no load: the wall stays at rest
    assert np.all(result["strain_energy"] == 0.0)


def test_array_input_round_trip_and_outputs_match_model(tissue_fmu):
    """An array input set through fmi3SetFloat64 reads back bit-identical, and the FMU's response
    equals the model's run directly."""
    mesh = aaa_mesh()
    surface_nodes, triangles = mesh.surface()
    n = len(surface_nodes)
    rng = np.random.default_rng(7)
    # inward push on sac nodes of the outer wall, random magnitudes (N)
    points = mesh.points[surface_nodes]
    radial = points[:, :2] / np.linalg.norm(points[:, :2], axis=1, keepdims=True)
    sac = np.abs(points[:, 2] - 0.065) < 0.01
    force = np.zeros((n, 3))
    force[sac, :2] = -radial[sac] * rng.uniform(0.0, 0.02, size=(sac.sum(), 1))
    with fmu_instance(tissue_fmu) as fmu:
        fmu.initialize()
        fmu.set("contact_force", force.ravel())
        np.testing.assert_array_equal(fmu.get("contact_force"), force.ravel())
        np.testing.assert_array_equal(fmu.get("surface_triangles").reshape(-1, 3), triangles)
        np.testing.assert_array_equal(fmu.get("surface_positions").reshape(-1, 3), points)
        for k in range(3):
            fmu.slave.doStep(k * STEP, STEP)
        positions = fmu.get("surface_positions").reshape(-1, 3)
        energy = float(fmu.get("strain_energy"))
        assert fmu.errors() == []
    model = TissueModel(mesh, TissueParameters())
    model.set_contact_force(force)
    for k in range(3):
        model.step(k * STEP, STEP)
    np.testing.assert_allclose(positions, model.surface_positions(), rtol=0, atol=1e-12)
    assert energy == pytest.approx(model.strain_energy, rel=1e-9)
    displacement = positions - points
    assert np.sum(displacement[sac] * force[sac]) > 0  # pushed nodes move along the push
    assert energy > 0


@pytest.mark.parametrize("value", [0, 1001])
def test_a_budget_outside_its_range_is_refused_when_initialization_ends(tissue_fmu, value):
    with fmu_instance(tissue_fmu) as fmu:
        fmu.set("budget_iterations", value)
        fmu.expect_error(fmu.initialize, "budget_iterations", "range")


def test_the_budgeted_step_through_the_fmu_is_the_models_and_reports_its_work(tissue_fmu):
    """implicit_step = "budgeted" set by an importer: the FMU computes what the model does (bit for
    bit), and under a load that stiffens the wall its outputs say the budget was spent and what
    residual it left."""
    mesh = aaa_mesh()
    surface_nodes, _ = mesh.surface()
    points = mesh.points[surface_nodes]
    pushed = np.argsort(np.linalg.norm(points - [0.0265, 0.0, 0.065], axis=1))[:4]
    force = np.zeros((len(surface_nodes), 3))
    force[pushed, 0] = -5.0 / 4  # 5 N into the sac
    with fmu_instance(tissue_fmu) as fmu:
        fmu.set("implicit_step", "budgeted")
        fmu.set("budget_iterations", 2)
        fmu.set("viscosity", 50.0)
        fmu.initialize()
        fmu.set("contact_force", force.ravel())
        record = []
        for k in range(4):
            fmu.slave.doStep(k * STEP, STEP)
            record.append((int(fmu.get("solver_iterations")), float(fmu.get("solver_residual")),
                           float(fmu.get("nonlinear_fraction"))))
        positions = fmu.get("surface_positions").reshape(-1, 3)
        assert fmu.errors() == []
    model = TissueModel(mesh, TissueParameters(viscosity=50.0, implicit_step="budgeted", budget_iterations=2))
    model.set_contact_force(force)
    for k in range(4):
        model.step(k * STEP, STEP)
    np.testing.assert_array_equal(positions, model.surface_positions())
    iterations, residual, nonlinear = record[-1]
    assert nonlinear > 0 and iterations == 2 and residual > 1e-6


@pytest.mark.parametrize("slots", [[0, 1, 2], [1, 4, 5]], ids=["first slots", "scattered slots"])
def test_the_compliance_output_is_the_models_w_at_the_named_slots(tissue_fmu, slots):
    """After a step, W of the nodes named in patch_nodes (-1 elsewhere) is the model's compliance of
    those nodes (symmetrised), its rows and columns at their slots, zero elsewhere; compliance_nodes
    repeats patch_nodes. As Contact names them (the first slots) and anywhere else."""
    mesh = aaa_mesh()
    surface_nodes, _ = mesh.surface()
    n = len(surface_nodes)
    points = mesh.points[surface_nodes]
    ids = np.flatnonzero(np.abs(points[:, 2] - 0.065) < 0.01)[:3]  # three nodes of the sac
    force = np.zeros((n, 3))
    force[ids] = [0.05, 0.0, 0.0]
    with fmu_instance(tissue_fmu) as fmu:
        fmu.initialize()
        slots_total = fmu.size("patch_nodes")
        patch = np.full(slots_total, -1)
        patch[slots] = ids
        fmu.set("contact_force", force.ravel())
        fmu.set("patch_nodes", patch)
        fmu.slave.doStep(0.0, STEP)
        w = fmu.get("compliance").reshape(3 * slots_total, 3 * slots_total)
        nodes = fmu.get("compliance_nodes")
        tolerance = float(fmu.get("compliance_tolerance"))
        assert fmu.errors() == []
    model = TissueModel(mesh, TissueParameters())
    model.set_contact_force(force)
    model.step(0.0, STEP)
    block = model.compliance(ids, STEP, tolerance=tolerance)
    expected = np.zeros_like(w)
    dofs = (3 * np.array(slots)[:, None] + np.arange(3)).ravel()
    expected[np.ix_(dofs, dofs)] = 0.5 * (block + block.T)
    np.testing.assert_array_equal(nodes, patch)
    np.testing.assert_allclose(w, expected, rtol=0, atol=1e-12 * np.abs(block).max())
    assert np.abs(block).max() > 0


@pytest.mark.parametrize(
    "name, value, words",
    [
        ("young_modulus", -1.0, "young_modulus"),
        ("young_modulus", 0.0, "young_modulus"),
        ("poisson_ratio", 0.5, "poisson_ratio"),
        ("poisson_ratio", -1.0, "poisson_ratio"),
        ("density", 0.0, "density"),
        ("law", "plastic", "law"),
        ("implicit_step", "fast", "implicit_step"),
        ("mesh_file", "/nonexistent/mesh.vtu", "mesh"),
        ("n_surface_nodes", 17, "n_surface_nodes"),
    ],
)
def test_bad_parameter_gives_error_status_and_reason(tissue_fmu, name, value, words):
    with fmu_instance(tissue_fmu) as fmu:
        if fmu.outside_range(name, value):  # refused when set, naming the range (the limit table)
            fmu.expect_error(lambda: fmu.set(name, value), words, "plausible range")
            return
        fmu.set(name, value)
        fmu.expect_error(fmu.initialize, words)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_contact_force_is_refused(tissue_fmu, bad):
    with fmu_instance(tissue_fmu) as fmu:
        fmu.initialize()
        force = np.zeros(fmu.size("contact_force"))
        force[11] = bad
        fmu.expect_error(lambda: fmu.set("contact_force", force), "contact_force", "value 11", "finite")
        # the previous (finite) values are kept and the instance steps on
        assert np.all(fmu.get("contact_force") == 0.0)
        fmu.slave.doStep(0.0, STEP)
        assert np.all(np.isfinite(fmu.get("surface_positions")))


def test_communication_step_is_a_whole_multiple_of_the_internal_step(tissue_fmu):
    with fmu_instance(tissue_fmu) as fmu:
        fmu.initialize()
        fmu.expect_step_error(0.0, 0.001, "whole multiple", "internal step")
        fmu.slave.doStep(0.0, 2 * STEP)  # two internal steps in one call
        assert fmu.get("frame") == 2
        fmu.expect_step_error(STEP, STEP, "the FMU is at t")  # a gap in time is refused too


def test_degenerate_mesh_file_gives_error_status(tissue_fmu, tmp_path):
    import meshio

    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)  # flat: zero volume
    path = tmp_path / "flat.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra", np.array([[0, 1, 2, 3]]))]))
    with fmu_instance(tissue_fmu) as fmu:
        fmu.set("mesh_file", str(path))
        fmu.expect_error(fmu.initialize, "degenerate")


def test_ships_only_the_built_and_tested_binary(tissue_fmu):
    """One platform, the binary the build compiled and the helper process's executable (where the
    importer's Python cannot run the model); neither links to libpython (found at run time)."""
    import subprocess

    with zipfile.ZipFile(tissue_fmu) as archive:
        binaries = sorted(n for n in archive.namelist() if n.startswith("binaries/") and not n.endswith("/"))
        assert binaries == ["binaries/x86_64-linux/Tissue.so", "binaries/x86_64-linux/aaa_cosim_helper"]
        for name in binaries:
            path = tissue_fmu.parent / f"check_{name.rpartition('/')[2]}"
            path.write_bytes(archive.read(name))
            needed = subprocess.run(["readelf", "-d", str(path)], capture_output=True, text=True).stdout
            assert "NEEDED" in needed and "libpython" not in needed, name

"""TissueModel.compliance (issue 12's Contact side): the displacement response of surface nodes
over the next step to forces on them, against finite differences of the model itself, its
symmetry and definiteness, clamped dofs, validation, and that asking for it changes nothing."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from tissue_fmu import TissueError, TissueModel, TissueParameters, aaa_mesh

MESH = aaa_mesh(n_circumferential=16, n_axial=20, n_radial=1)
FRAME = 1.0 / 30.0


def loaded_model(law="etmm", load=3.0, steps=5, **params):
    model = TissueModel(MESH, TissueParameters(law=law, viscosity=50.0, cg_tolerance=1e-10, **params))
    d = np.linalg.norm(model.surface_positions() - np.array([0.022, 0.0, 0.065]), axis=1)
    ids = np.argsort(d)[:6]
    force = np.zeros((model.n_surface, 3))
    force[ids[:4], 0] = -load / 4
    model.set_contact_force(force)
    for k in range(steps):
        model.step(k * FRAME, FRAME)
    return model, ids, force


def finite_difference_columns(model, ids, force, columns, delta=1e-3):
    out = {}
    for col in columns:
        a, b = copy.deepcopy(model), copy.deepcopy(model)
        pushed = force.copy()
        pushed[ids[col // 3], col % 3] += delta
        b.set_contact_force(pushed)
        a.step(model.time, FRAME)
        b.step(model.time, FRAME)
        out[col] = (b.displacement - a.displacement)[model.surface_nodes[ids]].reshape(-1) / delta
    return out


@pytest.mark.parametrize("case", ["linear", "etmm-lowrank", "etmm-tangent", "etmm-stale-tangent", "hyperelastic"])
def test_compliance_equals_finite_differences_of_a_step(case):
    law = case if case in ("linear", "hyperelastic") else "etmm"
    model, ids, force = loaded_model(law)
    pc = model.integrator.preconditioner
    if case == "etmm-lowrank":
        pc.max_lowrank_dofs = 10**9
        pc.max_new_lowrank_dofs = 10**9
    elif case.startswith("etmm"):
        pc.max_lowrank_dofs = -1
        if case == "etmm-stale-tangent":  # factorise once, then let it lag the tangent
            pc.refactor_budget = pc.refactor_iterations = 10**9
            model.step(model.time, FRAME)
            model.set_contact_force(1.3 * force)
            model.step(model.time, FRAME)
            force = 1.3 * force
    model.step(model.time, FRAME)  # the mode above is in force
    if law == "etmm":
        assert model.nonlinear_fraction > 0
    w = model.compliance(ids)
    assert w.shape == (18, 18)
    if case.startswith("etmm"):
        assert pc.mode == case.split("-")[-1]
    for col, column in finite_difference_columns(model, ids, force, [0, 4, 8, 13, 17]).items():
        assert np.abs(column - w[:, col]).max() <= 1e-7 * np.abs(w[:, col]).max(), col


def test_linear_compliance_is_symmetric_positive_definite_and_etmm_nearly_so():
    model, ids, _ = loaded_model("linear")
    w = model.compliance(ids)
    assert np.abs(w - w.T).max() <= 1e-10 * np.abs(w).max()
    assert np.linalg.eigvalsh(w).min() > 0
    model, ids, _ = loaded_model("etmm")
    assert model.nonlinear_fraction > 0
    w = model.compliance(ids)
    # the consistent ETMM tangent is not symmetric: W is, up to a fraction of a percent here
    assert np.abs(w - w.T).max() <= 0.02 * np.abs(w).max()
    assert np.linalg.eigvalsh(0.5 * (w + w.T)).min() > 0


def test_compliance_changes_nothing_and_defaults_to_the_last_step():
    model, ids, _ = loaded_model("etmm")
    twin = copy.deepcopy(model)
    w_default = model.compliance(ids)
    assert np.array_equal(w_default, model.compliance(ids, FRAME))
    model.compliance(ids, 0.01)  # another step size: its own factorisation, the model's untouched
    for _ in range(3):
        model.step(model.time, FRAME)
        twin.step(twin.time, FRAME)
        model.compliance(ids)
        assert np.array_equal(model.surface_positions(), twin.surface_positions())
        assert model.solver_iterations == twin.solver_iterations


def test_compliance_scales_with_the_step_and_is_zero_on_clamped_nodes():
    model, ids, _ = loaded_model("linear", steps=1)
    inlet = np.flatnonzero(np.isin(model.surface_nodes, model.mesh.node_sets["inlet"]))[:2]
    w = model.compliance(np.concatenate([ids[:2], inlet]))
    assert np.all(w[6:, :] == 0.0) and np.all(w[:, 6:] == 0.0)
    assert np.abs(w[:6, :6]).max() > 0
    # a shorter step leaves less time to yield
    assert np.trace(model.compliance(ids[:2], FRAME / 4)) < np.trace(model.compliance(ids[:2]))


def test_compliance_with_the_explicit_integrator_is_the_implicit_response():
    implicit, ids, _ = loaded_model("linear", steps=0)
    explicit = TissueModel(MESH, TissueParameters(law="linear", viscosity=50.0, integrator="explicit"))
    assert np.allclose(explicit.compliance(ids, FRAME), implicit.compliance(ids, FRAME), rtol=1e-10, atol=0)


def test_compliance_validation():
    model = TissueModel(MESH, TissueParameters(law="linear"))
    with pytest.raises(TissueError, match="no step has been taken yet"):
        model.compliance([0, 1])
    for bad, match in [([], "non-empty"), ([0.5], "integers"), ([0, 0], "repeat"),
                       ([model.n_surface], r"must lie in \[0, "), ([[0, 1]], "1-D")]:
        with pytest.raises(TissueError, match=match):
            model.compliance(bad, FRAME)
    with pytest.raises(TissueError, match="dt must be"):
        model.compliance([0], -1.0)

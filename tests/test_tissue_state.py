"""FMU state support: a stepped TissueModel copied with ``copy.deepcopy`` or through ``pickle``
continues bit for bit like the original (positions, energies, iterations), for the linear and
ETMM laws, implicit and explicit integration, and each way the implicit preconditioner keeps
the tangent (rest factor, Woodbury correction, assembled tangent, the rest-only factorisation,
Jacobi).  The SuperLU factors are dropped on pickling and rebuilt deterministically on load."""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest

from tissue_fmu import FactorizedPreconditioner, TissueModel, TissueParameters, aaa_mesh

MESH = aaa_mesh(n_circumferential=12, n_axial=16, n_radial=1)


def load(model: TissueModel, total: float) -> np.ndarray:
    d = np.linalg.norm(model.surface_positions() - np.array([0.022, 0.0, 0.065]), axis=1)
    force = np.zeros((model.n_surface, 3))
    force[np.argsort(d)[:4], 0] = -total / 4
    return force


def clone(model, how):
    if how == "deepcopy":
        return copy.deepcopy(model)
    return pickle.loads(pickle.dumps(model))


def outputs(model):
    return (model.surface_positions(), model.surface_velocities(), model.strain_energy, model.kinetic_energy,
            model.max_strain, model.solver_iterations, model.solver_residual, model.nonlinear_fraction, model.time)


def assert_identical(a, b):
    for x, y in zip(outputs(a), outputs(b)):
        if isinstance(x, np.ndarray):
            assert np.array_equal(x, y)
        else:
            assert x == y


CASES = {
    "linear-implicit": (dict(law="linear"), 1 / 30, 1.0, None),
    "etmm-implicit-auto": (dict(law="etmm", viscosity=50.0), 1 / 30, 3.0, None),
    "etmm-implicit-lowrank": (dict(law="etmm", viscosity=50.0), 1 / 30, 3.0, 10**9),
    "etmm-implicit-tangent": (dict(law="etmm", viscosity=50.0), 1 / 30, 3.0, -1),
    "etmm-implicit-jacobi": (dict(law="etmm", preconditioner="jacobi", cg_max_iterations=200), 1 / 30, 3.0, None),
    "linear-explicit": (dict(law="linear", integrator="explicit"), 2e-4, 1.0, None),
    "etmm-explicit": (dict(law="etmm", integrator="explicit"), 2e-4, 3.0, None),
}


@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
@pytest.mark.parametrize("case", list(CASES))
def test_copy_of_a_stepped_model_continues_bit_identically(case, how):
    params, dt, force, max_lowrank = CASES[case]
    model = TissueModel(MESH, TissueParameters(**params))
    if max_lowrank is not None:
        model.integrator.preconditioner.max_lowrank_dofs = max_lowrank
        model.integrator.preconditioner.max_new_lowrank_dofs = max(max_lowrank, 0)
    model.set_contact_force(load(model, force))
    for k in range(4):
        model.step(k * dt, dt)
    nonlinear_at_copy = model.nonlinear_fraction
    twin = clone(model, how)
    assert_identical(model, twin)
    for k in range(4, 9):
        if k == 6:  # a changed input after the copy
            model.set_contact_force(load(model, 0.5 * force))
            twin.set_contact_force(load(twin, 0.5 * force))
        model.step(k * dt, dt)
        twin.step(k * dt, dt)
        assert_identical(model, twin)
    if "etmm-implicit" in case and "jacobi" not in case:
        assert nonlinear_at_copy > 0  # the copies were taken with a non-linear tangent


def test_copy_is_independent_of_the_original():
    model = TissueModel(MESH, TissueParameters(law="etmm"))
    model.set_contact_force(load(model, 3.0))
    model.step(0.0, 1 / 30)
    twin = pickle.loads(pickle.dumps(model))
    twin.step(1 / 30, 1 / 30)
    assert model.time == pytest.approx(1 / 30) and twin.time == pytest.approx(2 / 30)
    assert not np.shares_memory(model.displacement, twin.displacement)


def test_rest_only_factorisation_pickles():
    model = TissueModel(MESH, TissueParameters(law="linear"))
    ff = model.force_field
    pc = FactorizedPreconditioner(ff.stiffness_matrix(), model.masses, model.fixed)
    pc.update(1 / 30)
    copy_ = pickle.loads(pickle.dumps(pc))
    r = np.random.default_rng(1).standard_normal((ff.n_nodes, 3))
    a, b = np.zeros_like(r), np.zeros_like(r)
    pc(r, a)
    copy_(r, b)
    assert np.array_equal(a, b)

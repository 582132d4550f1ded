"""Wall failure (issue 32): the failure criterion against the uniaxial closed form, and a wall that
tears during a run: energy bookkeeping, the record and log line, and a run through a failure that
a saved copy reproduces bit for bit."""
from __future__ import annotations

import copy
import logging

import numpy as np
import pytest

from tissue_fmu import TissueModel, TissueParameters, aaa_mesh
from tissue_fmu.failure import DEFAULT_FAILURE_STRESS, failed_elements, failure_stretch, rv_uniaxial_cauchy_stress
from tissue_fmu.forcefield import TensorMassForceField
from tissue_fmu.mesh import box_mesh
from tissue_fmu.precompute import element_pair_blocks
from tissue_statics import roller_dofs, solve_statics

ALPHA, BETA = 0.174e6, 1.881e6


def test_the_failure_stretch_is_where_the_closed_form_reaches_the_failure_stress():
    for stress in (0.5e6, DEFAULT_FAILURE_STRESS, 1.4e6):
        stretch = failure_stretch(stress, ALPHA, BETA)
        assert rv_uniaxial_cauchy_stress(stretch, ALPHA, BETA) == pytest.approx(stress, rel=1e-12)
        below = np.linspace(1.0 + 1e-6, stretch - 1e-9, 200)
        assert (rv_uniaxial_cauchy_stress(below, ALPHA, BETA) < stress).all()
    # the measured 0.8-1.4 MPa is a stretch of 1.21-1.28 on the Raghavan-Vorp wall
    assert 1.2 < failure_stretch(0.8e6, ALPHA, BETA) < failure_stretch(1.4e6, ALPHA, BETA) < 1.3
    with pytest.raises(ValueError, match="failure_stress"):
        failure_stretch(0.0, ALPHA, BETA)


def _uniaxial_until_failure(divisions, law, increment):
    """Pull a unit box (rollers on three faces, the top face displaced) in stretch increments,
    solving statics by Newton with the consistent tangent; returns (stretch, Cauchy stress from the
    reaction) of the last increment before failure and of the first at which elements fail, and the
    elements that failed then."""
    mesh = box_mesh(size=(1.0, 1.0, float(divisions[2])), divisions=divisions)
    n = mesh.n_nodes
    ff = TensorMassForceField(mesh.points, mesh.tets, 6 * ALPHA, 0.49, law=law, rv_alpha=ALPHA, rv_beta=BETA)
    limit = failure_stretch(DEFAULT_FAILURE_STRESS, ALPHA, BETA)
    top = 3 * mesh.node_sets["zmax"] + 2
    free = np.setdiff1d(np.arange(3 * n), np.union1d(roller_dofs(mesh), top))
    length = float(divisions[2])
    u = np.zeros(3 * n)
    previous = None
    for stretch in np.arange(1.0 + increment, 1.5, increment):
        u[top] = (stretch - 1.0) * length
        f, _ = solve_statics(ff, u, free, 1e-10 * ALPHA, max_iterations=40)
        cauchy = stretch * -f.reshape(-1)[top].sum()  # reaction over the unit reference area, times l
        failed = failed_elements(ff, u.reshape(-1, 3), limit)
        if failed.size:
            return previous, (stretch, cauchy), failed, ff
        previous = (stretch, cauchy)
    raise AssertionError("the box never failed")


@pytest.mark.parametrize("divisions", [(1, 1, 1), (1, 1, 4)], ids=["single element", "strip"])
def test_a_pulled_element_and_strip_fail_at_the_closed_form_stress_not_before(divisions):
    """ETMM reproduces the Raghavan-Vorp uniaxial response (tissue_fmu.materials), so the wall's own
    reaction gives the failure stress: below it at the last increment, at or above it (by less than
    one increment) when the elements fail; every element of the uniform box fails together."""
    increment = 0.002
    (l_before, s_before), (l_fail, s_fail), failed, ff = _uniaxial_until_failure(divisions, "etmm", increment)
    limit = failure_stretch(DEFAULT_FAILURE_STRESS, ALPHA, BETA)
    assert l_before < limit <= l_fail < limit + increment + 1e-12
    assert s_before < DEFAULT_FAILURE_STRESS <= s_fail
    assert s_fail - DEFAULT_FAILURE_STRESS <= s_fail - s_before  # within the step's resolution
    assert s_fail == pytest.approx(rv_uniaxial_cauchy_stress(l_fail, ALPHA, BETA), rel=1e-9)
    assert failed.size == ff.active_tets.shape[0]


def _pushed_wall(peak, frames, **parameters):
    mesh = aaa_mesh(n_circumferential=16, n_axial=20, n_radial=1)
    model = TissueModel(mesh, TissueParameters(law="etmm", viscosity=50.0, **parameters))
    model.prepare(1 / 30)
    d = np.linalg.norm(model.surface_positions() - [0.0265, 0.0, 0.065], axis=1)
    force = np.zeros((model.n_surface, 3))
    force[np.argsort(d)[:4], 0] = -peak / 4
    return model, force


def _run(model, force, frames, start=0, ramp=10):
    for k in range(start, frames):
        model.set_contact_force(force * min(k + 1, ramp) / ramp)
        model.step(k / 30, 1 / 30)


def test_a_wall_that_never_fails_by_default_and_one_that_tears_under_20_n(caplog):
    model, force = _pushed_wall(20.0, 12)
    _run(model, force, 12)
    assert not model.perforated and model.failures == []
    model, force = _pushed_wall(20.0, 12, failure_stress=DEFAULT_FAILURE_STRESS)
    with caplog.at_level(logging.WARNING, logger="tissue_fmu.model"):
        _run(model, force, 12)
    assert model.perforated and model.failures
    first = model.failures[0]
    assert first["elements"] > 0 and first["contact_force"] > 0 and first["released_energy"] > 0
    assert model.failed.sum() == model.failures[-1]["failed_total"] == model.force_field.removed.sum()
    assert any("failed at t = " in r.getMessage() and "failure stress 1 MPa" in r.getMessage()
               for r in caplog.records)
    # nothing of a failed element is left: no mass, no strain measured on it, its orphaned nodes frozen
    assert np.isfinite(model.displacement).all()
    orphans = np.setdiff1d(np.arange(model.mesh.n_nodes), model.mesh.tets[~model.failed].reshape(-1))
    assert model.fixed[orphans].all() and (model.masses[orphans] == 0).all()


def test_released_energy_is_the_removed_elements_own_strain_energy():
    """Linear law: each element's energy is 1/2 u_T . K_T u_T (its blocks, computed independently);
    ETMM: the secant energy is a sum over elements, so removing two sets one after the other
    releases what removing them together does."""
    mesh = aaa_mesh(n_circumferential=12, n_axial=16, n_radial=1)
    u = np.random.default_rng(32).normal(0.0, 3e-4, mesh.points.shape)
    ff = TensorMassForceField(mesh.points, mesh.tets, 1.044e6, 0.45, law="linear")
    ids = np.arange(0, mesh.n_tets, 7)
    from tissue_fmu.precompute import shape_gradients

    grads, volumes = shape_gradients(mesh.points, mesh.tets[ids])
    lam, mu = ff._lam[ids], ff._mu[ids]
    pairs = np.array([[j, k] for j in range(4) for k in range(4)])
    blocks = element_pair_blocks(grads, volumes, lam, mu, pairs).reshape(ids.size, 4, 4, 3, 3)
    u_t = u[mesh.tets[ids]]
    expected = 0.5 * np.einsum("eja,ejkab,ekb->", u_t, blocks, u_t)
    before = ff.strain_energy(u)
    ff.remove_elements(ids)
    assert before - ff.strain_energy(u) == pytest.approx(expected, rel=1e-10)

    a, b = np.arange(0, mesh.n_tets, 11), np.arange(5, mesh.n_tets, 13)
    b = np.setdiff1d(b, a)

    def etmm():
        return TensorMassForceField(mesh.points, mesh.tets, 1.044e6, 0.45, law="etmm")

    together, one_by_one = etmm(), etmm()
    e0 = together.strain_energy(u)
    together.remove_elements(np.concatenate([a, b]))
    released_together = e0 - together.strain_energy(u)
    one_by_one.remove_elements(a)
    e_a = one_by_one.strain_energy(u)
    one_by_one.remove_elements(b)
    released_in_two = (e0 - e_a) + (e_a - one_by_one.strain_energy(u))
    assert released_in_two == pytest.approx(released_together, rel=1e-12)
    assert released_together > 0


def test_a_copy_saved_before_the_failure_runs_through_it_bit_for_bit():
    """The FMU state is a copy of the model: restored, it reproduces the failure and what follows."""
    model, force = _pushed_wall(20.0, 14, failure_stress=DEFAULT_FAILURE_STRESS)
    _run(model, force, 8)
    assert not model.perforated
    saved = copy.deepcopy(model)
    _run(model, force, 14, start=8)
    _run(saved, force, 14, start=8)
    assert model.perforated
    np.testing.assert_array_equal(saved.displacement, model.displacement)
    np.testing.assert_array_equal(saved.failed, model.failed)
    assert saved.failures == model.failures

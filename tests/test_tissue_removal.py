"""Local topology change of the tensor-mass model (issue 32): elements taken out of a running wall.

The tensor-mass model's point (Cotin, Delingette and Ayache 2000) is that removing an element only
changes the tensors of its own vertices and edges. Whatever set is removed, the updated force field
must be the one a from-scratch precomputation builds on the mesh without those elements: its
stiffness and damping operators, forces (also above the ETMM threshold), tangents, energies,
strains and masses, to 1e-12 relative.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tissue_fmu import aaa_mesh
from tissue_fmu.forcefield import TensorMassForceField
from tissue_fmu.precompute import tensors_to_csr

MESH = aaa_mesh(n_circumferential=12, n_axial=16, n_radial=1)
M = MESH.tets.shape[0]
TOLERANCE = 1e-12


def _field(law: str, viscosity, active=None) -> TensorMassForceField:
    return TensorMassForceField(MESH.points, MESH.tets, 1.044e6, 0.45, law=law, viscosity=viscosity,
                                active_elements=active)


def _viscosity(kind: str):
    if kind == "none":
        return 0.0
    if kind == "uniform":  # C = tau K: folded into the stiffness tensors
        return 50.0
    return np.random.default_rng(3).uniform(10.0, 100.0, M)  # per element: separate damping tensors


def _relative(a, b) -> float:
    scale = max(np.abs(b).max(), np.finfo(float).tiny)
    return float(np.abs(a - b).max() / scale)


def _compare(updated: TensorMassForceField, scratch: TensorMassForceField, removed: np.ndarray, seed: int):
    k_updated, k_scratch = tensors_to_csr(updated.stiffness), tensors_to_csr(scratch.stiffness)
    assert _relative(k_updated.toarray(), k_scratch.toarray()) <= TOLERANCE
    c_updated, c_scratch = updated.damping_tensors(), scratch.damping_tensors()
    assert (c_updated is None) == (c_scratch is None)
    if c_scratch is not None:
        c_scratch = tensors_to_csr(c_scratch).toarray()
        assert _relative(tensors_to_csr(c_updated).toarray(), c_scratch) <= TOLERANCE
    rng = np.random.default_rng(seed)
    # displacements large enough that many elements are over the ETMM threshold (Green strain 0.05)
    u = rng.normal(0.0, 3e-4, MESH.points.shape)
    v = rng.normal(0.0, 1e-2, MESH.points.shape)
    f_updated, f_scratch = np.zeros_like(u), np.zeros_like(u)
    updated.add_forces(u, v, f_updated)
    scratch.add_forces(u, v, f_scratch)
    assert _relative(f_updated, f_scratch) <= TOLERANCE
    assert updated.nonlinear_element_ids().size == scratch.nonlinear_element_ids().size
    if updated.law == "etmm":
        assert scratch.nonlinear_element_ids().size > 0  # the correction and its tangent are exercised
    du = rng.normal(0.0, 1e-4, u.shape)
    t_updated, t_scratch = np.zeros_like(u), np.zeros_like(u)
    updated.consistent_tangent_matvec(du, t_updated)
    scratch.consistent_tangent_matvec(du, t_scratch)
    assert _relative(t_updated, t_scratch) <= TOLERANCE
    assert updated.strain_energy(u) == pytest.approx(scratch.strain_energy(u), rel=TOLERANCE)
    assert updated.max_strain(u) == pytest.approx(scratch.max_strain(u), rel=TOLERANCE)
    np.testing.assert_allclose(updated.lumped_masses(1120.0), scratch.lumped_masses(1120.0), rtol=TOLERANCE,
                               atol=TOLERANCE * scratch.lumped_masses(1120.0).max())


@settings(max_examples=30, deadline=None)
@given(law=st.sampled_from(["linear", "etmm"]), viscosity=st.sampled_from(["none", "uniform", "per element"]),
       removed=st.sets(st.integers(0, M - 1), min_size=1, max_size=60), seed=st.integers(0, 2**31 - 1),
       batches=st.integers(1, 3))
def test_removing_any_elements_equals_a_from_scratch_precomputation(law, viscosity, removed, seed, batches):
    removed = np.array(sorted(removed))
    eta = _viscosity(viscosity)
    updated = _field(law, eta)
    orphans = []
    for batch in np.array_split(np.random.default_rng(seed).permutation(removed), batches):  # in several steps
        orphans.append(updated.remove_elements(batch))
    keep = np.ones(M, dtype=bool)
    keep[removed] = False
    scratch = _field(law, eta, active=keep)
    _compare(updated, scratch, removed, seed)
    # the nodes left without an element are exactly those no kept element uses
    used = np.zeros(MESH.points.shape[0], dtype=bool)
    used[MESH.tets[keep].reshape(-1)] = True
    np.testing.assert_array_equal(np.sort(np.concatenate(orphans)), np.flatnonzero(~used))


def test_a_strip_through_the_wall_leaves_its_inner_nodes_orphaned():
    """Every element around a node removed: the node is returned (once), its tensors vanish."""
    node = int(MESH.tets[M // 2, 0])
    around = np.flatnonzero((MESH.tets == node).any(axis=1))
    updated = _field("etmm", 50.0)
    orphans = updated.remove_elements(around)
    assert node in orphans
    scale = np.abs(_field("etmm", 50.0).stiffness.vertex).max()
    assert np.abs(updated.stiffness.vertex[node]).max() <= TOLERANCE * scale
    assert updated.remove_elements(around).size == 0  # removing them again changes nothing


@pytest.mark.parametrize("bad", [[-1], [M], ["a"]])
def test_remove_elements_refuses_ids_that_are_not_rows_of_the_active_tets(bad):
    from tissue_fmu.errors import ForceFieldError

    with pytest.raises(ForceFieldError, match="remove_elements"):
        _field("linear", 0.0).remove_elements(bad)

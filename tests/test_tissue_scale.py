"""The implicit step at scale (issue 13): the factorised, kept-exact preconditioner gives the same
displacement as the former implementation, to solver tolerance, at several mesh sizes and loads.

The former implementation is kept here as a slow reference (plain scipy, in the style of
stumpy's test references): one linearised backward-Euler step, the consistent ETMM tangent from
the original all-candidate kernel (``kernels.etmm_consistent_tangent``), solved by scipy's GMRES
preconditioned with the rest-state factorisation ``M + h C + h^2 K_0``, to a tight tolerance.
Also here: the assembled tangent blocks against that kernel, the cheap max-strain kernel, and
any vertex order of a rest tet.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from orchestration.hosts.native_threads import NATIVE_THREAD_LIMITS
from tissue_fmu import kernels
from tissue_fmu.errors import MeshError, TissueError
from tissue_fmu.forcefield import TensorMassForceField, assemble_stiffness
from tissue_fmu.mesh import TetMesh, aaa_mesh, box_mesh
from tissue_fmu.model import TissueModel, TissueParameters
from tissue_fmu.precompute import tensors_to_csr

FRAME = 1.0 / 30.0
CONTACT_POINT = (0.022, 0.0, 0.065)


def patch_force(model: TissueModel, total: float, k: int = 4) -> np.ndarray:
    """(n_surface, 3): ``total`` N in -x spread over the k surface nodes nearest the sac contact point."""
    d = np.linalg.norm(model.surface_positions() - np.asarray(CONTACT_POINT), axis=1)
    force = np.zeros((model.n_surface, 3))
    force[np.argsort(d)[:k], 0] = -total / k
    return force


# --------------------------------------------------------------------------------------
# the former implementation, as a slow reference
# --------------------------------------------------------------------------------------


class ReferenceStep:
    """The step as it was before issue 13 (rest factorisation + matrix-free all-candidate tangent)."""

    def __init__(self, model: TissueModel, tolerance: float = 1e-10):
        ff = self.ff = model.force_field
        self.h = None
        self.tolerance = tolerance
        self.free = np.flatnonzero(np.repeat(~model.fixed, 3))
        self.mass = np.repeat(np.where(model.masses > 0, model.masses, 1.0), 3)
        self.k0 = ff.stiffness_matrix()
        damping = ff.damping_tensors()
        self.c0 = None if damping is None else tensors_to_csr(damping)
        self.viscous = model.params.viscosity > 0

    def _tangent(self, x_flat, consistent):
        ff = self.ff
        x = x_flat.reshape(-1, 3)
        out = np.zeros_like(x)
        if consistent:
            k = ff.stiffness
            kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, x, 1.0, out)
            kernels.etmm_consistent_tangent(ff._tets, ff._grads, ff._volumes, ff._lam, ff._mu, ff._candidates,
                                            ff._u_last, np.ascontiguousarray(x), ff.nonlinear_strain_threshold,
                                            ff._beta_over_alpha, out)
        else:
            ff.tangent_matvec(np.ascontiguousarray(x), out)
        return out.reshape(-1)

    def step(self, u, v, f_ext, h):
        ff = self.ff
        free = self.free
        if h != self.h:
            a0 = sp.diags(self.mass) + (h * h) * self.k0 + (0 if self.c0 is None else h * self.c0)
            self.lu = spla.splu(a0.tocsr()[free][:, free].tocsc())
            self.h = h
        b = f_ext.copy()
        ff.add_forces(u, v, b)
        consistent = ff.law == "etmm" and ff.nonlinear_fraction > 0
        rhs = h * (b.reshape(-1) - h * self._tangent(v.reshape(-1), consistent))

        def apply(x_free):
            x = np.zeros(3 * u.shape[0])
            x[free] = x_free
            y = (h * h) * self._tangent(x, consistent) + self.mass * x
            if self.viscous:
                y += h * (self.c0 @ x)
            return y[free]

        n = free.size
        a = spla.LinearOperator((n, n), matvec=apply)
        m = spla.LinearOperator((n, n), matvec=self.lu.solve)
        dv_free, info = spla.gmres(a, rhs[free], M=m, rtol=self.tolerance, atol=0.0, restart=50, maxiter=200)
        residual = np.linalg.norm(rhs[free] - apply(dv_free)) / np.linalg.norm(rhs[free])
        assert residual <= 10 * self.tolerance, (info, residual)
        dv = np.zeros(3 * u.shape[0])
        dv[free] = dv_free
        v += dv.reshape(-1, 3)
        u += h * v


SIZES = [dict(n_circumferential=12, n_axial=16, n_radial=1), dict(n_circumferential=16, n_axial=20, n_radial=1),
         dict(n_circumferential=24, n_axial=30, n_radial=1)]


@pytest.mark.parametrize("sizes", SIZES, ids=["12x16x1", "16x20x1", "24x30x1"])
@pytest.mark.parametrize("load", [0.5, 3.0])
@pytest.mark.parametrize("strategy", ["auto", "lowrank", "tangent"])
def test_displacement_equals_former_implementation_to_solver_tolerance(sizes, load, strategy):
    """Same trajectory as the former step to solver tolerance, whichever way the tangent is kept
    (auto: the default choice; lowrank: Woodbury always; tangent: assembled factor always)."""
    mesh = aaa_mesh(**sizes)
    params = TissueParameters(law="etmm", viscosity=50.0, cg_tolerance=1e-9)
    model = TissueModel(mesh, params)
    pc = model.integrator.preconditioner
    if strategy == "lowrank":
        pc.max_lowrank_dofs = 10**9
        pc.max_new_lowrank_dofs = 10**9
    elif strategy == "tangent":
        pc.max_lowrank_dofs = -1
    reference_model = TissueModel(mesh, params)
    reference = ReferenceStep(reference_model)
    force = patch_force(model, load)
    model.set_contact_force(force)
    f_ext = reference_model._external_force
    f_ext[reference_model.surface_nodes] = force
    u_ref = np.zeros_like(model.displacement)
    v_ref = np.zeros_like(model.velocity)
    modes, nonlinear, v_scale = set(), 0.0, 0.0
    for k in range(8):
        model.step(k * FRAME, FRAME)
        reference.step(u_ref, v_ref, f_ext, FRAME)
        modes.add(pc.mode)
        nonlinear = max(nonlinear, model.nonlinear_fraction)
        assert model.solver_converged
        scale = np.abs(u_ref).max()
        assert np.abs(model.displacement - u_ref).max() <= 1e-7 * scale, (k, pc.mode)
        v_scale = max(v_scale, np.abs(v_ref).max())
        assert np.abs(model.velocity - v_ref).max() <= 1e-6 * v_scale, (k, pc.mode)
    if nonlinear > 0 and strategy != "auto":
        assert strategy in modes
    if load == 3.0:
        assert nonlinear > 0.0  # the loads reach the non-linear regime


def test_default_wall_under_5N_equals_former_implementation():
    """The issue's case: full default wall, ETMM, 5 N, about half the tets non-linear."""
    mesh = aaa_mesh()
    params = TissueParameters(law="etmm", viscosity=50.0, cg_tolerance=1e-9)
    model = TissueModel(mesh, params)
    reference_model = TissueModel(mesh, params)
    reference = ReferenceStep(reference_model, tolerance=1e-10)
    force = patch_force(model, 5.0)
    model.set_contact_force(force)
    reference_model.set_contact_force(force)
    u_ref, v_ref = np.zeros_like(model.displacement), np.zeros_like(model.velocity)
    for k in range(6):
        model.step(k * FRAME, FRAME)
        reference.step(u_ref, v_ref, reference_model._external_force, FRAME)
        assert np.abs(model.displacement - u_ref).max() <= 1e-6 * np.abs(u_ref).max(), k
    assert model.nonlinear_fraction > 0.3
    assert model.integrator.preconditioner.mode == "tangent"


def test_default_tolerance_stays_within_tolerance_of_the_reference():
    """At the default cg_tolerance 1e-6 the displacement differs from the tight reference by the
    order of the tolerance, as the former implementation's did."""
    mesh = aaa_mesh(n_circumferential=16, n_axial=20, n_radial=1)
    model = TissueModel(mesh, TissueParameters(law="etmm", viscosity=50.0))
    reference_model = TissueModel(mesh, TissueParameters(law="etmm", viscosity=50.0))
    reference = ReferenceStep(reference_model)
    force = patch_force(model, 3.0)
    model.set_contact_force(force)
    reference_model.set_contact_force(force)
    u_ref, v_ref = np.zeros_like(model.displacement), np.zeros_like(model.velocity)
    for k in range(10):
        model.step(k * FRAME, FRAME)
        reference.step(u_ref, v_ref, reference_model._external_force, FRAME)
    assert np.abs(model.displacement - u_ref).max() <= 1e-5 * np.abs(u_ref).max()


def test_solver_backends_agree():
    """The rest factor by every backend installed here (the system's CHOLMOD through scikit-sparse,
    cholespy's CHOLMOD, SuperLU): the same preconditioner to round-off, and the same
    Woodbury-corrected step matrix inverse."""
    from tissue_fmu.factorization import BACKENDS, TangentFactorization, backend_available

    backends = [name for name in BACKENDS if backend_available(name)]
    if len(backends) < 2:
        pytest.skip(f"only {backends} installed: nothing to compare")
    model = TissueModel(aaa_mesh(**SIZES[1]), TissueParameters(law="etmm", viscosity=50.0))
    model.set_contact_force(patch_force(model, 3.0))
    for k in range(3):
        model.step(k * FRAME, FRAME)
    assert model.nonlinear_fraction > 0
    r = np.random.default_rng(2).standard_normal(model.displacement.shape)
    results = {}
    for backend in backends:
        pc = TangentFactorization(model.force_field, model.masses, model.fixed, backend=backend)
        pc.update(FRAME)
        assert pc.mode == "lowrank"
        out = np.zeros_like(r)
        pc(r, out)
        results[backend] = out
    reference = results.pop("superlu")
    for backend, out in results.items():
        assert np.abs(out - reference).max() <= 1e-9 * np.abs(reference).max(), backend


def test_backend_choice_and_refusal():
    """``auto`` takes the fastest backend installed; a backend that is not installed, or unknown, is
    refused with what to do, not an ImportError from inside the first factorisation."""
    from tissue_fmu.factorization import BACKENDS, TangentFactorization, backend_available, default_backend

    model = TissueModel(aaa_mesh(**SIZES[0]), TissueParameters(law="linear"))
    chosen = TangentFactorization(model.force_field, model.masses, model.fixed).backend
    assert chosen == default_backend() == next(name for name in BACKENDS if backend_available(name))
    with pytest.raises(ValueError, match="backend must be 'auto' or one of scikit-sparse, cholespy, superlu"):
        TangentFactorization(model.force_field, model.masses, model.fixed, backend="pardiso")
    missing = [name for name in BACKENDS if not backend_available(name)]
    for name in missing:
        with pytest.raises(ValueError, match="not installed here"):
            TangentFactorization(model.force_field, model.masses, model.fixed, backend=name)


_THREADS_SCRIPT = """
import hashlib, json, os, sys
if sys.argv[1] == "limited":
    from orchestration.hosts.native_threads import limit_native_threads
    limit_native_threads()  # what the orchestrator's processes do before loading an FMU
import numpy as np
from threadpoolctl import threadpool_info
from tissue_fmu import TissueModel, TissueParameters, aaa_mesh
from orchestration.hosts.native_threads import NATIVE_THREAD_LIMITS
from tissue_fmu.factorization import _SYSTEM_BLAS, backend_available

threads = lambda: len(os.listdir("/proc/self/task"))
system_blas = lambda: [i["num_threads"] for i in threadpool_info() if i["prefix"] in _SYSTEM_BLAS]
before = threads()
assert backend_available("scikit-sparse")  # loads CHOLMOD, libgomp and the system's OpenBLAS
blas_before = system_blas()
model = TissueModel(aaa_mesh(), TissueParameters(law="linear"))
model.step(0.0, 1.0 / 30.0)  # factorises the whole default wall's rest matrix
assert model.integrator.preconditioner.backend == "scikit-sparse"
rhs = np.random.default_rng(0).standard_normal((model.integrator.preconditioner.free_dofs.size, 12))
solved = model.integrator.preconditioner.solve_matrix(rhs)
print(json.dumps(dict(before=before, after=threads(), blas_before=blas_before, blas_after=system_blas(),
                      bits=hashlib.sha1(np.ascontiguousarray(solved).tobytes()).hexdigest(),
                      environment={k: os.environ.get(k) for k in NATIVE_THREAD_LIMITS})))
"""


def _threads_report(mode: str, cpus: str | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in NATIVE_THREAD_LIMITS}
    command = [sys.executable, "-c", _THREADS_SCRIPT, mode]
    done = subprocess.run(["taskset", "-c", cpus, *command] if cpus else command, capture_output=True, text=True,
                          env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_system_cholmod_threads_bits_and_good_manners():
    """The system's CHOLMOD, in fresh interpreters (the limits are read when the libraries load):
    * the same bits whatever the process's CPUs and thread settings: its BLAS runs on one thread in
      every CHOLMOD call (two OpenBLAS threads round differently), and the thread count it found
      is restored afterwards, for an importer that uses the same OpenBLAS;
    * with the orchestrator's limits in the environment (orchestration.hosts.native_threads) loading
      and factorising start no thread (CHOLMOD would take 4 OpenMP threads beside the 1 kHz loop);
    * the library itself leaves the environment alone: it also runs inside other people's FMU
      importers, whose OpenMP it must not cap."""
    from tissue_fmu.factorization import backend_available

    if not backend_available("scikit-sparse"):
        pytest.skip("scikit-sparse (the system's CHOLMOD) not installed")
    limited = _threads_report("limited")
    assert limited["after"] == limited["before"], limited
    assert limited["environment"] == NATIVE_THREAD_LIMITS, limited
    free = _threads_report("as-is")
    assert free["environment"] == dict.fromkeys(NATIVE_THREAD_LIMITS), free
    assert free["after"] > free["before"], free  # what the limits prevent (this test's premise)
    assert free["blas_after"] == free["blas_before"], free
    pinned = _threads_report("as-is", cpus="0")
    assert free["bits"] == limited["bits"] == pinned["bits"], (free, limited, pinned)


# --------------------------------------------------------------------------------------
# kernels against references
# --------------------------------------------------------------------------------------


def strained_etmm_field():
    mesh = box_mesh((0.02, 0.02, 0.04), (2, 2, 4))
    ff = TensorMassForceField(mesh.points, mesh.tets, 1.044e6, 0.45, law="etmm")
    rng = np.random.default_rng(3)
    z = mesh.points[:, 2]
    u = 2e-4 * rng.standard_normal(mesh.points.shape)
    u[:, 2] += 0.2 * z * z / (2 * 0.04)  # axial strain rising from 0 to 0.2 along the bar
    ff.add_forces(u, None, np.zeros_like(u))
    assert 0 < ff.nonlinear_fraction < 1
    return mesh, ff, u


def test_assembled_tangent_blocks_equal_the_all_candidate_consistent_kernel():
    mesh, ff, u = strained_etmm_field()
    n = mesh.n_nodes
    ids, blocks = ff.tangent_blocks()
    dense = ff.stiffness_matrix().toarray()
    tets = ff.active_tets
    for c, e in enumerate(ids):
        for j in range(4):
            for k in range(4):
                dense[3 * tets[e, j]: 3 * tets[e, j] + 3, 3 * tets[e, k]: 3 * tets[e, k] + 3] += blocks[c, j, k]
    reference = np.zeros((3 * n, 3 * n))
    for col in range(3 * n):
        x = np.zeros((n, 3))
        x.reshape(-1)[col] = 1.0
        out = np.zeros((n, 3))
        k0 = ff.stiffness
        kernels.tensor_mass_matvec(k0.vertex, k0.edges, k0.edge_tensors, x, 1.0, out)
        kernels.etmm_consistent_tangent(ff._tets, ff._grads, ff._volumes, ff._lam, ff._mu, ff._candidates, u, x,
                                        ff.nonlinear_strain_threshold, ff._beta_over_alpha, out)
        reference[:, col] = out.reshape(-1)
    assert np.allclose(dense, reference, rtol=0, atol=1e-10 * np.abs(reference).max())
    # and the super-threshold-only matrix-free product is the same operator
    x = np.random.default_rng(0).standard_normal((n, 3))
    out = np.zeros((n, 3))
    ff.consistent_tangent_matvec(x, out)
    assert np.allclose(out.reshape(-1), reference @ x.reshape(-1), rtol=0, atol=1e-10 * np.abs(reference).max())


def test_max_strain_kernel_equals_the_per_element_maximum_bit_for_bit():
    mesh, ff, u = strained_etmm_field()
    assert ff.max_strain(u) == ff.element_max_strain(u).max()
    assert ff.max_strain(np.zeros_like(u)) == 0.0


def test_max_strain_skip_bound_keeps_the_maximum_bit_for_bit():
    """The kernel skips elements by ||H|| + ||H||^2 / 2 >= ||E||: small, large, random and rotated
    displacement fields still give exactly the per-element maximum."""
    mesh, ff, u = strained_etmm_field()
    rng = np.random.default_rng(3)
    points = ff._points
    angle = 0.3  # a rigid rotation: large H, E = 0 up to round-off (the bound skips nothing)
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    fields = [1e-6 * u, 1e-3 * u, 10.0 * u, 1e-4 * rng.standard_normal(u.shape), points @ rotation.T - points,
              points @ rotation.T - points + 1e-3 * u]
    for field in fields:
        assert ff.max_strain(field) == ff.element_max_strain(field).max()


# --------------------------------------------------------------------------------------
# vertex order of a rest tetrahedron
# --------------------------------------------------------------------------------------


def test_assemble_stiffness_is_the_same_for_any_vertex_order():
    mesh = box_mesh((0.01, 0.02, 0.03), (2, 2, 2))
    k = assemble_stiffness(mesh.points, mesh.tets, 1.044e6, 0.45).toarray()
    rng = np.random.default_rng(7)
    shuffled = np.array([row[rng.permutation(4)] for row in mesh.tets])
    assert (np.linalg.det(np.stack([mesh.points[shuffled[:, i]] - mesh.points[shuffled[:, 0]]
                                    for i in (1, 2, 3)], axis=2)) < 0).any()  # some are now inverted
    k_shuffled = assemble_stiffness(mesh.points, shuffled, 1.044e6, 0.45).toarray()
    assert np.allclose(k_shuffled, k, rtol=0, atol=1e-9 * np.abs(k).max())
    assert np.linalg.eigvalsh(k).min() > -1e-6 * np.abs(k).max()  # positive semi-definite


def test_entry_points_refuse_an_inverted_rest_tet_clearly():
    mesh = box_mesh((0.01, 0.01, 0.01), (1, 1, 1))
    tets = mesh.tets.copy()
    tets[0, [0, 1]] = tets[0, [1, 0]]
    with pytest.raises(MeshError, match="inverted tet.*fix_orientation"):
        TetMesh(mesh.points, tets, mesh.node_sets, {})
    with pytest.raises(MeshError, match="inverted"):
        TensorMassForceField(mesh.points, tets, 1.0e6, 0.45)
    with pytest.raises(MeshError, match="degenerate"):
        flat = mesh.points.copy()
        flat[:, 2] = 0.0
        assemble_stiffness(flat, mesh.tets, 1.0e6, 0.45)


def test_one_error_base_class():
    from tissue_fmu import errors, forcefield, integrators, materials, mesh, model

    assert mesh.MeshError is errors.MeshError and materials.MaterialError is errors.MaterialError
    assert forcefield.ForceFieldError is errors.ForceFieldError and model.TissueError is errors.TissueError
    assert integrators.StabilityError is errors.StabilityError
    for cls in (errors.MeshError, errors.MaterialError, errors.ForceFieldError, errors.StabilityError):
        assert issubclass(cls, TissueError) and issubclass(cls, ValueError)

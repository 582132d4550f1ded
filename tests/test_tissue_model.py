"""Tests of tissue_fmu.integrators and tissue_fmu.model against known answers.

Explicit symplectic Euler: the exact discrete solution of one oscillator mode, its conserved
shadow energy, the analytic frequency, and the stability threshold.  Implicit backward Euler:
its exact per-step energy factor 1/(1 + (omega h)^2) and the static limit K u = f (scipy
spsolve), the non-linear static equilibrium, the default AAA at 30 Hz.  Validation messages,
active region, per-element materials, state save/restore.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import scipy.linalg as sla
import scipy.sparse.linalg as spla

from tissue_fmu.forcefield import TensorMassForceField, assemble_stiffness
from tissue_fmu.errors import StabilityError, TissueError
from tissue_fmu.integrators import BackwardEuler, SymplecticEuler
from tissue_fmu.solvers import (
    BiCGStabWorkspace,
    CGWorkspace,
    GMRESWorkspace,
    preconditioned_bicgstab,
    preconditioned_cg,
    preconditioned_gmres,
)
from tissue_fmu.mesh import TetMesh, aaa_mesh, box_mesh
from tissue_fmu.model import TissueModel, TissueParameters

E, NU, RHO = 1.044e6, 0.45, 1120.0
FRAME = 1.0 / 30.0


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def one_tet_mesh(size=0.01) -> TetMesh:
    """A single tet; nodes 0, 1, 2 form the clamped base, node 3 is the one free mass."""
    points = size * np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.2, 0.3, 1.0]])
    return TetMesh(points, np.array([[0, 1, 2, 3]]), {"base": np.array([0, 1, 2])}, {})


def free_node_modes(model: TissueModel):
    """(omega (3,), modes (3, 3) columns) of the free node of one_tet_mesh: K_33 e = omega^2 m e."""
    k = assemble_stiffness(model.mesh.points, model.mesh.tets, E, NU).toarray()[9:12, 9:12]
    stiffness, modes = np.linalg.eigh(k)
    return np.sqrt(stiffness / model.masses[3]), modes


def cantilever(divisions=(2, 2, 6)) -> TetMesh:
    return box_mesh((0.02, 0.02, 0.06), divisions)


def tip_load(model: TissueModel, total: float, axis: int = 0) -> np.ndarray:
    """(n, 3) nodal force: ``total`` N along ``axis`` spread over the zmax face; applied to the model."""
    tip = model.mesh.node_sets["zmax"]
    force = np.zeros((model.mesh.n_nodes, 3))
    force[tip, axis] = total / tip.size
    model.set_contact_force(force[model.surface_nodes])
    return force


def static_solution(model: TissueModel, force: np.ndarray, active=None) -> np.ndarray:
    """u with K u = f on the free dofs (scipy spsolve), 0 on fixed dofs."""
    tets = model.mesh.tets if active is None else model.mesh.tets[active]
    young = model.young_modulus if active is None else model.young_modulus[active]
    poisson = model.poisson_ratio if active is None else model.poisson_ratio[active]
    k = assemble_stiffness(model.mesh.points, tets, young, poisson).tocsr()
    free = np.flatnonzero(np.repeat(~model.fixed, 3))
    u = np.zeros(3 * model.mesh.n_nodes)
    u[free] = spla.spsolve(k[free][:, free].tocsc(), force.reshape(-1)[free])
    return u.reshape(-1, 3)


def shadow_energy(model: TissueModel, h: float, stiffness) -> float:
    """The exactly conserved quantity of symplectic Euler on a linear system:
    1/2 v.M v + 1/2 u.K u - h/2 v.K u (u, v after the step)."""
    u = model.displacement.reshape(-1)
    v = model.velocity.reshape(-1)
    return model.kinetic_energy + model.strain_energy - 0.5 * h * float(v @ (stiffness @ u))


def total_energy(model: TissueModel) -> float:
    return model.kinetic_energy + model.strain_energy


# --------------------------------------------------------------------------------------
# explicit symplectic Euler
# --------------------------------------------------------------------------------------


def test_symplectic_euler_reproduces_discrete_solution_and_analytic_frequency():
    mesh = one_tet_mesh()
    model = TissueModel(mesh, TissueParameters(law="linear", integrator="explicit", substeps=1, clamp=("base",)))
    assert model.masses[3] == pytest.approx(RHO * mesh.volumes()[0] / 4.0, rel=1e-12)
    omega, modes = free_node_modes(model)
    w, e = omega[0], modes[:, 0]
    h = 0.05 / w
    assert h < model.critical_time_step
    x0 = 1e-4
    model.displacement[3] = x0 * e
    # Symplectic Euler on x'' = -w^2 x: cos(theta) = 1 - (w h)^2 / 2 and, from v0 = 0,
    # x_n = x0 (cos(n theta) - (w h)^2 / (2 sin(theta)) sin(n theta)).
    a2 = (w * h) ** 2
    theta = math.acos(1.0 - a2 / 2.0)
    n_steps = 3000  # about 24 periods
    x = np.empty(n_steps)
    for n in range(n_steps):
        model.step(n * h, h)
        x[n] = model.displacement[3] @ e
        # the mode does not leak into the other two directions
        assert np.linalg.norm(model.displacement[3] - x[n] * e) <= 1e-12 * x0
    n = np.arange(1, n_steps + 1)
    exact = x0 * (np.cos(n * theta) - a2 / (2.0 * math.sin(theta)) * np.sin(n * theta))
    np.testing.assert_allclose(x, exact, rtol=0, atol=1e-10 * x0)
    # Frequency measured from the zero crossings vs the analytic omega: the scheme's
    # theta / h = omega (1 + (omega h)^2 / 24 + ...), here 1.04e-4 relative.
    signal = np.concatenate([[x0], x])
    k = np.flatnonzero(np.sign(signal[:-1]) != np.sign(signal[1:]))
    crossings = k + signal[k] / (signal[k] - signal[k + 1])
    half_period = np.mean(np.diff(crossings)) * h
    measured = math.pi / half_period
    assert abs(measured / w - 1.0) == pytest.approx(theta / (w * h) - 1.0, rel=0.05)
    assert abs(measured / w - 1.0) < 1.1 * a2 / 24.0


@pytest.fixture(scope="module")
def free_vibration():
    """Undamped cantilever plucked from its static deflection under a tip load."""
    mesh = box_mesh((0.01, 0.01, 0.02), (2, 2, 4))
    model = TissueModel(mesh, TissueParameters(law="linear", integrator="explicit", substeps=1, clamp=("zmin",)))
    force = np.zeros((mesh.n_nodes, 3))
    force[mesh.node_sets["zmax"], 0] = 1e-3
    pluck = static_solution(model, force)
    stiffness = assemble_stiffness(mesh.points, mesh.tets, E, NU).tocsr()
    free = np.repeat(~model.fixed, 3)
    omega2 = sla.eigh(stiffness.toarray()[np.ix_(free, free)], np.diag(np.repeat(model.masses, 3)[free]),
                      eigvals_only=True)
    return model, pluck, stiffness, math.sqrt(omega2.min()), math.sqrt(omega2.max())


def test_force_field_critical_step_is_a_safe_bound(free_vibration):
    model, _, _, _, omega_max = free_vibration
    assert model.critical_time_step <= 2.0 / omega_max


def test_explicit_stable_just_below_critical_step(free_vibration):
    model, pluck, stiffness, omega_min, _ = free_vibration
    h = 0.99 * model.critical_time_step
    substeps = 200
    model.integrator = SymplecticEuler(model.force_field, model.masses, model.fixed, substeps)
    model.reset()
    model.displacement[:] = pluck
    e0 = total_energy(model)
    s0 = shadow_energy(model, h, stiffness)
    periods = 0.0
    energies, shadows = [], []
    while periods < 50.0:
        model.step(model.time, substeps * h)
        energies.append(total_energy(model))
        shadows.append(shadow_energy(model, h, stiffness))
        periods = model.time * omega_min / (2.0 * math.pi)
    assert model.substeps == substeps
    # exactly conserved shadow energy: no growth at all over 50 periods
    np.testing.assert_allclose(shadows, s0, rtol=1e-10)
    # the physical energy oscillates around it by O(omega h) only: within a few %
    assert max(energies) < 1.05 * e0 and min(energies) > 0.95 * e0


def test_explicit_refuses_step_above_critical_with_fix_in_message(free_vibration):
    model = TissueModel(free_vibration[0].mesh,
                        TissueParameters(law="linear", integrator="explicit", substeps=1, clamp=("zmin",)))
    critical = model.critical_time_step
    with pytest.raises(StabilityError) as info:
        model.step(0.0, 1.01 * critical)
    message = str(info.value)
    assert f"{critical:.4g}" in message and f"{1.01 * critical:.4g}" in message
    assert "at least 2 substeps" in message and "implicit" in message
    # the count the message asks for is enough
    model.integrator = SymplecticEuler(model.force_field, model.masses, model.fixed, 11)
    with pytest.raises(StabilityError, match="at least 11 substeps"):
        SymplecticEuler(model.force_field, model.masses, model.fixed, 10).step(
            model.displacement, model.velocity, np.zeros_like(model.velocity), 10.5 * critical)
    model.step(0.0, 10.5 * critical)
    assert isinstance(StabilityError("x"), TissueError) and isinstance(StabilityError("x"), ValueError)


def test_explicit_instability_is_real_just_above_true_critical_step(free_vibration):
    """With the check bypassed, 2 % above the TRUE limit 2/omega_max the energy explodes; 2 %
    below it stays bounded: the threshold the integrator enforces is the physical one."""
    model, pluck, stiffness, _, omega_max = free_vibration
    rng = np.random.default_rng(3)
    noise = 1e-6 * rng.standard_normal(pluck.shape) * ~model.fixed[:, None]  # excites every mode
    for factor in (0.98, 1.02):
        h = factor * 2.0 / omega_max
        model.integrator = SymplecticEuler(model.force_field, model.masses, model.fixed, 100,
                                           critical_time_step=np.inf)
        model.reset()
        model.displacement[:] = pluck + noise
        e0, s0 = total_energy(model), shadow_energy(model, h, stiffness)
        shadows = []
        for _ in range(20 if factor < 1.0 else 1):  # unstable: 100 steps suffice, more overflow
            model.integrator.step(model.displacement, model.velocity, np.zeros_like(pluck), 100 * h)
            shadows.append(shadow_energy(model, h, stiffness))
        if factor < 1.0:
            # the shadow energy is a positive norm for h omega_max < 2 and is conserved
            np.testing.assert_allclose(shadows, s0, rtol=1e-9)
        else:
            assert total_energy(model) > 1e6 * e0


def test_model_never_hands_on_a_diverged_state(free_vibration):
    model, pluck, _, _, omega_max = free_vibration
    model.integrator = SymplecticEuler(model.force_field, model.masses, model.fixed, 50, critical_time_step=np.inf)
    model.reset()
    model.displacement[:] = pluck
    with np.errstate(over="ignore", invalid="ignore"):
        with pytest.raises(TissueError, match="diverged|NaN"):
            for k in range(20):
                model.step(model.time, 50 * 1.5 * 2.0 / omega_max)


def test_auto_substeps_picks_smallest_safe_count_and_logs(caplog):
    mesh = box_mesh((0.01, 0.01, 0.02), (2, 2, 4))
    model = TissueModel(mesh, TissueParameters(law="linear", integrator="explicit", substeps="auto", clamp=("zmin",)))
    critical = model.critical_time_step
    dt = 2e-3
    expected = math.ceil(dt / (0.9 * critical))
    tip_load(model, 1e-3)
    with caplog.at_level(logging.INFO, logger="tissue_fmu.integrators"):
        for k in range(5):
            model.step(k * dt, dt)
    assert model.substeps == expected == model.solver_iterations
    assert dt / expected <= 0.9 * critical < dt / (expected - 1)
    assert f"{expected} substeps" in caplog.text
    # no blow-up: the dynamic response under a suddenly applied load stays below twice the
    # static deflection (undamped: it oscillates between 0 and 2 u_static)
    u_static = static_solution(model, np.where(np.isin(np.arange(mesh.n_nodes), mesh.node_sets["zmax"])[:, None],
                                               [1e-3 / mesh.node_sets["zmax"].size, 0.0, 0.0], 0.0))
    assert np.abs(model.displacement).max() <= 2.0 * np.abs(u_static).max() * 1.01


# --------------------------------------------------------------------------------------
# implicit backward Euler
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("solver", ["cg", "gmres", "bicgstab"])
def test_krylov_solvers_match_dense_solve_on_free_dofs(solver):
    """Each solver against numpy's dense solve of the free block; fixed dofs stay exactly 0."""
    rng = np.random.default_rng(7)
    n = 20
    dofs = 3 * n
    a = rng.standard_normal((dofs, dofs))
    matrix = a @ a.T + dofs * np.eye(dofs)  # symmetric positive definite
    if solver != "cg":
        # add a skew part: not symmetric, but its symmetric part stays positive definite (like the
        # ETMM consistent tangent), so restarted GMRES is guaranteed to converge
        skew = rng.standard_normal((dofs, dofs))
        matrix = matrix + 2.0 * (skew - skew.T)
    fixed_nodes = np.zeros(n, bool)
    fixed_nodes[[0, 7, 13]] = True
    free = np.repeat(~fixed_nodes[:, None], 3, axis=1).astype(float)
    b = rng.standard_normal((n, 3))
    mask = free.reshape(-1) > 0
    expected = np.zeros(dofs)
    expected[mask] = np.linalg.solve(matrix[np.ix_(mask, mask)], b.reshape(-1)[mask])
    inverse_diagonal = free / np.diag(matrix).reshape(n, 3)

    def apply(p, out):
        out[...] = (matrix @ p.reshape(-1)).reshape(n, 3)

    def jacobi(r, out):
        np.multiply(r, inverse_diagonal, out=out)

    x = rng.standard_normal((n, 3))  # a warm start with junk on the fixed dofs too
    solve, work = {
        "cg": (preconditioned_cg, CGWorkspace(n)),
        "gmres": (preconditioned_gmres, GMRESWorkspace(n, restart=5)),  # forces restarts
        "bicgstab": (preconditioned_bicgstab, BiCGStabWorkspace(n)),
    }[solver]
    iterations, residual, converged = solve(apply, b, x, jacobi, free, 1e-12, 500, work)
    assert converged and residual <= 1e-12 and 0 < iterations < 500
    assert not x[fixed_nodes].any()
    np.testing.assert_allclose(x.reshape(-1), expected, rtol=0, atol=1e-10 * np.abs(expected).max())
    true_residual = (b.reshape(-1) - matrix @ x.reshape(-1))[mask]
    assert np.linalg.norm(true_residual) <= 1.01e-12 * np.linalg.norm(b.reshape(-1)[mask])
    # too few iterations: reported, not raised
    x.fill(0.0)
    iterations, residual, converged = solve(apply, b, x, jacobi, free, 1e-12, 2, work)
    assert not converged and iterations == 2 and residual > 1e-12


@pytest.mark.parametrize("preconditioner", ["factorized", "jacobi"])
@pytest.mark.parametrize("omega_h", [0.3, 1.0, 3.0])
def test_backward_euler_energy_factor_per_step_is_exact(preconditioner, omega_h):
    mesh = one_tet_mesh()
    params = TissueParameters(law="linear", clamp=("base",), cg_tolerance=1e-14, preconditioner=preconditioner)
    model = TissueModel(mesh, params)
    omega, modes = free_node_modes(model)
    w, e = omega[1], modes[:, 1]
    h = omega_h / w
    model.displacement[3] = 1e-4 * e
    energy = total_energy(model)
    for n in range(8):
        model.step(n * h, h)
        new_energy = total_energy(model)
        # backward Euler amplification |1 / (1 - i omega h)|^2 per step, exactly
        assert new_energy / energy == pytest.approx(1.0 / (1.0 + omega_h**2), rel=1e-9)
        energy = new_energy
        assert model.solver_converged


@pytest.mark.parametrize(
    "params",
    [
        dict(preconditioner="factorized"),
        dict(preconditioner="jacobi", cg_tolerance=1e-12, cg_max_iterations=20000),
        dict(preconditioner="factorized", viscosity=500.0),
        dict(preconditioner="jacobi", viscosity=500.0, cg_tolerance=1e-12, cg_max_iterations=20000),
    ],
    ids=["factorized", "jacobi", "factorized-viscous", "jacobi-viscous"],
)
def test_implicit_converges_to_static_solution(params):
    mesh = cantilever()
    model = TissueModel(mesh, TissueParameters(law="linear", clamp=("zmin",), **params))
    force = tip_load(model, 0.05)
    expected = static_solution(model, force)
    for k in range(40):
        model.step(k * FRAME, FRAME)
        assert model.solver_converged
    error = np.linalg.norm(model.displacement - expected) / np.linalg.norm(expected)
    assert error < 1e-8
    if params["preconditioner"] == "factorized" and "viscosity" not in params:
        assert model.solver_iterations == 1  # exact preconditioner for the linear law


@pytest.mark.parametrize("law, solver", [("etmm", "gmres"), ("etmm", "bicgstab"), ("hyperelastic", "cg")])
def test_nonlinear_implicit_reaches_static_equilibrium(law, solver):
    """Large load (strains > 10 %): the state converges to f_int(u) + f_ext = 0 on the free dofs.
    (With the symmetric ETMM secant instead of the consistent tangent this limit cycles.)"""
    mesh = cantilever()
    model = TissueModel(mesh, TissueParameters(law=law, clamp=("zmin",)))
    if solver != "cg":
        model.integrator.nonsymmetric_solver = solver
    force = tip_load(model, 10.0)
    linear = static_solution(model, force)
    for k in range(40):
        model.step(k * FRAME, FRAME)
    residual = force.copy()
    model.force_field.add_forces(model.displacement, np.zeros_like(force), residual)
    residual[model.fixed] = 0.0
    assert np.linalg.norm(residual) < 1e-8 * np.linalg.norm(force)
    assert model.max_strain > 0.1
    # the Raghavan-Vorp laws stiffen: less deflection than the linear answer
    assert np.abs(model.displacement).max() < np.abs(linear).max()
    assert model.integrator.last_solver == solver
    if law == "etmm":
        assert model.nonlinear_fraction > 0.0


def test_etmm_secant_tangent_does_not_converge_where_consistent_does():
    """Why the consistent tangent: with the symmetric secant the quasi-static step is the
    fixed-point map u <- K_s(u)^-1 f, which does not settle once the law stiffens fast."""
    mesh = cantilever()
    model = TissueModel(mesh, TissueParameters(law="etmm", clamp=("zmin",)))
    model.integrator.consistent_tangent = False
    force = tip_load(model, 20.0)
    for k in range(40):
        model.step(k * FRAME, FRAME)
    residual = force.copy()
    model.force_field.add_forces(model.displacement, np.zeros_like(force), residual)
    residual[model.fixed] = 0.0
    assert np.linalg.norm(residual) > 0.1 * np.linalg.norm(force)
    assert model.integrator.last_solver == "cg"


def test_etmm_below_threshold_equals_linear_static():
    mesh = cantilever()
    model = TissueModel(mesh, TissueParameters(law="etmm", clamp=("zmin",)))
    force = tip_load(model, 0.05)
    for k in range(40):
        model.step(k * FRAME, FRAME)
    assert model.max_strain < model.params.nonlinear_strain_threshold
    assert model.nonlinear_fraction == 0.0
    expected = static_solution(model, force)
    assert np.linalg.norm(model.displacement - expected) < 1e-8 * np.linalg.norm(expected)


@pytest.fixture(scope="module")
def aaa():
    return aaa_mesh()


def sac_patch(model: TissueModel, half_height=0.008) -> np.ndarray:
    """Outer-wall surface nodes on the +x side of the sac, around its middle."""
    points = model.mesh.points
    outer = np.intersect1d(model.mesh.node_sets["outer"], model.surface_nodes)
    middle = 0.5 * points[:, 2].max()
    p = points[outer]
    near = (np.abs(p[:, 2] - middle) < half_height) & (p[:, 0] > 0.9 * np.hypot(p[:, 0], p[:, 1]))
    return outer[near]


def test_default_aaa_implicit_stable_at_30hz_under_1N(aaa):
    model = TissueModel(aaa, TissueParameters())  # defaults: etmm, implicit, inlet+outlet clamped
    patch = sac_patch(model)
    assert patch.size >= 10
    force = np.zeros((aaa.n_nodes, 3))
    force[patch, 0] = -1.0 / patch.size  # 1 N total pushing the sac wall inward
    model.set_contact_force(force[model.surface_nodes].reshape(-1))  # flat, as the FMU sends it
    for k in range(30):
        model.step(k * FRAME, FRAME)
        assert model.solver_converged and model.solver_residual <= 1e-6
        assert np.isfinite(model.surface_positions()).all()
        # backward Euler only dissipates: stored energy never exceeds the work of the load
        work = float(np.einsum("ij,ij->", force, model.displacement))
        assert total_energy(model) <= work * (1.0 + 1e-9)
    reach = np.abs(model.displacement).max()
    assert 0.5e-3 < reach < 10e-3  # millimetres
    # the largest motion is under the load, inward
    peak = np.argmax(np.linalg.norm(model.displacement, axis=1))
    assert np.linalg.norm(aaa.points[peak] - aaa.points[patch].mean(axis=0)) < 0.01
    assert model.displacement[peak, 0] < 0.0
    assert model.kinetic_energy < 1e-9 * model.strain_energy  # quasi-static after one second
    # 1 N keeps the wall below the ETMM threshold: the answer is the linear static one
    expected = static_solution(model, force)
    assert np.linalg.norm(model.displacement - expected) < 1e-6 * np.linalg.norm(expected)
    assert model.critical_time_step < 2e-5  # why the explicit integrator is no option at 30 Hz


# --------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, value",
    [
        ("young_modulus", -3.0), ("young_modulus", 0.0), ("young_modulus", float("nan")), ("young_modulus", "1e6"),
        ("poisson_ratio", 0.5), ("poisson_ratio", -1.0), ("poisson_ratio", 0.7),
        ("density", 0.0), ("density", -1120.0), ("density", float("inf")),
        ("viscosity", -1.0),
        ("law", "neo-hookean"), ("integrator", "rk4"), ("preconditioner", "ilu"),
        ("substeps", 0), ("substeps", 2.5), ("substeps", "many"), ("substeps", True),
        ("cg_tolerance", 0.0), ("cg_tolerance", -1e-6), ("cg_max_iterations", 0), ("cg_max_iterations", 10.0),
        ("clamp", "inlet"), ("active_region", (0.0, 0.0, 0.0)), ("active_region", (0.0, 0.0, 0.0, -1.0)),
        ("nonlinear_region", (0.0, 0.0, float("nan"), 1.0)), ("nonlinear_strain_threshold", -0.1),
        ("rv_alpha", 0.0), ("rv_beta", -1.0),
    ],
)
def test_bad_parameter_is_named_in_error(name, value):
    params = TissueParameters(**{name: value})
    with pytest.raises(TissueError, match=name):
        params.validate()
    with pytest.raises(ValueError, match=name):
        TissueModel(cantilever((1, 1, 1)), TissueParameters(clamp=("zmin",), **{name: value}) if name != "clamp"
                    else params)


def test_model_level_validation_messages():
    mesh = cantilever((1, 1, 2))
    with pytest.raises(TissueError, match="clamp.*'inlet'.*xmax"):
        TissueModel(mesh, TissueParameters())  # a box has no inlet: the message lists its sets
    with pytest.raises(TissueError, match="active_region"):
        TissueModel(mesh, TissueParameters(clamp=("zmin",), active_region=(1.0, 1.0, 1.0, 0.01)))
    with pytest.raises(TissueError, match=r"materials\[0\] young_modulus"):
        TissueModel(mesh, TissueParameters(clamp=("zmin",)), materials=[(np.ones(mesh.n_tets, bool), -1.0, 0.45)])
    with pytest.raises(TissueError, match=r"materials\[0\] poisson_ratio"):
        TissueModel(mesh, TissueParameters(clamp=("zmin",)), materials=[(np.ones(mesh.n_tets, bool), 1e6, 0.5)])
    with pytest.raises(TissueError, match=r"materials\[0\].*shape"):
        TissueModel(mesh, TissueParameters(clamp=("zmin",)), materials=[(np.ones(3, bool), 1e6, 0.45)])
    with pytest.raises(TissueError, match=r"materials\[0\].*element set 'calcified'"):
        TissueModel(mesh, TissueParameters(clamp=("zmin",)), materials=[("calcified", 1e7, 0.45)])
    with pytest.raises(TissueError, match="mesh must be a TetMesh"):
        TissueModel(mesh.points, TissueParameters(clamp=("zmin",)))

    model = TissueModel(mesh, TissueParameters(clamp=("zmin",)))
    k = model.n_surface
    good = np.zeros((k, 3))
    for bad in (np.full((k, 3), np.nan), np.where(np.arange(3 * k).reshape(k, 3) == 4, np.inf, 0.0)):
        with pytest.raises(TissueError, match="NaN/Inf"):
            model.set_contact_force(bad)
    for bad in (np.zeros((k - 1, 3)), np.zeros((k, 2)), np.zeros(3 * k + 1), np.zeros((3, k))):
        with pytest.raises(TissueError, match=f"expected \\({k}, 3\\)"):
            model.set_contact_force(bad)
    model.set_contact_force(good)
    for dt in (0.0, -FRAME, float("nan"), float("inf")):
        with pytest.raises(TissueError, match="dt"):
            model.step(0.0, dt)
    # nothing reached the state
    assert not model.displacement.any() and model.time == 0.0


def test_nan_in_solution_raises_and_non_convergence_only_warns(caplog):
    mesh = cantilever((1, 1, 2))
    ff = TensorMassForceField(mesh.points, mesh.tets, E, NU)
    masses = ff.lumped_masses(RHO)
    fixed = np.zeros(mesh.n_nodes, bool)
    fixed[mesh.node_sets["zmin"]] = True
    load = np.zeros((mesh.n_nodes, 3))
    load[mesh.node_sets["zmax"], 0] = 0.1

    integrator = BackwardEuler(ff, masses, fixed, tolerance=1e-12, max_iterations=2)
    u, v = np.zeros_like(load), np.zeros_like(load)
    with caplog.at_level(logging.WARNING, logger="tissue_fmu.integrators"):
        stats = integrator.step(u, v, load, FRAME)
    assert not stats.converged and stats.iterations == 2 and stats.relative_residual > 1e-12
    assert "did not reach tolerance" in caplog.text
    assert np.isfinite(u).all() and np.abs(u).max() > 0.0

    class NaNTangent:
        """The real force field, except that its tangent returns NaN."""

        def __init__(self, inner):
            self.inner = inner
            self.n_nodes = inner.n_nodes

        def __getattr__(self, name):
            return getattr(self.inner, name)

        def tangent_matvec(self, du, out):
            out.fill(np.nan)

    broken = BackwardEuler(NaNTangent(ff), masses, fixed)
    u, v = np.zeros_like(load), np.zeros_like(load)
    with pytest.raises(TissueError, match="NaN"):
        broken.step(u, v, load, FRAME)
    assert not u.any() and not v.any()  # the state was not touched


# --------------------------------------------------------------------------------------
# active region, materials, state
# --------------------------------------------------------------------------------------


def test_active_region_freezes_outside_nodes_and_solves_the_active_part():
    mesh = cantilever()
    sphere = (0.01, 0.01, 0.05, 0.02)
    model = TissueModel(mesh, TissueParameters(law="linear", clamp=("zmin",), active_region=sphere))
    active = model.active_elements
    centroids = mesh.points[mesh.tets].mean(axis=1)
    np.testing.assert_array_equal(active, np.linalg.norm(centroids - sphere[:3], axis=1) <= sphere[3])
    assert 0 < active.sum() < mesh.n_tets
    # frozen: every node of an inactive element (outside nodes and the interface)
    frozen = np.zeros(mesh.n_nodes, bool)
    frozen[mesh.tets[~active].ravel()] = True
    np.testing.assert_array_equal(model.fixed, frozen | model.clamped)
    interior = np.setdiff1d(np.arange(mesh.n_nodes), mesh.tets[~active].ravel())
    assert interior.size > 0
    force = tip_load(model, 0.05)
    for k in range(30):
        model.step(k * FRAME, FRAME)
    assert not model.displacement[frozen].any() and not model.velocity[frozen].any()
    assert np.linalg.norm(model.displacement[interior], axis=1).min() > 0.0
    # the active part behaves as if clamped where it meets the frozen part
    expected = static_solution(model, force, active=active)
    assert np.linalg.norm(model.displacement - expected) < 1e-8 * np.linalg.norm(expected)
    frozen_surface = frozen[model.surface_nodes]
    np.testing.assert_array_equal(model.surface_positions()[frozen_surface],
                                  mesh.points[model.surface_nodes][frozen_surface])


def test_per_element_materials():
    mesh = cantilever()
    base = TissueParameters(law="linear", clamp=("zmin",))

    def static_tip(materials=None, mesh_=mesh):
        model = TissueModel(mesh_, base, materials=materials)
        tip_load(model, 0.05)
        for k in range(30):
            model.step(k * FRAME, FRAME)
        return model

    soft = static_tip()
    everywhere = np.ones(mesh.n_tets, bool)
    # ten times stiffer everywhere (a mask override): exactly a tenth of the displacement
    stiff = static_tip([(everywhere, 10.0 * E, NU)])
    np.testing.assert_allclose(stiff.displacement, 0.1 * soft.displacement, rtol=1e-8, atol=1e-14)
    # a stiffer (calcified) patch at the loaded end, given as an element set name
    top = np.flatnonzero(mesh.points[mesh.tets].mean(axis=1)[:, 2] > 0.04)
    patched_mesh = TetMesh(mesh.points, mesh.tets, mesh.node_sets, {"calcified": top})
    patched = static_tip([("calcified", 10.0 * E, NU)], patched_mesh)
    assert (patched.young_modulus[top] == 10.0 * E).all() and (np.delete(patched.young_modulus, top) == E).all()
    loaded = mesh.node_sets["zmax"]
    assert np.abs(patched.displacement[loaded]).max() < np.abs(soft.displacement[loaded]).max()
    # the patch itself strains less: its nodes stay closer to a rigid motion
    grad_soft = soft.force_field.element_max_strain(soft.displacement)[top].max()
    grad_patched = patched.force_field.element_max_strain(patched.displacement)[top].max()
    assert grad_patched < 0.2 * grad_soft


def test_state_save_restore_and_reset_reproduce_the_run():
    mesh = cantilever((1, 1, 3))
    model = TissueModel(mesh, TissueParameters(clamp=("zmin",)))
    tip_load(model, 0.5)
    for k in range(3):
        model.step(k * FRAME, FRAME)
    saved = model.get_state()
    for k in range(3, 6):
        model.step(k * FRAME, FRAME)
    first = (model.surface_positions().copy(), model.surface_velocities().copy(), model.time)
    model.set_state(saved)
    for k in range(3, 6):
        model.step(k * FRAME, FRAME)
    np.testing.assert_array_equal(model.surface_positions(), first[0])
    np.testing.assert_array_equal(model.surface_velocities(), first[1])
    assert model.time == first[2] == pytest.approx(6 * FRAME)
    model.reset()
    assert not model.displacement.any() and model.strain_energy == 0.0 and model.kinetic_energy == 0.0


def test_surface_outputs_follow_the_mesh_surface():
    mesh = cantilever((1, 1, 2))
    model = TissueModel(mesh, TissueParameters(clamp=("zmin",)))
    nodes, triangles = mesh.surface()
    np.testing.assert_array_equal(model.surface_nodes, nodes)
    np.testing.assert_array_equal(model.surface_triangles, triangles)
    assert model.n_surface == nodes.size
    tip_load(model, 0.1)
    model.step(0.0, FRAME)
    np.testing.assert_array_equal(model.surface_positions(), mesh.points[nodes] + model.displacement[nodes])
    np.testing.assert_array_equal(model.surface_velocities(), model.velocity[nodes])
    assert model.kinetic_energy == pytest.approx(0.5 * np.sum(model.masses[:, None] * model.velocity**2), rel=1e-12)


def test_package_docstring_example_runs():
    import doctest

    import tissue_fmu

    result = doctest.testmod(tissue_fmu)
    assert result.attempted >= 5 and result.failed == 0

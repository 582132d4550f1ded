"""Unit tests of the tensor-mass force field: invariances, the spectrum of K, and the numba kernels
against slow plain-numpy per-element references written here (B-matrix FEM for the linear law,
eigvalsh-based ETMM, finite-difference-of-energy hyperelasticity), plus tangent checks."""

import numpy as np
import pytest

from tissue_fmu.forcefield import ForceFieldError, TensorMassForceField, assemble_stiffness
from tissue_fmu.materials import MaterialError, lame_parameters
from tissue_fmu.mesh import box_mesh

ALPHA, BETA = 0.174e6, 1.881e6
E_RV = 6 * ALPHA
LAWS = ("linear", "etmm", "hyperelastic")


def _mesh(div=(2, 2, 2), size=(1.0, 1.0, 1.0), jitter=0.0, seed=0):
    m = box_mesh(size=size, divisions=div)
    pts = m.points.copy()
    if jitter:
        # Perturb interior nodes so elements are not all congruent (orientation stays positive).
        boundary = np.unique(np.concatenate(list(m.node_sets.values())))
        interior = np.setdiff1d(np.arange(m.n_nodes), boundary)
        h = min(s / d for s, d in zip(size, div))
        pts[interior] += jitter * h * np.random.default_rng(seed).uniform(-1, 1, (interior.size, 3))
    return pts, m.tets, m


def _force(ff, u, v=None):
    out = np.zeros_like(u)
    ff.add_forces(u, v, out)
    return out


def _dense(matvec, n):
    """Dense 3n x 3n matrix of a node-major matvec (column by column)."""
    cols = []
    e = np.zeros((n, 3))
    out = np.zeros((n, 3))
    for k in range(3 * n):
        e.reshape(-1)[:] = 0.0
        e.reshape(-1)[k] = 1.0
        matvec(e, out)
        cols.append(out.reshape(-1).copy())
    return np.array(cols).T


# ---------------------------------------------------------------- slow numpy references
def _reference_linear_K(points, tets, young, nu):
    """Standard FEM: K_e = V B^T D B (Voigt, engineering shear), independent of the tensor form."""
    n = points.shape[0]
    k = np.zeros((3 * n, 3 * n))
    young = np.broadcast_to(young, (tets.shape[0],))
    for e, t in enumerate(tets):
        x = points[t]
        jac = np.array([x[1] - x[0], x[2] - x[0], x[3] - x[0]]).T
        vol = np.linalg.det(jac) / 6.0
        inv = np.linalg.inv(jac)
        grads = np.vstack([-inv.sum(axis=0), inv])  # rows: grad N_j
        b = np.zeros((6, 12))
        for j in range(4):
            gx, gy, gz = grads[j]
            b[:, 3 * j:3 * j + 3] = [[gx, 0, 0], [0, gy, 0], [0, 0, gz], [0, gz, gy], [gz, 0, gx], [gy, gx, 0]]
        lam, mu = lame_parameters(young[e], nu)
        d = np.zeros((6, 6))
        d[:3, :3] = lam
        d[:3, :3] += 2 * mu * np.eye(3)
        d[3:, 3:] = mu * np.eye(3)
        ke = vol * b.T @ d @ b
        dofs = (3 * t[:, None] + np.arange(3)).reshape(-1)
        k[np.ix_(dofs, dofs)] += ke
    return k


def _grads(points, t):
    x = points[t]
    jac = np.array([x[1] - x[0], x[2] - x[0], x[3] - x[0]]).T
    inv = np.linalg.inv(jac)
    return np.vstack([-inv.sum(axis=0), inv]), np.linalg.det(jac) / 6.0


def _rv_ratio(green, ba):
    l = np.sqrt(1 + 2 * max(green, -0.45))
    return (l * l + l + 1) / (3 * l * l) * (1 + 2 * ba * (l * l + 2 / l - 3))


def _reference_etmm_force(points, tets, young, nu, u, threshold, ba):
    """Per element: phi blended from the tension and compression branches, f = -(1+phi) K_e u_e."""
    k = _reference_linear_K(points, tets, young, nu)
    f = -(k @ u.reshape(-1))
    lam, mu = lame_parameters(young, nu)
    for t in tets:
        g, vol = _grads(points, t)
        h = u[t].T @ g
        green = 0.5 * (h + h.T + h.T @ h)
        # axisymmetric-equivalent extremes from the invariants (q, p, det of the deviator)
        q = np.trace(green) / 3
        dev = green - q * np.eye(3)
        p = np.sqrt(np.sum(dev * dev) / 6)
        r = np.clip(np.linalg.det(dev / p) / 2, -1, 1) if p > 0 else 0.0
        w = (q - p * (1.5 - 0.5 * r), None, q + p * (1.5 + 0.5 * r))

        def branch(s):
            mag = abs(s)
            if threshold > 0 and mag <= threshold:
                return 0.0
            ramp = 1.0 if threshold == 0 or mag >= 2 * threshold else (mag - threshold) / threshold
            return ramp * (_rv_ratio(s, ba) - 1)

        s_t, s_c = max(w[2], 0.0), max(-w[0], 0.0)
        if s_t + s_c == 0.0:
            continue
        w_c = np.clip((s_c / (s_t + s_c) - 0.4) / 0.2, 0.0, 1.0)
        phi = (1 - w_c) * (branch(w[2]) if w[2] > 0 else 0.0) + w_c * (branch(w[0]) if w[0] < 0 else 0.0)
        if phi == 0.0:
            continue
        stress = lam * np.trace(h) * np.eye(3) + mu * (h + h.T)
        for j in range(4):
            f[3 * t[j]:3 * t[j] + 3] -= phi * vol * stress @ g[j]
    return f.reshape(-1, 3)


def _reference_hyper_force(points, tets, young, nu, u, ba):
    """f_j = -V P g_j with P = dW/dF by central differences of the energy (independent of the kernel's P)."""
    lam, mu = lame_parameters(young, nu)
    a, b, kappa = mu / 2, mu / 2 * ba, lam + 2 * mu / 3

    def energy(f):
        j = np.linalg.det(f)
        i1bar = j ** (-2 / 3) * np.sum(f * f)
        return a * (i1bar - 3) + b * (i1bar - 3) ** 2 + 0.5 * kappa * (j - 1) ** 2

    out = np.zeros_like(u)
    for t in tets:
        g, vol = _grads(points, t)
        f = np.eye(3) + u[t].T @ g
        p = np.zeros((3, 3))
        for r in range(3):
            for c in range(3):
                d = np.zeros((3, 3))
                d[r, c] = 1e-6
                p[r, c] = (energy(f + d) - energy(f - d)) / 2e-6
        for j in range(4):
            out[t[j]] -= vol * p @ g[j]
    return out


def _rigid_modes(points):
    n = points.shape[0]
    modes = []
    for a in range(3):
        m = np.zeros((n, 3))
        m[:, a] = 1.0
        modes.append(m.reshape(-1))
    for a in range(3):
        w = np.zeros(3)
        w[a] = 1.0
        modes.append(np.cross(w, points).reshape(-1))
    return np.array(modes).T


# ---------------------------------------------------------------- invariances and spectrum
@pytest.mark.parametrize("law", LAWS)
def test_rigid_translation_gives_zero_force(law):
    pts, tets, _ = _mesh(jitter=0.2)
    ff = TensorMassForceField(pts, tets, E_RV, 0.45, law=law, nonlinear_strain_threshold=0.0)
    u = np.tile([0.3, -0.2, 0.5], (pts.shape[0], 1))
    assert np.abs(_force(ff, u)).max() < 1e-9 * E_RV  # forces scale as E * length^2 = E here


def test_infinitesimal_rotation_gives_zero_linear_force():
    pts, tets, _ = _mesh(jitter=0.2)
    ff = TensorMassForceField(pts, tets, E_RV, 0.45)
    u = np.cross([1e-3, -2e-3, 0.5e-3], pts)
    scale = np.abs(_force(ff, np.random.default_rng(1).normal(0, 1e-3, pts.shape))).max()
    assert np.abs(_force(ff, u)).max() < 1e-12 * scale / 1e-3


def test_finite_rotation_gives_zero_hyperelastic_force():
    pts, tets, _ = _mesh(jitter=0.2)
    ff = TensorMassForceField(pts, tets, E_RV, 0.45, law="hyperelastic")
    c, s = np.cos(0.7), np.sin(0.7)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    u = pts @ rot.T - pts + 0.1
    assert np.abs(_force(ff, u)).max() < 1e-8 * E_RV
    assert abs(ff.strain_energy(u)) < 1e-8 * E_RV


def test_stiffness_symmetric_with_six_rigid_zero_modes():
    pts, tets, _ = _mesh(jitter=0.2)
    k = assemble_stiffness(pts, tets, E_RV, 0.45).toarray()
    assert np.abs(k - k.T).max() <= 1e-12 * np.abs(k).max()
    w, v = np.linalg.eigh(k)
    assert np.all(np.abs(w[:6]) < 1e-10 * w[-1])
    assert w[6] > 1e-4 * w[-1]
    rigid, _ = np.linalg.qr(_rigid_modes(pts))
    # The null space (first six eigenvectors) and the rigid modes span the same space.
    cosines = np.linalg.svd(v[:, :6].T @ rigid, compute_uv=False)
    np.testing.assert_allclose(cosines, 1.0, atol=1e-10)


def test_kernel_force_equals_minus_K_u_and_the_numpy_fem_reference():
    pts, tets, _ = _mesh(div=(2, 3, 2), size=(1.0, 1.5, 0.8), jitter=0.25)
    young = np.random.default_rng(3).uniform(0.5e6, 2e6, tets.shape[0])  # per-element moduli
    ff = TensorMassForceField(pts, tets, young, 0.3)
    u = np.random.default_rng(4).normal(0, 1e-2, pts.shape)
    f = _force(ff, u)
    k = assemble_stiffness(pts, tets, young, 0.3)
    scale = np.abs(f).max()
    assert np.abs(f.reshape(-1) + k @ u.reshape(-1)).max() < 1e-13 * scale
    k_ref = _reference_linear_K(pts, tets, young, 0.3)
    assert np.abs(k.toarray() - k_ref).max() < 1e-12 * np.abs(k_ref).max()
    assert np.abs(f.reshape(-1) + k_ref @ u.reshape(-1)).max() < 1e-12 * scale


def test_stiffer_patch_adds_up():
    pts, tets, _ = _mesh(div=(3, 2, 2))
    patch = np.zeros(tets.shape[0], dtype=bool)
    patch[::3] = True
    young = np.where(patch, 5e6, 1e6)
    k = assemble_stiffness(pts, tets, young, 0.45)
    k_sum = assemble_stiffness(pts, tets[patch], 5e6, 0.45) + assemble_stiffness(pts, tets[~patch], 1e6, 0.45)
    assert abs(k - k_sum).max() < 1e-12 * abs(k).max()


def test_lambda_and_mu_parts():
    """K = K_lambda + K_mu; the lambda part (A = V g_j (x) g_k) sees only tr(grad u), so it vanishes
    on every node for an isochoric affine field, and both parts vanish for an infinitesimal rotation."""
    from tissue_fmu.precompute import tensor_mass_parts, tensors_to_csr

    pts, tets, _ = _mesh(jitter=0.2)
    lam, mu = lame_parameters(E_RV, 0.45)
    full, k_lam, k_mu = (tensors_to_csr(t) for t in tensor_mass_parts(pts, tets, lam, mu))
    assert abs(full - k_lam - k_mu).max() < 1e-12 * abs(full).max()
    assert abs(full - assemble_stiffness(pts, tets, E_RV, 0.45)).max() < 1e-12 * abs(full).max()
    g = np.random.default_rng(17).normal(size=(3, 3))
    g -= np.trace(g) / 3 * np.eye(3)
    u = (pts @ g.T).reshape(-1)
    assert np.abs(k_lam @ u).max() < 1e-12 * np.abs(k_mu @ u).max()
    rot = np.cross([0.3, -0.2, 0.1], pts).reshape(-1)
    assert np.abs(k_lam @ rot).max() < 1e-9 and np.abs(k_mu @ rot).max() < 1e-9 * mu


def test_inactive_elements_contribute_nothing():
    pts, tets, _ = _mesh(div=(3, 2, 2))
    active = np.zeros(tets.shape[0], dtype=bool)
    active[: tets.shape[0] // 2] = True
    u = np.random.default_rng(5).normal(0, 1e-2, pts.shape)
    for law in LAWS:
        f_mask = _force(TensorMassForceField(pts, tets, E_RV, 0.45, law=law, active_elements=active), u)
        f_sub = _force(TensorMassForceField(pts, tets[active], E_RV, 0.45, law=law), u)
        np.testing.assert_allclose(f_mask, f_sub, rtol=0, atol=1e-12 * np.abs(f_sub).max())


# ---------------------------------------------------------------- non-linear laws vs references
def _strained_etmm(seed: int, subset: bool, fraction: float):
    """A jittered mesh, an ETMM force field (threshold 0.05; a random ``fraction`` of the tets
    candidates when ``subset``, else all) and a displacement with some tets over the threshold."""
    pts, tets, _ = _mesh(div=(3, 3, 2), jitter=0.2)
    rng = np.random.default_rng(seed)
    u = 0.006 * rng.normal(size=pts.shape) + 0.03 * pts * np.array([1.0, -0.3, 0.2])
    nonlinear = rng.random(tets.shape[0]) < fraction if subset else None
    ff = TensorMassForceField(pts, tets, E_RV, 0.45, law="etmm", nonlinear_strain_threshold=0.05,
                              nonlinear_elements=nonlinear)
    return pts, tets, u, nonlinear, ff


@pytest.mark.parametrize("subset", [False, True])
def test_etmm_kernel_equals_numpy_reference(subset):
    """Both code paths: all tets candidates (edge pre-screen fused in the linear pass) and a
    candidate subset (direct check).  The screen must never miss an element over the threshold."""
    pts, tets, u, nonlinear, ff = _strained_etmm(6, subset, 0.2)
    f = _force(ff, u)
    sel = tets if nonlinear is None else tets[nonlinear]
    f_ref = _reference_etmm_force(pts, sel, E_RV, 0.45, u, 0.05, BETA / ALPHA)
    if nonlinear is not None:  # linear part over all tets, correction only on the subset
        k = _reference_linear_K(pts, tets, E_RV, 0.45) - _reference_linear_K(pts, sel, E_RV, 0.45)
        f_ref -= (k @ u.reshape(-1)).reshape(-1, 3)
    assert 0.2 < ff.nonlinear_fraction * (1 if nonlinear is None else 1 / nonlinear.mean()) < 1.0
    np.testing.assert_allclose(f, f_ref, rtol=0, atol=1e-10 * np.abs(f_ref).max())


def test_hyperelastic_kernel_equals_energy_derivative_reference():
    pts, tets, _ = _mesh(div=(2, 2, 2), jitter=0.2)
    u = 0.08 * np.random.default_rng(7).normal(size=pts.shape)
    ff = TensorMassForceField(pts, tets, E_RV, 0.45, law="hyperelastic")
    f_ref = _reference_hyper_force(pts, tets, E_RV, 0.45, u, BETA / ALPHA)
    # central differences of W with step 1e-6: truncation ~1e-12 relative, round-off ~1e-10 * W/1e-6
    np.testing.assert_allclose(_force(ff, u), f_ref, rtol=0, atol=1e-6 * np.abs(f_ref).max())


def test_hyperelastic_energy_is_the_force_potential():
    pts, tets, _ = _mesh(div=(2, 2, 2), jitter=0.2)
    rng = np.random.default_rng(8)
    u = 0.08 * rng.normal(size=pts.shape)
    du = rng.normal(size=pts.shape)
    ff = TensorMassForceField(pts, tets, E_RV, 0.45, law="hyperelastic")
    h = 1e-6
    d_energy = (ff.strain_energy(u + h * du) - ff.strain_energy(u - h * du)) / (2 * h)
    assert d_energy == pytest.approx(-np.sum(_force(ff, u) * du), rel=1e-7)


# ---------------------------------------------------------------- tangents (SOFA-style FD checks)
def _fd_derivative(ff, u, du, eps):
    return (_force(ff, u + eps * du) - _force(ff, u - eps * du)) / (2 * eps)


@pytest.mark.parametrize("law", LAWS)
def test_tangent_matches_finite_differences(law):
    """(f(u + e du) - f(u - e du)) / 2e vs -K_t du, e = 1e-6 relative to the state.

    Tolerance 1e-6 relative: central differences have O(e^2) truncation (~1e-12) and round-off
    ~1e-16 |f| / (e |du|) ~ 1e-9; 1e-6 leaves margin but catches any missing term (which would be
    O(1) relative).  linear: K; hyperelastic: the analytic tangent; etmm: the consistent tangent
    (including the change of dlam, dmu).  The etmm secant tangent used by CG is checked separately."""
    pts, tets, _ = _mesh(div=(2, 2, 2), jitter=0.2)
    rng = np.random.default_rng(9)
    u = 0.01 * rng.normal(size=pts.shape) + 0.04 * pts * np.array([1.0, -0.3, 0.2])
    du = rng.normal(size=pts.shape)
    ff = TensorMassForceField(pts, tets, E_RV, 0.45, law=law, nonlinear_strain_threshold=0.05)
    fd = _fd_derivative(ff, u, du, 1e-6)
    _force(ff, u)  # set the tangent state
    kt = np.zeros_like(u)
    ff.consistent_tangent_matvec(du, kt)
    np.testing.assert_allclose(-fd, kt, rtol=0, atol=1e-6 * np.abs(kt).max())
    if law == "etmm":
        assert 0.1 < ff.nonlinear_fraction < 1.0  # the correction (and its ramp) is really active


@pytest.mark.parametrize("subset", [False, True])
def test_etmm_strain_energy_is_half_u_secant_stiffness_u(subset):
    """The secant energy 1/2 sum_T (1 + phi_T) u_T.K_T u_T, taken in one pass over the elements, is
    1/2 u.K_sec(u) u with K_sec the secant tangent that add_forces leaves at u (assembled by columns),
    with all tets candidates and with a subset; and 1/2 u.K u from the numpy FEM reference when no
    element is over the threshold."""
    pts, tets, u, _, ff = _strained_etmm(16, subset, 0.3)
    _force(ff, u)
    assert ff.nonlinear_fraction > 0.05  # the correction takes part
    secant = _dense(ff.tangent_matvec, pts.shape[0])
    assert ff.strain_energy(u) == pytest.approx(0.5 * u.reshape(-1) @ secant @ u.reshape(-1), rel=1e-12)
    small = 1e-4 * u  # strains about 3e-6: no element over the threshold
    k = _reference_linear_K(pts, tets, E_RV, 0.45)
    assert ff.strain_energy(small) == pytest.approx(0.5 * small.reshape(-1) @ k @ small.reshape(-1), rel=1e-12)


def test_etmm_secant_tangent_is_symmetric_and_reproduces_the_force():
    """The CG tangent of etmm is K + sum_T phi_T K_T at the current state: symmetric, PSD, and
    f(u) = -K_sec(u) u exactly (secant property).  It omits d(phi)/du, so it is NOT the FD slope."""
    pts, tets, _ = _mesh(div=(2, 2, 2), jitter=0.2)
    rng = np.random.default_rng(10)
    u = 0.06 * rng.normal(size=pts.shape) + 0.15 * pts * np.array([1.0, -0.3, 0.2])
    ff = TensorMassForceField(pts, tets, E_RV, 0.45, law="etmm")
    f = _force(ff, u)
    ks = _dense(ff.tangent_matvec, pts.shape[0])
    assert np.abs(ks - ks.T).max() < 1e-12 * np.abs(ks).max()
    assert np.linalg.eigvalsh(ks)[0] > -1e-9 * np.abs(ks).max()
    np.testing.assert_allclose(f.reshape(-1), -ks @ u.reshape(-1), rtol=0, atol=1e-12 * np.abs(f).max())
    diag = ff.stiffness_diagonal()
    np.testing.assert_allclose(diag.reshape(-1), np.diag(ks), rtol=1e-13)


def test_damping_is_kelvin_voigt_scaled_stiffness():
    pts, tets, _ = _mesh(div=(2, 2, 2), jitter=0.2)
    n = pts.shape[0]
    young = np.random.default_rng(11).uniform(0.5e6, 2e6, tets.shape[0])
    eta = np.random.default_rng(12).uniform(10, 100, tets.shape[0])  # non-uniform eta / E: own tensors
    ff = TensorMassForceField(pts, tets, young, 0.4, viscosity=eta)
    c_ref = assemble_stiffness(pts, tets, eta, 0.4).toarray()  # (eta/E) K_e(E) = K_e(eta)
    c = _dense(ff.damping_matvec, n)
    assert np.abs(c - c_ref).max() < 1e-12 * np.abs(c_ref).max()
    v = np.random.default_rng(13).normal(size=pts.shape)
    u = np.random.default_rng(14).normal(size=pts.shape) * 1e-3
    k = assemble_stiffness(pts, tets, young, 0.4)
    expected = -(k @ u.reshape(-1) + c_ref @ v.reshape(-1))
    np.testing.assert_allclose(_force(ff, u, v).reshape(-1), expected, atol=1e-12 * np.abs(expected).max())
    # uniform eta / E: the fused K (u + tau v) path
    ff_u = TensorMassForceField(pts, tets, 1e6, 0.4, viscosity=50.0)
    k1 = assemble_stiffness(pts, tets, 1e6, 0.4)
    expected = -(k1 @ (u + 50.0 / 1e6 * v).reshape(-1))
    np.testing.assert_allclose(_force(ff_u, u, v).reshape(-1), expected, atol=1e-12 * np.abs(expected).max())


# ---------------------------------------------------------------- diagnostics
def test_energy_strain_masses():
    pts, tets, m = _mesh(div=(2, 2, 2), size=(2.0, 1.0, 1.0))
    ff = TensorMassForceField(pts, tets, 1e6, 0.3)
    u = np.random.default_rng(15).normal(size=pts.shape) * 1e-3
    k = assemble_stiffness(pts, tets, 1e6, 0.3)
    assert ff.strain_energy(u) == pytest.approx(0.5 * u.reshape(-1) @ (k @ u.reshape(-1)), rel=1e-12)
    stretch = pts * np.array([0.1, 0.0, 0.0])  # x -> 1.1 x: Green strain (1.1^2 - 1)/2 = 0.105
    assert ff.max_strain(stretch) == pytest.approx(0.105, rel=1e-12)
    masses = ff.lumped_masses(1120.0)
    assert masses.sum() == pytest.approx(1120.0 * 2.0, rel=1e-12)
    assert np.all(masses > 0)


def test_validation_messages():
    pts, tets, _ = _mesh()
    with pytest.raises(MaterialError, match="young_modulus must be finite and > 0"):
        TensorMassForceField(pts, tets, -3.0, 0.45)
    with pytest.raises(MaterialError, match=r"poisson_ratio must be in \(-1, 0.5\)"):
        TensorMassForceField(pts, tets, 1e6, 0.5)
    with pytest.raises(MaterialError, match="viscosity must be finite and >= 0"):
        TensorMassForceField(pts, tets, 1e6, 0.45, viscosity=-1.0)
    with pytest.raises(MaterialError, match="shape"):
        TensorMassForceField(pts, tets, np.ones(3), 0.45)
    with pytest.raises(ForceFieldError, match="law must be one of"):
        TensorMassForceField(pts, tets, 1e6, 0.45, law="neo-hookean")
    with pytest.raises(MaterialError, match="rv_alpha must be a finite number > 0"):
        TensorMassForceField(pts, tets, 1e6, 0.45, law="etmm", rv_alpha=0.0)
    with pytest.raises(MaterialError, match="nonlinear_strain_threshold"):
        TensorMassForceField(pts, tets, 1e6, 0.45, nonlinear_strain_threshold=-0.1)
    with pytest.raises(ForceFieldError, match="active_elements selects no element"):
        TensorMassForceField(pts, tets, 1e6, 0.45, active_elements=np.zeros(tets.shape[0], bool))
    ff = TensorMassForceField(pts, tets, 1e6, 0.45)
    with pytest.raises(ForceFieldError, match=r"u must be a float64 numpy array of shape"):
        ff.add_forces(np.zeros((3, 3)), None, np.zeros_like(pts))
    with pytest.raises(ValueError):  # mesh problems are reported by the mesh validator
        TensorMassForceField(pts, tets[:, [0, 2, 1, 3]], 1e6, 0.45)


def test_axisymmetric_equivalent_strains_exact_when_two_principal_values_coincide():
    from tissue_fmu.kernels import _axisymmetric_extremes

    rng = np.random.default_rng(16)
    for _ in range(200):
        q, _r = np.linalg.qr(rng.normal(size=(3, 3)))
        a, b = rng.normal(size=2) * 0.1
        for diag in ((a, b, b), (a, a, b), tuple(rng.normal(size=3) * 0.1)):
            m = q @ np.diag(diag) @ q.T
            lo, hi = _axisymmetric_extremes(m[0, 0], m[1, 1], m[2, 2], m[0, 1], m[0, 2], m[1, 2])
            w = np.sort(diag)
            if len(set(np.round(diag, 15))) < 3:  # two coincide: exact
                assert lo == pytest.approx(w[0], abs=1e-14) and hi == pytest.approx(w[2], abs=1e-14)
            else:  # between the middle and the extreme principal values
                assert w[0] - 1e-14 <= lo <= w[1] + 1e-14 and w[1] - 1e-14 <= hi <= w[2] + 1e-14


def test_etmm_does_not_stiffen_a_rigidly_rotated_mesh():
    pts, tets, _ = _mesh(jitter=0.2)
    ff = TensorMassForceField(pts, tets, E_RV, 0.45, law="etmm")
    c, s = np.cos(0.5), np.sin(0.5)
    u = pts @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T - pts
    f = _force(ff, u)
    assert ff.nonlinear_fraction == 0.0  # Green strain is zero: no correction
    assert ff.max_strain(u) < 1e-14
    linear = TensorMassForceField(pts, tets, E_RV, 0.45)
    np.testing.assert_array_equal(f, _force(linear, u))  # (the linear law itself is not rotation invariant)

"""Material parameters of the tensor-mass force field: Lame coefficients, viscosity, and the
Raghavan-Vorp stiffening used by the Extended Tensor-Mass Model (ETMM).

Everything here is plain numpy and validates its input; the numba kernels receive only
checked, per-element float64 arrays.

Kelvin-Voigt viscosity
----------------------
``viscosity`` is the extensional (Kelvin-Voigt) viscosity eta in Pa s.  The viscous stress has
the elastic form with the same Poisson ratio, ``sigma_v = (eta / E) C : d(eps)/dt``, i.e. the
viscous Lame coefficients are ``(eta / E) (lam, mu)``.  A bar under a constant traction sigma then
creeps as ``eps(t) = sigma / E (1 - exp(-E t / eta))`` (uniaxial stress, lateral strain -nu eps).

ETMM stiffening (derivation)
----------------------------
Raghavan-Vorp: ``W = alpha (I1 - 3) + beta (I1 - 3)^2``.  Incompressible uniaxial stretch l gives
the nominal (first Piola, force per reference area) stress

    P_RV(l) = 2 (l - 1/l^2) (alpha + 2 beta (l^2 + 2/l - 3))       (Cauchy sigma = l P)

and the small-strain Young modulus E = 6 alpha (mu0 = 2 alpha).

The tensor-mass force is linear in the displacement with the reference gradients, so an element
whose moduli are scaled by a factor r (``lam(T) = r lam0``, ``mu(T) = r mu0``, same Poisson ratio)
carries, in uniaxial stress with axial stretch l, the nominal stress ``P = r E (l - 1)``.  Setting
this equal to ``P_RV`` with ``E = 6 alpha`` and using ``(l - 1/l^2)/(l - 1) = (l^2 + l + 1)/l^2``:

    r(l) = g(l) h(l),   g(l) = (l^2 + l + 1) / (3 l^2),   h(l) = 1 + 2 (beta/alpha) (I1*(l) - 3),
    I1*(l) = l^2 + 2/l  (first invariant of the isochoric uniaxial stretch l).

Equivalently ``mu(T) = g(l) (2 alpha + 4 beta (I1* - 3))``: the secant shear modulus 2 W_1 of the
Raghavan-Vorp law times the geometric factor g that converts the finite-strain Cauchy response to
the tensor-mass small-strain, nominal-stress form.  ``dmu = (r - 1) mu0`` and ``dlam = (r - 1) lam0``
(the Poisson ratio is kept).  With this choice the ETMM uniaxial response equals the closed form
*exactly* (for any Poisson ratio) once the correction is fully on.

Which stretch l for a general 3D state?  Not the raw I1 = tr(F^T F) of the element: with the
linear lateral contraction -nu eps of the tensor-mass element the element is not isochoric at
finite strain; at l = 1.2 and nu = 0.5 its I1 - 3 is 0.060 instead of 0.107, which would
under-predict the stiffening by ~45 %.  Instead l is taken from the element's Green strain
E = (F^T F - I)/2 (rotation invariant, so a rigidly rotated element does not stiffen), through
its invariants q = tr(E)/3, p = sqrt(dev E : dev E / 6) and the Lode parameter
xi = det(dev E / p)/2 in [-1, 1]:

    E_max* = q + p (1.5 + 0.5 xi),   E_min* = q - p (1.5 - 0.5 xi)    (axisymmetric-equivalent)

These equal the largest / smallest principal Green strains whenever two principal strains
coincide (xi = +-1: uniaxial tension or compression, equibiaxial), which includes the uniaxial
stress state of the calibration; otherwise they lie between the middle and the extreme principal
strain (at most 0.23 p inside, pure shear).  They need no eigen-solve (several times cheaper than
the acos/cos closed form) and are smooth, which keeps the consistent tangent exact.
The tension branch uses l_t = sqrt(1 + 2 E_max*) (if E_max* > 0), the compression branch
l_c = sqrt(1 + 2 E_min*) (if E_min* < 0); ``phi_b = r(l_b) - 1``.  They are blended by
x = s_c / (s_t + s_c) (s_t = max(E_max*, 0), s_c = max(-E_min*, 0)): pure tension branch for
x <= 0.4, pure compression for x >= 0.6, linear in between.  Uniaxial tension has
x = nu/(1+nu) < 0.34 and uniaxial compression x >= 0.62 (nu <= 0.49, up to 30 % compression), so
both are reproduced exactly and phi stays continuous.

Threshold: the correction is paid only where the element's strain measure
``s = max(s_t, s_c)`` exceeds the threshold t (s <= largest principal Green strain magnitude), and
each branch is ramped in linearly over [t, 2 t] so the force stays continuous (no jump in
stiffness when an element crosses the threshold): ``phi_b = w(s_b) (r(l_b) - 1)``,
``w = clip((s_b - t) / t, 0, 1)`` (w = 1 if t = 0).  The element force is then ``(1 + phi)``
times its linear force, i.e. ``f_T = -(K_T + dlam A_T + dmu B_T) u_T`` with ``dlam = phi lam0``,
``dmu = phi mu0``.  Since ``r > 0`` always (g > 0, h >= 1), ``1 + phi >= min(1, r) > 0``: the
secant stiffness stays positive semi-definite, which the conjugate-gradient implicit solver needs.

Per-element moduli (e.g. a stiffer calcified patch) keep their own small-strain stiffness: the
Raghavan-Vorp law enters only through the ratio beta/alpha.  To reproduce the law exactly use
``young_modulus = 6 rv_alpha`` (1.044e6 Pa for the AAA defaults).
"""

from __future__ import annotations

import numpy as np

from .errors import MaterialError

__all__ = [
    "MaterialError",
    "LAWS",
    "lame_parameters",
    "viscous_lame_parameters",
    "bulk_modulus",
    "element_array",
    "rv_stiffening_ratio",
]

LAWS = ("linear", "etmm", "hyperelastic")

# Green strains below -0.5 mean a collapsed element (stretch 0); the equivalent stretch is taken
# from max(E, GREEN_STRAIN_FLOOR) so sqrt(1 + 2 E) stays real for badly compressed elements.
GREEN_STRAIN_FLOOR = -0.45


def element_array(name: str, value, n_elements: int, example: str) -> np.ndarray:
    """Scalar or (m,) input -> finite float64 (m,) array, or MaterialError."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise MaterialError(f"{name} must be a number or an array of numbers (got {value!r}): e.g. {example}") from None
    if arr.ndim == 0:
        arr = np.full(n_elements, float(arr))
    elif arr.shape != (n_elements,):
        raise MaterialError(
            f"{name} must be a scalar or have shape ({n_elements},), one value per element "
            f"(got shape {arr.shape}): e.g. {example}"
        )
    if not np.isfinite(arr).all():
        bad = np.flatnonzero(~np.isfinite(arr))
        raise MaterialError(f"{name} must be finite (NaN/Inf at element(s) {bad[:10].tolist()}): e.g. {example}")
    return np.ascontiguousarray(arr)


def _check_elastic(young_modulus, poisson_ratio) -> tuple[np.ndarray, np.ndarray]:
    e = np.asarray(young_modulus, dtype=np.float64)
    nu = np.asarray(poisson_ratio, dtype=np.float64)
    if not np.isfinite(e).all() or (e <= 0.0).any():
        bad = e[~(np.isfinite(e) & (e > 0.0))].reshape(-1)[0]
        raise MaterialError(
            f"young_modulus must be finite and > 0 (got {bad!r}): give Young's modulus in Pa, e.g. 1.044e6"
        )
    if not np.isfinite(nu).all() or (nu <= -1.0).any() or (nu >= 0.5).any():
        bad = nu[~(np.isfinite(nu) & (nu > -1.0) & (nu < 0.5))].reshape(-1)[0]
        raise MaterialError(
            f"poisson_ratio must be in (-1, 0.5) (got {bad!r}): 0.5 is incompressible and has no "
            "finite Lame lambda; use 0.45-0.49 for soft tissue"
        )
    return e, nu


def lame_parameters(young_modulus, poisson_ratio):
    """(lam, mu) in Pa from Young's modulus (Pa) and Poisson ratio; scalars or per-element arrays."""
    e, nu = _check_elastic(young_modulus, poisson_ratio)
    lam = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    mu = e / (2.0 * (1.0 + nu))
    if lam.ndim == 0:
        return float(lam), float(mu)
    return lam, mu


def bulk_modulus(young_modulus, poisson_ratio):
    """kappa = E / (3 (1 - 2 nu)) in Pa."""
    e, nu = _check_elastic(young_modulus, poisson_ratio)
    kappa = e / (3.0 * (1.0 - 2.0 * nu))
    return float(kappa) if kappa.ndim == 0 else kappa


def viscous_lame_parameters(viscosity, young_modulus, poisson_ratio):
    """Kelvin-Voigt viscous Lame coefficients (Pa s): (eta / E) (lam, mu), see module docstring."""
    eta = np.asarray(viscosity, dtype=np.float64)
    if not np.isfinite(eta).all() or (eta < 0.0).any():
        bad = eta[~(np.isfinite(eta) & (eta >= 0.0))].reshape(-1)[0]
        raise MaterialError(
            f"viscosity must be finite and >= 0 (got {bad!r}): give the extensional Kelvin-Voigt "
            "viscosity in Pa s (0 switches damping off), e.g. 1.0e3"
        )
    lam, mu = lame_parameters(young_modulus, poisson_ratio)
    tau = eta / np.asarray(young_modulus, dtype=np.float64)
    lam_v, mu_v = tau * lam, tau * mu
    if np.ndim(lam_v) == 0:
        return float(lam_v), float(mu_v)
    return lam_v, mu_v


def rv_stiffening_ratio(green_strain, beta_over_alpha: float) -> np.ndarray:
    """r = g(l) h(l) for the equivalent uniaxial stretch l = sqrt(1 + 2 E) (module docstring).

    Reference (numpy) version of what the ETMM kernel computes per element; also used for the
    stiffening margin of the critical time step.
    """
    e = np.maximum(np.asarray(green_strain, dtype=np.float64), GREEN_STRAIN_FLOOR)
    stretch = np.sqrt(1.0 + 2.0 * e)
    g = (stretch * stretch + stretch + 1.0) / (3.0 * stretch * stretch)
    h = 1.0 + 2.0 * beta_over_alpha * (stretch * stretch + 2.0 / stretch - 3.0)
    return g * h

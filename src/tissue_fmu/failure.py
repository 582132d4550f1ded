"""Wall failure: which elements have reached the aneurysm wall's failure stress (issue 32).

Criterion. A perforation is a tear, so the wall fails in tension: an element fails when its
equivalent uniaxial Cauchy stress reaches ``failure_stress``. That stress is the Raghavan-Vorp
closed form

    sigma(l) = l P_RV(l) = 2 (l^2 - 1/l) (alpha + 2 beta (l^2 + 2/l - 3))

at the element's largest principal stretch ``l = sqrt(1 + 2 E_1)`` (``E_1`` its largest principal
Green strain). Why this and not the stress tensor of the tensor-mass element: that tensor is a
small-strain, nominal measure, equal to the Raghavan-Vorp stress only in the uniaxial state the
ETMM is calibrated on (tissue_fmu.materials); the failure data are uniaxial tension tests of
aneurysm wall strips, reported as Cauchy stress (the failure tension over the deformed section).
The same closed form maps the element's state to the quantity that was measured, for every law
(linear, ETMM, hyperelastic). ``sigma`` grows monotonically with ``l > 1``, so the criterion is a
stretch limit ``l >= l_f`` with ``sigma(l_f) = failure_stress``, solved once.

The default, :data:`DEFAULT_FAILURE_STRESS`, lies in the 0.8-1.4 MPa failure strength measured on
aneurysm wall (Raghavan and Vorp; Vorp 2007, J Biomech 40:1887, reviews the data); at the
Raghavan-Vorp wall's alpha and beta it is a stretch of about 1.24 (Green strain 0.27).

Which elements: every active element, through a compiled pass over the largest principal Green
strain magnitude (about a millisecond on the 15k-element default wall), then an exact check of
the few at or above the limit.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq

from . import kernels

__all__ = ["DEFAULT_FAILURE_STRESS", "rv_uniaxial_cauchy_stress", "failure_stretch", "failed_elements"]

#: Pa: the aneurysm wall's uniaxial failure strength, within the 0.8-1.4 MPa measured (Raghavan and Vorp)
DEFAULT_FAILURE_STRESS = 1.0e6


def rv_uniaxial_cauchy_stress(stretch, alpha: float, beta: float):
    """Cauchy stress (Pa) of the incompressible Raghavan-Vorp wall in uniaxial tension at ``stretch``."""
    stretch = np.asarray(stretch, dtype=np.float64)
    return 2.0 * (stretch**2 - 1.0 / stretch) * (alpha + 2.0 * beta * (stretch**2 + 2.0 / stretch - 3.0))


def failure_stretch(failure_stress: float, alpha: float, beta: float) -> float:
    """The stretch ``l_f > 1`` at which the uniaxial Cauchy stress reaches ``failure_stress``."""
    if not (math.isfinite(failure_stress) and failure_stress > 0.0):
        raise ValueError(f"failure_stress must be a finite number > 0 Pa (got {failure_stress!r}), e.g. "
                         f"{DEFAULT_FAILURE_STRESS:g}")
    high = 2.0
    while rv_uniaxial_cauchy_stress(high, alpha, beta) < failure_stress:
        high *= 2.0
    return float(brentq(lambda s: float(rv_uniaxial_cauchy_stress(s, alpha, beta)) - failure_stress, 1.0, high,
                        xtol=1e-15, rtol=4 * np.finfo(float).eps))


def failed_elements(force_field, u: np.ndarray, stretch_limit: float) -> np.ndarray:
    """Active element ids (rows of ``force_field.active_tets``) whose largest principal stretch has
    reached ``stretch_limit`` at displacement ``u``; elements already removed never appear."""
    green_limit = 0.5 * (stretch_limit * stretch_limit - 1.0)
    tets, grads = force_field.active_tets, force_field._grads
    magnitude = np.empty(tets.shape[0])
    kernels.element_max_green_strain(tets, grads, u, magnitude)
    ids = np.flatnonzero((magnitude >= green_limit) & ~force_field.removed)
    if ids.size == 0:
        return ids
    # exact: the largest principal Green strain (tension), E = (H + H^T + H^T H) / 2
    h = np.einsum("ekc,ekd->ecd", u[tets[ids]], grads[ids])  # H[c, d] = sum_k u_k[c] g_k[d]
    green = 0.5 * (h + np.swapaxes(h, 1, 2) + np.einsum("eki,ekj->eij", h, h))
    return ids[np.linalg.eigvalsh(green)[:, -1] >= green_limit]

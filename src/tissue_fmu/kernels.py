"""Numba kernels of the tensor-mass force field: arrays in, preallocated arrays out, no validation.

Layouts (see precompute.py): vertex (n,3,3), edges (e,2) int32 with i < j, edge_tensors (e,3,3),
tets (m,4) int64, grads (m,4,3) reference shape-function gradients, volumes (m,), per-element
lam/mu (m,), node arrays (n,3).  Every "matvec" kernel ACCUMULATES ``scale * (operator x)`` into
``out`` so forces (scale -1) and tangents (scale +1) share one code path.

ETMM correction (derivation in materials.py): per element, ``phi`` scales the element's linear
force, ``f_T = -phi K_T u_T = -(dlam A_T + dmu B_T) u_T`` with ``dlam = phi lam``, ``dmu = phi mu``;
``K_T u_T`` is evaluated from the displacement gradient ``H = sum_k u_k (x) g_k`` as
``(K_T u_T)_j = V (lam tr(H) g_j + mu (H + H^T) g_j)``, so neither A nor B is stored.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .materials import GREEN_STRAIN_FLOOR

# ----------------------------------------------------------------------------------------------
# Linear tensor-mass operator (vertex + edge tensors)
# ----------------------------------------------------------------------------------------------


@njit(cache=True)
def tensor_mass_matvec(vertex, edges, edge_tensors, x, scale, out):
    """out += scale * K x with K given by vertex and edge tensors.

    Each edge tensor is read once and applied to both ends (K_ij x_j to i, K_ij^T x_i to j).
    """
    n = vertex.shape[0]
    for i in range(n):
        x0 = x[i, 0]
        x1 = x[i, 1]
        x2 = x[i, 2]
        out[i, 0] += scale * (vertex[i, 0, 0] * x0 + vertex[i, 0, 1] * x1 + vertex[i, 0, 2] * x2)
        out[i, 1] += scale * (vertex[i, 1, 0] * x0 + vertex[i, 1, 1] * x1 + vertex[i, 1, 2] * x2)
        out[i, 2] += scale * (vertex[i, 2, 0] * x0 + vertex[i, 2, 1] * x1 + vertex[i, 2, 2] * x2)
    for e in range(edges.shape[0]):
        a = edges[e, 0]
        b = edges[e, 1]
        k00 = edge_tensors[e, 0, 0]
        k01 = edge_tensors[e, 0, 1]
        k02 = edge_tensors[e, 0, 2]
        k10 = edge_tensors[e, 1, 0]
        k11 = edge_tensors[e, 1, 1]
        k12 = edge_tensors[e, 1, 2]
        k20 = edge_tensors[e, 2, 0]
        k21 = edge_tensors[e, 2, 1]
        k22 = edge_tensors[e, 2, 2]
        xa0 = x[a, 0]
        xa1 = x[a, 1]
        xa2 = x[a, 2]
        xb0 = x[b, 0]
        xb1 = x[b, 1]
        xb2 = x[b, 2]
        out[a, 0] += scale * (k00 * xb0 + k01 * xb1 + k02 * xb2)
        out[a, 1] += scale * (k10 * xb0 + k11 * xb1 + k12 * xb2)
        out[a, 2] += scale * (k20 * xb0 + k21 * xb1 + k22 * xb2)
        out[b, 0] += scale * (k00 * xa0 + k10 * xa1 + k20 * xa2)
        out[b, 1] += scale * (k01 * xa0 + k11 * xa1 + k21 * xa2)
        out[b, 2] += scale * (k02 * xa0 + k12 * xa1 + k22 * xa2)


@njit(cache=True)
def tensor_mass_force_screened(vertex, edges, edge_tensors, edge_screen, u, out, flagged):
    """out -= K u (as tensor_mass_matvec with scale -1) and, in the same pass over the edges,
    flag every edge whose Green strain |(l^2 - L^2) / (2 L^2)| exceeds its limit:
    flagged[:count] = edge ids; returns count.  edge_screen[e] (float32, streamed, cheaper than
    gathering rest positions) = (d / limit_e, 1 / (2 limit_e)) with d = rest edge vector scaled so the test
    is |d . du + du . du / (2 limit)| > L^2 ... written as |s . du + c du . du| > 1.
    """
    n = vertex.shape[0]
    for i in range(n):
        x0 = u[i, 0]
        x1 = u[i, 1]
        x2 = u[i, 2]
        out[i, 0] -= vertex[i, 0, 0] * x0 + vertex[i, 0, 1] * x1 + vertex[i, 0, 2] * x2
        out[i, 1] -= vertex[i, 1, 0] * x0 + vertex[i, 1, 1] * x1 + vertex[i, 1, 2] * x2
        out[i, 2] -= vertex[i, 2, 0] * x0 + vertex[i, 2, 1] * x1 + vertex[i, 2, 2] * x2
    count = 0
    for e in range(edges.shape[0]):
        a = edges[e, 0]
        b = edges[e, 1]
        k00 = edge_tensors[e, 0, 0]
        k01 = edge_tensors[e, 0, 1]
        k02 = edge_tensors[e, 0, 2]
        k10 = edge_tensors[e, 1, 0]
        k11 = edge_tensors[e, 1, 1]
        k12 = edge_tensors[e, 1, 2]
        k20 = edge_tensors[e, 2, 0]
        k21 = edge_tensors[e, 2, 1]
        k22 = edge_tensors[e, 2, 2]
        xa0 = u[a, 0]
        xa1 = u[a, 1]
        xa2 = u[a, 2]
        xb0 = u[b, 0]
        xb1 = u[b, 1]
        xb2 = u[b, 2]
        out[a, 0] -= k00 * xb0 + k01 * xb1 + k02 * xb2
        out[a, 1] -= k10 * xb0 + k11 * xb1 + k12 * xb2
        out[a, 2] -= k20 * xb0 + k21 * xb1 + k22 * xb2
        out[b, 0] -= k00 * xa0 + k10 * xa1 + k20 * xa2
        out[b, 1] -= k01 * xa0 + k11 * xa1 + k21 * xa2
        out[b, 2] -= k02 * xa0 + k12 * xa1 + k22 * xa2
        du0 = xb0 - xa0
        du1 = xb1 - xa1
        du2 = xb2 - xa2
        measure = (edge_screen[e, 0] * du0 + edge_screen[e, 1] * du1 + edge_screen[e, 2] * du2
                   + edge_screen[e, 3] * (du0 * du0 + du1 * du1 + du2 * du2))
        if abs(measure) > 1.0:
            flagged[count] = e
            count += 1
    return count


@njit(cache=True)
def elements_of_flagged_edges(flagged, n_flagged, edge_elem_ptr, edge_elem_ids, candidate, stamp, stamp_value,
                              out_ids):
    """Distinct candidate elements touching the flagged edges -> out_ids[:count]; returns count.

    stamp[e] == stamp_value marks elements already listed in this call (no clearing pass needed).
    """
    count = 0
    for f in range(n_flagged):
        edge = flagged[f]
        for k in range(edge_elem_ptr[edge], edge_elem_ptr[edge + 1]):
            e = edge_elem_ids[k]
            if candidate[e] and stamp[e] != stamp_value:
                stamp[e] = stamp_value
                out_ids[count] = e
                count += 1
    return count


@njit(cache=True)
def gershgorin_row_sums(vertex, edges, edge_tensors, out):
    """out (n,3) = sum of |K| over each row (node i, component a) of the 3n x 3n operator."""
    n = vertex.shape[0]
    for i in range(n):
        for a in range(3):
            s = 0.0
            for c in range(3):
                s += abs(vertex[i, a, c])
            out[i, a] = s
    for e in range(edges.shape[0]):
        a = edges[e, 0]
        b = edges[e, 1]
        for r in range(3):
            for c in range(3):
                v = abs(edge_tensors[e, r, c])
                out[a, r] += v  # row (a, r) of K_ab
                out[b, c] += v  # row (b, c) of K_ba = K_ab^T


# ----------------------------------------------------------------------------------------------
# Small 3x3 helpers
# ----------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _displacement_gradient(tets, grads, e, x, h):
    """h = sum_k x[t_k] (x) g_k for element e."""
    for r in range(3):
        for c in range(3):
            h[r, c] = 0.0
    for k in range(4):
        node = tets[e, k]
        for r in range(3):
            xr = x[node, r]
            for c in range(3):
                h[r, c] += xr * grads[e, k, c]


@njit(cache=True)
def _green_strain(h, g):
    """g = (H + H^T + H^T H) / 2."""
    for r in range(3):
        for c in range(3):
            s = h[r, c] + h[c, r]
            for k in range(3):
                s += h[k, r] * h[k, c]
            g[r, c] = 0.5 * s


@njit(cache=True)
def sym3_eigenvalues(m):
    """Eigenvalues (ascending) of a symmetric 3x3 matrix (closed form, trigonometric)."""
    p1 = m[0, 1] * m[0, 1] + m[0, 2] * m[0, 2] + m[1, 2] * m[1, 2]
    q = (m[0, 0] + m[1, 1] + m[2, 2]) / 3.0
    d0 = m[0, 0] - q
    d1 = m[1, 1] - q
    d2 = m[2, 2] - q
    p2 = d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * p1
    if p2 <= 1e-300:
        return q, q, q
    p = math.sqrt(p2 / 6.0)
    b00 = d0 / p
    b11 = d1 / p
    b22 = d2 / p
    b01 = m[0, 1] / p
    b02 = m[0, 2] / p
    b12 = m[1, 2] / p
    det_b = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
    r = 0.5 * det_b
    if r <= -1.0:
        angle = math.pi / 3.0
    elif r >= 1.0:
        angle = 0.0
    else:
        angle = math.acos(r) / 3.0
    e_max = q + 2.0 * p * math.cos(angle)
    e_min = q + 2.0 * p * math.cos(angle + 2.0 * math.pi / 3.0)
    e_mid = 3.0 * q - e_max - e_min
    return e_min, e_mid, e_max


# ----------------------------------------------------------------------------------------------
# ETMM: Raghavan-Vorp secant stiffening (see materials.py for the derivation)
# ----------------------------------------------------------------------------------------------



@njit(cache=True)
def _rv_ratio_and_slope(green, beta_over_alpha):
    """(r, dr/dE) of r = g(l) h(l), l = sqrt(1 + 2 E)."""
    floored = green < GREEN_STRAIN_FLOOR
    e = GREEN_STRAIN_FLOOR if floored else green
    lam = math.sqrt(1.0 + 2.0 * e)
    l2 = lam * lam
    g = (l2 + lam + 1.0) / (3.0 * l2)
    h = 1.0 + 2.0 * beta_over_alpha * (l2 + 2.0 / lam - 3.0)
    if floored:
        return g * h, 0.0
    dg = -1.0 / (3.0 * l2) - 2.0 / (3.0 * l2 * lam)
    dh = 2.0 * beta_over_alpha * (2.0 * lam - 2.0 / l2)
    return g * h, (dg * h + g * dh) / lam


@njit(cache=True)
def _branch_phi(green, threshold, beta_over_alpha):
    """(phi, dphi/dE) of one principal strain branch: w(|E|) (r(E) - 1), ramp over [t, 2t]."""
    mag = abs(green)
    r, dr = _rv_ratio_and_slope(green, beta_over_alpha)
    if threshold <= 0.0:
        return r - 1.0, dr
    if mag <= threshold:
        return 0.0, 0.0
    if mag >= 2.0 * threshold:
        return r - 1.0, dr
    w = (mag - threshold) / threshold
    sgn = 1.0 if green > 0.0 else -1.0
    return w * (r - 1.0), sgn / threshold * (r - 1.0) + w * dr


@njit(cache=True)
def _element_phi_gradient(g, threshold, beta_over_alpha):
    """(phi, c_max, c_min, e_min, e_max) with d(phi) = c_max dE_max + c_min dE_min, where E_max,
    E_min are the axisymmetric-equivalent extremes (same phi as the hot path, exact derivatives)."""
    e_min, e_max = _axisymmetric_extremes(g[0, 0], g[1, 1], g[2, 2], g[0, 1], g[0, 2], g[1, 2])
    s_t = e_max if e_max > 0.0 else 0.0
    s_c = -e_min if e_min < 0.0 else 0.0
    if (threshold > 0.0 and s_t <= threshold and s_c <= threshold) or s_t + s_c == 0.0:
        return 0.0, 0.0, 0.0, e_min, e_max
    phi_t, dphi_t = 0.0, 0.0
    phi_c, dphi_c = 0.0, 0.0
    if s_t > threshold:
        phi_t, dphi_t = _branch_phi(e_max, threshold, beta_over_alpha)
    if s_c > threshold:
        phi_c, dphi_c = _branch_phi(e_min, threshold, beta_over_alpha)
    total = s_t + s_c
    x = s_c / total
    w_c = (x - BLEND_LOW) / BLEND_WIDTH
    if w_c <= 0.0:
        return phi_t, dphi_t, 0.0, e_min, e_max
    if w_c >= 1.0:
        return phi_c, 0.0, dphi_c, e_min, e_max
    dx_dmax = -s_c / (total * total) if e_max > 0.0 else 0.0
    dx_dmin = -s_t / (total * total) if e_min < 0.0 else 0.0
    jump = (phi_c - phi_t) / BLEND_WIDTH
    phi = (1.0 - w_c) * phi_t + w_c * phi_c
    return phi, (1.0 - w_c) * dphi_t + jump * dx_dmax, w_c * dphi_c + jump * dx_dmin, e_min, e_max


@njit(cache=True)
def _axisymmetric_extremes_gradient(g, sign, grad, d, cof):
    """grad = d(extreme)/dE (symmetric 3x3) of the largest (sign +1) or smallest (sign -1)
    axisymmetric-equivalent value: I/3 + sign D/(4p) + d(p r)/2 with
    d(p r)/dE = 3 dev(cof D) / (D:D) - 6 det(D) D / (D:D)^2."""
    q = (g[0, 0] + g[1, 1] + g[2, 2]) / 3.0
    for r in range(3):
        for c in range(3):
            d[r, c] = g[r, c]
        d[r, r] -= q
    p2 = 0.0
    for r in range(3):
        for c in range(3):
            p2 += d[r, c] * d[r, c]
    for r in range(3):
        for c in range(3):
            grad[r, c] = 0.0
        grad[r, r] = 1.0 / 3.0
    if p2 <= 1e-300:
        return
    p = math.sqrt(p2 / 6.0)
    cof[0, 0] = d[1, 1] * d[2, 2] - d[1, 2] * d[2, 1]
    cof[0, 1] = d[1, 2] * d[2, 0] - d[1, 0] * d[2, 2]
    cof[0, 2] = d[1, 0] * d[2, 1] - d[1, 1] * d[2, 0]
    cof[1, 0] = d[0, 2] * d[2, 1] - d[0, 1] * d[2, 2]
    cof[1, 1] = d[0, 0] * d[2, 2] - d[0, 2] * d[2, 0]
    cof[1, 2] = d[0, 1] * d[2, 0] - d[0, 0] * d[2, 1]
    cof[2, 0] = d[0, 1] * d[1, 2] - d[0, 2] * d[1, 1]
    cof[2, 1] = d[0, 2] * d[1, 0] - d[0, 0] * d[1, 2]
    cof[2, 2] = d[0, 0] * d[1, 1] - d[0, 1] * d[1, 0]
    det_d = d[0, 0] * cof[0, 0] + d[0, 1] * cof[0, 1] + d[0, 2] * cof[0, 2]
    dpr_cof, dpr_d = 3.0 / p2, -6.0 * det_d / (p2 * p2)
    tr_cof = (cof[0, 0] + cof[1, 1] + cof[2, 2]) / 3.0
    for r in range(3):
        for c in range(3):
            dev_cof = cof[r, c] - (tr_cof if r == c else 0.0)
            grad[r, c] += sign * d[r, c] / (4.0 * p) + 0.5 * (dpr_cof * dev_cof + dpr_d * d[r, c])


@njit(cache=True, inline="always")
def _add_scaled_element_force(tets, grads, volumes, lam, mu, e, h, factor, out):
    """out[t_j] += factor * V (lam tr(H) g_j + mu (H + H^T) g_j)  (= factor * K_T x_T)."""
    tr = h[0, 0] + h[1, 1] + h[2, 2]
    cl = factor * volumes[e] * lam[e] * tr
    cm = factor * volumes[e] * mu[e]
    s00 = 2.0 * h[0, 0]
    s11 = 2.0 * h[1, 1]
    s22 = 2.0 * h[2, 2]
    s01 = h[0, 1] + h[1, 0]
    s02 = h[0, 2] + h[2, 0]
    s12 = h[1, 2] + h[2, 1]
    for j in range(4):
        g0 = grads[e, j, 0]
        g1 = grads[e, j, 1]
        g2 = grads[e, j, 2]
        node = tets[e, j]
        out[node, 0] += cl * g0 + cm * (s00 * g0 + s01 * g1 + s02 * g2)
        out[node, 1] += cl * g1 + cm * (s01 * g0 + s11 * g1 + s12 * g2)
        out[node, 2] += cl * g2 + cm * (s02 * g0 + s12 * g1 + s22 * g2)


@njit(cache=True, inline="always")
def _grad9(tets, grads, e, x):
    """The nine entries of H = sum_k x[t_k] (x) g_k as scalars (row-major)."""
    h00 = h01 = h02 = h10 = h11 = h12 = h20 = h21 = h22 = 0.0
    for k in range(4):
        node = tets[e, k]
        x0 = x[node, 0]
        x1 = x[node, 1]
        x2 = x[node, 2]
        g0 = grads[e, k, 0]
        g1 = grads[e, k, 1]
        g2 = grads[e, k, 2]
        h00 += x0 * g0
        h01 += x0 * g1
        h02 += x0 * g2
        h10 += x1 * g0
        h11 += x1 * g1
        h12 += x1 * g2
        h20 += x2 * g0
        h21 += x2 * g1
        h22 += x2 * g2
    return h00, h01, h02, h10, h11, h12, h20, h21, h22


@njit(cache=True, inline="always")
def _axisymmetric_extremes(a00, a11, a22, a01, a02, a12):
    """Axisymmetric-equivalent (smallest, largest) principal values of a symmetric 3x3, from its
    invariants only (no eigen-solve; see materials.py):

        q = tr/3, D = A - q I, p = sqrt(D:D / 6), p r = det(D) / (2 p^2) = 3 det(D) / (D:D),
        largest ~ q + 1.5 p + 0.5 p r,   smallest ~ q - 1.5 p + 0.5 p r.

    Exact when two principal values coincide (uniaxial tension/compression, equibiaxial: r = +-1);
    otherwise between the middle and the extreme principal value (up to 0.23 p inside, pure
    shear).  Smooth in A (the true extremes are not where they cross), and ~6x cheaper.
    """
    q = (a00 + a11 + a22) / 3.0
    d0 = a00 - q
    d1 = a11 - q
    d2 = a22 - q
    p2 = d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)
    if p2 <= 1e-300:
        return q, q
    p = math.sqrt(p2 / 6.0)
    det_d = d0 * (d1 * d2 - a12 * a12) - a01 * (a01 * d2 - a12 * a02) + a02 * (a01 * a12 - d1 * a02)
    pr = 3.0 * det_d / p2  # |p r| <= p analytically; smooth in A, so no clamp
    return q - 1.5 * p + 0.5 * pr, q + 1.5 * p + 0.5 * pr


@njit(cache=True, inline="always")
def _green9(h00, h01, h02, h10, h11, h12, h20, h21, h22):
    """Green strain (E00, E11, E22, E01, E02, E12) of F = I + H."""
    e00 = h00 + 0.5 * (h00 * h00 + h10 * h10 + h20 * h20)
    e11 = h11 + 0.5 * (h01 * h01 + h11 * h11 + h21 * h21)
    e22 = h22 + 0.5 * (h02 * h02 + h12 * h12 + h22 * h22)
    e01 = 0.5 * (h01 + h10 + h00 * h01 + h10 * h11 + h20 * h21)
    e02 = 0.5 * (h02 + h20 + h00 * h02 + h10 * h12 + h20 * h22)
    e12 = 0.5 * (h12 + h21 + h01 * h02 + h11 * h12 + h21 * h22)
    return e00, e11, e22, e01, e02, e12


@njit(cache=True, inline="always")
def _branch_phi_value(green, threshold, beta_over_alpha):
    """Value of _branch_phi only (hot path: one sqrt, one division)."""
    mag = abs(green)
    e = green if green > GREEN_STRAIN_FLOOR else GREEN_STRAIN_FLOOR
    l2 = 1.0 + 2.0 * e
    lam = math.sqrt(l2)
    il = 1.0 / lam
    il2 = il * il
    r = (1.0 + il + il2) * (1.0 / 3.0) * (1.0 + 2.0 * beta_over_alpha * (l2 + 2.0 * il - 3.0))
    if threshold <= 0.0 or mag >= 2.0 * threshold:
        return r - 1.0
    return (mag - threshold) / threshold * (r - 1.0)


# Branch blending: x = s_c / (s_t + s_c) with s_t = max(E_max, 0), s_c = max(-E_min, 0).
# Uniaxial tension has x <= nu/(1+nu) < 0.34, uniaxial compression x >= 0.62 (nu <= 0.49,
# compression up to 30 %), so the blend over [0.4, 0.6] keeps both exact and phi continuous.
BLEND_LOW = 0.4
BLEND_WIDTH = 0.2


@njit(cache=True, inline="always")
def _phi_from_extremes(e_min, e_max, threshold, beta_over_alpha):
    """phi = (1 - w_c) phi_t + w_c phi_c: tension branch from E_max, compression from E_min."""
    s_t = e_max if e_max > 0.0 else 0.0
    s_c = -e_min if e_min < 0.0 else 0.0
    if s_t <= threshold and s_c <= threshold:
        return 0.0
    phi_t = _branch_phi_value(e_max, threshold, beta_over_alpha) if s_t > threshold else 0.0
    phi_c = _branch_phi_value(e_min, threshold, beta_over_alpha) if s_c > threshold else 0.0
    x = s_c / (s_t + s_c)
    w_c = (x - BLEND_LOW) / BLEND_WIDTH
    if w_c <= 0.0:
        return phi_t
    if w_c >= 1.0:
        return phi_c
    return (1.0 - w_c) * phi_t + w_c * phi_c


@njit(cache=True, inline="always")
def _scatter_scaled_force(tets, grads, e, cl_tr, cm, h00, h01, h02, h10, h11, h12, h20, h21, h22, out):
    """out[t_j] += cl_tr g_j + cm (H + H^T) g_j."""
    s00 = 2.0 * h00
    s11 = 2.0 * h11
    s22 = 2.0 * h22
    s01 = h01 + h10
    s02 = h02 + h20
    s12 = h12 + h21
    for j in range(4):
        g0 = grads[e, j, 0]
        g1 = grads[e, j, 1]
        g2 = grads[e, j, 2]
        node = tets[e, j]
        out[node, 0] += cl_tr * g0 + cm * (s00 * g0 + s01 * g1 + s02 * g2)
        out[node, 1] += cl_tr * g1 + cm * (s01 * g0 + s11 * g1 + s12 * g2)
        out[node, 2] += cl_tr * g2 + cm * (s02 * g0 + s12 * g1 + s22 * g2)


@njit(cache=True)
def etmm_correction(tets, grads, volumes, lam, mu, candidates, u, threshold, beta_over_alpha,
                    phi, nonlinear_ids, out):
    """Add the ETMM non-linear correction force of the candidate elements to out.

    For each candidate element: Green strain from u, phi (0 below the threshold), and
    out += -phi K_T u_T.  phi[e] is written for every candidate; the ids of elements with
    phi != 0 go to nonlinear_ids[:count].  Returns count.
    The strain measure is the axisymmetric-equivalent extreme Green strain (materials.py); a
    cheap screen skips it below the threshold: measure <= max |principal strain| <= ||E||_F.
    """
    count = 0
    t2 = threshold * threshold
    for c in range(candidates.shape[0]):
        e = candidates[c]
        phi[e] = 0.0
        h00, h01, h02, h10, h11, h12, h20, h21, h22 = _grad9(tets, grads, e, u)
        e00, e11, e22, e01, e02, e12 = _green9(h00, h01, h02, h10, h11, h12, h20, h21, h22)
        if threshold > 0.0:
            fro2 = e00 * e00 + e11 * e11 + e22 * e22 + 2.0 * (e01 * e01 + e02 * e02 + e12 * e12)
            if fro2 <= t2:
                continue
        e_min, e_max = _axisymmetric_extremes(e00, e11, e22, e01, e02, e12)
        p = _phi_from_extremes(e_min, e_max, threshold, beta_over_alpha)
        if p == 0.0:
            continue
        phi[e] = p
        nonlinear_ids[count] = e
        count += 1
        cv = -p * volumes[e]
        _scatter_scaled_force(tets, grads, e, cv * lam[e] * (h00 + h11 + h22), cv * mu[e],
                              h00, h01, h02, h10, h11, h12, h20, h21, h22, out)
    return count


@njit(cache=True)
def scaled_elements_matvec(tets, grads, volumes, lam, mu, ids, count, weights, x, scale, out):
    """out += scale * sum_{e in ids[:count]} weights[e] K_e x_e  (secant correction of the tangent)."""
    h = np.empty((3, 3))
    for c in range(count):
        e = ids[c]
        _displacement_gradient(tets, grads, e, x, h)
        _add_scaled_element_force(tets, grads, volumes, lam, mu, e, h, scale * weights[e], out)


@njit(cache=True, inline="always")
def _extreme_strain_rate(g, h, dh, sign, grad, d, cof):
    """d(extreme) = G : dE with dE = sym(F^T dH), G symmetric: = (F G) : dH, F = I + H."""
    _axisymmetric_extremes_gradient(g, sign, grad, d, cof)
    ds = 0.0
    for r in range(3):
        for c in range(3):
            fg = grad[r, c] + h[r, 0] * grad[0, c] + h[r, 1] * grad[1, c] + h[r, 2] * grad[2, c]
            ds += fg * dh[r, c]
    return ds


@njit(cache=True)
def etmm_consistent_tangent(tets, grads, volumes, lam, mu, candidates, u, du, threshold,
                            beta_over_alpha, out):
    """out += d/d(eps) [phi(u + eps du) K_T (u + eps du)] at eps = 0 summed over candidates
    (the exact derivative of the correction, including the change of phi; not symmetric).

    The all-candidate form (strain, phi and its gradient recomputed per product): the reference
    that etmm_tangent_data + etmm_nonlinear_tangent_matvec, which the step uses, are checked
    against."""
    h = np.empty((3, 3))
    dh = np.empty((3, 3))
    g = np.empty((3, 3))
    grad = np.empty((3, 3))
    d = np.empty((3, 3))
    cof = np.empty((3, 3))
    for c in range(candidates.shape[0]):
        e = candidates[c]
        _displacement_gradient(tets, grads, e, u, h)
        _green_strain(h, g)
        p, c_max, c_min, e_min, e_max = _element_phi_gradient(g, threshold, beta_over_alpha)
        if p == 0.0 and c_max == 0.0 and c_min == 0.0:
            continue
        _displacement_gradient(tets, grads, e, du, dh)
        _add_scaled_element_force(tets, grads, volumes, lam, mu, e, dh, p, out)
        dphi = 0.0
        if c_max != 0.0:
            dphi += c_max * _extreme_strain_rate(g, h, dh, 1.0, grad, d, cof)
        if c_min != 0.0:
            dphi += c_min * _extreme_strain_rate(g, h, dh, -1.0, grad, d, cof)
        if dphi != 0.0:
            _add_scaled_element_force(tets, grads, volumes, lam, mu, e, h, dphi, out)


@njit(cache=True)
def etmm_tangent_data(tets, grads, volumes, lam, mu, ids, count, u, threshold, beta_over_alpha, p_out, wg_out,
                      ku_out):
    """Per super-threshold element c (e = ids[c], c < count) at displacement u, the data of its
    consistent-tangent contribution  d(phi K_e u_e) = phi K_e du_e + (K_e u_e) (dphi/du_e . du_e):
    p_out[c] = phi, wg_out[c, k] = dphi/du_k (= W g_k, W = c_max F G_max + c_min F G_min),
    ku_out[c, j] = (K_e u_e)_j.  Elements below the threshold have phi = dphi = 0 and are not listed."""
    h = np.empty((3, 3))
    g = np.empty((3, 3))
    grad = np.empty((3, 3))
    w = np.empty((3, 3))
    d = np.empty((3, 3))
    cof = np.empty((3, 3))
    for c in range(count):
        e = ids[c]
        _displacement_gradient(tets, grads, e, u, h)
        _green_strain(h, g)
        p, c_max, c_min, e_min, e_max = _element_phi_gradient(g, threshold, beta_over_alpha)
        p_out[c] = p
        for r in range(3):
            for k in range(3):
                w[r, k] = 0.0
        for sign, coefficient in ((1.0, c_max), (-1.0, c_min)):
            if coefficient != 0.0:
                _axisymmetric_extremes_gradient(g, sign, grad, d, cof)
                for r in range(3):
                    for k in range(3):
                        fg = grad[r, k] + h[r, 0] * grad[0, k] + h[r, 1] * grad[1, k] + h[r, 2] * grad[2, k]
                        w[r, k] += coefficient * fg
        for k in range(4):
            for r in range(3):
                wg_out[c, k, r] = w[r, 0] * grads[e, k, 0] + w[r, 1] * grads[e, k, 1] + w[r, 2] * grads[e, k, 2]
                ku_out[c, k, r] = 0.0
        tr = h[0, 0] + h[1, 1] + h[2, 2]
        cl = volumes[e] * lam[e] * tr
        cm = volumes[e] * mu[e]
        for j in range(4):
            for r in range(3):
                s = 0.0
                for k in range(3):
                    s += (h[r, k] + h[k, r]) * grads[e, j, k]
                ku_out[c, j, r] = cl * grads[e, j, r] + cm * s


@njit(cache=True)
def etmm_nonlinear_tangent_matvec(tets, grads, volumes, lam, mu, ids, count, p, wg, ku, x, scale, out):
    """out += scale * sum_c [p_c K_e x_e + ku_c (wg_c . x_e)]: the consistent ETMM correction of
    the super-threshold elements only (data from etmm_tangent_data)."""
    h = np.empty((3, 3))
    for c in range(count):
        e = ids[c]
        _displacement_gradient(tets, grads, e, x, h)
        _add_scaled_element_force(tets, grads, volumes, lam, mu, e, h, scale * p[c], out)
        s = 0.0
        for k in range(4):
            node = tets[e, k]
            s += wg[c, k, 0] * x[node, 0] + wg[c, k, 1] * x[node, 1] + wg[c, k, 2] * x[node, 2]
        s *= scale
        for j in range(4):
            node = tets[e, j]
            out[node, 0] += s * ku[c, j, 0]
            out[node, 1] += s * ku[c, j, 1]
            out[node, 2] += s * ku[c, j, 2]


@njit(cache=True)
def etmm_nonlinear_tangent_blocks(grads, volumes, lam, mu, ids, count, p, wg, ku, blocks):
    """blocks[c, j, k] (3x3) = p_c K_e[j, k] + ku_c[j] (x) wg_c[k]: the element matrices of the
    consistent ETMM correction, K_e[j, k] = V (lam g_j (x) g_k + mu g_k (x) g_j + mu (g_j . g_k) I)."""
    for c in range(count):
        e = ids[c]
        vl = p[c] * volumes[e] * lam[e]
        vm = p[c] * volumes[e] * mu[e]
        for j in range(4):
            for k in range(4):
                dot = grads[e, j, 0] * grads[e, k, 0] + grads[e, j, 1] * grads[e, k, 1] + grads[e, j, 2] * grads[e, k, 2]
                for a in range(3):
                    for b in range(3):
                        v = vl * grads[e, j, a] * grads[e, k, b] + vm * grads[e, k, a] * grads[e, j, b]
                        if a == b:
                            v += vm * dot
                        blocks[c, j, k, a, b] = v + ku[c, j, a] * wg[c, k, b]


@njit(cache=True)
def scatter_element_blocks(tets, ids, count, blocks, scale, indptr, offsets, data):
    """data[CSR entry of (3 t_j + a, 3 t_k + b)] += scale * blocks[c, j, k, a, b] for the elements
    ids[:count]; offsets[e, j, k] = position of column 3 t_k in row 3 t_j minus indptr[3 t_j] (the
    three rows of a node share one column pattern)."""
    for c in range(count):
        e = ids[c]
        for j in range(4):
            row = 3 * tets[e, j]
            for k in range(4):
                off = offsets[e, j, k]
                for a in range(3):
                    base = indptr[row + a] + off
                    for b in range(3):
                        data[base + b] += scale * blocks[c, j, k, a, b]


@njit(cache=True)
def rows_transpose_subtract(z_rows, rows, s, out):
    """out -= sum_c s[c] z_rows[rows[c]] (= Z s with Z's columns stored as rows), without BLAS
    (its threads spin-wait on a busy machine)."""
    n = out.shape[0]
    for c in range(rows.shape[0]):
        r = rows[c]
        sc = s[c]
        for i in range(n):
            out[i] -= sc * z_rows[r, i]


@njit(cache=True)
def scaled_elements_diagonal(tets, grads, volumes, lam, mu, ids, count, weights, out):
    """out[node] += weights[e] * diag of the element block K_jj = V((lam+mu) g_j g_j^T + mu |g_j|^2 I)."""
    for c in range(count):
        e = ids[c]
        w = weights[e] * volumes[e]
        for j in range(4):
            g0 = grads[e, j, 0]
            g1 = grads[e, j, 1]
            g2 = grads[e, j, 2]
            gg = g0 * g0 + g1 * g1 + g2 * g2
            lm = lam[e] + mu[e]
            node = tets[e, j]
            out[node, 0] += w * (lm * g0 * g0 + mu[e] * gg)
            out[node, 1] += w * (lm * g1 * g1 + mu[e] * gg)
            out[node, 2] += w * (lm * g2 * g2 + mu[e] * gg)


@njit(cache=True)
def etmm_secant_energy(tets, grads, volumes, lam, mu, candidate, u, threshold, beta_over_alpha):
    """ETMM's secant energy 1/2 sum_T (1 + phi_T) u_T^T K_T u_T in one pass over the elements:
    the linear energy V (lam/2 tr(eps)^2 + mu eps:eps) of each, times 1 + phi for the candidates
    (``candidate[e]`` != 0), phi exactly as etmm_correction takes it at u: 1/2 u.K u plus the
    correction's part in one gradient per element (one pass costs less than half of the matvec and
    the correction pass apart)."""
    total = 0.0
    t2 = threshold * threshold
    for e in range(tets.shape[0]):
        h00, h01, h02, h10, h11, h12, h20, h21, h22 = _grad9(tets, grads, e, u)
        tr = h00 + h11 + h22
        s01 = 0.5 * (h01 + h10)
        s02 = 0.5 * (h02 + h20)
        s12 = 0.5 * (h12 + h21)
        ee = h00 * h00 + h11 * h11 + h22 * h22 + 2.0 * (s01 * s01 + s02 * s02 + s12 * s12)
        energy = volumes[e] * (0.5 * lam[e] * tr * tr + mu[e] * ee)
        if candidate[e]:
            e00, e11, e22, e01, e02, e12 = _green9(h00, h01, h02, h10, h11, h12, h20, h21, h22)
            below = False
            if threshold > 0.0:
                fro2 = e00 * e00 + e11 * e11 + e22 * e22 + 2.0 * (e01 * e01 + e02 * e02 + e12 * e12)
                below = fro2 <= t2
            if not below:
                e_min, e_max = _axisymmetric_extremes(e00, e11, e22, e01, e02, e12)
                energy *= 1.0 + _phi_from_extremes(e_min, e_max, threshold, beta_over_alpha)
        total += energy
    return total


@njit(cache=True)
def kinetic_energy(masses, velocity):
    """1/2 sum_i m_i |v_i|^2 over the nodes."""
    total = 0.0
    for i in range(masses.shape[0]):
        v0 = velocity[i, 0]
        v1 = velocity[i, 1]
        v2 = velocity[i, 2]
        total += masses[i] * (v0 * v0 + v1 * v1 + v2 * v2)
    return 0.5 * total


@njit(cache=True)
def max_green_strain(tets, grads, u):
    """max over elements of the largest principal Green strain magnitude (= element_max_green_strain
    (...).max(), bit for bit): an element whose ||E||_F (>= every |principal strain|) does not exceed
    the running maximum cannot raise it, so its eigenvalues are skipped; and since
    E = (H + H^T + H^T H) / 2, ||E||_F <= ||H||_F + ||H||_F^2 / 2, so most elements are skipped before
    E is formed (the 1e-12 margin of ``best2`` covers the rounding of that bound)."""
    h = np.empty((3, 3))
    g = np.empty((3, 3))
    best = 0.0
    best2 = 0.0
    for e in range(tets.shape[0]):
        _displacement_gradient(tets, grads, e, u, h)
        if e > 0:
            hf2 = 0.0
            for r in range(3):
                for c in range(3):
                    hf2 += h[r, c] * h[r, c]
            bound = math.sqrt(hf2) + 0.5 * hf2
            if bound * bound <= best2:
                continue
        _green_strain(h, g)
        fro2 = 0.0
        for r in range(3):
            for c in range(3):
                fro2 += g[r, c] * g[r, c]
        if fro2 <= best2 and e > 0:
            continue
        e_min, e_mid, e_max = sym3_eigenvalues(g)
        value = max(abs(e_min), abs(e_max))
        if e == 0 or value > best:
            best = value
            best2 = value * value * (1.0 - 1e-12)
    return best


@njit(cache=True)
def element_max_green_strain(tets, grads, u, out):
    """out[e] = largest principal Green strain magnitude of element e."""
    h = np.empty((3, 3))
    g = np.empty((3, 3))
    for e in range(tets.shape[0]):
        _displacement_gradient(tets, grads, e, u, h)
        _green_strain(h, g)
        e_min, e_mid, e_max = sym3_eigenvalues(g)
        out[e] = max(abs(e_min), abs(e_max))


# ----------------------------------------------------------------------------------------------
# Hyperelastic reference: compressible Raghavan-Vorp, finite strain
#   W = alpha (I1bar - 3) + beta (I1bar - 3)^2 + kappa/2 (J - 1)^2,  I1bar = J^(-2/3) tr(F^T F)
#   P = W1 J^(-2/3) (2 F - 2/3 I1 F^-T) + kappa (J - 1) J F^-T,  W1 = alpha + 2 beta (I1bar - 3)
#   nodal force f_j = -V P g_j
# ----------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _det_inv_t(f, finv_t):
    """det(F) and F^-T."""
    c00 = f[1, 1] * f[2, 2] - f[1, 2] * f[2, 1]
    c01 = f[1, 2] * f[2, 0] - f[1, 0] * f[2, 2]
    c02 = f[1, 0] * f[2, 1] - f[1, 1] * f[2, 0]
    c10 = f[0, 2] * f[2, 1] - f[0, 1] * f[2, 2]
    c11 = f[0, 0] * f[2, 2] - f[0, 2] * f[2, 0]
    c12 = f[0, 1] * f[2, 0] - f[0, 0] * f[2, 1]
    c20 = f[0, 1] * f[1, 2] - f[0, 2] * f[1, 1]
    c21 = f[0, 2] * f[1, 0] - f[0, 0] * f[1, 2]
    c22 = f[0, 0] * f[1, 1] - f[0, 1] * f[1, 0]
    det = f[0, 0] * c00 + f[0, 1] * c01 + f[0, 2] * c02
    inv = 1.0 / det
    # cofactor matrix / det = F^-T
    finv_t[0, 0] = c00 * inv
    finv_t[0, 1] = c01 * inv
    finv_t[0, 2] = c02 * inv
    finv_t[1, 0] = c10 * inv
    finv_t[1, 1] = c11 * inv
    finv_t[1, 2] = c12 * inv
    finv_t[2, 0] = c20 * inv
    finv_t[2, 1] = c21 * inv
    finv_t[2, 2] = c22 * inv
    return det


@njit(cache=True, inline="always")
def _add_piola_force(tets, grads, volumes, e, p, factor, out):
    """out[t_j] += factor * V P g_j."""
    c = factor * volumes[e]
    for j in range(4):
        node = tets[e, j]
        for r in range(3):
            out[node, r] += c * (p[r, 0] * grads[e, j, 0] + p[r, 1] * grads[e, j, 1] + p[r, 2] * grads[e, j, 2])


@njit(cache=True)
def hyperelastic_forces(tets, grads, volumes, alpha, beta, kappa, u, out):
    """out += -V P(F) g_j for every element (compressible Raghavan-Vorp)."""
    f = np.empty((3, 3))
    fit = np.empty((3, 3))
    p = np.empty((3, 3))
    for e in range(tets.shape[0]):
        _displacement_gradient(tets, grads, e, u, f)
        f[0, 0] += 1.0
        f[1, 1] += 1.0
        f[2, 2] += 1.0
        jac = _det_inv_t(f, fit)
        i1 = 0.0
        for r in range(3):
            for c in range(3):
                i1 += f[r, c] * f[r, c]
        a = 1.0 / (np.cbrt(jac) ** 2)
        w1 = alpha[e] + 2.0 * beta[e] * (a * i1 - 3.0)
        vol_term = kappa[e] * (jac - 1.0) * jac
        for r in range(3):
            for c in range(3):
                p[r, c] = w1 * a * (2.0 * f[r, c] - (2.0 / 3.0) * i1 * fit[r, c]) + vol_term * fit[r, c]
        _add_piola_force(tets, grads, volumes, e, p, -1.0, out)


@njit(cache=True)
def hyperelastic_energy(tets, grads, volumes, alpha, beta, kappa, u):
    f = np.empty((3, 3))
    fit = np.empty((3, 3))
    total = 0.0
    for e in range(tets.shape[0]):
        _displacement_gradient(tets, grads, e, u, f)
        f[0, 0] += 1.0
        f[1, 1] += 1.0
        f[2, 2] += 1.0
        jac = _det_inv_t(f, fit)
        i1 = 0.0
        for r in range(3):
            for c in range(3):
                i1 += f[r, c] * f[r, c]
        dev = i1 / (np.cbrt(jac) ** 2) - 3.0
        total += volumes[e] * (alpha[e] * dev + beta[e] * dev * dev + 0.5 * kappa[e] * (jac - 1.0) ** 2)
    return total


@njit(cache=True)
def hyperelastic_tangent_matvec(tets, grads, volumes, alpha, beta, kappa, u, du, scale, out):
    """out += scale * K_t(u) du, K_t du = sum_T V dP[dF] g_j (analytic directional derivative)."""
    f = np.empty((3, 3))
    df = np.empty((3, 3))
    fit = np.empty((3, 3))
    dfit = np.empty((3, 3))
    tmp = np.empty((3, 3))
    dp = np.empty((3, 3))
    for e in range(tets.shape[0]):
        _displacement_gradient(tets, grads, e, u, f)
        f[0, 0] += 1.0
        f[1, 1] += 1.0
        f[2, 2] += 1.0
        _displacement_gradient(tets, grads, e, du, df)
        jac = _det_inv_t(f, fit)
        i1 = 0.0
        f_df = 0.0
        t = 0.0  # tr(F^-1 dF) = F^-T : dF
        for r in range(3):
            for c in range(3):
                i1 += f[r, c] * f[r, c]
                f_df += f[r, c] * df[r, c]
                t += fit[r, c] * df[r, c]
        a = 1.0 / (np.cbrt(jac) ** 2)
        i1bar = a * i1
        w1 = alpha[e] + 2.0 * beta[e] * (i1bar - 3.0)
        d_jac = jac * t
        d_a = -(2.0 / 3.0) * a * t
        d_i1 = 2.0 * f_df
        d_i1bar = a * (d_i1 - (2.0 / 3.0) * i1 * t)
        d_w1 = 2.0 * beta[e] * d_i1bar
        # d(F^-T) = -F^-T dF^T F^-T
        for r in range(3):
            for c in range(3):
                tmp[r, c] = df[0, r] * fit[0, c] + df[1, r] * fit[1, c] + df[2, r] * fit[2, c]  # dF^T F^-T
        for r in range(3):
            for c in range(3):
                dfit[r, c] = -(fit[r, 0] * tmp[0, c] + fit[r, 1] * tmp[1, c] + fit[r, 2] * tmp[2, c])
        c_g = d_w1 * a + w1 * d_a
        vol_a = kappa[e] * (2.0 * jac - 1.0) * d_jac
        vol_b = kappa[e] * (jac - 1.0) * jac
        for r in range(3):
            for c in range(3):
                g_rc = 2.0 * f[r, c] - (2.0 / 3.0) * i1 * fit[r, c]
                dg_rc = 2.0 * df[r, c] - (2.0 / 3.0) * d_i1 * fit[r, c] - (2.0 / 3.0) * i1 * dfit[r, c]
                dp[r, c] = c_g * g_rc + w1 * a * dg_rc + vol_a * fit[r, c] + vol_b * dfit[r, c]
        _add_piola_force(tets, grads, volumes, e, dp, scale, out)

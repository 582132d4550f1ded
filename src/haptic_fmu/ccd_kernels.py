"""Numba kernels for conservative continuous collision detection (CCD).

Method: inclusion-based bisection of the parametric domain (t, u, w) in [0, 1]^3, in the spirit of
Tight-Inclusion CCD (Wang et al. 2021), written from the paper's idea, generalised to Bezier
trajectories of any degree (1 = linear motion, 3 = cubic Hermite splines).

Both primitive pairs reduce to one function of the domain,

    F(t, u, w) = e0(t) - u e1(t) - w e2(t)

    vertex-face (v, f0, f1, f2):    e0 = v - f0,    e1 = f1 - f0,  e2 = f2 - f0,  u, w >= 0, u + w <= 1
    edge-edge (a0, a1, b0, b1):     e0 = a0 - b0,   e1 = a0 - a1,  e2 = b1 - b0,  u, w in [0, 1]

and contact means F = 0 somewhere in the domain. Each e_k(t) is a Bezier curve (its control points
are differences of the points' control points). On a sub-box [ta, tb] x [ua, ub] x [wa, wb] the
curve restricted to [ta, tb] has control points given by the blossom (exact dyadic parameters, no
re-parametrisation round-off), so every coordinate of F over the sub-box lies between the min and
max of the control values over the corners in (u, w) (convex-hull property, F linear in u and w).
A box is discarded only if that interval, widened by the floating-point error bound and the
separation margin, misses zero in some coordinate: no contact can be lost (conservative).

Besides the coordinate axes, two more separating directions are tried per box (e1 x e2, the face
normal or common edge normal, and F at the box centre), which removes thin sliding/grazing images
far faster than axis-aligned boxes alone; they are conservative for any direction.

A box that is not discarded is accepted as contact when its image is smaller than the tolerance,
or when the primitives are within the tolerance (plus margin) at its start time t_lo (a direct
floating-point distance; acceptance can only add hits, never lose one). Splits go to t when the
box straddles the moment the primitives cross each other's plane (a t-split is then what excludes
or accepts it), otherwise to the direction of largest image change (t favoured).

Search order: depth-first, earlier half in t first. The first accepted box bounds the first
contact from above by its t_lo = t_best; the remaining boxes
are then clipped to t < t_best, and every further accepted box lowers t_best. The returned time
of impact t_best is thus a lower bound of the first contact, at most one box (about
tolerance / |dF/dt|) early. If the box budget or stack runs out, the query is reported as a hit
at the earliest unresolved time (conservative) with status 1.
"""
import numpy as np
from numba import njit

# Unit round-off of float64 and the multiplier of the rounding-error bound: the image bounds are
# computed with at most ~(3 deg + 10) roundings of values bounded by 6 * max|coordinate|;
# 256 leaves a wide safety factor and is still ~6e-14 relative, far below any tolerance used.
_EPS = 2.0 ** -53
_ERR_FACTOR = 256.0

# Split choice: t if a t-split is what excludes the box (_t_split_helps), else the direction of
# largest image change, with t favoured by this factor (toi needs t resolved to tol; u and w only
# as far as needed to exclude or accept).
_T_BIAS = 64.0
_WELL_CONDITIONED_SINE = 0.1
# A box is also accepted when the primitives are within this fraction of tol (plus the contact
# margin) at its t_lo; 1.0 gives the same meaning of "contact" as the box-image criterion.
_ACCEPT_DISTANCE_FRACTION = 1.0
_STACK_COLS = 6  # t_lo, t_hi, u_lo, u_hi, w_lo, w_hi


@njit(cache=True)
def _blossom_restrict(ctrl, deg, ta, tb, sub, work):
    """Control points of the Bezier curves `ctrl` (deg+1, 3, 3) restricted to [ta, tb] -> `sub`."""
    if deg == 1:  # linear motion: the restriction is the pair of end values
        for a in range(3):
            for c in range(3):
                x0 = ctrl[0, a, c]
                x1 = ctrl[1, a, c]
                sub[0, a, c] = (1.0 - ta) * x0 + ta * x1
                sub[1, a, c] = (1.0 - tb) * x0 + tb * x1
        return
    for k in range(deg + 1):
        for i in range(deg + 1):
            for a in range(3):
                for c in range(3):
                    work[i, a, c] = ctrl[i, a, c]
        # blossom(ta repeated deg-k times, tb repeated k times): de Casteljau with one parameter per level
        for r in range(1, deg + 1):
            s = ta if r <= deg - k else tb
            one_minus = 1.0 - s
            for j in range(deg + 1 - r):
                for a in range(3):
                    for c in range(3):
                        work[j, a, c] = one_minus * work[j, a, c] + s * work[j + 1, a, c]
        for a in range(3):
            for c in range(3):
                sub[k, a, c] = work[0, a, c]


@njit(cache=True)
def _push(stack, size, t_lo, t_hi, u_lo, u_hi, w_lo, w_hi):
    stack[size, 0] = t_lo
    stack[size, 1] = t_hi
    stack[size, 2] = u_lo
    stack[size, 3] = u_hi
    stack[size, 4] = w_lo
    stack[size, 5] = w_hi


@njit(cache=True)
def _earliest_open(stack, size, t):
    """Earliest t_lo among the unresolved boxes (conservative time of impact when giving up)."""
    for k in range(size):
        t = min(t, stack[k, 0])
    return t


@njit(cache=True)
def _difference_curves(points, deg, edge_edge, ctrl):
    """points (deg+1, 4, 3) control points of the 4 primitive points -> ctrl (deg+1, 3, 3) of e0, e1, e2."""
    for i in range(deg + 1):
        for c in range(3):
            p0 = points[i, 0, c]
            p1 = points[i, 1, c]
            p2 = points[i, 2, c]
            p3 = points[i, 3, c]
            if edge_edge:
                ctrl[i, 0, c] = p0 - p2
                ctrl[i, 1, c] = p0 - p1
                ctrl[i, 2, c] = p3 - p2
            else:
                ctrl[i, 0, c] = p0 - p1
                ctrl[i, 1, c] = p2 - p1
                ctrl[i, 2, c] = p3 - p1


@njit(cache=True)
def _separated_along(sub, deg, u_lo, u_hi, w_lo, w_hi, margin, n0, n1, n2):
    """True if the image hull of the box lies beyond +-margin*|n|_1 along direction n.

    Conservative for any n: a contact point F* with |F*|_inf <= margin has |n . F*| <= |n|_1 margin.
    """
    n_l1 = abs(n0) + abs(n1) + abs(n2)
    if n_l1 == 0.0:
        return False, 0.0
    bound = margin * n_l1 * (1.0 + 16.0 * _EPS)
    d_lo = np.inf
    d_hi = -np.inf
    for k in range(deg + 1):
        e0 = n0 * sub[k, 0, 0] + n1 * sub[k, 0, 1] + n2 * sub[k, 0, 2]
        e1 = n0 * sub[k, 1, 0] + n1 * sub[k, 1, 1] + n2 * sub[k, 1, 2]
        e2 = n0 * sub[k, 2, 0] + n1 * sub[k, 2, 1] + n2 * sub[k, 2, 2]
        for u in (u_lo, u_hi):
            for w in (w_lo, w_hi):
                d = e0 - u * e1 - w * e2
                d_lo = min(d_lo, d)
                d_hi = max(d_hi, d)
    return d_lo > bound or d_hi < -bound, (d_hi - d_lo) / n_l1


@njit(cache=True)
def _t_split_helps(n0, n1, n2, a0, a1, a2, b0, b1, b2, c0, c1, c2, spread, tol, u_lo, u_hi, w_lo, w_hi):
    """Whether splitting the box in t (rather than u or w) is what it takes to resolve it.

    Along n = e1 x e2 the image hardly depends on u and w (n is normal to e1 and e2), so when the
    image straddles zero there, only a split in t can separate it: the box holds the moment the
    primitives cross each other's plane (a = e1, b = e2, c = e0 at mid-time, any common scale).
    A t-split is chosen when n is well defined (e1, e2 not near parallel), the image is spread
    along n by motion (not coplanar sliding, where t-splits never help), and the crossing point
    (u*, w*) = argmin |c - u a - w b| lies in the box's (u, w) range (else u/w splits exclude it).
    Only a heuristic for the split order: correctness does not depend on it.
    """
    nn = n0 * n0 + n1 * n1 + n2 * n2
    aa = a0 * a0 + a1 * a1 + a2 * a2
    bb = b0 * b0 + b1 * b1 + b2 * b2
    if nn < _WELL_CONDITIONED_SINE ** 2 * aa * bb or spread <= _ACCEPT_DISTANCE_FRACTION * tol:
        return False
    ab = a0 * b0 + a1 * b1 + a2 * b2
    ac = a0 * c0 + a1 * c1 + a2 * c2
    bc = b0 * c0 + b1 * c1 + b2 * c2
    det = aa * bb - ab * ab  # = |a x b|^2 > 0 here
    u = (bb * ac - ab * bc) / det
    w = (aa * bc - ab * ac) / det
    slack_u = 0.25 * (u_hi - u_lo)
    slack_w = 0.25 * (w_hi - w_lo)
    return u_lo - slack_u <= u <= u_hi + slack_u and w_lo - slack_w <= w <= w_hi + slack_w


@njit(cache=True)
def _separated_directions(sub, deg, u_lo, u_hi, w_lo, w_hi, margin, tol):
    """Separating-direction tests beyond the coordinate axes, at the box mid-time.
    Returns (separated, t_helps), see _t_split_helps.

    1. n = e1 x e2: for vertex-face the face normal, for edge-edge the common normal of the edges;
       the direction in which sliding or grazing contacts are thin.
    2. n = F at the box centre: the direction from the origin to the image, which separates thin
       images of any orientation (parallel edges, degenerate faces, where e1 x e2 vanishes).
    """
    a0 = 0.0
    a1 = 0.0
    a2 = 0.0
    b0 = 0.0
    b1 = 0.0
    b2 = 0.0
    c0 = 0.0
    c1 = 0.0
    c2 = 0.0
    for k in range(deg + 1):
        a0 += sub[k, 1, 0]
        a1 += sub[k, 1, 1]
        a2 += sub[k, 1, 2]
        b0 += sub[k, 2, 0]
        b1 += sub[k, 2, 1]
        b2 += sub[k, 2, 2]
        c0 += sub[k, 0, 0]
        c1 += sub[k, 0, 1]
        c2 += sub[k, 0, 2]
    n0 = a1 * b2 - a2 * b1
    n1 = a2 * b0 - a0 * b2
    n2 = a0 * b1 - a1 * b0
    separated, spread = _separated_along(sub, deg, u_lo, u_hi, w_lo, w_hi, margin, n0, n1, n2)
    if separated:
        return True, False
    t_helps = _t_split_helps(n0, n1, n2, a0, a1, a2, b0, b1, b2, c0, c1, c2, spread, tol, u_lo, u_hi, w_lo, w_hi)
    u_mid = 0.5 * (u_lo + u_hi)
    w_mid = 0.5 * (w_lo + w_hi)
    separated, spread = _separated_along(sub, deg, u_lo, u_hi, w_lo, w_hi, margin, c0 - u_mid * a0 - w_mid * b0,
                                         c1 - u_mid * a1 - w_mid * b1, c2 - u_mid * a2 - w_mid * b2)
    return separated, t_helps


@njit(cache=True)
def _box_test(ctrl, sub, work, deg, t_lo, t_hi, u_lo, u_hi, w_lo, w_hi, margin, dot_err, tol):
    """(keep, image width, t_helps): keep is False when the box provably holds no contact."""
    _blossom_restrict(ctrl, deg, t_lo, t_hi, sub, work)
    width = 0.0
    for c in range(3):
        f_lo = np.inf
        f_hi = -np.inf
        for k in range(deg + 1):
            e0 = sub[k, 0, c]
            e1a = u_lo * sub[k, 1, c]
            e1b = u_hi * sub[k, 1, c]
            e2a = w_lo * sub[k, 2, c]
            e2b = w_hi * sub[k, 2, c]
            lo_k = e0 - max(e1a, e1b) - max(e2a, e2b)
            hi_k = e0 - min(e1a, e1b) - min(e2a, e2b)
            f_lo = min(f_lo, lo_k)
            f_hi = max(f_hi, hi_k)
        if f_lo > margin or f_hi < -margin:
            return False, width, False
        width = max(width, f_hi - f_lo)
    separated, t_helps = _separated_directions(sub, deg, u_lo, u_hi, w_lo, w_hi, margin + dot_err, tol)
    return not separated, width, t_helps


@njit(cache=True)
def _lerp_pair(ctrl, a, c, ta, tb):
    x0 = ctrl[0, a, c]
    x1 = ctrl[1, a, c]
    return (1.0 - ta) * x0 + ta * x1, (1.0 - tb) * x0 + tb * x1


@njit(cache=True)
def _axis_range(p0, p1, q0, q1, r0, r1, u_lo, u_hi, w_lo, w_hi):
    """Range of p - u q - w r over the two time ends and the (u, w) corners (one coordinate)."""
    qa = u_lo * q0
    qb = u_hi * q0
    ra = w_lo * r0
    rb = w_hi * r0
    lo = p0 - max(qa, qb) - max(ra, rb)
    hi = p0 - min(qa, qb) - min(ra, rb)
    qa = u_lo * q1
    qb = u_hi * q1
    ra = w_lo * r1
    rb = w_hi * r1
    lo = min(lo, p1 - max(qa, qb) - max(ra, rb))
    hi = max(hi, p1 - min(qa, qb) - min(ra, rb))
    return lo, hi


@njit(cache=True)
def _dot_range(n0, n1, n2, px, py, pz, qx, qy, qz, rx, ry, rz, u_lo, u_hi, w_lo, w_hi, lo, hi):
    p = n0 * px + n1 * py + n2 * pz
    q = n0 * qx + n1 * qy + n2 * qz
    r = n0 * rx + n1 * ry + n2 * rz
    qa = u_lo * q
    qb = u_hi * q
    ra = w_lo * r
    rb = w_hi * r
    return min(lo, p - max(qa, qb) - max(ra, rb)), max(hi, p - min(qa, qb) - min(ra, rb))


@njit(cache=True)
def _box_test_linear(ctrl, t_lo, t_hi, u_lo, u_hi, w_lo, w_hi, margin, dot_err, tol):
    """Same as _box_test for degree 1, in scalars (the hot path of linear-motion CCD)."""
    px0, px1 = _lerp_pair(ctrl, 0, 0, t_lo, t_hi)
    qx0, qx1 = _lerp_pair(ctrl, 1, 0, t_lo, t_hi)
    rx0, rx1 = _lerp_pair(ctrl, 2, 0, t_lo, t_hi)
    lo, hi = _axis_range(px0, px1, qx0, qx1, rx0, rx1, u_lo, u_hi, w_lo, w_hi)
    if lo > margin or hi < -margin:
        return False, 0.0, False
    width = hi - lo
    py0, py1 = _lerp_pair(ctrl, 0, 1, t_lo, t_hi)
    qy0, qy1 = _lerp_pair(ctrl, 1, 1, t_lo, t_hi)
    ry0, ry1 = _lerp_pair(ctrl, 2, 1, t_lo, t_hi)
    lo, hi = _axis_range(py0, py1, qy0, qy1, ry0, ry1, u_lo, u_hi, w_lo, w_hi)
    if lo > margin or hi < -margin:
        return False, 0.0, False
    width = max(width, hi - lo)
    pz0, pz1 = _lerp_pair(ctrl, 0, 2, t_lo, t_hi)
    qz0, qz1 = _lerp_pair(ctrl, 1, 2, t_lo, t_hi)
    rz0, rz1 = _lerp_pair(ctrl, 2, 2, t_lo, t_hi)
    lo, hi = _axis_range(pz0, pz1, qz0, qz1, rz0, rz1, u_lo, u_hi, w_lo, w_hi)
    if lo > margin or hi < -margin:
        return False, 0.0, False
    width = max(width, hi - lo)

    dmargin = (margin + dot_err) * (1.0 + 16.0 * _EPS)
    # direction 1: e1 x e2 at mid-time (face normal / common edge normal)
    ax = qx0 + qx1
    ay = qy0 + qy1
    az = qz0 + qz1
    bx = rx0 + rx1
    by = ry0 + ry1
    bz = rz0 + rz1
    n0 = ay * bz - az * by
    n1 = az * bx - ax * bz
    n2 = ax * by - ay * bx
    n_l1 = abs(n0) + abs(n1) + abs(n2)
    t_helps = False
    if n_l1 > 0.0:
        lo, hi = _dot_range(n0, n1, n2, px0, py0, pz0, qx0, qy0, qz0, rx0, ry0, rz0, u_lo, u_hi, w_lo, w_hi,
                            np.inf, -np.inf)
        lo, hi = _dot_range(n0, n1, n2, px1, py1, pz1, qx1, qy1, qz1, rx1, ry1, rz1, u_lo, u_hi, w_lo, w_hi, lo, hi)
        bound = dmargin * n_l1
        if lo > bound or hi < -bound:
            return False, width, False
        t_helps = _t_split_helps(n0, n1, n2, ax, ay, az, bx, by, bz, px0 + px1, py0 + py1, pz0 + pz1,
                                 (hi - lo) / n_l1, tol, u_lo, u_hi, w_lo, w_hi)
    # direction 2: F at the box centre
    u_mid = 0.5 * (u_lo + u_hi)
    w_mid = 0.5 * (w_lo + w_hi)
    n0 = px0 + px1 - u_mid * ax - w_mid * bx
    n1 = py0 + py1 - u_mid * ay - w_mid * by
    n2 = pz0 + pz1 - u_mid * az - w_mid * bz
    n_l1 = abs(n0) + abs(n1) + abs(n2)
    if n_l1 > 0.0:
        lo, hi = _dot_range(n0, n1, n2, px0, py0, pz0, qx0, qy0, qz0, rx0, ry0, rz0, u_lo, u_hi, w_lo, w_hi,
                            np.inf, -np.inf)
        lo, hi = _dot_range(n0, n1, n2, px1, py1, pz1, qx1, qy1, qz1, rx1, ry1, rz1, u_lo, u_hi, w_lo, w_hi, lo, hi)
        bound = dmargin * n_l1
        if lo > bound or hi < -bound:
            return False, width, False
    return True, width, t_helps


@njit(cache=True)
def _point_segment_distance2(px, py, pz, ax, ay, az, bx, by, bz):
    dx = bx - ax
    dy = by - ay
    dz = bz - az
    rx = px - ax
    ry = py - ay
    rz = pz - az
    dd = dx * dx + dy * dy + dz * dz
    s = 0.0
    if dd > 0.0:
        s = min(1.0, max(0.0, (rx * dx + ry * dy + rz * dz) / dd))
    rx -= s * dx
    ry -= s * dy
    rz -= s * dz
    return rx * rx + ry * ry + rz * rz


@njit(cache=True)
def _point_triangle_distance2(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Squared distance from P to triangle ABC (plain floating point; degenerate triangles allowed)."""
    abx = bx - ax
    aby = by - ay
    abz = bz - az
    acx = cx - ax
    acy = cy - ay
    acz = cz - az
    dx = px - ax
    dy = py - ay
    dz = pz - az
    m00 = abx * abx + aby * aby + abz * abz
    m01 = abx * acx + aby * acy + abz * acz
    m11 = acx * acx + acy * acy + acz * acz
    det = m00 * m11 - m01 * m01
    if det > 1e-12 * m00 * m11:
        r0 = abx * dx + aby * dy + abz * dz
        r1 = acx * dx + acy * dy + acz * dz
        v = (m11 * r0 - m01 * r1) / det
        w = (m00 * r1 - m01 * r0) / det
        if v >= 0.0 and w >= 0.0 and v + w <= 1.0:
            ex = dx - v * abx - w * acx
            ey = dy - v * aby - w * acy
            ez = dz - v * abz - w * acz
            return ex * ex + ey * ey + ez * ez
    return min(_point_segment_distance2(px, py, pz, ax, ay, az, bx, by, bz),
               _point_segment_distance2(px, py, pz, bx, by, bz, cx, cy, cz),
               _point_segment_distance2(px, py, pz, cx, cy, cz, ax, ay, az))


@njit(cache=True)
def _evaluate(ctrl, deg, t, work):
    """de Casteljau: work[0] = the curves e0, e1, e2 at time t."""
    for i in range(deg + 1):
        for a in range(3):
            for c in range(3):
                work[i, a, c] = ctrl[i, a, c]
    for r in range(1, deg + 1):
        for j in range(deg + 1 - r):
            for a in range(3):
                for c in range(3):
                    work[j, a, c] = (1.0 - t) * work[j, a, c] + t * work[j + 1, a, c]


@njit(cache=True)
def _distance_at(ctrl, deg, edge_edge, t, work):
    """Euclidean distance between the primitives at time t: min |e0 - u e1 - w e2| over the domain,
    i.e. the distance from e0 to the triangle (0, e1, e2), or for edge-edge to the parallelogram
    spanned by e1 and e2 (two triangles). Plain floating point: used only to accept contacts."""
    _evaluate(ctrl, deg, t, work)
    px = work[0, 0, 0]
    py = work[0, 0, 1]
    pz = work[0, 0, 2]
    ax = work[0, 1, 0]
    ay = work[0, 1, 1]
    az = work[0, 1, 2]
    bx = work[0, 2, 0]
    by = work[0, 2, 1]
    bz = work[0, 2, 2]
    d2 = _point_triangle_distance2(px, py, pz, 0.0, 0.0, 0.0, ax, ay, az, bx, by, bz)
    if edge_edge:
        d2 = min(d2, _point_triangle_distance2(px, py, pz, ax + bx, ay + by, az + bz, ax, ay, az, bx, by, bz))
    return np.sqrt(d2)


@njit(cache=True)
def ccd_query(points, deg, edge_edge, rel_tolerance, rel_separation, min_distance, max_boxes,
              ctrl, sub, work, stack):
    """One query. points (deg+1, 4, 3). Returns (hit, toi, status, boxes_checked).

    status 0: resolved; 1: budget or stack exhausted, reported as a conservative hit.
    """
    _difference_curves(points, deg, edge_edge, ctrl)

    # Scales: extent of all control points (tolerances are relative to it) and the largest
    # absolute coordinate (round-off is relative to it).
    max_abs = 0.0
    extent = 0.0
    for c in range(3):
        lo = points[0, 0, c]
        hi = lo
        for i in range(deg + 1):
            for p in range(4):
                x = points[i, p, c]
                lo = min(lo, x)
                hi = max(hi, x)
                max_abs = max(max_abs, abs(x))
        extent = max(extent, hi - lo)
    tol = rel_tolerance * extent
    margin = rel_separation * extent + min_distance + _ERR_FACTOR * _EPS * max_abs

    # Bounds on |dF/dt|, |dF/du|, |dF/dw| over the domain, to pick the split direction that
    # shrinks the image most and to stop once the box can no longer change F by more than tol.
    d_t = 0.0
    d_u = 0.0
    d_w = 0.0
    for i in range(deg + 1):
        for c in range(3):
            d_u = max(d_u, abs(ctrl[i, 1, c]))
            d_w = max(d_w, abs(ctrl[i, 2, c]))
            if i < deg:
                s = 0.0
                for a in range(3):
                    s += abs(ctrl[i + 1, a, c] - ctrl[i, a, c])
                d_t = max(d_t, deg * s)

    # round-off of a dot product n . F (|F| <= 6 max_abs), per unit of |n|_1
    dot_err = 128.0 * _EPS * max_abs

    # Depth-first search, earlier half first: after a split one child is processed at once (the
    # earlier one for a split in t) and the other is pushed. The first accepted box gives an upper
    # bound t_best of the first contact; the search then only has to look for contacts before
    # t_best, so every remaining box is clipped to [t_lo, t_best] (t_best is dyadic: exact) or
    # dropped. Clipping is what makes degenerate cases (parallel edges, coplanar sliding) cheap:
    # the slab just before a contact is excluded at once, without resolving the contact set.
    capacity = stack.shape[0]
    size = 0
    t_best = np.inf
    t_lo = 0.0
    t_hi = 1.0
    u_lo = 0.0
    u_hi = 1.0
    w_lo = 0.0
    w_hi = 1.0
    checked = 0
    t_checked = -1.0
    while True:
        keep = t_lo < t_best
        if keep:
            t_hi = min(t_hi, t_best)
            checked += 1
            if checked > max_boxes:
                return True, _earliest_open(stack, size, min(t_lo, t_best)), 1, checked
            if not edge_edge and u_lo + w_lo > 1.0:
                keep = False  # box entirely outside the triangle (u + w <= 1); dyadic sums are exact
        width = 0.0
        t_helps = False
        if keep:
            # linear motion (the common case) has a scalar, unrolled version of the box test
            if deg == 1:
                keep, width, t_helps = _box_test_linear(ctrl, t_lo, t_hi, u_lo, u_hi, w_lo, w_hi, margin, dot_err,
                                                        tol)
            else:
                keep, width, t_helps = _box_test(ctrl, sub, work, deg, t_lo, t_hi, u_lo, u_hi, w_lo, w_hi, margin,
                                                 dot_err, tol)
        if keep:
            s_t = (t_hi - t_lo) * d_t
            s_u = (u_hi - u_lo) * d_u
            s_w = (w_hi - w_lo) * d_w
            if width <= tol or s_t + s_u + s_w <= tol:
                t_best = t_lo  # accepted: contact (within tolerance) at t_lo
                keep = False
            elif t_lo != t_checked:
                # accept if the primitives are within tol (+ margin) at t_lo: a direct distance, so
                # u and w need not be resolved; computed once per distinct t_lo. Accepting never
                # loses a contact, it only reports one (at worst a false positive within tol).
                t_checked = t_lo
                if _distance_at(ctrl, deg, edge_edge, t_lo, work) <= _ACCEPT_DISTANCE_FRACTION * tol + margin:
                    t_best = t_lo
                    keep = False
        if not keep:
            if size == 0:
                break
            size -= 1
            t_lo = stack[size, 0]
            t_hi = stack[size, 1]
            u_lo = stack[size, 2]
            u_hi = stack[size, 3]
            w_lo = stack[size, 4]
            w_hi = stack[size, 5]
            continue

        if size == capacity:
            return True, _earliest_open(stack, size, min(t_lo, t_best)), 1, checked
        if t_helps or (s_t * _T_BIAS >= s_u and s_t * _T_BIAS >= s_w):
            t_mid = 0.5 * (t_lo + t_hi)
            _push(stack, size, t_mid, t_hi, u_lo, u_hi, w_lo, w_hi)
            t_hi = t_mid
        elif s_u >= s_w:
            u_mid = 0.5 * (u_lo + u_hi)
            _push(stack, size, t_lo, t_hi, u_mid, u_hi, w_lo, w_hi)
            u_hi = u_mid
        else:
            w_mid = 0.5 * (w_lo + w_hi)
            _push(stack, size, t_lo, t_hi, u_lo, u_hi, w_mid, w_hi)
            w_hi = w_mid
        size += 1
    if t_best <= 1.0:
        return True, t_best, 0, checked
    return False, np.inf, 0, checked


@njit(cache=True)
def ccd_batch(points, edge_edge, rel_tolerance, rel_separation, min_distance, max_boxes, stack_capacity,
              hit, toi, status, boxes_checked):
    """points (n, deg+1, 4, 3) Bezier control points per query -> hit, toi, status, boxes_checked (n,)."""
    deg = points.shape[1] - 1
    ctrl = np.empty((deg + 1, 3, 3))
    sub = np.empty((deg + 1, 3, 3))
    work = np.empty((deg + 1, 3, 3))
    stack = np.empty((stack_capacity, _STACK_COLS))
    for q in range(points.shape[0]):
        h, t, s, n_checked = ccd_query(points[q], deg, edge_edge, rel_tolerance, rel_separation, min_distance,
                                       max_boxes, ctrl, sub, work, stack)
        hit[q] = h
        toi[q] = t
        status[q] = s
        boxes_checked[q] = n_checked

"""Geometric primitives of the narrow phase and the response (numba, no validation).

Shared by `narrow_phase` (closest features of the tool against the local model's facets),
`penalty` (the reference facet contact) and the tests.

Conventions: triangles (a, b, c) are wound so that n = (b - a) x (c - a) / |...| is the OUTWARD
normal of the tissue (the side the tool lives on); closest points are returned as barycentric
weights (wa, wb, wc) >= 0 summing to 1.
"""
import math

from numba import njit

_EPS_DEGENERATE = 1e-300


@njit(cache=True)
def face_normal(a, b, c):
    """Unit outward normal (nx, ny, nz) of triangle (a, b, c); zeros for a degenerate triangle."""
    ux = b[0] - a[0]
    uy = b[1] - a[1]
    uz = b[2] - a[2]
    vx = c[0] - a[0]
    vy = c[1] - a[1]
    vz = c[2] - a[2]
    nx = uy * vz - uz * vy
    ny = uz * vx - ux * vz
    nz = ux * vy - uy * vx
    norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    if norm <= _EPS_DEGENERATE:
        return 0.0, 0.0, 0.0
    return nx / norm, ny / norm, nz / norm


@njit(cache=True)
def vertex_angle(v, u, w):
    """Angle at v of the triangle (v, u, w), radians (atan2 of the cross and dot products: accurate
    for small and obtuse angles alike)."""
    ax = u[0] - v[0]
    ay = u[1] - v[1]
    az = u[2] - v[2]
    bx = w[0] - v[0]
    by = w[1] - v[1]
    bz = w[2] - v[2]
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    return math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz)


@njit(cache=True)
def closest_point_triangle(px, py, pz, a, b, c):
    """Barycentric weights (wa, wb, wc) of the point of triangle (a, b, c) closest to p.

    Region classification (vertex, edge, interior Voronoi regions) in the style of Ericson,
    Real-Time Collision Detection, 5.1.5; weights are >= 0 and sum to 1.
    """
    abx = b[0] - a[0]
    aby = b[1] - a[1]
    abz = b[2] - a[2]
    acx = c[0] - a[0]
    acy = c[1] - a[1]
    acz = c[2] - a[2]
    apx = px - a[0]
    apy = py - a[1]
    apz = pz - a[2]
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return 1.0, 0.0, 0.0
    bpx = px - b[0]
    bpy = py - b[1]
    bpz = pz - b[2]
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return 0.0, 1.0, 0.0
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return 1.0 - v, v, 0.0
    cpx = px - c[0]
    cpy = py - c[1]
    cpz = pz - c[2]
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return 0.0, 0.0, 1.0
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return 1.0 - w, 0.0, w
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return 0.0, 1.0 - w, w
    denom = va + vb + vc
    if denom <= _EPS_DEGENERATE:
        # degenerate (zero-area) triangle: fall back to vertex a
        return 1.0, 0.0, 0.0
    v = vb / denom
    w = vc / denom
    return 1.0 - v - w, v, w


@njit(cache=True)
def closest_segment_segment(p0, p1, q0, q1):
    """Parameters (s, t) in [0,1]^2 of the closest points p0 + s (p1-p0), q0 + t (q1-q0).

    Clamped closed form (Ericson 5.1.9), robust to degenerate (point-like) segments.
    """
    d1x = p1[0] - p0[0]
    d1y = p1[1] - p0[1]
    d1z = p1[2] - p0[2]
    d2x = q1[0] - q0[0]
    d2y = q1[1] - q0[1]
    d2z = q1[2] - q0[2]
    rx = p0[0] - q0[0]
    ry = p0[1] - q0[1]
    rz = p0[2] - q0[2]
    a = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    tiny = 1e-30
    if a <= tiny and e <= tiny:
        return 0.0, 0.0
    if a <= tiny:
        t = min(max(f / e, 0.0), 1.0)
        return 0.0, t
    c = d1x * rx + d1y * ry + d1z * rz
    if e <= tiny:
        s = min(max(-c / a, 0.0), 1.0)
        return s, 0.0
    b = d1x * d2x + d1y * d2y + d1z * d2z
    denom = a * e - b * b
    if denom > 1e-14 * a * e:
        s = min(max((b * f - c * e) / denom, 0.0), 1.0)
    else:
        s = 0.0  # parallel segments: any s works, pick the start
    t = (b * s + f) / e
    if t < 0.0:
        t = 0.0
        s = min(max(-c / a, 0.0), 1.0)
    elif t > 1.0:
        t = 1.0
        s = min(max((b - c) / a, 0.0), 1.0)
    return s, t


@njit(cache=True)
def dist2_point_bary(px, py, pz, a, b, c, wa, wb, wc):
    qx = wa * a[0] + wb * b[0] + wc * c[0]
    qy = wa * a[1] + wb * b[1] + wc * c[1]
    qz = wa * a[2] + wb * b[2] + wc * c[2]
    return (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2


@njit(cache=True)
def closest_segment_triangle(p0, p1, a, b, c):
    """Closest points of segment [p0, p1] and triangle (a, b, c).

    Returns (s, wa, wb, wc, dist2): segment parameter, barycentric weights of the triangle point,
    squared distance. If the segment pierces the triangle, dist2 = 0 at the piercing point;
    otherwise the minimum is attained on a boundary feature: an endpoint against the triangle or
    the segment against one of the three edges.
    """
    nx, ny, nz = face_normal(a, b, c)
    # piercing test: the plane distances of the endpoints have opposite signs
    s0 = (p0[0] - a[0]) * nx + (p0[1] - a[1]) * ny + (p0[2] - a[2]) * nz
    s1 = (p1[0] - a[0]) * nx + (p1[1] - a[1]) * ny + (p1[2] - a[2]) * nz
    if (s0 > 0.0 and s1 < 0.0) or (s0 < 0.0 and s1 > 0.0):
        s = s0 / (s0 - s1)
        xx = p0[0] + s * (p1[0] - p0[0])
        xy = p0[1] + s * (p1[1] - p0[1])
        xz = p0[2] + s * (p1[2] - p0[2])
        wa, wb, wc = closest_point_triangle(xx, xy, xz, a, b, c)
        if dist2_point_bary(xx, xy, xz, a, b, c, wa, wb, wc) <= 1e-24 * (
                1.0 + xx * xx + xy * xy + xz * xz):
            return s, wa, wb, wc, 0.0
    # endpoint p0
    best_s = 0.0
    ba, bb, bc = closest_point_triangle(p0[0], p0[1], p0[2], a, b, c)
    best = dist2_point_bary(p0[0], p0[1], p0[2], a, b, c, ba, bb, bc)
    # endpoint p1
    wa, wb, wc = closest_point_triangle(p1[0], p1[1], p1[2], a, b, c)
    d2 = dist2_point_bary(p1[0], p1[1], p1[2], a, b, c, wa, wb, wc)
    if d2 < best:
        best, best_s, ba, bb, bc = d2, 1.0, wa, wb, wc
    # the segment against each edge (ab, bc, ca)
    for edge in range(3):
        if edge == 0:
            e0, e1 = a, b
        elif edge == 1:
            e0, e1 = b, c
        else:
            e0, e1 = c, a
        s, t = closest_segment_segment(p0, p1, e0, e1)
        xx = p0[0] + s * (p1[0] - p0[0])
        xy = p0[1] + s * (p1[1] - p0[1])
        xz = p0[2] + s * (p1[2] - p0[2])
        yx = e0[0] + t * (e1[0] - e0[0])
        yy = e0[1] + t * (e1[1] - e0[1])
        yz = e0[2] + t * (e1[2] - e0[2])
        d2 = (xx - yx) ** 2 + (xy - yy) ** 2 + (xz - yz) ** 2
        if d2 < best:
            best = d2
            best_s = s
            if edge == 0:
                ba, bb, bc = 1.0 - t, t, 0.0
            elif edge == 1:
                ba, bb, bc = 0.0, 1.0 - t, t
            else:
                ba, bb, bc = t, 0.0, 1.0 - t
    return best_s, ba, bb, bc, best


@njit(cache=True)
def max_displacement(a, b):
    """Largest Euclidean distance between corresponding rows of a and b."""
    best = 0.0
    for i in range(a.shape[0]):
        d2 = (a[i, 0] - b[i, 0]) ** 2 + (a[i, 1] - b[i, 1]) ** 2 + (a[i, 2] - b[i, 2]) ** 2
        if d2 > best:
            best = d2
    return math.sqrt(best)


@njit(cache=True)
def max_displacement_rows(a, b, out):
    """out[i] = Euclidean distance between rows i of a and b."""
    for i in range(a.shape[0]):
        out[i] = math.sqrt((a[i, 0] - b[i, 0]) ** 2 + (a[i, 1] - b[i, 1]) ** 2 + (a[i, 2] - b[i, 2]) ** 2)


@njit(cache=True)
def all_finite(a):
    """True when every entry of the (n,3) array is finite (the input check of the 1 kHz path)."""
    for i in range(a.shape[0]):
        for d in range(3):
            if not math.isfinite(a[i, d]):
                return False
    return True


@njit(cache=True)
def difference_velocity(p1, p0, dt, out):
    """out = (p1 - p0) / dt, row by row (finite-difference tool velocities, no allocation)."""
    for i in range(p1.shape[0]):
        for d in range(3):
            out[i, d] = (p1[i, d] - p0[i, d]) / dt

"""Numba kernels of the contact response and haptic rendering (the hot 1 kHz path).

Arrays in, preallocated arrays out, no validation: the Python layer (`penalty`, `local_model`,
`model`) checks every input before it reaches these functions.

Conventions
- Triangles (a, b, c) are wound so that n = (b - a) x (c - a) / |...| is the OUTWARD normal of the
  tissue (the side the tool lives on).
- Signed distance of a tool point p to a triangle: dist = (p - q) . n with q the closest point of
  the triangle to p (q lies in the triangle's plane, so this is the plane distance). dist < 0 means
  the point is inside the tissue (penetration depth delta = -dist).
- Penalty laws (force magnitude along n, delta = penetration, rate = d(delta)/dt = -(v_rel . n)):
    LAW_LINEAR        f = k delta + b rate                        (= -k dist n - b (v.n) n, eq. 5)
    LAW_QUADRATIC     f = k delta (1 + delta/d0) + b rate         (stiffening)
    LAW_HUNT_CROSSLEY f = max(0, k delta sqrt(delta/d0) + b (delta/d0) rate)
  The linear law is the design equation verbatim (it may pull when separating fast); the
  Hunt-Crossley law has damping proportional to depth, so the force is continuous at first
  contact, and it never pulls.
"""
import math

import numpy as np
from numba import njit

LAW_LINEAR = 0
LAW_QUADRATIC = 1
LAW_HUNT_CROSSLEY = 2

_EPS_DEGENERATE = 1e-300


# ---------------------------------------------------------------------------- geometry primitives
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
def _dist2_point_bary(px, py, pz, a, b, c, wa, wb, wc):
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
        if _dist2_point_bary(xx, xy, xz, a, b, c, wa, wb, wc) <= 1e-24 * (
                1.0 + xx * xx + xy * xy + xz * xz):
            return s, wa, wb, wc, 0.0
    # endpoint p0
    best_s = 0.0
    ba, bb, bc = closest_point_triangle(p0[0], p0[1], p0[2], a, b, c)
    best = _dist2_point_bary(p0[0], p0[1], p0[2], a, b, c, ba, bb, bc)
    # endpoint p1
    wa, wb, wc = closest_point_triangle(p1[0], p1[1], p1[2], a, b, c)
    d2 = _dist2_point_bary(p1[0], p1[1], p1[2], a, b, c, wa, wb, wc)
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


# ---------------------------------------------------------------------------- penalty laws
@njit(cache=True)
def penalty_magnitude(depth, rate, law, k, b, d0):
    """Normal force magnitude (along the outward normal, on the tool) for penetration depth >= 0."""
    if depth <= 0.0:
        return 0.0
    if law == LAW_LINEAR:
        return k * depth + b * rate
    if law == LAW_QUADRATIC:
        return k * depth * (1.0 + depth / d0) + b * rate
    ratio = depth / d0
    f = k * depth * math.sqrt(ratio) + b * ratio * rate
    return f if f > 0.0 else 0.0


@njit(cache=True)
def penalty_energy(depth, law, k, d0):
    """Potential energy of the elastic part of the penalty law at penetration depth >= 0."""
    if depth <= 0.0:
        return 0.0
    if law == LAW_LINEAR:
        return 0.5 * k * depth * depth
    if law == LAW_QUADRATIC:
        return 0.5 * k * depth * depth + k * depth ** 3 / (3.0 * d0)
    return 0.4 * k * depth * depth * math.sqrt(depth / d0)


# ---------------------------------------------------------------------------- batch helpers
@njit(cache=True)
def closest_point_triangle_batch(points, a, b, c, bary_out):
    """Row-wise closest points: bary_out[i] = weights of the point of triangle i closest to point i."""
    for i in range(points.shape[0]):
        wa, wb, wc = closest_point_triangle(points[i, 0], points[i, 1], points[i, 2], a[i], b[i], c[i])
        bary_out[i, 0] = wa
        bary_out[i, 1] = wb
        bary_out[i, 2] = wc


@njit(cache=True)
def closest_segment_triangle_batch(p0, p1, a, b, c, s_out, bary_out, dist_out):
    """Row-wise segment-triangle closest points (see closest_segment_triangle)."""
    for i in range(p0.shape[0]):
        s, wa, wb, wc, d2 = closest_segment_triangle(p0[i], p1[i], a[i], b[i], c[i])
        s_out[i] = s
        bary_out[i, 0] = wa
        bary_out[i, 1] = wb
        bary_out[i, 2] = wc
        dist_out[i] = math.sqrt(d2)


# ---------------------------------------------------------------------------- local model motion
@njit(cache=True)
def local_positions(frame_pos, frame_vel, tau, extrapolate, out):
    """Local model vertex positions tau seconds after the frame (hold: frame positions)."""
    if extrapolate:
        for i in range(frame_pos.shape[0]):
            for d in range(3):
                out[i, d] = frame_pos[i, d] + frame_vel[i, d] * tau
    else:
        for i in range(frame_pos.shape[0]):
            for d in range(3):
                out[i, d] = frame_pos[i, d]


@njit(cache=True)
def max_displacement(a, b):
    """Largest Euclidean distance between corresponding rows of a and b."""
    best = 0.0
    for i in range(a.shape[0]):
        d2 = (a[i, 0] - b[i, 0]) ** 2 + (a[i, 1] - b[i, 1]) ** 2 + (a[i, 2] - b[i, 2]) ** 2
        if d2 > best:
            best = d2
    return math.sqrt(best)


# ---------------------------------------------------------------------------- CCD candidates
@njit(cache=True)
def ccd_candidates(pos0, pos1, tri, node_ptr, node_faces, tool0, tool1, radius, inside,
                   queries, q_node, q_face):
    """Vertex-face pairs whose offset plane (face moved by `radius` along its normal) the tool node
    crosses from outside (>= 0) to inside (< 0) during the step, within the face's swept box; such
    a crossing needs CCD to decide whether it happened within the face. Nodes already inside are
    skipped. Fills queries (n,8,3):
    rows node, f0, f1, f2 at the step start, then at the step end. Returns the count."""
    count = 0
    for i in range(tool0.shape[0]):
        if inside[i]:
            continue
        for j in range(node_ptr[i], node_ptr[i + 1]):
            f = node_faces[j]
            a0 = pos0[tri[f, 0]]
            b0 = pos0[tri[f, 1]]
            c0 = pos0[tri[f, 2]]
            a1 = pos1[tri[f, 0]]
            b1 = pos1[tri[f, 1]]
            c1 = pos1[tri[f, 2]]
            # cheap rejection first: the node's swept box (inflated by radius) must overlap the
            # face's swept box, otherwise the plane crossing happens far from the face
            separated = False
            for d in range(3):
                lo = min(a0[d], b0[d], c0[d], a1[d], b1[d], c1[d]) - radius
                hi = max(a0[d], b0[d], c0[d], a1[d], b1[d], c1[d]) + radius
                if max(tool0[i, d], tool1[i, d]) < lo or min(tool0[i, d], tool1[i, d]) > hi:
                    separated = True
            if separated:
                continue
            n0x, n0y, n0z = face_normal(a0, b0, c0)
            n1x, n1y, n1z = face_normal(a1, b1, c1)
            s0 = ((tool0[i, 0] - a0[0]) * n0x + (tool0[i, 1] - a0[1]) * n0y
                  + (tool0[i, 2] - a0[2]) * n0z - radius)
            s1 = ((tool1[i, 0] - a1[0]) * n1x + (tool1[i, 1] - a1[1]) * n1y
                  + (tool1[i, 2] - a1[2]) * n1z - radius)
            if not (s0 >= 0.0 and s1 < 0.0):
                continue
            for d in range(3):
                queries[count, 0, d] = tool0[i, d]
                queries[count, 4, d] = tool1[i, d]
            for d in range(3):
                off0 = radius * (n0x if d == 0 else (n0y if d == 1 else n0z))
                off1 = radius * (n1x if d == 0 else (n1y if d == 1 else n1z))
                queries[count, 1, d] = a0[d] + off0
                queries[count, 2, d] = b0[d] + off0
                queries[count, 3, d] = c0[d] + off0
                queries[count, 5, d] = a1[d] + off1
                queries[count, 6, d] = b1[d] + off1
                queries[count, 7, d] = c1[d] + off1
            q_node[count] = i
            q_face[count] = f
            count += 1
    return count


# ---------------------------------------------------------------------------- contact step
@njit(cache=True)
def _apply_contact(f, wa, wb, wc, fx, fy, fz, tri, local_to_global, tissue_force):
    """Distribute the reaction -F on the tissue to the face's vertices by barycentric weights."""
    va = local_to_global[tri[f, 0]]
    vb = local_to_global[tri[f, 1]]
    vc = local_to_global[tri[f, 2]]
    tissue_force[va, 0] -= wa * fx
    tissue_force[va, 1] -= wa * fy
    tissue_force[va, 2] -= wa * fz
    tissue_force[vb, 0] -= wb * fx
    tissue_force[vb, 1] -= wb * fy
    tissue_force[vb, 2] -= wb * fz
    tissue_force[vc, 0] -= wc * fx
    tissue_force[vc, 1] -= wc * fy
    tissue_force[vc, 2] -= wc * fz


@njit(cache=True)
def contact_step(pos, vel, tri, local_to_global,
                 node_ptr, node_faces, seg_ptr, seg_faces,
                 tool, tool_vel, radius, k, b, law, d0,
                 inside, entry_normal,
                 node_force, tissue_force, contact_face, contact_depth):
    """Narrow phase and penalty response of one haptic step against the local model.

    pos, vel (nv,3): local model vertex positions and velocities at the evaluation time;
    tri (nf,3) local vertex ids; local_to_global (nv,) surface node ids for the tissue output.
    node_ptr/node_faces, seg_ptr/seg_faces: CSR candidate faces per tool node / tool segment.
    tool, tool_vel (n_tool,3). inside (n_tool,) int8 and entry_normal (n_tool,3): the contact side
    memory of each node (in/out). Outputs: node_force (n_tool,3) forces on the tool nodes,
    tissue_force (n_surface,3) (overwritten), contact_face / contact_depth per primitive
    (nodes then segments; -1 / 0 when none).

    Nodes are spheres of `radius`: a node outside picks the nearest candidate face (unsigned
    distance |p - q|) and is in contact if it is behind the face's plane (depth = radius - plane
    distance) or in front of it closer than radius (depth = radius - |p - q|); a node inside keeps
    the side it entered from: it only considers faces whose normal agrees with its entry normal
    (so a thin wall it went through cannot flip the force). Segments (centerline only) add a
    contact where their interior, in front of the face, comes within radius of it (capsule, depth =
    radius - distance of the axis to the face).
    Returns (max penetration, contact count, penalty energy).
    """
    n_tool = tool.shape[0]
    for i in range(tissue_force.shape[0]):
        tissue_force[i, 0] = 0.0
        tissue_force[i, 1] = 0.0
        tissue_force[i, 2] = 0.0
    for i in range(n_tool):
        node_force[i, 0] = 0.0
        node_force[i, 1] = 0.0
        node_force[i, 2] = 0.0
    for i in range(contact_face.shape[0]):
        contact_face[i] = -1
        contact_depth[i] = 0.0
    max_depth = 0.0
    count = 0
    energy = 0.0

    # ---- nodes (spheres of `radius`)
    for i in range(n_tool):
        px = tool[i, 0]
        py = tool[i, 1]
        pz = tool[i, 2]
        best = np.inf
        best_f = -1
        bwa = 0.0
        bwb = 0.0
        bwc = 0.0
        bnx = 0.0
        bny = 0.0
        bnz = 0.0
        for j in range(node_ptr[i], node_ptr[i + 1]):
            f = node_faces[j]
            a = pos[tri[f, 0]]
            bb = pos[tri[f, 1]]
            c = pos[tri[f, 2]]
            nx, ny, nz = face_normal(a, bb, c)
            if inside[i] and (nx * entry_normal[i, 0] + ny * entry_normal[i, 1]
                              + nz * entry_normal[i, 2]) <= 0.0:
                continue  # the far side of the wall: not the side this node came from
            wa, wb, wc = closest_point_triangle(px, py, pz, a, bb, c)
            d2 = _dist2_point_bary(px, py, pz, a, bb, c, wa, wb, wc)
            if d2 < best:
                best = d2
                best_f = f
                bwa, bwb, bwc = wa, wb, wc
                bnx, bny, bnz = nx, ny, nz
        if best_f < 0:
            inside[i] = 0
            continue
        a = pos[tri[best_f, 0]]
        plane = (px - a[0]) * bnx + (py - a[1]) * bny + (pz - a[2]) * bnz
        if plane >= 0.0:
            # in front of the face: the sphere touches it where the true distance is below radius
            dist = math.sqrt(best) - radius
        else:
            # behind the face: penetration measured along the normal (smooth across the facets)
            dist = plane - radius
        if dist >= 0.0:
            inside[i] = 0
            continue
        inside[i] = 1
        entry_normal[i, 0] = bnx
        entry_normal[i, 1] = bny
        entry_normal[i, 2] = bnz
        va = vel[tri[best_f, 0]]
        vb = vel[tri[best_f, 1]]
        vc = vel[tri[best_f, 2]]
        # relative normal velocity of the tool with respect to the surface at the contact point
        vn = ((tool_vel[i, 0] - (bwa * va[0] + bwb * vb[0] + bwc * vc[0])) * bnx
              + (tool_vel[i, 1] - (bwa * va[1] + bwb * vb[1] + bwc * vc[1])) * bny
              + (tool_vel[i, 2] - (bwa * va[2] + bwb * vb[2] + bwc * vc[2])) * bnz)
        depth = -dist
        fmag = penalty_magnitude(depth, -vn, law, k, b, d0)
        fx = fmag * bnx
        fy = fmag * bny
        fz = fmag * bnz
        node_force[i, 0] += fx
        node_force[i, 1] += fy
        node_force[i, 2] += fz
        _apply_contact(best_f, bwa, bwb, bwc, fx, fy, fz, tri, local_to_global, tissue_force)
        contact_face[i] = best_f
        contact_depth[i] = depth
        if depth > max_depth:
            max_depth = depth
        count += 1
        energy += penalty_energy(depth, law, k, d0)

    # ---- segment interiors (capsules), only where the whole axis is in front of the face
    n_seg = seg_ptr.shape[0] - 1
    for sgi in range(n_seg):
        p0 = tool[sgi]
        p1 = tool[sgi + 1]
        best = radius * radius
        best_f = -1
        bs = 0.0
        bwa = 0.0
        bwb = 0.0
        bwc = 0.0
        bnx = 0.0
        bny = 0.0
        bnz = 0.0
        for j in range(seg_ptr[sgi], seg_ptr[sgi + 1]):
            f = seg_faces[j]
            a = pos[tri[f, 0]]
            bb = pos[tri[f, 1]]
            c = pos[tri[f, 2]]
            nx, ny, nz = face_normal(a, bb, c)
            s0 = (p0[0] - a[0]) * nx + (p0[1] - a[1]) * ny + (p0[2] - a[2]) * nz
            s1 = (p1[0] - a[0]) * nx + (p1[1] - a[1]) * ny + (p1[2] - a[2]) * nz
            if s0 <= 0.0 or s1 <= 0.0:
                continue  # an end at or behind the plane: the node spheres handle it
            near = min(s0, s1)
            if near * near >= best:
                continue  # the plane (so the face) is farther than radius or the best face so far
            s, wa, wb, wc, d2 = closest_segment_triangle(p0, p1, a, bb, c)
            if s <= 1e-9 or s >= 1.0 - 1e-9:
                continue  # closest at a node: the node sphere handles it
            if d2 < best:
                best = d2
                best_f = f
                bs = s
                bwa, bwb, bwc = wa, wb, wc
                bnx, bny, bnz = nx, ny, nz
        if best_f < 0:
            continue
        dist = math.sqrt(best) - radius
        if dist >= 0.0:
            continue
        va = vel[tri[best_f, 0]]
        vb = vel[tri[best_f, 1]]
        vc = vel[tri[best_f, 2]]
        tvx = (1.0 - bs) * tool_vel[sgi, 0] + bs * tool_vel[sgi + 1, 0]
        tvy = (1.0 - bs) * tool_vel[sgi, 1] + bs * tool_vel[sgi + 1, 1]
        tvz = (1.0 - bs) * tool_vel[sgi, 2] + bs * tool_vel[sgi + 1, 2]
        vn = ((tvx - (bwa * va[0] + bwb * vb[0] + bwc * vc[0])) * bnx
              + (tvy - (bwa * va[1] + bwb * vb[1] + bwc * vc[1])) * bny
              + (tvz - (bwa * va[2] + bwb * vb[2] + bwc * vc[2])) * bnz)
        depth = -dist
        fmag = penalty_magnitude(depth, -vn, law, k, b, d0)
        fx = fmag * bnx
        fy = fmag * bny
        fz = fmag * bnz
        node_force[sgi, 0] += (1.0 - bs) * fx
        node_force[sgi, 1] += (1.0 - bs) * fy
        node_force[sgi, 2] += (1.0 - bs) * fz
        node_force[sgi + 1, 0] += bs * fx
        node_force[sgi + 1, 1] += bs * fy
        node_force[sgi + 1, 2] += bs * fz
        _apply_contact(best_f, bwa, bwb, bwc, fx, fy, fz, tri, local_to_global, tissue_force)
        contact_face[n_tool + sgi] = best_f
        contact_depth[n_tool + sgi] = depth
        if depth > max_depth:
            max_depth = depth
        count += 1
        energy += penalty_energy(depth, law, k, d0)
    return max_depth, count, energy


@njit(cache=True)
def triangle_boxes(pos, end, use_end, tri, lo, hi):
    """Boxes of the triangles over pos (and end, when use_end: the box of both) into lo, hi (t,3)."""
    for f in range(tri.shape[0]):
        for d in range(3):
            mn = pos[tri[f, 0], d]
            mx = mn
            for j in range(3):
                x = pos[tri[f, j], d]
                mn = min(mn, x)
                mx = max(mx, x)
                if use_end:
                    x = end[tri[f, j], d]
                    mn = min(mn, x)
                    mx = max(mx, x)
            lo[f, d] = mn
            hi[f, d] = mx


# ---------------------------------------------------------------------------- passivity
@njit(cache=True)
def passivity_step(position, velocity, force, prev_position, prev_force, has_prev, energy, period,
                   controller, max_damping):
    """One sample of the passivity observer/controller (see passivity.py for the convention).

    Adds the work of the held prev_force over position - prev_position to the port energy, then,
    when the controller is on and the energy is negative, adds -alpha velocity to `force` (in place)
    with alpha = min(-E / (T v.v), max_damping). Stores position and force as the new held sample.
    Returns (energy, alpha).
    """
    if has_prev:
        work = 0.0
        for i in range(position.shape[0]):
            for d in range(3):
                work += prev_force[i, d] * (position[i, d] - prev_position[i, d])
        energy -= work
    alpha = 0.0
    if controller and energy < 0.0:
        vv = 0.0
        for i in range(velocity.shape[0]):
            for d in range(3):
                vv += velocity[i, d] * velocity[i, d]
        if vv > 0.0:
            alpha = min(-energy / (period * vv), max_damping)
            for i in range(force.shape[0]):
                for d in range(3):
                    force[i, d] -= alpha * velocity[i, d]
    for i in range(position.shape[0]):
        for d in range(3):
            prev_position[i, d] = position[i, d]
            prev_force[i, d] = force[i, d]
    return energy, alpha

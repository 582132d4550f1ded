"""Narrow phase of the haptic step: which facet each tool primitive touches, and how deep.

Two parts, both against the local model's candidate pairs (the broad phase's output, CSR per
tool primitive):

- continuous: `ccd_candidates` keeps the vertex-face pairs whose offset plane a tool node crosses
  from outside to inside during the step (within the face's swept box); the model runs the exact
  conservative CCD (`ccd.vertex_face`) on them and marks the crossing nodes inside, with the
  crossed face's normal (the contact side memory);
- discrete: `proximity` finds, for every tool primitive (nodes, then segments), its nearest
  candidate facet and the contact data the response needs: facet, barycentric weights of the
  closest point q, outward normal n, penetration depth (> 0), the rate of the depth, the segment
  parameter and q itself. It computes no force (that is the response's job, `penalty` or the
  compliance local model in `rendering`).

Nodes are spheres of `radius`: a node outside picks the nearest candidate face (unsigned distance
|p - q|) and is in contact if it is behind the face's plane (depth = radius - plane distance) or
in front of it closer than radius (depth = radius - |p - q|); a node inside keeps the side it
entered from: it only considers faces whose normal agrees with its entry normal (so a thin wall
it went through cannot flip the force). Segments (centerline only) add a contact where their
interior, in front of the face, comes within radius of it (capsule, depth = radius - distance
of the axis to the face).

The contact normal (the force's direction) is not the nearest face's alone: it is the sum of
the normals of every candidate face the sphere (capsule) reaches, within radius + band of it,
weighted by that reach radius + band - |p - q_f|, coplanar faces (the two triangles of a flat
quad) once (`_node_normal`, `_segment_normal`); the depth stays the nearest face's. On a flat patch every such face has the same normal, so nothing
changes; across an edge of the tessellated wall the direction turns continuously instead of
jumping from one facet's normal to the next's. With the nearest face's normal alone, a sphere
resting in a concave crease between two facets (the 14 degrees between neighbouring facets of
the AAA sac) is pushed toward the other facet by each one, which then becomes the nearest: the
force direction flips every haptic step, a relay that the one-step delays (the catheter's tip,
the wall's yielding under the last step's force) turn into a 500 Hz period-2 oscillation that
creates energy at the port (aaa_endovascular: -0.090 J over 60 s at 1000 N/m, now none). A point
probe (radius 0) reaches no face beyond the band: its normal is the nearest face's, as before.

Numba kernels: arrays in, preallocated arrays out, no validation (the model checks inputs).
"""
import math

import numpy as np
from numba import njit

from .geometry import closest_point_triangle, closest_segment_triangle, dist2_point_bary, face_normal


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




@njit(cache=True)
def proximity(pos, vel, tri, node_ptr, node_faces, seg_ptr, seg_faces, tool, tool_vel, radius, band,
              inside, entry_normal, contact_face, contact_w, contact_n, contact_depth, contact_rate,
              contact_s, contact_point, near_dist, work):
    """Closest facet and contact data of every tool primitive (nodes then segments).

    pos, vel (nv,3): local model vertex positions and velocities at the evaluation time;
    tri (nf,3) local vertex ids; node_ptr/node_faces, seg_ptr/seg_faces: CSR candidate faces per
    tool node / segment; tool, tool_vel (n_tool,3). inside (n_tool,) int8 and entry_normal
    (n_tool,3): the contact side memory (updated). Outputs per primitive: contact_face (local face,
    -1 when no contact), contact_w (weights of q), contact_n (outward normal), contact_depth
    (> 0), contact_rate (d depth/dt = -(v_tool - v_surface) . n), contact_s (segment parameter of
    the contact, 0 for nodes), contact_point (q); near_dist (n_tool,): distance of each node's
    sphere to its nearest candidate face (negative inside, inf without candidates).
    band >= 0: primitives closer than band to their face are reported too, with depth in
    (-band, 0] (the compliance model's wall may come back by up to its current yielding, so its
    solve decides those; 0 for the rigid local models: only penetrations).
    work (k, 8): scratch of the contact normal's blend, k >= the candidate faces of any primitive.
    Returns the number of primitives reported.
    """
    n_tool = tool.shape[0]
    for i in range(contact_face.shape[0]):
        contact_face[i] = -1
        contact_depth[i] = 0.0
        contact_rate[i] = 0.0
        contact_s[i] = 0.0
    count = 0

    # ---- nodes (spheres of `radius`)
    for i in range(n_tool):
        near_dist[i] = np.inf
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
        seen = 0
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
            d2 = dist2_point_bary(px, py, pz, a, bb, c, wa, wb, wc)
            work[seen, 0] = d2          # kept for the contact normal's blend
            work[seen, 1] = nx
            work[seen, 2] = ny
            work[seen, 3] = nz
            seen += 1
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
        near_dist[i] = dist
        if dist >= band or (band == 0.0 and dist >= 0.0):
            inside[i] = 0
            continue
        # the contact normal: the faces the sphere touches, each weighted by how far it is in
        # (continuous across the edges of the tessellated wall; see the module docstring)
        bnx, bny, bnz = _node_normal(work, seen, radius + band, bnx, bny, bnz)
        if dist < 0.0:
            inside[i] = 1
            entry_normal[i, 0] = bnx
            entry_normal[i, 1] = bny
            entry_normal[i, 2] = bnz
        else:
            inside[i] = 0
        va = vel[tri[best_f, 0]]
        vb = vel[tri[best_f, 1]]
        vc = vel[tri[best_f, 2]]
        # relative normal velocity of the tool with respect to the surface at the contact point
        vn = ((tool_vel[i, 0] - (bwa * va[0] + bwb * vb[0] + bwc * vc[0])) * bnx
              + (tool_vel[i, 1] - (bwa * va[1] + bwb * vb[1] + bwc * vc[1])) * bny
              + (tool_vel[i, 2] - (bwa * va[2] + bwb * vb[2] + bwc * vc[2])) * bnz)
        _store(i, best_f, bwa, bwb, bwc, bnx, bny, bnz, -dist, -vn, 0.0, pos, tri,
               contact_face, contact_w, contact_n, contact_depth, contact_rate, contact_s, contact_point)
        count += 1

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
        if dist >= band or (band == 0.0 and dist >= 0.0):
            continue
        bnx, bny, bnz = _segment_normal(p0, p1, pos, tri, seg_faces, seg_ptr[sgi], seg_ptr[sgi + 1], radius + band,
                                        work, bnx, bny, bnz)
        va = vel[tri[best_f, 0]]
        vb = vel[tri[best_f, 1]]
        vc = vel[tri[best_f, 2]]
        tvx = (1.0 - bs) * tool_vel[sgi, 0] + bs * tool_vel[sgi + 1, 0]
        tvy = (1.0 - bs) * tool_vel[sgi, 1] + bs * tool_vel[sgi + 1, 1]
        tvz = (1.0 - bs) * tool_vel[sgi, 2] + bs * tool_vel[sgi + 1, 2]
        vn = ((tvx - (bwa * va[0] + bwb * vb[0] + bwc * vc[0])) * bnx
              + (tvy - (bwa * va[1] + bwb * vb[1] + bwc * vc[1])) * bny
              + (tvz - (bwa * va[2] + bwb * vb[2] + bwc * vc[2])) * bnz)
        _store(n_tool + sgi, best_f, bwa, bwb, bwc, bnx, bny, bnz, -dist, -vn, bs, pos, tri,
               contact_face, contact_w, contact_n, contact_depth, contact_rate, contact_s, contact_point)
        count += 1
    return count


#: Faces whose normals agree to this (1 - cos) are one plane in the contact normal's blend.
COPLANAR = 1e-9


@njit(cache=True)
def _reach(work, count, w, nx, ny, nz):
    """Add a face within reach (weight w > 0, normal n) to the blend in work[:, 4:8]: a face
    coplanar with one already there (the two triangles of a flat quad) counts once, with the larger
    weight. Returns the new count."""
    for e in range(count):
        if nx * work[e, 5] + ny * work[e, 6] + nz * work[e, 7] > 1.0 - COPLANAR:
            if w > work[e, 4]:
                work[e, 4] = w
            return count
    work[count, 4] = w
    work[count, 5] = nx
    work[count, 6] = ny
    work[count, 7] = nz
    return count + 1


@njit(cache=True)
def _blend(work, count, bnx, bny, bnz):
    """The unit sum of the weighted normals in work[:count, 4:8]; (bnx, bny, bnz) when empty."""
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for e in range(count):
        sx += work[e, 4] * work[e, 5]
        sy += work[e, 4] * work[e, 6]
        sz += work[e, 4] * work[e, 7]
    norm = math.sqrt(sx * sx + sy * sy + sz * sz)
    if norm <= 0.0:
        return bnx, bny, bnz
    return sx / norm, sy / norm, sz / norm


@njit(cache=True)
def _node_normal(work, seen, reach, bnx, bny, bnz):
    """Contact normal of a node sphere from its `seen` candidate faces (work[:, 0:4]: squared
    distance to the face, normal; the side filter already applied): the normals of the faces
    closer than reach = radius + band (the sphere's overlap, plus the band), each weighted by
    reach - |p - q_f|, coplanar faces once, faces on the nearest face's side only (bnx, bny, bnz:
    that face's normal, returned unchanged when no face is within reach: a point probe, or a node
    deeper than radius + band behind the wall)."""
    count = 0
    for e in range(seen):
        nx = work[e, 1]
        ny = work[e, 2]
        nz = work[e, 3]
        if nx * bnx + ny * bny + nz * bnz <= 0.0:
            continue
        w = reach - math.sqrt(work[e, 0])
        if w > 0.0:
            count = _reach(work, count, w, nx, ny, nz)
    return _blend(work, count, bnx, bny, bnz)


@njit(cache=True)
def _segment_normal(p0, p1, pos, tri, faces, start, stop, reach, work, bnx, bny, bnz):
    """`_node_normal` for a segment capsule: the faces whose closest point is in the segment's
    interior and closer than reach = radius + band, weighted by reach - distance."""
    count = 0
    for j in range(start, stop):
        f = faces[j]
        a = pos[tri[f, 0]]
        bb = pos[tri[f, 1]]
        c = pos[tri[f, 2]]
        nx, ny, nz = face_normal(a, bb, c)
        if nx * bnx + ny * bny + nz * bnz <= 0.0:
            continue
        s0 = (p0[0] - a[0]) * nx + (p0[1] - a[1]) * ny + (p0[2] - a[2]) * nz
        s1 = (p1[0] - a[0]) * nx + (p1[1] - a[1]) * ny + (p1[2] - a[2]) * nz
        if s0 <= 0.0 or s1 <= 0.0:
            continue
        s, wa, wb, wc, d2 = closest_segment_triangle(p0, p1, a, bb, c)
        if s <= 1e-9 or s >= 1.0 - 1e-9:
            continue
        w = reach - math.sqrt(d2)
        if w > 0.0:
            count = _reach(work, count, w, nx, ny, nz)
    return _blend(work, count, bnx, bny, bnz)


@njit(cache=True)
def _store(k, f, wa, wb, wc, nx, ny, nz, depth, rate, s, pos, tri,
           contact_face, contact_w, contact_n, contact_depth, contact_rate, contact_s, contact_point):
    contact_face[k] = f
    contact_w[k, 0] = wa
    contact_w[k, 1] = wb
    contact_w[k, 2] = wc
    contact_n[k, 0] = nx
    contact_n[k, 1] = ny
    contact_n[k, 2] = nz
    contact_depth[k] = depth
    contact_rate[k] = rate
    contact_s[k] = s
    for d in range(3):
        contact_point[k, d] = (wa * pos[tri[f, 0], d] + wb * pos[tri[f, 1], d] + wc * pos[tri[f, 2], d])

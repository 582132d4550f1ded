"""Narrow phase of the haptic step: which facet each tool primitive touches, and how deep.

Two parts, both against the local model's candidate pairs (the broad phase's output, CSR per
tool primitive):

- continuous: `ccd_candidates` keeps the vertex-face pairs whose offset plane a tool node crosses
  from outside to inside during the step (within the face's swept box); the model runs the exact
  conservative CCD (`ccd.vertex_face`) on them and marks the crossing nodes inside, with the
  crossed face's normal (the contact side memory);
- discrete: `proximity` finds, for every tool primitive (nodes, then segments), its contact data
  for the response: facet, barycentric weights of the closest point q, outward normal n,
  penetration depth, the rate of the depth, the segment parameter and q itself. It computes no
  force (that is the response's job, `penalty` or the compliance local model in `rendering`).

The depth is a continuous function of the tool's configuration, so the force is too:

- **Signed distance.** A point's depth is measured by its signed distance sd to the wall: the
  distance to the nearest candidate face, negative behind the wall, the side judged by the
  angle-weighted pseudo-normal of the nearest feature (the face, the edge or the vertex the
  closest point lies on; Baerentzen and Aanaes 2005). That is correct on both sides of a closed
  shell (the lumen side and the outer side of the aneurysm wall) and of an open surface; "behind
  the nearest face's plane" is not: seen from the lumen, every face of the outer surface has the
  lumen behind its plane (a catheter node 8 mm inside the lumen would be 9 mm "deep" by that
  rule). A point behind faces farther than `trust` (the reach within which the broad phase's
  candidates are complete, plus its own motion this step) cannot tell which side it is on and is
  not in contact, unless it remembers entering the wall.
- **Nodes** are spheres of `radius`: depth = radius - sd, from zero when the sphere first touches,
  continuing past the radius when the node goes behind the wall. A node inside (depth > 0) keeps
  the side it entered from: it only considers faces whose normal agrees with its entry normal, so
  a thin wall it went through cannot flip the force.
- **Segments** (centerline only) are capsules. Their contact is what the segment's depth profile
  D(s) = radius - sd(p(s)) adds to the linear interpolation of its ends' depths (only the ends'
  positive depths count): max over s of D(s) - ((1 - s) max(D(0), 0) + s max(D(1), 0)). On a flat
  wall the profile is linear and the segment adds nothing (its end spheres carry it); over a ridge
  or a vertex between its ends it adds the extra overlap, growing from zero as the ridge rises and
  vanishing at either end: a capsule can neither appear with a finite depth when its closest point
  leaves an end nor drop out when its depth passes the radius. The profile is sampled at
  CAPSULE_SAMPLES interior points and its maximum refined by golden section; with both ends out of
  contact it is the segment's exact closest approach. The ends' depths are measured as the samples
  are (the segment's candidates and remembered side), so the excess is zero at both ends.
- **The contact normal** (the force's direction) is not the nearest face's alone: it is the
  weighted sum of the normals of the candidate faces within max(radius + band, d + NORMAL_BLEND_LENGTH)
  of the point (d: the nearest face's distance), each weighted by how far inside that reach it is,
  coplanar faces (the two triangles of a flat quad) once, faces on the nearest face's side only.
  On a flat patch every such face has the same normal; across an edge or around a vertex of the
  tessellated wall the direction turns continuously instead of jumping from one facet's normal to
  the next's. With the nearest face's normal alone a sphere resting in a concave crease between two
  facets, or a probe just behind a vertex, is pushed toward the other facet by each one, which then
  becomes the nearest: a relay every haptic step, which the one-step delays (the catheter's tip,
  the wall's yielding under the last step's force) turn into a 500 Hz oscillation.

Numba kernels: arrays in, preallocated arrays out, no validation (the model checks inputs).
"""
import math

import numpy as np
from numba import njit

from .geometry import closest_point_triangle, closest_segment_triangle, face_normal, vertex_angle


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
def proximity(pos, vel, tri, node_ptr, node_faces, seg_ptr, seg_faces, tool, tool_vel, radius, band, trust,
              inside, entry_normal, contact_face, contact_w, contact_n, contact_depth, contact_rate,
              contact_s, contact_point, near_dist, work):
    """Closest facet and contact data of every tool primitive (nodes then segments).

    pos, vel (nv,3): local model vertex positions and velocities at the evaluation time;
    tri (nf,3) local vertex ids; node_ptr/node_faces, seg_ptr/seg_faces: CSR candidate faces per
    tool node / segment; tool, tool_vel (n_tool,3). inside (n_tool,) int8 and entry_normal
    (n_tool,3): the contact side memory (updated). Outputs per primitive: contact_face (local face,
    -1 when no contact), contact_w (weights of q), contact_n (outward normal), contact_depth,
    contact_rate (d depth/dt = -(v_tool - v_surface) . n), contact_s (segment parameter of the
    contact, 0 for nodes), contact_point (q); near_dist (n_tool,): signed distance of each node's
    sphere to the wall (sd - radius: negative when it overlaps, inf when nothing is known).
    band >= 0: primitives closer than band to the wall are reported too, with depth in
    (-band, 0] (the compliance model's wall may come back by up to its current yielding, so its
    solve decides those; 0 for the rigid local models: only penetrations).
    trust (n_tool,) > 0: how far behind the wall each node can be found without remembering entering
    it: the reach within which the broad phase's candidates are complete, plus the node's motion
    this step (it may have crossed the surface within the step); a node of no remembered side found
    deeper is not in contact (its candidates cannot tell which side it is on). A segment takes the
    larger of its ends'.
    work (k, WORK_COLUMNS): scratch, k >= the candidate faces of any primitive.
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
        seen, best_e = _candidates(px, py, pz, pos, tri, node_faces, node_ptr[i], node_ptr[i + 1],
                                   inside[i], entry_normal[i, 0], entry_normal[i, 1], entry_normal[i, 2], work)
        if best_e < 0:
            inside[i] = 0
            continue
        sd = _signed_distance(px, py, pz, pos, tri, work, seen, best_e)
        if sd < 0.0 and -sd > trust[i] and not inside[i]:
            inside[i] = 0
            continue    # behind faces it cannot be sure of (the far side of the wall, seen from the lumen)
        dist = sd - radius
        near_dist[i] = dist
        if dist >= band or (band == 0.0 and dist >= 0.0):
            inside[i] = 0
            continue
        bnx, bny, bnz = _blend_normal(work, seen, best_e, radius + band)
        if dist < 0.0:
            inside[i] = 1
            entry_normal[i, 0] = bnx
            entry_normal[i, 1] = bny
            entry_normal[i, 2] = bnz
        else:
            inside[i] = 0
        f = int(work[best_e, FACE])
        _contact(i, f, px, py, pz, tool_vel[i, 0], tool_vel[i, 1], tool_vel[i, 2], bnx, bny, bnz, -dist, 0.0,
                 pos, vel, tri, contact_face, contact_w, contact_n, contact_depth, contact_rate, contact_s,
                 contact_point)
        count += 1

    # ---- segment interiors (capsules): what the segment's sampled depth profile adds to the
    # linear interpolation of its end spheres' depths (zero on a flat wall; continuous, from 0)
    n_seg = seg_ptr.shape[0] - 1
    for sgi in range(n_seg):
        start = seg_ptr[sgi]
        stop = seg_ptr[sgi + 1]
        if start == stop:
            continue
        p0 = tool[sgi]
        p1 = tool[sgi + 1]
        behind = max(trust[sgi], trust[sgi + 1])
        # the remembered side of the segment: that of its distal end when inside the wall, else that
        # of the other end (a fixed preference: a choice by depth would flip as two depths cross)
        side = 0
        snx = 0.0
        sny = 0.0
        snz = 0.0
        if inside[sgi] and inside[sgi + 1] and (entry_normal[sgi, 0] * entry_normal[sgi + 1, 0]
                                                + entry_normal[sgi, 1] * entry_normal[sgi + 1, 1]
                                                + entry_normal[sgi, 2] * entry_normal[sgi + 1, 2]) <= 0.0:
            continue    # its ends entered the wall from opposite sides: they carry its contact
        end = sgi + 1 if inside[sgi + 1] else (sgi if inside[sgi] else -1)
        if end >= 0:
            side = 1
            snx = entry_normal[end, 0]
            sny = entry_normal[end, 1]
            snz = entry_normal[end, 2]
        # no face within radius + band of the segment: no sample in reach
        nearest2 = np.inf
        nearest_s = 0.0
        reach = radius + band
        for j in range(start, stop):
            f = seg_faces[j]
            a = pos[tri[f, 0]]
            bb = pos[tri[f, 1]]
            c = pos[tri[f, 2]]
            nx, ny, nz = face_normal(a, bb, c)
            h0 = (p0[0] - a[0]) * nx + (p0[1] - a[1]) * ny + (p0[2] - a[2]) * nz
            h1 = (p1[0] - a[0]) * nx + (p1[1] - a[1]) * ny + (p1[2] - a[2]) * nz
            if h0 >= reach and h1 >= reach:
                continue    # the whole segment is farther than reach in front of the face's plane
            s, wa, wb, wc, d2 = closest_segment_triangle(p0, p1, a, bb, c)
            if d2 < nearest2:
                nearest2 = d2
                nearest_s = s
        if nearest2 >= reach * reach:
            continue
        # the ends' depths measured as the samples are (the segment's candidates and side), so the
        # excess is zero at both ends whatever side each end itself remembers
        e0 = max(_excess(0.0, p0, p1, 0.0, 0.0, radius, behind, pos, tri, seg_faces, start, stop, side,
                         snx, sny, snz, work), 0.0)
        e1 = max(_excess(1.0, p0, p1, 0.0, 0.0, radius, behind, pos, tri, seg_faces, start, stop, side,
                         snx, sny, snz, work), 0.0)
        if e0 == 0.0 and e1 == 0.0 and 0.0 < nearest_s < 1.0 and nearest2 > 0.0:
            # ends out of contact: the profile's maximum is the segment's closest approach to the
            # wall (exact), when that point is in front of the wall
            excess = _excess(nearest_s, p0, p1, e0, e1, radius, behind, pos, tri, seg_faces, start, stop, side,
                             snx, sny, snz, work)
            if excess <= radius:      # sd >= 0: the closest approach is in front of the wall
                _capsule(sgi, n_tool, nearest_s, excess, p0, p1, tool_vel, radius, band, pos, vel, tri,
                         seg_faces, start, stop, side, snx, sny, snz, work, contact_face, contact_w, contact_n,
                         contact_depth, contact_rate, contact_s, contact_point)
                count += contact_face[n_tool + sgi] >= 0
                continue
        best_excess = -np.inf
        best_k = 0
        for k in range(1, CAPSULE_SAMPLES + 1):
            excess = _excess(k / (CAPSULE_SAMPLES + 1.0), p0, p1, e0, e1, radius, behind, pos, tri, seg_faces,
                             start, stop, side, snx, sny, snz, work)
            if excess > best_excess:
                best_excess = excess
                best_k = k
        if not (best_excess > -band - CAPSULE_REFINE_MARGIN * radius):
            continue
        # the profile's maximum near the best sample (golden section on its two neighbours' span;
        # the ends themselves add nothing: their excess is <= 0 by construction)
        lo = (best_k - 1.0) / (CAPSULE_SAMPLES + 1.0)
        hi = (best_k + 1.0) / (CAPSULE_SAMPLES + 1.0)
        x1 = hi - GOLDEN * (hi - lo)
        x2 = lo + GOLDEN * (hi - lo)
        f1 = _excess(x1, p0, p1, e0, e1, radius, behind, pos, tri, seg_faces, start, stop, side, snx, sny, snz, work)
        f2 = _excess(x2, p0, p1, e0, e1, radius, behind, pos, tri, seg_faces, start, stop, side, snx, sny, snz, work)
        for _ in range(CAPSULE_REFINE_STEPS):
            if f1 >= f2:
                hi = x2
                x2 = x1
                f2 = f1
                x1 = hi - GOLDEN * (hi - lo)
                f1 = _excess(x1, p0, p1, e0, e1, radius, behind, pos, tri, seg_faces, start, stop, side,
                             snx, sny, snz, work)
            else:
                lo = x1
                x1 = x2
                f1 = f2
                x2 = lo + GOLDEN * (hi - lo)
                f2 = _excess(x2, p0, p1, e0, e1, radius, behind, pos, tri, seg_faces, start, stop, side,
                             snx, sny, snz, work)
        best_s = best_k / (CAPSULE_SAMPLES + 1.0)
        if f1 > best_excess:
            best_excess = f1
            best_s = x1
        if f2 > best_excess:
            best_excess = f2
            best_s = x2
        _capsule(sgi, n_tool, best_s, best_excess, p0, p1, tool_vel, radius, band, pos, vel, tri,
                 seg_faces, start, stop, side, snx, sny, snz, work, contact_face, contact_w, contact_n,
                 contact_depth, contact_rate, contact_s, contact_point)
        count += contact_face[n_tool + sgi] >= 0
    return count


@njit(cache=True)
def _capsule(sgi, n_tool, s, excess, p0, p1, tool_vel, radius, band, pos, vel, tri, faces, start, stop, side,
             snx, sny, snz, work, contact_face, contact_w, contact_n, contact_depth, contact_rate, contact_s,
             contact_point):
    """Store segment sgi's contact at parameter s with depth `excess` (over its ends' depths), if it
    is one."""
    if not (excess > -band and (band > 0.0 or excess > 0.0)):
        return
    cx = p0[0] + s * (p1[0] - p0[0])
    cy = p0[1] + s * (p1[1] - p0[1])
    cz = p0[2] + s * (p1[2] - p0[2])
    seen, best_e = _candidates(cx, cy, cz, pos, tri, faces, start, stop, side, snx, sny, snz, work)
    bnx, bny, bnz = _blend_normal(work, seen, best_e, radius + band)
    _contact(n_tool + sgi, int(work[best_e, FACE]), cx, cy, cz,
             (1.0 - s) * tool_vel[sgi, 0] + s * tool_vel[sgi + 1, 0],
             (1.0 - s) * tool_vel[sgi, 1] + s * tool_vel[sgi + 1, 1],
             (1.0 - s) * tool_vel[sgi, 2] + s * tool_vel[sgi + 1, 2],
             bnx, bny, bnz, excess, s, pos, vel, tri, contact_face, contact_w, contact_n, contact_depth,
             contact_rate, contact_s, contact_point)
    # the excess changes as the point's depth less the ends' (those in contact): the rate of what
    # this contact measures (on a flat wall the segment's sinking is its ends', not its own)
    _less_ends(n_tool + sgi, sgi, s, contact_face, contact_depth, contact_rate)


@njit(cache=True)
def clearance(pos, tri, node_ptr, node_faces, tool, i, radius, inside, entry_normal, work, out):
    """Node i's sphere's clearance to the wall where it does not touch it: out (4,) = (gap, normal)
    with gap = sd - radius >= 0 (m) and the contact normal the node would meet there (blended as a
    contact's); gap = inf when the node overlaps the wall or no candidate face is near enough to
    know (the broad phase's reach, as `proximity` decides)."""
    out[0] = np.inf
    px = tool[i, 0]
    py = tool[i, 1]
    pz = tool[i, 2]
    seen, best_e = _candidates(px, py, pz, pos, tri, node_faces, node_ptr[i], node_ptr[i + 1], inside[i],
                               entry_normal[i, 0], entry_normal[i, 1], entry_normal[i, 2], work)
    if best_e < 0:
        return
    gap = _signed_distance(px, py, pz, pos, tri, work, seen, best_e) - radius
    if not gap >= 0.0:
        return
    out[1], out[2], out[3] = _blend_normal(work, seen, best_e, radius)
    out[0] = gap


@njit(cache=True)
def normal_jacobian(pos, tri, node_ptr, node_faces, tool, i, reach, inside, entry_normal, h, work, out):
    """out (3, 3) = d n / d p of node i's contact normal (blended as `proximity` blends it, faces
    within ``reach`` = radius + band) by central differences of step h (m); zeros where a side has
    no candidate face. The contact force f n turns with the node as it slides over the facets: its
    geometric stiffness -f d n / d p, which the tip's stiffness must count: near a facet edge it
    can be the whole of K across the normal, and a catheter tip pressed hard and rolled slides to
    and fro every step without it."""
    for r in range(3):
        for c in range(3):
            out[r, c] = 0.0
    for c in range(3):
        for sign in (1.0, -1.0):
            px = tool[i, 0] + (sign * h if c == 0 else 0.0)
            py = tool[i, 1] + (sign * h if c == 1 else 0.0)
            pz = tool[i, 2] + (sign * h if c == 2 else 0.0)
            seen, best_e = _candidates(px, py, pz, pos, tri, node_faces, node_ptr[i], node_ptr[i + 1], inside[i],
                                       entry_normal[i, 0], entry_normal[i, 1], entry_normal[i, 2], work)
            if best_e < 0:
                for r in range(3):
                    out[r, c] = 0.0
                break
            nx, ny, nz = _blend_normal(work, seen, best_e, reach)
            out[0, c] += sign * nx / (2.0 * h)
            out[1, c] += sign * ny / (2.0 * h)
            out[2, c] += sign * nz / (2.0 * h)


@njit(cache=True)
def _less_ends(k, sgi, s, contact_face, contact_depth, rate):
    """rate[k] (segment sgi's contact at s) minus the ends' rates, weighted as the excess weights
    their depths, for the ends in contact."""
    if contact_face[sgi] >= 0 and contact_depth[sgi] > 0.0:
        rate[k] -= (1.0 - s) * rate[sgi]
    if contact_face[sgi + 1] >= 0 and contact_depth[sgi + 1] > 0.0:
        rate[k] -= s * rate[sgi + 1]


@njit(cache=True)
def approach(contact_face, contact_w, contact_n, contact_s, contact_depth, tri, vel, tool_vel, tool_vel_older, n_tool,
             hold, ahead, ahead_before):
    """ahead (n_prim,): the depth change each contact's tool motion predicts over the next hold
    interval, from its approach speed -(v_tool - v_surface) . n over the last step (tool_vel) and
    the step before (tool_vel_older), limited: the slower of the two where they agree in sign, zero
    where they do not (minmod). A steady approach is predicted exactly; a reversal, a period-2
    oscillation (which a one-step prediction would feed back) or a start from rest predicts no
    change; a jump the tool has just made is not carried into the next hold (their mean would carry
    it into two, and the force would dip and rise again after a dead stop). A segment's is less its
    ends' predicted positive depths (0 without a contact).

    ahead_before (n_prim,): last step's prediction, in: it relaxes toward this step's (`_relaxed`)
    instead of dropping to it while the tool keeps its direction; out: this step's."""
    for i in range(contact_face.shape[0]):
        ahead[i] = 0.0
        f = contact_face[i]
        if f < 0:
            continue
        vn1 = 0.0
        vn0 = 0.0
        for d in range(3):
            surface = (contact_w[i, 0] * vel[tri[f, 0], d] + contact_w[i, 1] * vel[tri[f, 1], d]
                       + contact_w[i, 2] * vel[tri[f, 2], d])
            if i < n_tool:
                t1 = tool_vel[i, d]
                t0 = tool_vel_older[i, d]
            else:
                s = contact_s[i]
                j = i - n_tool
                t1 = (1.0 - s) * tool_vel[j, d] + s * tool_vel[j + 1, d]
                t0 = (1.0 - s) * tool_vel_older[j, d] + s * tool_vel_older[j + 1, d]
            vn1 += (t1 - surface) * contact_n[i, d]
            vn0 += (t0 - surface) * contact_n[i, d]
        if vn1 * vn0 > 0.0:
            ahead[i] = -(vn1 if abs(vn1) < abs(vn0) else vn0) * hold
        ahead[i] = _relaxed(ahead[i], ahead_before[i], -vn1 * hold)
    # a segment's depth is its excess over its ends' positive depths: its predicted change is the
    # point's less what its ends' positive depths are predicted to gain (an end about to touch takes
    # over the segment's overlap near it; counting both gave a first touch twice the force)
    for i in range(n_tool, contact_face.shape[0]):
        if contact_face[i] < 0:
            continue
        j = i - n_tool
        s = contact_s[i]
        for end, weight in ((j, 1.0 - s), (j + 1, s)):
            if contact_face[end] >= 0:
                d = contact_depth[end]
                ahead[i] -= weight * (max(d + ahead[end], 0.0) - max(d, 0.0))
    for i in range(contact_face.shape[0]):
        ahead_before[i] = ahead[i]


#: Fraction of the prediction a contact's hold may drop per step beyond what the tool's own motion
#: in the step explains (`_relaxed`): after a dead stop the held force returns to the law within
#: about 10 steps (0.75^10 = 6 %).
PREDICTION_RELAX = 0.25


@njit(cache=True)
def _relaxed(target, before, moved):
    """The prediction of a contact whose last step's was ``before`` and whose tool moved its depth
    by ``moved`` in this step, given this step's limited prediction ``target``: ``target``, except
    that while the tool keeps the direction ``before`` predicted and ``target`` is smaller, it may
    drop by at most 2 |moved| + PREDICTION_RELAX |before|.

    Why: the held force is the law's mean over the predicted depths, k (d + p / 2) for the linear
    law, so a prediction that drops by more than twice the step's own motion turns the force back
    against the motion: after a sharp deceleration (a dead stop, an impact) it would fall, and rise
    again as the tool crept on. A prediction too large while the tool slows
    does more work against it than it gets back (dissipative), and none while it rests; against the
    motion (a reversal) it would hand energy back, so there it drops at once."""
    if before == 0.0 or moved * before < 0.0 or target * before < 0.0 or abs(target) >= abs(before):
        return target
    allowed = 2.0 * abs(moved) + PREDICTION_RELAX * abs(before)
    if abs(before) - abs(target) <= allowed:
        return target
    return before - allowed if before > 0.0 else before + allowed


@njit(cache=True)
def _excess(s, p0, p1, e0, e1, radius, trust, pos, tri, faces, start, stop, side, snx, sny, snz, work):
    """How much deeper the sphere at parameter s of segment [p0, p1] reaches into the wall than the
    linear interpolation of its ends' depths e0, e1 (>= 0: only the ends' contacts count); -inf when
    no candidate face is near enough to know."""
    cx = p0[0] + s * (p1[0] - p0[0])
    cy = p0[1] + s * (p1[1] - p0[1])
    cz = p0[2] + s * (p1[2] - p0[2])
    seen, best_e = _candidates(cx, cy, cz, pos, tri, faces, start, stop, side, snx, sny, snz, work)
    if best_e < 0:
        return -np.inf
    sd = _signed_distance(cx, cy, cz, pos, tri, work, seen, best_e)
    if sd < 0.0 and -sd > trust and side == 0:
        return -np.inf
    return (radius - sd) - ((1.0 - s) * e0 + s * e1)


#: Golden-section steps that refine a segment's deepest point between samples (an end in contact;
#: with both ends free the closest approach is exact): the bracket shrinks to 0.618^28 = 1.4e-6 of
#: two sample spacings, so the contact's parameter (which splits the force between the two ends) is
#: right to 4e-7, and its depth to round-off (its error is quadratic in the parameter's).
CAPSULE_REFINE_STEPS = 28
GOLDEN = 0.6180339887498949
#: A segment whose best sample is this fraction of the radius short of a contact is still refined
#: (its maximum between samples can reach further than the samples).
CAPSULE_REFINE_MARGIN = 0.25

#: Interior samples of a segment's depth profile (s = k / (CAPSULE_SAMPLES + 1)): 0.625 mm apart on
#: the catheter's 5 mm links, below its 1 mm radius, so a facet vertex cannot hide between two.
CAPSULE_SAMPLES = 7

#: Smoothing length (m) of the contact normal: faces within this of the nearest one share the
#: normal, so a point deeper than its radius (a probe, a deep node) does not relay between the
#: faces around a vertex or an edge.
NORMAL_BLEND_LENGTH = 1e-4

#: Faces whose normals agree to this (1 - cos) are one plane in the contact normal's blend.
COPLANAR = 1e-9

#: Columns of the scratch `work` per candidate face: squared distance, normal (3), blend (4),
#: closest point (3), face id.
D2, NX, NY, NZ, BW, BX, BY, BZ, QX, QY, QZ, FACE = range(12)
WORK_COLUMNS = 12


@njit(cache=True)
def _candidates(px, py, pz, pos, tri, faces, start, stop, side, enx, eny, enz, work):
    """Distance, normal and closest point of p to each candidate face faces[start:stop] into
    work[:seen] (faces facing away from the remembered side (enx, eny, enz) left out when side);
    returns (seen, row of the nearest, -1 when none)."""
    seen = 0
    best = np.inf
    best_e = -1
    for j in range(start, stop):
        f = faces[j]
        a = pos[tri[f, 0]]
        bb = pos[tri[f, 1]]
        c = pos[tri[f, 2]]
        nx, ny, nz = face_normal(a, bb, c)
        if side and nx * enx + ny * eny + nz * enz <= 0.0:
            continue  # the far side of the wall: not the side this point came from
        wa, wb, wc = closest_point_triangle(px, py, pz, a, bb, c)
        qx = wa * a[0] + wb * bb[0] + wc * c[0]
        qy = wa * a[1] + wb * bb[1] + wc * c[1]
        qz = wa * a[2] + wb * bb[2] + wc * c[2]
        d2 = (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2
        work[seen, D2] = d2
        work[seen, NX] = nx
        work[seen, NY] = ny
        work[seen, NZ] = nz
        work[seen, QX] = qx
        work[seen, QY] = qy
        work[seen, QZ] = qz
        work[seen, FACE] = f
        if d2 < best:
            best = d2
            best_e = seen
        seen += 1
    return seen, best_e


@njit(cache=True)
def _signed_distance(px, py, pz, pos, tri, work, seen, best_e):
    """Signed distance of p to the wall: the distance to the nearest candidate face, negative when p
    is behind the wall, judged by the angle-weighted pseudo-normal of the nearest feature (face,
    edge or vertex; Baerentzen and Aanaes 2005) from the faces sharing the closest point: correct
    on either side of a closed or open shell, where "behind the nearest face's plane" is not
    (seen from the lumen, the outer surface's faces all have the lumen behind their plane)."""
    qx = work[best_e, QX]
    qy = work[best_e, QY]
    qz = work[best_e, QZ]
    d = math.sqrt(work[best_e, D2])
    tol = 1e-12 + 1e-9 * (d + abs(qx) + abs(qy) + abs(qz))
    tol2 = tol * tol
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for e in range(seen):
        if (work[e, QX] - qx) ** 2 + (work[e, QY] - qy) ** 2 + (work[e, QZ] - qz) ** 2 > tol2:
            continue
        f = int(work[e, FACE])
        weight = 1.0        # q inside the face or on an edge: the faces count alike
        for corner in range(3):
            v = pos[tri[f, corner]]
            if (v[0] - qx) ** 2 + (v[1] - qy) ** 2 + (v[2] - qz) ** 2 <= tol2:
                u = pos[tri[f, (corner + 1) % 3]]
                w = pos[tri[f, (corner + 2) % 3]]
                weight = vertex_angle(v, u, w)    # q at a vertex: weighted by the face's angle there
                break
        sx += weight * work[e, NX]
        sy += weight * work[e, NY]
        sz += weight * work[e, NZ]
    if (px - qx) * sx + (py - qy) * sy + (pz - qz) * sz < 0.0:
        return -d
    return d


@njit(cache=True)
def _blend_normal(work, seen, best_e, reach):
    """Contact normal of a point from its candidate faces (work[:seen]): the normals of the faces
    within max(reach, d + NORMAL_BLEND_LENGTH) of it (d: the nearest face's distance; reach: the
    radius plus the band), each weighted by how far inside that distance it is, coplanar faces (the
    two triangles of a flat quad) once, faces facing the nearest face's side only. Continuous in
    the point, so the force turns smoothly across the edges and vertices of the tessellated wall
    (see the module docstring)."""
    bnx = work[best_e, NX]
    bny = work[best_e, NY]
    bnz = work[best_e, NZ]
    limit = max(reach, math.sqrt(work[best_e, D2]) + NORMAL_BLEND_LENGTH)
    count = 0
    for e in range(seen):
        nx = work[e, NX]
        ny = work[e, NY]
        nz = work[e, NZ]
        if nx * bnx + ny * bny + nz * bnz <= 0.0:
            continue
        w = limit - math.sqrt(work[e, D2])
        if w > 0.0:
            count = _reach(work, count, w, nx, ny, nz)
    return _blend(work, count, bnx, bny, bnz)


@njit(cache=True)
def _reach(work, count, w, nx, ny, nz):
    """Add a face within reach (weight w > 0, normal n) to the blend in work[:, BW:BZ+1] (rows
    already read): a face coplanar with one already there counts once, with the larger weight.
    Returns the new count."""
    for e in range(count):
        if nx * work[e, BX] + ny * work[e, BY] + nz * work[e, BZ] > 1.0 - COPLANAR:
            if w > work[e, BW]:
                work[e, BW] = w
            return count
    work[count, BW] = w
    work[count, BX] = nx
    work[count, BY] = ny
    work[count, BZ] = nz
    return count + 1


@njit(cache=True)
def _blend(work, count, bnx, bny, bnz):
    """The unit sum of the weighted normals in work[:count, BW:BZ+1]; (bnx, bny, bnz) when empty."""
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for e in range(count):
        sx += work[e, BW] * work[e, BX]
        sy += work[e, BW] * work[e, BY]
        sz += work[e, BW] * work[e, BZ]
    norm = math.sqrt(sx * sx + sy * sy + sz * sz)
    if norm <= 0.0:
        return bnx, bny, bnz
    return sx / norm, sy / norm, sz / norm


@njit(cache=True)
def _contact(k, f, px, py, pz, tvx, tvy, tvz, nx, ny, nz, depth, s, pos, vel, tri,
             contact_face, contact_w, contact_n, contact_depth, contact_rate, contact_s, contact_point):
    """Store primitive k's contact with face f at the point of f closest to p (tool velocity tv at p):
    the rate is the relative normal velocity of the tool with respect to the surface there."""
    a = pos[tri[f, 0]]
    bb = pos[tri[f, 1]]
    c = pos[tri[f, 2]]
    wa, wb, wc = closest_point_triangle(px, py, pz, a, bb, c)
    va = vel[tri[f, 0]]
    vb = vel[tri[f, 1]]
    vc = vel[tri[f, 2]]
    vn = ((tvx - (wa * va[0] + wb * vb[0] + wc * vc[0])) * nx
          + (tvy - (wa * va[1] + wb * vb[1] + wc * vc[1])) * ny
          + (tvz - (wa * va[2] + wb * vb[2] + wc * vc[2])) * nz)
    contact_face[k] = f
    contact_w[k, 0] = wa
    contact_w[k, 1] = wb
    contact_w[k, 2] = wc
    contact_n[k, 0] = nx
    contact_n[k, 1] = ny
    contact_n[k, 2] = nz
    contact_depth[k] = depth
    contact_rate[k] = -vn
    contact_s[k] = s
    for d in range(3):
        contact_point[k, d] = wa * a[d] + wb * bb[d] + wc * c[d]

"""Numba kernels of the contact response: penalty laws and the force distribution.

Arrays in, preallocated arrays out, no validation (see `penalty` for the laws and conventions).
Penalty laws (force magnitude along the outward normal n, on the tool; delta = penetration depth,
rate = d delta/dt = -(v_rel . n)):
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


@njit(cache=True)
def penalty_magnitude(depth, rate, law, k, b, d0, ahead):
    """Normal force magnitude (along the outward normal, on the tool) for penetration depth >= 0.

    ahead: the depth change predicted over the interval the force will be held (the tool's depth
    rate times the step, or 0): the elastic part is its mean over [depth, depth + ahead]
    (`elastic_mean`), which starts before the contact does when the tool will touch within the
    interval (depth <= 0 < depth + ahead); with ahead = 0 the elastic force at the sampled depth.
    The damping acts in contact only."""
    if depth <= 0.0:
        if depth + ahead <= 0.0:
            return 0.0
        return elastic_mean(depth, depth + ahead, law, k, d0)
    elastic = elastic_mean(depth, depth + ahead, law, k, d0)
    if law == LAW_HUNT_CROSSLEY:
        f = elastic + b * (depth / d0) * rate
        return f if f > 0.0 else 0.0
    return elastic + b * rate


@njit(cache=True)
def penalty_slopes(depth, rate, law, k, b, d0, ahead):
    """(d f / d depth, d f / d rate, d f / d ahead) of the unclamped law (zeros where it is 0)."""
    if depth <= 0.0:
        if depth + ahead <= 0.0:
            return 0.0, 0.0, 0.0
        s0, s1 = elastic_mean_slopes(depth, depth + ahead, law, k, d0)
        return s0 + s1, 0.0, s1
    s0, s1 = elastic_mean_slopes(depth, depth + ahead, law, k, d0)
    if law == LAW_HUNT_CROSSLEY:
        return s0 + s1 + b * rate / d0, b * depth / d0, s1
    return s0 + s1, b, s1


@njit(cache=True)
def elastic_force(x, law, k, d0):
    """The elastic part of the law at depth x (0 at x <= 0): k x, k x (1 + x/d0), k x (x/d0)^0.5."""
    if x <= 0.0:
        return 0.0
    if law == LAW_LINEAR:
        return k * x
    if law == LAW_QUADRATIC:
        return k * x * (1.0 + x / d0)
    return k * x * math.sqrt(x / d0)


@njit(cache=True)
def elastic_mean(x0, x1, law, k, d0):
    """Mean of the elastic force over the depths [x0, x1]: the difference quotient of the penalty
    potential, (E(x1) - E(x0)) / (x1 - x0), with E = 0 at depths <= 0.

    Held over an interval in which the depth goes from x0 to x1, this force does exactly the work
    E(x1) - E(x0): the zero-order hold neither creates nor loses energy (the sampled force k x0
    would create k (x1 - x0)^2 / 2 per step, K T / 2 v^2 per unit time, in both directions of
    motion). Closed forms, free of cancellation when x1 is near x0."""
    if x1 == x0:
        return elastic_force(x0, law, k, d0)
    if x0 <= 0.0:       # the contact starts within the interval
        return penalty_energy(x1, law, k, d0) / (x1 - x0) if x1 > 0.0 else 0.0
    if x1 < 0.0:        # the contact ends within the interval: the stored energy over the whole of it
        return penalty_energy(x0, law, k, d0) / (x0 - x1)
    if law == LAW_LINEAR:
        return 0.5 * k * (x0 + x1)
    if law == LAW_QUADRATIC:
        return 0.5 * k * (x0 + x1) + k * (x0 * x0 + x0 * x1 + x1 * x1) / (3.0 * d0)
    a = math.sqrt(x1)
    c = math.sqrt(x0)
    return 0.4 * k / math.sqrt(d0) * (a ** 4 + a ** 3 * c + a * a * c * c + a * c ** 3 + c ** 4) / (a + c)


@njit(cache=True)
def elastic_mean_slopes(x0, x1, law, k, d0):
    """(d / d x0, d / d x1) of `elastic_mean`."""
    if x0 <= 0.0 and x1 <= 0.0:
        return 0.0, 0.0
    if law == LAW_LINEAR and x0 > 0.0:
        if x1 >= 0.0:
            return 0.5 * k, 0.5 * k
        span = x0 - x1
        return k * x0 / span - 0.5 * k * x0 * x0 / (span * span), 0.5 * k * x0 * x0 / (span * span)
    span = x1 - x0
    if abs(span) <= 1e-6 * x0:      # the mean's slopes tend to half the force's slope at x0
        h = 1e-7 * x0
        slope = (elastic_force(x0 + h, law, k, d0) - elastic_force(x0 - h, law, k, d0)) / (2.0 * h)
        return 0.5 * slope, 0.5 * slope
    mean = elastic_mean(x0, x1, law, k, d0)
    return (mean - elastic_force(x0, law, k, d0)) / span, (elastic_force(x1, law, k, d0) - mean) / span


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


@njit(cache=True)
def penalty_forces(contact_face, contact_depth, contact_rate, contact_ahead, law, k, b, d0, fmag):
    """Force magnitude of every contact from its depth, rate and predicted depth change over the
    hold (the rigid-wall response; contact_ahead all 0: the law at the sampled depth, see `penalty`)."""
    for i in range(contact_face.shape[0]):
        fmag[i] = 0.0
        if contact_face[i] >= 0:
            fmag[i] = penalty_magnitude(contact_depth[i], contact_rate[i], law, k, b, d0, contact_ahead[i])


@njit(cache=True)
def distribute(fmag, fmag_wall, contact_face, contact_w, contact_n, contact_s, contact_depth, tri, local_to_global,
               n_tool, law, k, d0, node_force, tissue_force, force_sum):
    """Forces of the contacts on the tool nodes and the tissue nodes (both overwritten).

    Contact i (nodes first, then segments i = n_tool + s) pushes the tool by fmag[i] n_i (the haptic
    port's held force): a node takes it whole, a segment (s, s+1) splits it by its contact
    parameter; the tissue gets the opposite of the law's force fmag_wall[i] n_i (the two differ by
    the hold's prediction only), applied at q and split over the face's vertices by the barycentric
    weights (so the nodal forces sum to -F and their moment equals that of -F at q). force_sum
    (n_surface,3), when it has rows, accumulates the tissue forces too (the compliance model's
    record of the force the tissue is sent). Returns (max depth, contact count, penalty energy).
    """
    for i in range(tissue_force.shape[0]):
        tissue_force[i, 0] = 0.0
        tissue_force[i, 1] = 0.0
        tissue_force[i, 2] = 0.0
    for i in range(node_force.shape[0]):
        node_force[i, 0] = 0.0
        node_force[i, 1] = 0.0
        node_force[i, 2] = 0.0
    record = force_sum.shape[0] > 0
    max_depth = 0.0
    count = 0
    energy = 0.0
    for i in range(contact_face.shape[0]):
        f = contact_face[i]
        if f < 0:
            continue
        fx = fmag[i] * contact_n[i, 0]
        fy = fmag[i] * contact_n[i, 1]
        fz = fmag[i] * contact_n[i, 2]
        wx = fmag_wall[i] * contact_n[i, 0]
        wy = fmag_wall[i] * contact_n[i, 1]
        wz = fmag_wall[i] * contact_n[i, 2]
        if i < n_tool:
            node_force[i, 0] += fx
            node_force[i, 1] += fy
            node_force[i, 2] += fz
        else:
            sgi = i - n_tool
            bs = contact_s[i]
            node_force[sgi, 0] += (1.0 - bs) * fx
            node_force[sgi, 1] += (1.0 - bs) * fy
            node_force[sgi, 2] += (1.0 - bs) * fz
            node_force[sgi + 1, 0] += bs * fx
            node_force[sgi + 1, 1] += bs * fy
            node_force[sgi + 1, 2] += bs * fz
        for j in range(3):
            v = local_to_global[tri[f, j]]
            w = contact_w[i, j]
            tissue_force[v, 0] -= w * wx
            tissue_force[v, 1] -= w * wy
            tissue_force[v, 2] -= w * wz
            if record:
                force_sum[v, 0] -= w * wx
                force_sum[v, 1] -= w * wy
                force_sum[v, 2] -= w * wz
        depth = contact_depth[i]
        if depth > max_depth:
            max_depth = depth
        if depth > 0.0 or fmag[i] != 0.0:     # not a primitive only about to touch
            count += 1
        energy += penalty_energy(depth, law, k, d0)
    return max_depth, count, energy


@njit(cache=True)
def tip_stiffness(fmag, contact_face, contact_w, contact_n, contact_depth, contact_rate, contact_s, contact_point,
                  tool, tri, slot, W, n_tool, n_segments, law, k, b, d0, dt, out):
    """out (3, 3): K = -d F_tip / d x_tip (N/m), the stiffness of the force on the last tool point
    (the catheter tip, `tip_response`: the law at this step's depths, fmag) against the tip's own
    motion.

    The tip's contact (its node, and the last segment's with its share s of the segment force)
    pushes by f n with f = phi(depth, rate), n the blended contact normal; the tip moving by dx
    changes the depth by -g . dx, g the signed distance's gradient there (the direction from the
    nearest point of the wall, contact_point, to the tool's point: the face's normal inside a face,
    the edge's or vertex's own direction next to one), and the differenced rate by -n . dx / dt, so
    K = sum c^2 n (phi_depth g + phi_rate / dt n)^T, c = 1 for the node and s for the segment. Against the yielding wall (W, slot non-empty: the
    compliance local model) the wall gives way by w = a^T W a per newton (a the contact's weighted
    normal on its face's patch slots) under the same force, so s_eff = s / (1 + s w): k / (1 + k w)
    for the linear law. Contacts that push nothing (f <= 0) add nothing.

    The last segment's depth is what its profile adds to its ends' depths (narrow_phase): with the
    tip in contact (depth > 0, as `narrow_phase._less_ends` counts it) the tip moving by dx changes
    it by -s (g - g_tip) . dx, not -s g . dx (and its rate likewise), so its term is
    c^2 n (phi_depth (g - g_tip) + phi_rate / dt (n - n_tip))^T: nothing on a flat wall, where the
    tip's own sphere carries the change. Counted as s^2 s_eff n n^T, K would be too stiff by an
    amount that jumps with the segment's contact parameter, and the catheter's implicit passive
    bend would follow the jumps.
    """
    for r in range(3):
        for c in range(3):
            out[r, c] = 0.0
    tip = n_tool - 1
    for which in range(2):
        if which == 0:
            i = tip
            share = 1.0
        else:
            if n_segments < 1:
                break
            i = n_tool + n_segments - 1
            share = contact_s[i]
        f = contact_face[i]
        if f < 0 or fmag[i] <= 0.0:
            continue
        s_delta, s_rate, _ = penalty_slopes(contact_depth[i], contact_rate[i], law, k, b, d0, 0.0)
        s = s_delta + s_rate / dt
        if s <= 0.0:
            continue
        gx, gy, gz = _gradient(contact_point, contact_n, contact_s, tool, n_tool, i)
        w = contact_compliance(i, f, contact_w, contact_n, tri, slot, W)
        factor = share * share / (1.0 + s * w)
        g = (gx, gy, gz)
        if which == 1 and contact_face[tip] >= 0 and contact_depth[tip] > 0.0:
            ex, ey, ez = _gradient(contact_point, contact_n, contact_s, tool, n_tool, tip)
            end = (ex, ey, ez)
            for c in range(3):
                right = s_delta * (g[c] - end[c]) + s_rate / dt * (contact_n[i, c] - contact_n[tip, c])
                for r in range(3):
                    out[r, c] += factor * contact_n[i, r] * right
        else:
            for c in range(3):
                right = s_delta * g[c] + s_rate / dt * contact_n[i, c]
                for r in range(3):
                    out[r, c] += factor * contact_n[i, r] * right


@njit(cache=True)
def contact_compliance(i, f, contact_w, contact_n, tri, slot, W):
    """w = a^T W a (m/N): how far contact i's point on face f gives way along its normal per newton
    it pushes, a its normal weighted onto the face's vertices in the patch (slot >= 0); 0 without
    W (a rigid local model)."""
    w = 0.0
    if W.shape[0] == 0:
        return w
    for j in range(3):
        sj = slot[tri[f, j]]
        if sj < 0:
            continue
        for l in range(3):
            sl = slot[tri[f, l]]
            if sl < 0:
                continue
            acc = 0.0
            for p in range(3):
                for q in range(3):
                    acc += contact_n[i, p] * W[3 * sj + p, 3 * sl + q] * contact_n[i, q]
            w += contact_w[i, j] * contact_w[i, l] * acc
    return w


@njit(cache=True)
def _gradient(contact_point, contact_n, contact_s, tool, n_tool, i):
    """The signed distance's gradient at contact i's tool point p (a node, or the segment's point
    at its parameter): the unit direction from the contact's nearest wall point q to p, on the side
    of the contact normal n (p behind the wall: from p to q); n itself when p is on the wall."""
    if i < n_tool:
        px = tool[i, 0]
        py = tool[i, 1]
        pz = tool[i, 2]
    else:
        j = i - n_tool
        t = contact_s[i]
        px = (1.0 - t) * tool[j, 0] + t * tool[j + 1, 0]
        py = (1.0 - t) * tool[j, 1] + t * tool[j + 1, 1]
        pz = (1.0 - t) * tool[j, 2] + t * tool[j + 1, 2]
    dx = px - contact_point[i, 0]
    dy = py - contact_point[i, 1]
    dz = pz - contact_point[i, 2]
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    nx = contact_n[i, 0]
    ny = contact_n[i, 1]
    nz = contact_n[i, 2]
    if dist <= 1e-12:
        return nx, ny, nz
    if dx * nx + dy * ny + dz * nz < 0.0:
        dist = -dist
    return dx / dist, dy / dist, dz / dist


@njit(cache=True)
def tip_gap(contact_face, fmag, contact_n, contact_depth, tip, near, law, k, b, d0, dt, out, gap):
    """The wall at a tip whose own sphere does not press on it (clear of the wall, or in it with a
    law that gives f <= 0): adds to out (3, 3) (what its last segment's contact gives, if any) the
    stiffness s n n^T the sphere meets on pressing, s = s_delta + s_rate / dt at depth 0+ (as
    `tip_stiffness` counts it, without the wall's yielding, which would only lower it), and sets gap
    (3,) so that out . gap = s g n, g the clearance at which the sphere would push: its force is
    then -out (dx + gap) where that pushes, zero elsewhere (gap = g n without a segment's part):
    - the tip's sphere overlaps the wall but its law gives f <= 0 (a fast release, whose damping
      outweighs the depth): g = -f / s;
    - the tip is clear of the wall (within the narrow phase's band, or near = (clearance, normal)
      from `narrow_phase.clearance`): g = the clearance; nothing when near[0] = inf (no wall
      within reach).

    Why: the catheter bends its passive tip against that one-sided affine force, which it can only
    do when it knows the wall where the tip does not press on it. Without it, a tip released from
    the wall (a fast retraction, a tap's turn) springs back into it by a whole step's relaxation, is
    thrown out again one step later, and touches again: the force alternates at 500 Hz."""
    for r in range(3):
        gap[r] = 0.0
    f = contact_face[tip]
    if f >= 0 and fmag[tip] > 0.0 and contact_depth[tip] > 0.0:
        return      # pressing: tip_stiffness has it
    s_delta, s_rate, _ = penalty_slopes(1e-12, 0.0, law, k, b, d0, 0.0)
    s_eff = s_delta + s_rate / dt
    if s_eff <= 0.0:
        return
    if f >= 0:
        g = -fmag[tip] / s_eff if contact_depth[tip] > 0.0 else -contact_depth[tip]
        nx = contact_n[tip, 0]
        ny = contact_n[tip, 1]
        nz = contact_n[tip, 2]
    elif near[0] < np.inf:
        g = near[0]
        nx = near[1]
        ny = near[2]
        nz = near[3]
    else:
        return
    n = (nx, ny, nz)
    for r in range(3):
        for c in range(3):
            out[r, c] += s_eff * n[r] * n[c]
    along = 0.0     # n . out . n: the sphere's s plus what the segment adds along its normal
    for r in range(3):
        for c in range(3):
            along += n[r] * out[r, c] * n[c]
    for r in range(3):
        gap[r] = s_eff * g / along * n[r]


@njit(cache=True)
def rigid_response(contact_face, contact_w, contact_n, contact_s, contact_depth, contact_rate, tri, local_to_global,
                   n_tool, law, k, b, d0, contact_ahead, no_ahead, fmag, fmag_wall, node_force, tissue_force,
                   force_sum):
    """The response against a rigid local model in one call (the 1 kHz path): `penalty_forces` held
    over the predicted depths (the port's, fmag) and at the sampled ones (the wall's, fmag_wall;
    no_ahead: zeros), then `distribute`. Returns (max depth, contact count, penalty energy)."""
    penalty_forces(contact_face, contact_depth, contact_rate, contact_ahead, law, k, b, d0, fmag)
    penalty_forces(contact_face, contact_depth, contact_rate, no_ahead, law, k, b, d0, fmag_wall)
    return distribute(fmag, fmag_wall, contact_face, contact_w, contact_n, contact_s, contact_depth, tri,
                      local_to_global, n_tool, law, k, d0, node_force, tissue_force, force_sum)


@njit(cache=True)
def tip_response(fmag_wall, contact_face, contact_w, contact_n, contact_s, contact_depth, contact_rate, contact_point,
                 tool, tri, slot, W, n_tool, n_segments, law, k, b, d0, dt, near, tip_dn, tip_force, tip_k, gap):
    """What the catheter's tip meets, into tip_force (3,), tip_k (3, 3) and gap (3,): the wall's
    force on the last tool point (fmag_wall of its node's contact and its share of the last
    segment's: the law at this step's depths and rates, against the yielding wall its solution,
    without the haptic hold's prediction); its stiffness (`tip_stiffness`, plus the geometric
    -f d n / d p of the node's normal turning as it slides, tip_dn from
    `narrow_phase.normal_jacobian`); and, where the tip's sphere does not press, the wall it will
    meet (`tip_gap`, near from `narrow_phase.clearance` when its node has no contact).

    Why the law and not the held force: the hold's prediction is the haptic port's (the device holds
    the force over the next millisecond); it remembers the tool's last motion. The catheter bends
    its passive tip against this force implicitly, through K, and a force that depends on the tip's
    own past motion returns that motion a step later: after a dead stop or a release the prediction
    overshoots, the tip follows, and the force wobbles up and down."""
    for r in range(3):
        tip_force[r] = 0.0
    tip = n_tool - 1
    last = n_tool + n_segments - 1      # the segment before the tip (none for a probe)
    for which in range(2 if n_segments > 0 else 1):
        i = tip if which == 0 else last
        if contact_face[i] < 0:
            continue
        share = 1.0 if which == 0 else contact_s[i]
        for r in range(3):
            tip_force[r] += share * fmag_wall[i] * contact_n[i, r]
    tip_stiffness(fmag_wall, contact_face, contact_w, contact_n, contact_depth, contact_rate, contact_s, contact_point,
                  tool, tri, slot, W, n_tool, n_segments, law, k, b, d0, dt, tip_k)
    if contact_face[tip] >= 0 and fmag_wall[tip] > 0.0:
        for r in range(3):
            for c in range(3):
                tip_k[r, c] -= fmag_wall[tip] * tip_dn[r, c]
    for r in range(3):
        gap[r] = 0.0
    if n_segments < 1:
        return      # a probe
    tip_gap(contact_face, fmag_wall, contact_n, contact_depth, tip, near, law, k, b, d0, dt, tip_k, gap)

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
def distribute(fmag, contact_face, contact_w, contact_n, contact_s, contact_depth, tri, local_to_global,
               n_tool, law, k, d0, node_force, tissue_force, force_sum):
    """Forces of the contacts on the tool nodes and the tissue nodes (both overwritten).

    Contact i (nodes first, then segments i = n_tool + s) pushes the tool by fmag[i] n_i: a node
    takes it whole, a segment (s, s+1) splits it by its contact parameter; the tissue gets exactly
    the opposite, applied at q and split over the face's vertices by the barycentric weights (so
    the nodal forces sum to -F and their moment equals that of -F at q). force_sum (n_surface,3),
    when it has rows, accumulates the tissue forces too (the compliance model's record of the
    force the tissue is sent). Returns (max depth, contact count, penalty energy).
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
            tissue_force[v, 0] -= w * fx
            tissue_force[v, 1] -= w * fy
            tissue_force[v, 2] -= w * fz
            if record:
                force_sum[v, 0] -= w * fx
                force_sum[v, 1] -= w * fy
                force_sum[v, 2] -= w * fz
        depth = contact_depth[i]
        if depth > max_depth:
            max_depth = depth
        if depth > 0.0 or fmag[i] != 0.0:     # not a primitive only about to touch
            count += 1
        energy += penalty_energy(depth, law, k, d0)
    return max_depth, count, energy


@njit(cache=True)
def tip_stiffness(fmag, contact_face, contact_w, contact_n, contact_depth, contact_rate, contact_s, tri, slot, W,
                  n_tool, n_segments, law, k, b, d0, dt, contact_ahead, ahead_gain, out):
    """out (3, 3): K = -d F_tip / d x_tip (N/m), the stiffness of the force on the last tool point
    (the catheter tip) against the tip's own motion, as this step's response gives it.

    The tip's contact (its node, and the last segment's with its share s of the segment force)
    pushes by f n with f = phi(depth, rate); the tip moving by dx changes the depth by -n . dx and
    the differenced rate by -n . dx / dt and the predicted depth change by -ahead_gain n . dx, so
    K = sum c^2 s_eff n n^T with s_eff = s + s_tool, s = phi_depth + phi_rate / dt,
    s_tool = ahead_gain phi_ahead, c = 1 for the node and s for the segment. Against the yielding wall
    (W, slot non-empty: the compliance local model) the wall gives way by w = a^T W a per newton (a
    the contact's weighted normal on its face's patch slots) under the law's response to the depth,
    so s_eff = (s + s_tool) / (1 + s w), k / (1 + k w) for the sampled linear law. Contacts that
    push nothing (f <= 0) add nothing.
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
        s_delta, s_rate, s_ahead = penalty_slopes(contact_depth[i], contact_rate[i], law, k, b, d0, contact_ahead[i])
        s = s_delta + s_rate / dt           # against the depth, as the wall's yielding sees it
        s_tool = ahead_gain * s_ahead       # the tool's own motion also moves the predicted depths
        if s + s_tool <= 0.0:
            continue
        w = 0.0
        if W.shape[0] > 0:
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
        s_eff = share * share * (s + s_tool) / (1.0 + s * w)
        for r in range(3):
            for c in range(3):
                out[r, c] += s_eff * contact_n[i, r] * contact_n[i, c]


@njit(cache=True)
def rigid_response(contact_face, contact_w, contact_n, contact_s, contact_depth, contact_rate, tri, local_to_global,
                   n_tool, n_segments, law, k, b, d0, dt, contact_ahead, ahead_gain, fmag, node_force, tissue_force,
                   force_sum, tip_k):
    """The response against a rigid local model in one call (the 1 kHz path): `penalty_forces`,
    `distribute`, then the tip's stiffness into tip_k (3, 3) (`tip_stiffness`, no wall compliance).
    Returns (max depth, contact count, penalty energy)."""
    penalty_forces(contact_face, contact_depth, contact_rate, contact_ahead, law, k, b, d0, fmag)
    result = distribute(fmag, contact_face, contact_w, contact_n, contact_s, contact_depth, tri, local_to_global,
                        n_tool, law, k, d0, node_force, tissue_force, force_sum)
    tip_stiffness(fmag, contact_face, contact_w, contact_n, contact_depth, contact_rate, contact_s, tri,
                  contact_face[:0], contact_w[:0, :0], n_tool, n_segments, law, k, b, d0, dt, contact_ahead, ahead_gain,
                  tip_k)
    return result

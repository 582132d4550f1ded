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
def penalty_slopes(depth, rate, law, k, b, d0):
    """(d f / d depth, d f / d rate) of the unclamped law at depth > 0 (zeros at depth <= 0)."""
    if depth <= 0.0:
        return 0.0, 0.0
    if law == LAW_LINEAR:
        return k, b
    if law == LAW_QUADRATIC:
        return k * (1.0 + 2.0 * depth / d0), b
    ratio = depth / d0
    return 1.5 * k * math.sqrt(ratio) + b * rate / d0, b * ratio


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
def penalty_forces(contact_face, contact_depth, contact_rate, law, k, b, d0, fmag):
    """Force magnitude of every contact from its depth and rate (the rigid-wall response)."""
    for i in range(contact_face.shape[0]):
        fmag[i] = 0.0
        if contact_face[i] >= 0:
            fmag[i] = penalty_magnitude(contact_depth[i], contact_rate[i], law, k, b, d0)


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
        count += 1
        energy += penalty_energy(depth, law, k, d0)
    return max_depth, count, energy


@njit(cache=True)
def tip_stiffness(fmag, contact_face, contact_w, contact_n, contact_depth, contact_rate, contact_s, tri, slot, W,
                  n_tool, n_segments, law, k, b, d0, dt, out):
    """out (3, 3): K = -d F_tip / d x_tip (N/m), the stiffness of the force on the last tool point
    (the catheter tip) against the tip's own motion, as this step's response gives it.

    The tip's contact (its node, and the last segment's with its share s of the segment force)
    pushes by f n with f = phi(depth, rate); the tip moving by dx changes the depth by -n . dx and
    the differenced rate by -n . dx / dt, so K = sum c^2 s_eff n n^T with s = phi_depth +
    phi_rate / dt, c = 1 for the node and s for the segment. Against the yielding wall (W, slot
    non-empty: the compliance local model) the wall gives way by w = a^T W a per newton (a the
    contact's weighted normal on its face's patch slots), so s_eff = s / (1 + s w), k / (1 + k w)
    for the linear law. Contacts that push nothing (f <= 0) add nothing.
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
        s_delta, s_rate = penalty_slopes(contact_depth[i], contact_rate[i], law, k, b, d0)
        s = s_delta + s_rate / dt
        if s <= 0.0:
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
        s_eff = share * share * s / (1.0 + s * w)
        for r in range(3):
            for c in range(3):
                out[r, c] += s_eff * contact_n[i, r] * contact_n[i, c]


@njit(cache=True)
def rigid_response(contact_face, contact_w, contact_n, contact_s, contact_depth, contact_rate, tri, local_to_global,
                   n_tool, n_segments, law, k, b, d0, dt, fmag, node_force, tissue_force, force_sum, tip_k):
    """The response against a rigid local model in one call (the 1 kHz path): `penalty_forces`,
    `distribute`, then the tip's stiffness into tip_k (3, 3) (`tip_stiffness`, no wall compliance).
    Returns (max depth, contact count, penalty energy)."""
    penalty_forces(contact_face, contact_depth, contact_rate, law, k, b, d0, fmag)
    result = distribute(fmag, contact_face, contact_w, contact_n, contact_s, contact_depth, tri, local_to_global,
                        n_tool, law, k, d0, node_force, tissue_force, force_sum)
    tip_stiffness(fmag, contact_face, contact_w, contact_n, contact_depth, contact_rate, contact_s, tri,
                  contact_face[:0], contact_w[:0, :0], n_tool, n_segments, law, k, b, d0, dt, tip_k)
    return result

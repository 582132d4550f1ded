"""Numba kernels of the catheter shape: arrays in, preallocated arrays out, NO validation.

Curve layout (see ``geometry.CenterlineCurve``): ``vertices`` (k, 3), ``directions`` (k-1, 3)
unit segment directions, ``arc`` (k,) arc length at the vertices (arc[0] = 0, increasing),
``segment_lengths`` (k-1,), ``vertex_tangents`` (k, 3) smoothed unit tangents and
``vertex_normals`` (k, 3) parallel-transported first normals. Beyond both ends the curve
continues along the end segments (the end segments extend to infinity).

A frame buffer ``frame4`` (4, 3) holds rows (base point, tangent t, e1, e2).

The arithmetic repeats the plain-numpy algorithms operation by operation (only dot products
are summed in a fixed left-to-right order), so results agree with them to rounding; callers
(the Python layer) validate every input first.
"""

from __future__ import annotations

import math

from numba import njit


@njit(cache=True)
def segment_index(arc, s):
    """Index of the segment holding arc length s: like ``searchsorted(arc, s, 'right') - 1``
    clamped to [0, k-2] (NaN sorts last, as in numpy)."""
    lo = 0
    hi = arc.shape[0]
    # first index i with s < arc[i]
    while lo < hi:
        mid = (lo + hi) >> 1
        if s < arc[mid]:
            hi = mid
        else:
            lo = mid + 1
    i = lo - 1
    last = arc.shape[0] - 2
    if i < 0:
        i = 0
    elif i > last:
        i = last
    return i


@njit(cache=True)
def point(vertices, directions, arc, s, out):
    """out (3,) = c(s) on the ray-extended polyline."""
    i = segment_index(arc, s)
    u = s - arc[i]
    for c in range(3):
        out[c] = vertices[i, c] + u * directions[i, c]


@njit(cache=True)
def frame(arc, segment_lengths, vertex_tangents, vertex_normals, s, out, row):
    """Rows row, row+1, row+2 of out = smoothed unit tangent t, e1, e2 at arc length s.

    t blends the vertex tangents linearly (weight clamped to [0, 1]) and is normalised; e1 is
    the vertex normal minimally rotated from the vertex tangent to t, re-orthogonalised and
    normalised; e2 = t x e1.
    """
    i = segment_index(arc, s)
    w = (s - arc[i]) / segment_lengths[i]
    w = min(max(w, 0.0), 1.0)
    t0 = (1.0 - w) * vertex_tangents[i, 0] + w * vertex_tangents[i + 1, 0]
    t1 = (1.0 - w) * vertex_tangents[i, 1] + w * vertex_tangents[i + 1, 1]
    t2 = (1.0 - w) * vertex_tangents[i, 2] + w * vertex_tangents[i + 1, 2]
    nt = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    t0 /= nt
    t1 /= nt
    t2 /= nt
    # Minimal rotation taking a = vertex_tangents[i] to t, applied to x = vertex_normals[i]:
    # x + v x x + v x (v x x) / (1 + a.t), v = a x t (Rodrigues without trigonometry).
    a0, a1, a2 = vertex_tangents[i, 0], vertex_tangents[i, 1], vertex_tangents[i, 2]
    x0, x1, x2 = vertex_normals[i, 0], vertex_normals[i, 1], vertex_normals[i, 2]
    v0 = a1 * t2 - a2 * t1
    v1 = a2 * t0 - a0 * t2
    v2 = a0 * t1 - a1 * t0
    c = a0 * t0 + a1 * t1 + a2 * t2
    vx0 = v1 * x2 - v2 * x1
    vx1 = v2 * x0 - v0 * x2
    vx2 = v0 * x1 - v1 * x0
    w0 = v1 * vx2 - v2 * vx1
    w1 = v2 * vx0 - v0 * vx2
    w2 = v0 * vx1 - v1 * vx0
    e0 = x0 + vx0 + w0 / (1.0 + c)
    e1 = x1 + vx1 + w1 / (1.0 + c)
    e2 = x2 + vx2 + w2 / (1.0 + c)
    p = e0 * t0 + e1 * t1 + e2 * t2
    e0 -= p * t0
    e1 -= p * t1
    e2 -= p * t2
    ne = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    e0 /= ne
    e1 /= ne
    e2 /= ne
    out[row, 0] = t0
    out[row, 1] = t1
    out[row, 2] = t2
    out[row + 1, 0] = e0
    out[row + 1, 1] = e1
    out[row + 1, 2] = e2
    out[row + 2, 0] = t1 * e2 - t2 * e1
    out[row + 2, 1] = t2 * e0 - t0 * e2
    out[row + 2, 2] = t0 * e1 - t1 * e0


@njit(cache=True)
def base_frame(vertices, directions, arc, segment_lengths, vertex_tangents, vertex_normals, s, frame4):
    """frame4 (4, 3) = (c(s), t, e1, e2) at arc length s."""
    i = segment_index(arc, s)
    u = s - arc[i]
    for c in range(3):
        frame4[0, c] = vertices[i, c] + u * directions[i, c]
    frame(arc, segment_lengths, vertex_tangents, vertex_normals, s, frame4, 1)


@njit(cache=True)
def chain_back(vertices, directions, arc, segment_lengths, s_start, spacing, out):
    """out (n, 3): points walking back along the curve from c(s_start), each exactly ``spacing``
    (Euclidean) from the previous one.

    Inside a straight segment the chord equals the arc step (point k at s_cur - (k+1) spacing
    from the last vertex crossing). Behind a vertex the sphere |x - p| = spacing is intersected
    with earlier segments, taking the first crossing going backward (nearest root along the
    curve). A root at the far end of a segment may come out a rounding above the segment
    length: it is accepted there, clamped to the vertex, rather than searching on past
    segment 0. Past the first vertex the chain continues straight back along the entry ray.
    """
    n = out.shape[0]
    s_cur = s_start
    j = segment_index(arc, s_cur)
    u = s_cur - arc[j]
    p0 = vertices[j, 0] + u * directions[j, 0]
    p1 = vertices[j, 1] + u * directions[j, 1]
    p2 = vertices[j, 2] + u * directions[j, 2]
    k = 0
    while k < n:
        # Run of points inside segment j (all of them on segment 0, which extends backward).
        base_k = k
        while k < n:
            cand = s_cur - spacing * (k - base_k + 1)
            if j != 0 and not (cand >= arc[j]):
                break
            u = cand - arc[j]
            out[k, 0] = vertices[j, 0] + u * directions[j, 0]
            out[k, 1] = vertices[j, 1] + u * directions[j, 1]
            out[k, 2] = vertices[j, 2] + u * directions[j, 2]
            k += 1
        if k > base_k:
            s_cur = s_cur - spacing * (k - base_k)
            p0, p1, p2 = out[k - 1, 0], out[k - 1, 1], out[k - 1, 2]
            if k == n:
                break
        jj = j - 1
        root = 0.0
        while True:
            r0 = vertices[jj, 0] - p0
            r1 = vertices[jj, 1] - p1
            r2 = vertices[jj, 2] - p2
            b = directions[jj, 0] * r0 + directions[jj, 1] * r1 + directions[jj, 2] * r2
            c = (r0 * r0 + r1 * r1 + r2 * r2) - spacing * spacing
            disc = b * b - c
            if disc >= 0.0:
                root = -b - math.sqrt(disc)
                length = segment_lengths[jj]
                if root <= length * (1.0 + 1e-12) and (root >= 0.0 or jj == 0):
                    root = min(root, length)
                    break
            if jj == 0:  # no crossing found (only by rounding): continue straight back
                root = (
                    (p0 - vertices[0, 0]) * directions[0, 0]
                    + (p1 - vertices[0, 1]) * directions[0, 1]
                    + (p2 - vertices[0, 2]) * directions[0, 2]
                ) - spacing
                break
            jj -= 1
        p0 = vertices[jj, 0] + root * directions[jj, 0]
        p1 = vertices[jj, 1] + root * directions[jj, 1]
        p2 = vertices[jj, 2] + root * directions[jj, 2]
        s_cur = arc[jj] + root
        out[k, 0] = p0
        out[k, 1] = p1
        out[k, 2] = p2
        k += 1
        j = jj


@njit(cache=True)
def active_chain(frame4, b1, b2, link_fraction, segment_length, out):
    """out (n_active, 3): joints after the base of an active section bent by (b1, b2) (rad) in
    the (e1, e2) frame of frame4 = (base, t, e1, e2).

    Link j points along cos(f_j beta) t + sin(f_j beta) d, f_j = link_fraction[j],
    beta = |(b1, b2)|, d = (b1 e1 + b2 e2) / beta (e1 when beta = 0); the joints are the base
    plus segment_length times the running sum of the links.
    """
    beta = math.hypot(b1, b2)
    if beta > 0.0:
        d0 = (b1 * frame4[2, 0] + b2 * frame4[3, 0]) / beta
        d1 = (b1 * frame4[2, 1] + b2 * frame4[3, 1]) / beta
        d2 = (b1 * frame4[2, 2] + b2 * frame4[3, 2]) / beta
    else:
        d0, d1, d2 = frame4[2, 0], frame4[2, 1], frame4[2, 2]
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    for j in range(out.shape[0]):
        ang = beta * link_fraction[j]
        ca = math.cos(ang)
        sa = math.sin(ang)
        s0 += ca * frame4[1, 0] + sa * d0
        s1 += ca * frame4[1, 1] + sa * d1
        s2 += ca * frame4[1, 2] + sa * d2
        out[j, 0] = frame4[0, 0] + segment_length * s0
        out[j, 1] = frame4[0, 1] + segment_length * s1
        out[j, 2] = frame4[0, 2] + segment_length * s2


@njit(cache=True)
def catheter_shape(
    vertices, directions, arc, segment_lengths, frame4, s_base, b1, b2, link_fraction, segment_length, positions
):
    """positions (n_segments + 1, 3), proximal end first: the proximal joints chained back
    along the curve from the base at arc length s_base (spaced by segment_length), the base
    (frame4[0]) and the active joints bent by (b1, b2) (see ``active_chain``)."""
    n_active = link_fraction.shape[0]
    n_prox = positions.shape[0] - 1 - n_active
    if n_prox > 0:
        chain_back(vertices, directions, arc, segment_lengths, s_base, segment_length, positions[n_prox - 1 :: -1])
    for c in range(3):
        positions[n_prox, c] = frame4[0, c]
    active_chain(frame4, b1, b2, link_fraction, segment_length, positions[n_prox + 1 :])


@njit(cache=True)
def tip_jacobian(frame4, b1, b2, link_fraction, segment_length, out):
    """out (3, 2): d tip / d (b1, b2) of ``active_chain`` (m/rad), the tip's motion per unit bend.

    tip = base + l sum_j [cos(f_j beta) t + sin(f_j beta) / beta u], u = b1 e1 + b2 e2, so with
    A = sum_j sin(f_j beta) / beta, B = -sum_j f_j sin(f_j beta), C = dA/dbeta:
    d tip / d b_k = l [(B t + C u) b_k / beta + A e_k] (A = sum_j f_j = n / 2, B = C = 0 at beta = 0:
    the straight tip moves by L/2 per radian across its tangent).
    """
    beta = math.hypot(b1, b2)
    a_sum = 0.0
    b_sum = 0.0
    c_sum = 0.0
    for j in range(link_fraction.shape[0]):
        f = link_fraction[j]
        x = f * beta
        if x < 1e-4:  # series: sin(x)/beta = f (1 - x^2/6), dA/dbeta = -f^3 beta / 3
            a_sum += f * (1.0 - x * x / 6.0)
            b_sum -= f * x
            c_sum -= f * f * f * beta / 3.0
        else:
            s = math.sin(x)
            a_sum += s / beta
            b_sum -= f * s
            c_sum += (x * math.cos(x) - s) / (beta * beta)
    for k in range(2):
        bk = b1 if k == 0 else b2
        ratio = bk / beta if beta > 0.0 else 0.0
        for d in range(3):
            u = b1 * frame4[2, d] + b2 * frame4[3, d]
            out[d, k] = segment_length * ((b_sum * frame4[1, d] + c_sum * u) * ratio + a_sum * frame4[2 + k, d])


@njit(cache=True)
def implicit_passive_bend(frame4, b1, b2, link_fraction, segment_length, K, jac, p1, p2, target1, target2, alpha,
                          gain, da1, da2, gap):
    """One step of the passive bend (p1, p2) against the force linearised at its new value.

    Explicit, the bend relaxes toward gain * F_n across the tangent (target1, target2):
    pb' = pb + alpha (target - pb). With K = -dF/dx (3, 3) of the contact at the shape the force
    came from (total bend (b1, b2)) and J = d tip / d bend there (``tip_jacobian``, into jac),
    the force at the new bend is F_n - K J (pb' - pb + da), da = (da1, da2) the actuator's bend
    change in this step, so
    (I + alpha gain P K J) (pb' - pb) = alpha (target - pb) - alpha gain P K J da, P the rows e1, e2
    of frame4. Leaving da out treats the force the actuator's own motion adds as one step late:
    against a stiff wall the regulator's command then returns through the wall with a gain near 1
    and the tip force alternates every step.
    A tip near the wall that carries no force comes with its clearance ``gap`` (3,) = g n and the
    stiffness K it will meet (the Contact FMU's tip_gap): the force is then the one-sided
    F = -K (J (pb' - pb + da) + gap) alone (F_n, zero or a release's pull, is what it is at
    J (pb' - pb + da) = 0, and target is not used), solved as above with K gap on the right; a
    solution where it would pull (F . gap <= 0: the step does not reach the wall) is the free step
    (status 3).
    Returns (pb1', pb2', status): status 1 solved; 0 K is zero (nothing to linearise: the caller
    takes the explicit step); 2 the 2x2 system is not positive (K J not restoring there: explicit);
    3 the free tip does not reach the wall in this step (explicit); -1 K or gap is not finite.
    """
    g0 = gap[0]
    g1 = gap[1]
    g2 = gap[2]
    if not (math.isfinite(g0) and math.isfinite(g1) and math.isfinite(g2)):
        return p1, p2, -1
    clear = g0 != 0.0 or g1 != 0.0 or g2 != 0.0
    if clear:
        target1 = 0.0
        target2 = 0.0
    zero = True
    for r in range(3):
        for c in range(3):
            x = K[r, c]
            if not math.isfinite(x):
                return p1, p2, -1
            if x != 0.0:
                zero = False
    if zero:
        return p1, p2, 0
    tip_jacobian(frame4, b1, b2, link_fraction, segment_length, jac)
    m00 = 0.0
    m01 = 0.0
    m10 = 0.0
    m11 = 0.0
    # P K J: m_ab = e_a . K . J[:, b]
    for a in range(2):
        for b in range(2):
            acc = 0.0
            for r in range(3):
                kj = 0.0
                for c in range(3):
                    kj += K[r, c] * jac[c, b]
                acc += frame4[2 + a, r] * kj
            if a == 0 and b == 0:
                m00 = acc
            elif a == 0:
                m01 = acc
            elif b == 0:
                m10 = acc
            else:
                m11 = acc
    ag = alpha * gain
    a00 = 1.0 + ag * m00
    a01 = ag * m01
    a10 = ag * m10
    a11 = 1.0 + ag * m11
    # P K gap: the force the clearance takes off (zero in contact)
    kg1 = 0.0
    kg2 = 0.0
    for r in range(3):
        kg = K[r, 0] * g0 + K[r, 1] * g1 + K[r, 2] * g2
        kg1 += frame4[2, r] * kg
        kg2 += frame4[3, r] * kg
    r1 = alpha * (target1 - p1) - ag * (m00 * da1 + m01 * da2 + kg1)
    r2 = alpha * (target2 - p2) - ag * (m10 * da1 + m11 * da2 + kg2)
    det = a00 * a11 - a01 * a10
    if not (det > 0.0 and math.isfinite(det)):
        return p1, p2, 2
    d1 = (a11 * r1 - a01 * r2) / det
    d2 = (a00 * r2 - a10 * r1) / det
    if clear:
        # F . gap with F = -K (J (d + da) + gap): a pull means the free step stays clear of the wall
        push = 0.0
        for r in range(3):
            u = 0.0
            for c in range(3):
                u += K[r, c] * (jac[c, 0] * (d1 + da1) + jac[c, 1] * (d2 + da2) + gap[c])
            push -= u * gap[r]
        if not push > 0.0:
            return p1, p2, 3
    return p1 + d1, p2 + d2, 1

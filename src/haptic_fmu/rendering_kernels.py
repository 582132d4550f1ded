"""Numba kernels of the haptic rendering between tissue frames (the local models).

Arrays in, preallocated arrays out, no validation, no allocation (see `rendering` for the models
and `penalty_kernels` for the laws).

Compliance local model, notation: the patch holds p surface nodes with the compliance block W
(3p x 3p, m/N, symmetric positive semi-definite); `slot[v]` is the patch slot of local model
vertex v (-1 when the vertex has no compliance: it is rendered rigid). Contact i (a tool primitive
against local face F_i, barycentric weights w_i, outward normal n_i) loads the patch with
g = -sum_i a_i f_i, where a_i (3p) holds w_ij n_i in the slots of the face's vertices; the wall
moves by u = W (g - g_applied), so the depth of contact i changes by a_i . du and

    delta_i(f) = depth_i - a_i^T W (g(f) - g_prev) = delta0_i - sum_j D_ij f_j,   D = A^T W A

(depth_i measured against the wall predicted with the previous step's patch force g_prev). The
wall's yielding this step also moves the surface: rate_i(f) = rate_i + (delta_i(f) - depth_i)/dt.
The wall yields under the law's force at the sampled depths (`compliance_response` passes ahead_i
= 0); the haptic port holds the law's mean over the depth change the tool's own motion predicts
for the hold interval from the solved depth (`port_forces`: the motion shared with the yielding
wall as by two springs in series; `narrow_phase.approach`, `penalty_kernels.elastic_mean`).
`compliance_forces` solves f_i = phi(delta_i(f), rate_i(f), ahead_i) (the penalty law phi) by semi-smooth
Newton: the Jacobian is I + diag(phi_delta + phi_rate / dt) D on contacts that stay in contact
(delta > 0), the identity elsewhere (f_i = 0). For the linear law on a fixed contact set one
iteration is exact; a few handle contacts that separate and the non-linear laws. Where the law
jumps at delta = 0 (damping: f(0+) = b rate) the solution can be a wall resting exactly at the
tool (delta = 0, f between 0 and f(0+)), which Newton cannot reach (it cycles): after max_iter
iterations the solve falls back to projected Gauss-Seidel with that set-valued law, contact by
contact (`_scalar_contact`).
"""
import math

from numba import njit

from .penalty_kernels import LAW_HUNT_CROSSLEY, contact_compliance, distribute, penalty_magnitude, penalty_slopes

#: Sweeps of the Gauss-Seidel fallback of the compliance solve (linear convergence; a few contacts).
GAUSS_SEIDEL_SWEEPS = 500

# The compliance kernels take what belongs together as one argument each: plain tuples in the
# orders below, made by the functions after them, built once by the model and reused every step.
# Plain tuples, because numba's dispatcher types a tuple of arrays about as fast as the arrays
# passed one by one, where a NamedTuple is typed in Python, microseconds per call at 1 kHz.

#: The contact state (``contact_state``, ContactModel's per-primitive arrays, nodes then segments):
#: local face (int64, -1: no contact), barycentric weights (n_prim, 3), outward normal (n_prim, 3),
#: depth, rate, segment parameter s, the depth change the tool's motion predicts over the hold,
#: the haptic port's held force and the law's force at the sampled depths (the wall's).
CONTACT_FACE, CONTACT_W, CONTACT_N, CONTACT_DEPTH, CONTACT_RATE, CONTACT_S, CONTACT_AHEAD, PORT_FORCE, \
    WALL_FORCE = range(9)
#: The penalty law (``penalty_law``): its kernel code, k, b and d0.
PENALTY_LAW, PENALTY_K, PENALTY_B, PENALTY_D0 = range(4)
#: The wall's compliance state the response updates (``patch_state``, WallCompliance): slot (local
#: vertex -> patch slot or -1), W (3p, 3p), g (3p, the patch force of the last step), g_new (3p, this
#: step's), u (3p, the wall's displacement W (g - g_applied)) and force_sum (n_surface, 3), the sum
#: of the forces sent to the tissue over the current frame interval (its record).
PATCH_SLOT, PATCH_W, PATCH_G, PATCH_G_NEW, PATCH_U, PATCH_FORCE_SUM = range(6)
#: The compliance solve's work arrays (``solve_work``): act (n_prim,) int64, Wa (n_prim, >= 3p),
#: D, J (n_prim, n_prim), and the rows rhs, delta0, f of one (3, n_prim) array.
WORK_ACT, WORK_WA, WORK_D, WORK_J, WORK_VECTORS = range(5)


def contact_state(face, w, n, depth, rate, s, ahead, port_force, wall_force) -> tuple:
    """The contact state tuple (the order of CONTACT_FACE ... WALL_FORCE)."""
    return _ordered(9, ((CONTACT_FACE, face), (CONTACT_W, w), (CONTACT_N, n), (CONTACT_DEPTH, depth),
                        (CONTACT_RATE, rate), (CONTACT_S, s), (CONTACT_AHEAD, ahead), (PORT_FORCE, port_force),
                        (WALL_FORCE, wall_force)))


def penalty_law(law, k, b, d0) -> tuple:
    """The penalty law tuple (the order of PENALTY_LAW ... PENALTY_D0)."""
    return _ordered(4, ((PENALTY_LAW, law), (PENALTY_K, k), (PENALTY_B, b), (PENALTY_D0, d0)))


def patch_state(slot, W, g, g_new, u, force_sum) -> tuple:
    """The wall's compliance state tuple (the order of PATCH_SLOT ... PATCH_FORCE_SUM)."""
    return _ordered(6, ((PATCH_SLOT, slot), (PATCH_W, W), (PATCH_G, g), (PATCH_G_NEW, g_new), (PATCH_U, u),
                        (PATCH_FORCE_SUM, force_sum)))


def solve_work(act, Wa, D, J, vectors) -> tuple:
    """The compliance solve's work tuple (the order of WORK_ACT ... WORK_VECTORS)."""
    return _ordered(5, ((WORK_ACT, act), (WORK_WA, Wa), (WORK_D, D), (WORK_J, J), (WORK_VECTORS, vectors)))


def _ordered(size, entries) -> tuple:
    items = [None] * size
    for index, value in entries:
        items[index] = value
    return tuple(items)


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
def add_displacement(pos, slot, u):
    """pos[v] += u[slot[v]] for the local vertices that have a patch slot (the wall's yielding)."""
    for v in range(pos.shape[0]):
        s = slot[v]
        if s >= 0:
            pos[v, 0] += u[3 * s]
            pos[v, 1] += u[3 * s + 1]
            pos[v, 2] += u[3 * s + 2]


@njit(cache=True)
def _largest_node_norm(u):
    """Largest |u_s| over the nodes of a (3p,) displacement."""
    largest = 0.0
    for s in range(u.shape[0] // 3):
        norm = math.sqrt(u[3 * s] ** 2 + u[3 * s + 1] ** 2 + u[3 * s + 2] ** 2)
        if norm > largest:
            largest = norm
    return largest


@njit(cache=True)
def patch_displacement(W, g, g_applied, u):
    """u = W (g - g_applied) (3p); returns the largest node displacement |u_s| (m)."""
    n = u.shape[0]
    for r in range(n):
        acc = 0.0
        for c in range(n):
            acc += W[r, c] * (g[c] - g_applied[c])
        u[r] = acc
    return _largest_node_norm(u)


@njit(cache=True)
def patch_forces(tissue_force, nodes, count, g):
    """g (3p) = tissue_force at the patch nodes (the force the wall is loaded with)."""
    for s in range(count):
        for d in range(3):
            g[3 * s + d] = tissue_force[nodes[s], d]


@njit(cache=True)
def _solve_dense(J, rhs, m):
    """Solve J x = rhs in place (x in rhs) for the leading m x m block, partial pivoting."""
    for col in range(m):
        piv = col
        best = abs(J[col, col])
        for r in range(col + 1, m):
            if abs(J[r, col]) > best:
                best = abs(J[r, col])
                piv = r
        if piv != col:
            for c in range(m):
                tmp = J[col, c]
                J[col, c] = J[piv, c]
                J[piv, c] = tmp
            tmp = rhs[col]
            rhs[col] = rhs[piv]
            rhs[piv] = tmp
        diag = J[col, col]
        for r in range(col + 1, m):
            factor = J[r, col] / diag
            if factor != 0.0:
                for c in range(col, m):
                    J[r, c] -= factor * J[col, c]
                rhs[r] -= factor * rhs[col]
    for r in range(m - 1, -1, -1):
        acc = rhs[r]
        for c in range(r + 1, m):
            acc -= J[r, c] * rhs[c]
        rhs[r] = acc / J[r, r]


@njit(cache=True)
def _solved_contact(ia, i, m, delta0, D, f, contact_depth, contact_rate, dt):
    """(depth, rate) of contact ia (primitive i) against the wall yielding under the forces f."""
    delta = delta0[ia]
    for ib in range(m):
        delta -= D[ia, ib] * f[ib]
    return delta, contact_rate[i] + (delta - contact_depth[i]) / dt


@njit(cache=True)
def _scalar_contact(e, d, r_base, ahead, law, k, b, d0, dt):
    """Force of one contact whose depth is delta = e - d f (the others held), rate r_base + delta/dt.

    The law may jump at delta = 0 (linear and quadratic laws with damping: f(0+) = b rate): the
    graph is then set-valued there and a wall that yields enough rests exactly at the tool
    (delta = 0, f = e/d within [0, f(0+)]). Otherwise the root of the monotone
    h(delta) = phi(delta, r_base + delta/dt) - (e - delta)/d, by safeguarded Newton."""
    if e <= 0.0:
        return 0.0
    if d <= 0.0:
        return penalty_magnitude(e, r_base + e / dt, law, k, b, d0, ahead)
    tiny = 1e-300
    if penalty_magnitude(tiny, r_base, law, k, b, d0, ahead) >= e / d:
        return e / d
    lo = 0.0
    hi = e
    for _ in range(200):
        if penalty_magnitude(hi, r_base + hi / dt, law, k, b, d0, ahead) - (e - hi) / d >= 0.0:
            break
        lo = hi
        hi *= 2.0
    x = hi
    for _ in range(100):
        h = penalty_magnitude(x, r_base + x / dt, law, k, b, d0, ahead) - (e - x) / d
        if h >= 0.0:
            hi = x
        else:
            lo = x
        s_delta, s_rate, _ = penalty_slopes(x, r_base + x / dt, law, k, b, d0, ahead)
        slope = s_delta + s_rate / dt + 1.0 / d
        x_new = x - h / slope
        if not (lo < x_new < hi):
            x_new = 0.5 * (lo + hi)
        if abs(x_new - x) <= 1e-15 * x or hi - lo <= 1e-15 * hi:
            x = x_new
            break
        x = x_new
    return (e - x) / d


@njit(cache=True)
def _gauss_seidel(m, act, delta0, D, contact_depth, contact_rate, contact_ahead, law, k, b, d0, dt, tol, max_sweeps,
                  f):
    """Projected Gauss-Seidel over the contacts, each solved exactly with the others held (converges
    for the positive semi-definite D). Returns the sweeps used, -1 when max_sweeps did not reach tol."""
    for sweep in range(max_sweeps):
        change = 0.0
        fmax = 0.0
        for ia in range(m):
            i = act[ia]
            e = delta0[ia]
            for ib in range(m):
                if ib != ia:
                    e -= D[ia, ib] * f[ib]
            new = _scalar_contact(e, D[ia, ia], contact_rate[i] - contact_depth[i] / dt, contact_ahead[i], law,
                                  k, b, d0, dt)
            if abs(new - f[ia]) > change:
                change = abs(new - f[ia])
            f[ia] = new
            if abs(new) > fmax:
                fmax = abs(new)
        if change <= tol * (1.0 + fmax):
            return sweep + 1
    return -1


@njit(cache=True)
def compliance_forces(contacts, contact_ahead, fmag, tri, slot, W, g_prev, penalty, dt, max_iter, tol, g_out, work):
    """Contact forces against the yielding wall (see the module docstring).

    Inputs: the narrow phase's contact data in ``contacts`` (its face, weights, normals, depth and
    rate; depth and rate against the wall predicted with g_prev), contact_ahead (the depth change
    the law's hold takes, `narrow_phase.approach`; zeros for the wall's force), tri (local faces),
    slot (local vertex -> patch slot or -1), W (3p,3p), g_prev (3p), ``penalty`` (the law).
    Outputs: fmag (per primitive: force magnitude along n), the contacts' depth and rate updated
    to the solved wall, their face set to -1 for contacts the yielding wall has left, g_out (3p)
    the patch force of the solution. ``work``: `solve_work`. Returns the Newton iterations used
    (-1 when max_iter did not reach tol: the last iterate is kept).
    """
    vectors = work[WORK_VECTORS]
    return _compliance_forces(contacts[CONTACT_FACE], contacts[CONTACT_W], contacts[CONTACT_N],
                              contacts[CONTACT_DEPTH], contacts[CONTACT_RATE], tri, slot, W, g_prev, contact_ahead,
                              penalty[PENALTY_LAW], penalty[PENALTY_K], penalty[PENALTY_B], penalty[PENALTY_D0], dt,
                              max_iter, tol, fmag, g_out, work[WORK_ACT], work[WORK_WA], work[WORK_D], work[WORK_J],
                              vectors[0], vectors[1], vectors[2])


@njit(cache=True)
def _compliance_forces(contact_face, contact_w, contact_n, contact_depth, contact_rate, tri, slot, W, g_prev,
                       contact_ahead, law, k, b, d0, dt, max_iter, tol, fmag, g_out, act, Wa, D, J, rhs, delta0, f):
    """`compliance_forces` on its arrays one by one (what the kernels above it call: each array
    taken out of its tuple once)."""
    n3 = W.shape[0]
    m = 0
    for i in range(contact_face.shape[0]):
        fmag[i] = 0.0
        if contact_face[i] >= 0:
            act[m] = i
            m += 1
    for r in range(n3):
        g_out[r] = 0.0
    if m == 0:
        return 0
    # W a_i for every contact, then D = A^T W A and delta0 = depth - a^T W g_prev
    for ia in range(m):
        i = act[ia]
        fc = contact_face[i]
        for r in range(n3):
            Wa[ia, r] = 0.0
        for j in range(3):
            s = slot[tri[fc, j]]
            if s < 0:
                continue
            w = contact_w[i, j]
            n0 = w * contact_n[i, 0]
            n1 = w * contact_n[i, 1]
            n2 = w * contact_n[i, 2]
            for r in range(n3):
                Wa[ia, r] += W[r, 3 * s] * n0 + W[r, 3 * s + 1] * n1 + W[r, 3 * s + 2] * n2
    for ia in range(m):
        i = act[ia]
        fc = contact_face[i]
        for ib in range(m):
            acc = 0.0
            for j in range(3):
                s = slot[tri[fc, j]]
                if s < 0:
                    continue
                w = contact_w[i, j]
                acc += w * (contact_n[i, 0] * Wa[ib, 3 * s] + contact_n[i, 1] * Wa[ib, 3 * s + 1]
                            + contact_n[i, 2] * Wa[ib, 3 * s + 2])
            D[ia, ib] = acc
        e = 0.0
        for r in range(n3):
            e += Wa[ia, r] * g_prev[r]
        delta0[ia] = contact_depth[i] - e
        f[ia] = 0.0
    iterations = -1
    for it in range(max_iter):
        fmax = 0.0
        for ia in range(m):
            delta, rate = _solved_contact(ia, act[ia], m, delta0, D, f, contact_depth, contact_rate, dt)
            ahead = contact_ahead[act[ia]]       # the tool's motion over the hold, not the yielding
            phi = penalty_magnitude(delta, rate, law, k, b, d0, ahead)
            slope = 0.0
            if delta > 0.0 and (law != LAW_HUNT_CROSSLEY or phi > 0.0):  # Hunt-Crossley clamps at 0
                s_delta, s_rate, _ = penalty_slopes(delta, rate, law, k, b, d0, ahead)
                slope = s_delta + s_rate / dt
            rhs[ia] = phi - f[ia]
            for ib in range(m):
                J[ia, ib] = slope * D[ia, ib]
            J[ia, ia] += 1.0
            if abs(f[ia]) > fmax:
                fmax = abs(f[ia])
        _solve_dense(J, rhs, m)
        step = 0.0
        for ia in range(m):
            f[ia] += rhs[ia]
            if abs(rhs[ia]) > step:
                step = abs(rhs[ia])
        if step <= tol * (1.0 + fmax):
            iterations = it + 1
            break
    if iterations < 0:
        # Newton cycles where the law jumps at delta = 0 (the wall rests exactly at the tool): solve
        # contact by contact with the set-valued law instead
        for ia in range(m):
            f[ia] = 0.0
        sweeps = _gauss_seidel(m, act, delta0, D, contact_depth, contact_rate, contact_ahead, law, k, b, d0, dt, tol,
                               GAUSS_SEIDEL_SWEEPS, f)
        iterations = -1 if sweeps < 0 else max_iter + sweeps
    # final state: depths and rates of the solved wall, forces, patch load
    for ia in range(m):
        i = act[ia]
        delta, rate = _solved_contact(ia, i, m, delta0, D, f, contact_depth, contact_rate, dt)
        fc = contact_face[i]
        if delta <= 0.0 and f[ia] <= 0.0:
            f[ia] = 0.0
            contact_face[i] = -1
            contact_depth[i] = 0.0
            contact_rate[i] = 0.0
            continue
        fmag[i] = f[ia]
        contact_depth[i] = max(delta, 0.0)       # 0 (to round-off) where the wall rests at the tool
        contact_rate[i] = rate
        for j in range(3):
            s = slot[tri[fc, j]]
            if s < 0:
                continue
            w = contact_w[i, j] * f[ia]
            g_out[3 * s] -= w * contact_n[i, 0]
            g_out[3 * s + 1] -= w * contact_n[i, 1]
            g_out[3 * s + 2] -= w * contact_n[i, 2]
    return iterations


@njit(cache=True)
def _before(c1, d1, id1, c2, d2, id2):
    """Order of patch candidates: contact-face vertices first, then nearer, then lower id."""
    if c1 != c2:
        return c1 < c2
    if d1 != d2:
        return d1 < d2
    return id1 < id2


@njit(cache=True)
def name_patch(pos, vertices, tri, contact_face, contact_point, tool, near_dist, reach, max_nodes,
               key_class, key_dist, key_id, out):
    """The patch: at most max_nodes surface nodes in or near the contact, ascending ids, -1 padded.

    Candidates are the local model's vertices (pos (nv,3), global ids `vertices`). With contacts,
    the vertices of the contact faces come first, then the others by distance to the nearest
    contact point; without contacts, the vertices nearest to the tool node closest to the surface
    if that node is within `reach` of it (near_dist from the narrow phase), else none.
    key_class/key_dist/key_id (max_nodes,) are work arrays. Returns the node count.
    """
    n_prim = contact_face.shape[0]
    n_contacts = 0
    for i in range(n_prim):
        if contact_face[i] >= 0:
            n_contacts += 1
    focus = -1
    if n_contacts == 0:
        best = math.inf
        for i in range(near_dist.shape[0]):
            if near_dist[i] < best:
                best = near_dist[i]
                focus = i
        if focus < 0 or best > reach:
            for s in range(max_nodes):
                out[s] = -1
            return 0
    count = 0
    for v in range(pos.shape[0]):
        cls = 1
        dist2 = math.inf
        if n_contacts:
            for i in range(n_prim):
                fc = contact_face[i]
                if fc < 0:
                    continue
                if tri[fc, 0] == v or tri[fc, 1] == v or tri[fc, 2] == v:
                    cls = 0
                d2 = ((pos[v, 0] - contact_point[i, 0]) ** 2 + (pos[v, 1] - contact_point[i, 1]) ** 2
                      + (pos[v, 2] - contact_point[i, 2]) ** 2)
                if d2 < dist2:
                    dist2 = d2
        else:
            dist2 = ((pos[v, 0] - tool[focus, 0]) ** 2 + (pos[v, 1] - tool[focus, 1]) ** 2
                     + (pos[v, 2] - tool[focus, 2]) ** 2)
        gid = vertices[v]
        if count == max_nodes and not _before(cls, dist2, gid, key_class[count - 1], key_dist[count - 1],
                                              key_id[count - 1]):
            continue
        # insert into the sorted buffer (dropping the last one when full)
        pos_ins = count if count < max_nodes else max_nodes - 1
        while pos_ins > 0 and _before(cls, dist2, gid, key_class[pos_ins - 1], key_dist[pos_ins - 1],
                                      key_id[pos_ins - 1]):
            if pos_ins < max_nodes:
                key_class[pos_ins] = key_class[pos_ins - 1]
                key_dist[pos_ins] = key_dist[pos_ins - 1]
                key_id[pos_ins] = key_id[pos_ins - 1]
            pos_ins -= 1
        key_class[pos_ins] = cls
        key_dist[pos_ins] = dist2
        key_id[pos_ins] = gid
        if count < max_nodes:
            count += 1
    # ascending ids (insertion sort of at most max_nodes entries), -1 padded
    for s in range(count):
        out[s] = key_id[s]
    for s in range(1, count):
        x = out[s]
        j = s - 1
        while j >= 0 and out[j] > x:
            out[j + 1] = out[j]
            j -= 1
        out[j + 1] = x
    for s in range(count, max_nodes):
        out[s] = -1
    return count


@njit(cache=True)
def port_forces(contacts, tri, slot, W, penalty, dt):
    """The haptic port's held force of each contact against the yielding wall (the contacts' port
    force): the law's mean over the depths the tool's predicted motion (their ahead) reaches from
    the solved depth, that motion shared with the wall as by two springs in series: the wall gives
    way by w = a^T W a per newton (the contact's own compliance), so the depth changes by
    ahead / (1 + s w) (s the law's slope). For a lone contact of the linear law,
    k (d + ahead / 2) / (1 + k w): the mean of the series spring over the tool's motion, which is
    what makes a tap on the yielding wall return what it took."""
    _port_forces(contacts[CONTACT_FACE], contacts[CONTACT_W], contacts[CONTACT_N], contacts[CONTACT_DEPTH],
                 contacts[CONTACT_RATE], contacts[CONTACT_AHEAD], tri, slot, W, penalty[PENALTY_LAW],
                 penalty[PENALTY_K], penalty[PENALTY_B], penalty[PENALTY_D0], dt, contacts[PORT_FORCE])


@njit(cache=True)
def _port_forces(contact_face, contact_w, contact_n, contact_depth, contact_rate, contact_ahead, tri, slot, W, law, k,
                 b, d0, dt, fmag):
    """`port_forces` on its arrays one by one."""
    for i in range(contact_face.shape[0]):
        fmag[i] = 0.0
        f = contact_face[i]
        if f < 0:
            continue
        ahead = contact_ahead[i]
        if ahead != 0.0 and W.shape[0] > 0:
            # the slope the contact meets (about to touch: the law's at depth 0+)
            s_delta, s_rate, _ = penalty_slopes(max(contact_depth[i], 1e-12), contact_rate[i], law, k, b, d0, 0.0)
            w = contact_compliance(i, f, contact_w, contact_n, tri, slot, W)
            s = s_delta + s_rate / dt
            if s > 0.0 and w > 0.0:
                ahead = ahead / (1.0 + s * w)
        fmag[i] = penalty_magnitude(contact_depth[i], contact_rate[i], law, k, b, d0, ahead)


@njit(cache=True)
def compliance_response(contacts, no_ahead, tri, local_to_global, n_tool, patch, penalty, dt, max_iter, tol, work,
                        node_force, tissue_force, out):
    """The compliance model's response in one call (the 1 kHz path): `compliance_forces` (the wall
    yields under the law's force, the contacts' wall force; no_ahead: zeros), the haptic port's
    force held over the predicted depths against the solved wall (their port force,
    `port_forces`), `penalty_kernels.distribute`, then the patch's new load g and displacement
    u = W (g - g_applied) (updated by the changed columns of g only: u is W (g - g_applied) to
    round-off). ``patch``: `patch_state`; ``work``: `solve_work`. out (5,) receives
    (max depth, contact count, penalty energy, Newton iterations or -1, largest |u|)."""
    contact_face = contacts[CONTACT_FACE]
    contact_w = contacts[CONTACT_W]
    contact_n = contacts[CONTACT_N]
    contact_depth = contacts[CONTACT_DEPTH]
    contact_rate = contacts[CONTACT_RATE]
    fmag = contacts[PORT_FORCE]
    fmag_wall = contacts[WALL_FORCE]
    slot = patch[PATCH_SLOT]
    W = patch[PATCH_W]
    g = patch[PATCH_G]
    u = patch[PATCH_U]
    law = penalty[PENALTY_LAW]
    k = penalty[PENALTY_K]
    b = penalty[PENALTY_B]
    d0 = penalty[PENALTY_D0]
    vectors = work[WORK_VECTORS]
    iterations = _compliance_forces(contact_face, contact_w, contact_n, contact_depth, contact_rate, tri, slot, W, g,
                                    no_ahead, law, k, b, d0, dt, max_iter, tol, fmag_wall, patch[PATCH_G_NEW],
                                    work[WORK_ACT], work[WORK_WA], work[WORK_D], work[WORK_J], vectors[0], vectors[1],
                                    vectors[2])
    _port_forces(contact_face, contact_w, contact_n, contact_depth, contact_rate, contacts[CONTACT_AHEAD], tri, slot,
                 W, law, k, b, d0, dt, fmag)
    max_depth, count, energy = distribute(fmag, fmag_wall, contact_face, contact_w, contact_n, contacts[CONTACT_S],
                                          contact_depth, tri, local_to_global, n_tool, law, k, d0, node_force,
                                          tissue_force, patch[PATCH_FORCE_SUM])
    g_new = patch[PATCH_G_NEW]
    # u = W (g - g_applied), updated by the columns whose load changed (at most 9 per contact:
    # the contact faces' vertices; none while nothing touches the patch)
    n3 = g.shape[0]
    for col in range(n3):
        dg = g_new[col] - g[col]
        if dg != 0.0:
            for r in range(n3):
                u[r] += W[r, col] * dg
            g[col] = g_new[col]
    out[0] = max_depth
    out[1] = count
    out[2] = energy
    out[3] = iterations
    out[4] = _largest_node_norm(u)


@njit(cache=True)
def publish(node_force, tip, tool_force, tip_force, patch, patch_out):
    """A step's outputs into the caller's arrays: the tool force summed point after point (the
    order of ``node_force.sum(axis=0)``, so the same bits), the tip force (``tip``,
    penalty_kernels.tip_response), and the patch ids (``patch_out`` of any integer type; nothing
    when ``patch`` is empty)."""
    n = node_force.shape[0]
    for d in range(3):
        total = node_force[0, d]
        for i in range(1, n):
            total += node_force[i, d]
        tool_force[d] = total
        tip_force[d] = tip[d]
    for i in range(patch.shape[0]):
        patch_out[i] = patch[i]


@njit(cache=True)
def _sort_segment(values, lo, hi):
    """Insertion sort of values[lo:hi] (a tool primitive's few candidate faces)."""
    for i in range(lo + 1, hi):
        v = values[i]
        j = i - 1
        while j >= lo and values[j] > v:
            values[j + 1] = values[j]
            j -= 1
        values[j + 1] = v


@njit(cache=True)
def _candidate_csr(pairs, n_rows, face_map, ptr, faces):
    """CSR of (row, global face) pairs with faces mapped to local ids, ascending within a row
    (the order of a lexsort by row, then face: local ids ascend with the global ones)."""
    for r in range(n_rows + 1):
        ptr[r] = 0
    for k in range(pairs.shape[0]):
        ptr[pairs[k, 0] + 1] += 1
    for r in range(n_rows):
        ptr[r + 1] += ptr[r]
    for k in range(pairs.shape[0]):  # ptr[r] walks from row r's start to its end ...
        r = pairs[k, 0]
        faces[ptr[r]] = face_map[pairs[k, 1]]
        ptr[r] += 1
    for r in range(n_rows, 0, -1):  # ... which is row r + 1's start: shift back
        ptr[r] = ptr[r - 1]
    ptr[0] = 0
    for r in range(n_rows):
        _sort_segment(faces, ptr[r], ptr[r + 1])


@njit(cache=True)
def _number_marked(index_map, ids):
    """Number the entries marked 0 in index_map consecutively in ascending order (the order of
    np.unique), writing them into ids; returns how many."""
    n = 0
    for i in range(index_map.shape[0]):
        if index_map[i] == 0:
            index_map[i] = n
            ids[n] = i
            n += 1
    return n


@njit(cache=True)
def capture_topology(triangles, node_pairs, seg_pairs, face_map, vertex_map,
                     faces, vertices, local_tri, node_ptr, node_faces, seg_ptr, seg_faces):
    """The local model's topology from the broad phase's candidate pairs (``LocalModel.capture``).

    triangles (t,3) global surface triangles; node_pairs (k,2) (tool node, global face) and
    seg_pairs (k2,2) (tool segment, global face) in any order. Out: faces (sorted global ids of
    every face named), vertices (their sorted global vertex ids), local_tri (faces' vertices as
    local ids), the CSR of the candidates per tool node and per segment (local face ids,
    ascending within a row). face_map (t) and vertex_map (n_surface) are scratch, all -1 on entry
    and on return. Returns (number of faces, number of vertices): the used lengths of faces,
    local_tri rows and vertices; node_faces and seg_faces are filled in full (k and k2).
    """
    for k in range(node_pairs.shape[0]):
        face_map[node_pairs[k, 1]] = 0
    for k in range(seg_pairs.shape[0]):
        face_map[seg_pairs[k, 1]] = 0
    n_faces = _number_marked(face_map, faces)
    for i in range(n_faces):
        for j in range(3):
            vertex_map[triangles[faces[i], j]] = 0
    n_vertices = _number_marked(vertex_map, vertices)
    for i in range(n_faces):
        for j in range(3):
            local_tri[i, j] = vertex_map[triangles[faces[i], j]]
    _candidate_csr(node_pairs, node_ptr.shape[0] - 1, face_map, node_ptr, node_faces)
    _candidate_csr(seg_pairs, seg_ptr.shape[0] - 1, face_map, seg_ptr, seg_faces)
    for i in range(n_faces):  # leave the scratch as it came
        face_map[faces[i]] = -1
    for i in range(n_vertices):
        vertex_map[vertices[i]] = -1
    return n_faces, n_vertices


@njit(cache=True)
def patch_id_status(ids, n_surface, max_nodes, valid_sorted):
    """Check a -1 padded patch id list (``rendering.check_compliance``): 0 fine, 1 an id outside
    -1..n_surface-1, 2 more than max_nodes valid ids, 3 an id repeated. valid_sorted (len(ids))
    is scratch: its first p entries end as the valid ids, ascending."""
    p = 0
    for i in range(ids.shape[0]):
        v = ids[i]
        if v < -1 or v >= n_surface:
            return 1
        if v >= 0:
            valid_sorted[p] = v
            p += 1
    if p > max_nodes:
        return 2
    _sort_segment(valid_sorted, 0, p)
    for i in range(1, p):
        if valid_sorted[i] == valid_sorted[i - 1]:
            return 3
    return 0


@njit(cache=True)
def compliance_block(w, cols, out):
    """out = the symmetric part of the block w[cols][:, cols] (row-major, so the same bits as
    ``0.5 * (b + b.T)``). Returns (first non-finite entry of the block as row * len(cols) + col,
    or -1; its largest |entry|; its largest |b_ij - b_ji|); out is left partial when an entry is
    not finite."""
    m = cols.shape[0]
    scale = 0.0
    for i in range(m):
        for j in range(m):
            a = w[cols[i], cols[j]]
            if not math.isfinite(a):
                return i * m + j, 0.0, 0.0
            scale = max(scale, abs(a))
    asym = 0.0
    for i in range(m):
        for j in range(m):
            a = w[cols[i], cols[j]]
            b = w[cols[j], cols[i]]
            asym = max(asym, abs(a - b))
            out[i, j] = 0.5 * (a + b)
    return -1, scale, asym


@njit(cache=True)
def cholesky_succeeds(a, shift, work):
    """Whether a + shift I (symmetric) has a Cholesky factor: every pivot positive (work: m x m)."""
    m = a.shape[0]
    for i in range(m):
        for j in range(i + 1):
            work[i, j] = a[i, j]
        work[i, i] += shift
    for j in range(m):
        s = work[j, j]
        for k in range(j):
            s -= work[j, k] * work[j, k]
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        work[j, j] = d
        for i in range(j + 1, m):
            s = work[i, j]
            for k in range(j):
                s -= work[i, k] * work[j, k]
            work[i, j] = s / d
    return True


@njit(cache=True)
def patch_slots(ids, local_vertices, slot):
    """slot[k] = the index of local_vertices[k] in ids (distinct surface node ids, the patch's
    few), -1 when it is not there."""
    for k in range(local_vertices.shape[0]):
        slot[k] = -1
        v = local_vertices[k]
        for i in range(ids.shape[0]):
            if ids[i] == v:
                slot[k] = i
                break


@njit(cache=True)
def longest_row(ptr):
    """The largest ptr[r + 1] - ptr[r] of a CSR row pointer (0 for no rows)."""
    most = 0
    for r in range(ptr.shape[0] - 1):
        most = max(most, ptr[r + 1] - ptr[r])
    return most

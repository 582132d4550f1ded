"""Continuous collision detection: ground-truth sample queries, analytic times of impact, a plain-numpy
cubic-root reference on random queries, tunnelling, and cubic Hermite (spline) trajectories."""
from pathlib import Path

import numpy as np
import pytest

from haptic_fmu import ccd
from haptic_fmu.ccd import CCDInputError

SAMPLE_ROOT = Path("/work/shared/data/ccd-sample-queries")
# False positives of the reference Tight-Inclusion implementation on the same 7,279 queries.
REFERENCE_FALSE_POSITIVES = 471
TRIANGLE = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


# ---------------------------------------------------------------------------- plain-numpy references
def point_segment_distance(p, a, b):
    d = b - a
    s = np.clip(np.dot(p - a, d) / max(np.dot(d, d), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - (a + s * d))


def point_triangle_distance(p, a, b, c):
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal)
    height = np.dot(p - a, normal)
    q = p - height * normal
    signs = [np.dot(np.cross(y - x, q - x), normal) for x, y in ((a, b), (b, c), (c, a))]
    if min(signs) >= 0.0:
        return abs(height)
    return min(point_segment_distance(p, a, b), point_segment_distance(p, b, c), point_segment_distance(p, c, a))


def segment_segment_distance(a0, a1, b0, b1):
    da, db, r = a1 - a0, b1 - b0, a0 - b0
    m = np.array([[da @ da, -da @ db], [-da @ db, db @ db]])
    best = min(point_segment_distance(a0, b0, b1), point_segment_distance(a1, b0, b1),
               point_segment_distance(b0, a0, a1), point_segment_distance(b1, a0, a1))
    if abs(np.linalg.det(m)) > 1e-14 * np.trace(m) ** 2:
        u, w = np.linalg.solve(m, [-(da @ r), db @ r])
        if 0.0 <= u <= 1.0 and 0.0 <= w <= 1.0:
            best = min(best, np.linalg.norm(a0 + u * da - b0 - w * db))
    return best


def reference_first_contact(query, edge_edge, ambiguity=1e-4):
    """First time of contact from the coplanarity cubic (numpy.roots) and an inside test at each root.

    Returns (hit, toi, ambiguous): ambiguous when a root or an inside test is within `ambiguity`
    of a decision boundary, where a floating-point reference cannot be trusted.
    """
    start, end = query[:4], query[4:]

    def coplanarity(t):
        p = (1.0 - t) * start + t * end
        if edge_edge:
            return np.dot(np.cross(p[1] - p[0], p[3] - p[2]), p[2] - p[0])
        return np.dot(np.cross(p[2] - p[1], p[3] - p[1]), p[0] - p[1])

    ts = np.array([0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0])
    coefficients = np.polyfit(ts, [coplanarity(t) for t in ts], 3)
    scale = np.max(np.abs(coefficients))
    roots = np.roots(coefficients)
    real = np.sort(roots[np.abs(roots.imag) < 1e-7].real)
    ambiguous = scale == 0.0 or np.any(np.abs(roots.imag[np.abs(roots.imag) >= 1e-7]) < 1e-3)
    ambiguous |= np.any(np.abs(np.diff(real)) < ambiguity)
    for t in real:
        if abs(t) < ambiguity or abs(t - 1.0) < ambiguity:
            ambiguous = True
        if not 0.0 <= t <= 1.0:
            continue
        p = (1.0 - t) * start + t * end
        if edge_edge:
            matrix = np.stack([p[1] - p[0], -(p[3] - p[2])], axis=1)
            (u, w), *_ = np.linalg.lstsq(matrix, p[2] - p[0], rcond=None)
            margins = np.array([u, 1.0 - u, w, 1.0 - w])
        else:
            matrix = np.stack([p[2] - p[1], p[3] - p[1]], axis=1)
            (u, w), *_ = np.linalg.lstsq(matrix, p[0] - p[1], rcond=None)
            margins = np.array([u, w, 1.0 - u - w])
        if np.any(np.abs(margins) < ambiguity):
            ambiguous = True
        if np.all(margins >= 0.0):
            return True, t, ambiguous
    return False, np.inf, ambiguous


def inside_margins(p, edge_edge):
    """Parameters of the closest points of the two primitives' planes/lines at a coplanar instant,
    as margins that are all >= 0 iff the contact point lies inside both primitives."""
    if edge_edge:
        matrix = np.stack([p[1] - p[0], -(p[3] - p[2])], axis=1)
        (u, w), *_ = np.linalg.lstsq(matrix, p[2] - p[0], rcond=None)
        return np.array([u, 1.0 - u, w, 1.0 - w])
    matrix = np.stack([p[2] - p[1], p[3] - p[1]], axis=1)
    (u, w), *_ = np.linalg.lstsq(matrix, p[0] - p[1], rcond=None)
    return np.array([u, w, 1.0 - u - w])


def coplanarity(p, edge_edge):
    """Signed volume whose zeros are the coplanar instants; p (..., 4, 3)."""
    p = np.asarray(p)
    if edge_edge:
        return np.einsum("...i,...i->...", np.cross(p[..., 1, :] - p[..., 0, :], p[..., 3, :] - p[..., 2, :]),
                         p[..., 2, :] - p[..., 0, :])
    return np.einsum("...i,...i->...", np.cross(p[..., 2, :] - p[..., 1, :], p[..., 3, :] - p[..., 1, :]),
                     p[..., 0, :] - p[..., 1, :])


def reference_first_contact_sampled(position_at, edge_edge, n_samples=4001, ambiguity=1e-3):
    """First contact of any trajectory by sign changes of the coplanarity function on a fine grid,
    refined by bisection, then the inside test. (hit, toi, ambiguous) as reference_first_contact;
    ambiguous also when the function comes near zero without a sign change (possible double root)."""
    ts = np.linspace(0.0, 1.0, n_samples)
    g = coplanarity(position_at(ts[:, None, None]), edge_edge)
    scale = np.max(np.abs(g))
    ambiguous = scale == 0.0 or abs(g[0]) < ambiguity * scale or abs(g[-1]) < ambiguity * scale
    crossings = np.flatnonzero(np.sign(g[:-1]) * np.sign(g[1:]) < 0)
    near_zero = np.flatnonzero(np.abs(g) < ambiguity * scale)
    if np.any(np.min(np.abs(near_zero[:, None] - crossings[None, :]), axis=1, initial=n_samples) > 2):
        ambiguous = True
    for k in crossings:
        a, b = ts[k], ts[k + 1]
        ga = g[k]
        for _ in range(60):
            mid = 0.5 * (a + b)
            gm = coplanarity(position_at(mid), edge_edge)
            if np.sign(gm) == np.sign(ga):
                a, ga = mid, gm
            else:
                b = mid
        margins = inside_margins(position_at(a), edge_edge)
        if np.any(np.abs(margins) < ambiguity):
            ambiguous = True
        if np.all(margins >= 0.0):
            return True, a, ambiguous
    return False, np.inf, ambiguous


def hermite(p0, p1, v0, v1, dt, s):
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    return h00 * p0 + h10 * dt * v0 + h01 * p1 + h11 * dt * v1


def falling_vertex_query(z0, z1, xy=(0.25, 0.25)):
    start = np.vstack([[xy[0], xy[1], z0], TRIANGLE])
    end = np.vstack([[xy[0], xy[1], z1], TRIANGLE])
    return np.concatenate([start, end])[None]


# ---------------------------------------------------------------------------- ground-truth sample queries
@pytest.fixture(scope="module")
def sample_queries():
    if not SAMPLE_ROOT.is_dir():
        pytest.fail(f"sample queries not found at {SAMPLE_ROOT} (see docs/design.md section 7)")
    return {kind: ccd.read_sample_query_set(SAMPLE_ROOT, kind) for kind in ("vertex-face", "edge-edge")}


def test_sample_queries_have_documented_counts(sample_queries):
    queries, truth = sample_queries["vertex-face"]
    assert queries.shape == (3085, 8, 3) and truth.sum() == 248
    queries, truth = sample_queries["edge-edge"]
    assert queries.shape == (4194, 8, 3) and truth.sum() == 187


def test_sample_queries_zero_false_negatives(sample_queries, record_property, capsys):
    false_positives = 0
    for kind, detect in (("vertex-face", ccd.vertex_face), ("edge-edge", ccd.edge_edge)):
        queries, truth = sample_queries[kind]
        hit, toi = detect(queries)
        missed = np.flatnonzero(truth & ~hit)
        assert missed.size == 0, f"{kind}: false negatives at queries {missed[:10]}"
        assert np.all((toi[hit] >= 0.0) & (toi[hit] <= 1.0))
        assert np.all(np.isinf(toi[~hit]))
        fp = int(np.count_nonzero(hit & ~truth))
        false_positives += fp
        record_property(f"false_positives_{kind}", fp)
        with capsys.disabled():
            print(f"\n[ccd] {kind}: {len(truth)} queries, {truth.sum()} colliding, 0 false negatives, "
                  f"{fp} false positives")
    assert false_positives <= REFERENCE_FALSE_POSITIVES


def test_sample_queries_spline_with_linear_velocities_equals_linear(sample_queries):
    """Hermite trajectories with v0 = v1 = (p1 - p0)/dt are the straight lines: same hits and times."""
    dt = 1e-3
    for kind, linear, spline in (("vertex-face", ccd.vertex_face, ccd.vertex_face_spline),
                                 ("edge-edge", ccd.edge_edge, ccd.edge_edge_spline)):
        queries, truth = sample_queries[kind]
        p0, p1 = queries[:, :4], queries[:, 4:]
        velocity = (p1 - p0) / dt
        hit_linear, toi_linear = linear(queries)
        hit_spline, toi_spline = spline(p0, p1, velocity, velocity, dt)
        assert not np.any(truth & ~hit_spline)
        np.testing.assert_array_equal(hit_spline, hit_linear)
        np.testing.assert_allclose(toi_spline[hit_spline], toi_linear[hit_linear], rtol=0.0, atol=1e-9)


def test_sample_queries_power_of_two_scaling_gives_identical_results(sample_queries):
    """Scaling every coordinate by 2^-10 (metres of a 1 mm-sized scene) is exact in floating point and all
    tolerances are relative, so hits and times must be bit-identical."""
    for kind, detect in (("vertex-face", ccd.vertex_face), ("edge-edge", ccd.edge_edge)):
        queries, _ = sample_queries[kind]
        hit, toi = detect(queries)
        hit_scaled, toi_scaled = detect(queries * 2.0**-10)
        np.testing.assert_array_equal(hit_scaled, hit)
        np.testing.assert_array_equal(toi_scaled, toi)


# ---------------------------------------------------------------------------- analytic cases
@pytest.mark.parametrize("z0,z1", [(0.3, -0.7), (1.0, -1.0), (0.05, -3.0), (2.0, -0.001)])
def test_vertex_falling_onto_static_triangle_has_exact_toi(z0, z1):
    hit, toi = ccd.vertex_face(falling_vertex_query(z0, z1))
    exact = z0 / (z0 - z1)
    assert hit[0]
    # toi is a lower bound at most one resolution box early: tolerance 1e-6 of the extent / speed
    extent = max(1.0, z0 - z1)
    assert 0.0 <= exact - toi[0] <= 2e-6 * extent / (z0 - z1)
    z_at_toi = z0 + toi[0] * (z1 - z0)
    assert 0.0 <= z_at_toi <= 2e-6 * extent


def test_vertex_passing_beside_triangle_is_missed():
    hit, toi = ccd.vertex_face(falling_vertex_query(0.3, -0.7, xy=(0.6, 0.6)))  # u + w = 1.2 > 1
    assert not hit[0] and np.isinf(toi[0])


def test_min_distance_margin_detects_near_approach():
    """A vertex that stops 0.01 above the face is no contact, unless the margin (e.g. a tool radius) exceeds it;
    with margin r the contact starts when the height reaches r: z(t) = 0.3 - 0.29 t = 0.02 at t = 28/29."""
    query = falling_vertex_query(0.3, 0.01)
    assert not ccd.vertex_face(query)[0][0]
    hit, toi = ccd.vertex_face(query, min_distance=0.02)
    assert hit[0] and 0.0 <= 28.0 / 29.0 - toi[0] <= 1e-5


def test_degenerate_triangle_is_handled_conservatively():
    """A zero-area (collinear) face: a vertex crossing its segment is a hit, one passing beside it is not."""
    sliver = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
    through = np.concatenate([np.vstack([[0.25, 0.0, 0.5], sliver]), np.vstack([[0.25, 0.0, -0.5], sliver])])
    beside = np.concatenate([np.vstack([[0.25, 0.3, 0.5], sliver]), np.vstack([[0.25, 0.3, -0.5], sliver])])
    hit, toi = ccd.vertex_face(np.stack([through, beside]))
    assert hit.tolist() == [True, False]
    assert 0.0 <= 0.5 - toi[0] <= 2e-6


def test_edge_falling_onto_crossing_edge_has_exact_toi():
    start = np.array([[-1.0, 0.0, 0.5], [1.0, 0.0, 0.5], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    end = start + np.array([[0.0, 0.0, -2.0], [0.0, 0.0, -2.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    hit, toi = ccd.edge_edge(np.concatenate([start, end])[None])
    assert hit[0]
    assert 0.0 <= 0.25 - toi[0] <= 2e-6
    p = (1 - toi[0]) * start + toi[0] * end
    assert segment_segment_distance(*p) <= 4e-6
    # the same edges shifted so they pass beside each other
    start[:2, 0] += 2.5
    end[:2, 0] += 2.5
    hit, toi = ccd.edge_edge(np.concatenate([start, end])[None])
    assert not hit[0]


def test_parallel_edges_and_coplanar_sliding():
    """Degenerate configurations: parallel edges closing their gap; a vertex sliding in the face plane."""
    start = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.5, 0.0], [1.0, 0.5, 0.0]])
    end = start + np.array([[0.0, 0.4, 0.0]] * 2 + [[0.0, 0.0, 0.0]] * 2)  # gap 0.5 -> 0.1: miss
    assert not ccd.edge_edge(np.concatenate([start, end])[None])[0][0]
    end = start + np.array([[0.0, 1.0, 0.0]] * 2 + [[0.0, 0.0, 0.0]] * 2)  # gap closes at t = 0.5
    hit, toi = ccd.edge_edge(np.concatenate([start, end])[None])
    assert hit[0] and 0.0 <= 0.5 - toi[0] <= 2e-6
    # vertex in the plane of the face, sliding into it from outside: contact when it crosses the edge u + w = 1
    query = np.concatenate([np.vstack([[1.0, 1.0, 0.0], TRIANGLE]), np.vstack([[0.0, 0.0, 0.0], TRIANGLE])])
    hit, toi = ccd.vertex_face(query[None])
    assert hit[0] and 0.0 <= 0.5 - toi[0] <= 2e-6


def test_tunnelling_missed_by_discrete_test_is_caught():
    """A vertex crossing a thin wall (1.5 mm) within one 1 ms step at 50 m/s: the end-of-step penetration
    test (behind the face by less than the wall thickness, inside its outline) sees nothing."""
    scale = 0.01
    thickness = 1.5e-3
    start = np.vstack([[0.25 * scale, 0.25 * scale, 0.025], scale * TRIANGLE])
    end = np.vstack([[0.25 * scale, 0.25 * scale, -0.025], scale * TRIANGLE])

    def discrete_penetration(points):
        v, a, b, c = points
        normal = np.cross(b - a, c - a)
        normal /= np.linalg.norm(normal)
        depth = np.dot(v - a, normal)
        q = v - depth * normal
        inside = min(np.dot(np.cross(y - x, q - x), normal) for x, y in ((a, b), (b, c), (c, a))) >= 0.0
        return inside and -thickness < depth <= 0.0

    assert not discrete_penetration(start) and not discrete_penetration(end)
    hit, toi = ccd.vertex_face(np.concatenate([start, end])[None])
    assert hit[0] and 0.0 <= 0.5 - toi[0] <= 2e-6


# ---------------------------------------------------------------------------- random queries vs numpy reference
@pytest.mark.parametrize("edge_edge", [False, True])
def test_random_queries_against_cubic_root_reference(edge_edge):
    rng = np.random.default_rng(11 + edge_edge)
    n = 1500
    start = rng.uniform(-1.0, 1.0, (n, 4, 3))
    end = start + rng.normal(0.0, 0.8, (n, 4, 3))
    queries = np.concatenate([start, end], axis=1)
    detect = ccd.edge_edge if edge_edge else ccd.vertex_face
    hit, toi = detect(queries)
    n_checked = n_hits = 0
    for q in range(n):
        ref_hit, ref_toi, ambiguous = reference_first_contact(queries[q], edge_edge)
        if ambiguous:
            continue
        n_checked += 1
        assert hit[q] == ref_hit, f"query {q}: ccd {hit[q]} reference {ref_hit}"
        if ref_hit:
            n_hits += 1
            assert ref_toi - 1e-4 <= toi[q] <= ref_toi + 1e-12, f"query {q}: toi {toi[q]} reference {ref_toi}"
            p = (1 - toi[q]) * queries[q, :4] + toi[q] * queries[q, 4:]
            distance = segment_segment_distance(*p) if edge_edge else point_triangle_distance(*p)
            assert distance <= 1e-5
    assert n_checked > 0.8 * n and n_hits > 50


# ---------------------------------------------------------------------------- cubic Hermite trajectories
def test_spline_hits_where_straight_chord_misses():
    """Vertex starts and ends at the same point 1 above the face but dips through it:
    z(s) = 1 - a dt s (1 - s) with a dt = 8, first contact at s = (1 - sqrt(1/2)) / 2."""
    dt, a = 0.01, 800.0
    p = np.vstack([[0.2, 0.2, 1.0], TRIANGLE])
    v0 = np.zeros((4, 3))
    v1 = np.zeros((4, 3))
    v0[0, 2], v1[0, 2] = -a, a
    hit_chord, _ = ccd.vertex_face(np.concatenate([p, p])[None])
    assert not hit_chord[0]
    hit, toi = ccd.vertex_face_spline(p[None], p[None], v0[None], v1[None], dt)
    exact = (1.0 - np.sqrt(0.5)) / 2.0
    assert hit[0]
    assert 0.0 <= exact - toi[0] <= 2e-6  # the first of the two roots, approached from before
    z = hermite(p[0], p[0], v0[0], v1[0], dt, toi[0])[2]
    assert 0.0 <= z <= 1e-5


def test_spline_misses_where_straight_chord_hits():
    """Chord crosses the face at (0.2, 0.2); the Hermite path bulges to x = 0.2 + 16 s (1 - s)^2, i.e.
    x = 2.2 when it crosses the plane (z linear, s = 0.5), outside the face."""
    dt = 0.01
    p0 = np.vstack([[0.2, 0.2, 1.0], TRIANGLE])
    p1 = np.vstack([[0.2, 0.2, -1.0], TRIANGLE])
    v0 = np.zeros((4, 3))
    v1 = np.zeros((4, 3))
    v0[0] = [16.0 / dt, 0.0, -2.0 / dt]
    v1[0] = [0.0, 0.0, -2.0 / dt]
    hit_chord, toi_chord = ccd.vertex_face(np.concatenate([p0, p1])[None])
    assert hit_chord[0] and 0.0 <= 0.5 - toi_chord[0] <= 2e-6
    hit, toi = ccd.vertex_face_spline(p0[None], p1[None], v0[None], v1[None], dt)
    assert not hit[0] and np.isinf(toi[0])
    assert hermite(p0[0], p1[0], v0[0], v1[0], dt, 0.5)[0] == pytest.approx(2.2)


def test_spline_edge_edge_curved_path_hit_and_miss():
    """Edge A (along x) travels on a Hermite arc through static edge B (along y) at z = 0."""
    dt = 1.0
    p0 = np.array([[-1.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    p1 = p0.copy()
    p1[:2, 2] = -1.0
    v = np.zeros((4, 3))
    v[:2, 2] = -2.0  # z linear in s: crossing at s = 0.5
    hit, toi = ccd.edge_edge_spline(p0[None], p1[None], v[None], v[None], dt)
    assert hit[0] and 0.0 <= 0.5 - toi[0] <= 2e-6
    bulge = v.copy()
    bulge[:2, 1] = 40.0  # y = 40 s (1 - s)^2 = 5 at s = 0.5: edge A passes beyond edge B's end (|y| <= 1)
    hit, _ = ccd.edge_edge_spline(p0[None], p1[None], bulge[None], v[None], dt)
    assert not hit[0]


def test_spline_accepts_per_query_dt():
    p = np.vstack([[0.2, 0.2, 1.0], TRIANGLE])
    v0 = np.zeros((2, 4, 3))
    v1 = np.zeros((2, 4, 3))
    v0[:, 0, 2] = [-800.0, -80.0]
    v1[:, 0, 2] = [800.0, 80.0]
    hit, toi = ccd.vertex_face_spline(np.stack([p, p]), np.stack([p, p]), v0, v1, np.array([0.01, 0.01]))
    # a dt = 8 dips through the face, a dt = 0.8 only to z = 0.8
    assert hit.tolist() == [True, False]


@pytest.mark.parametrize("edge_edge", [False, True])
def test_random_spline_queries_against_sampled_reference(edge_edge):
    """Random cubic Hermite trajectories (velocities far from the chord) against a fine-grid
    sign-change reference of the degree-9 coplanarity function."""
    rng = np.random.default_rng(21 + edge_edge)
    n, dt = 600, 0.01
    p0 = rng.uniform(-1.0, 1.0, (n, 4, 3))
    p1 = p0 + rng.normal(0.0, 0.6, (n, 4, 3))
    # first point's chord aimed through the middle of the other primitive, so that many cross it
    p1[:, 0] = 2.0 * p1[:, 1:].mean(axis=1) - p0[:, 0] + rng.normal(0.0, 0.3, (n, 3))
    v0 = rng.normal(0.0, 1.0, (n, 4, 3)) / dt
    v1 = rng.normal(0.0, 1.0, (n, 4, 3)) / dt
    detect = ccd.edge_edge_spline if edge_edge else ccd.vertex_face_spline
    hit, toi = detect(p0, p1, v0, v1, dt)
    n_checked = n_hits = 0
    for q in range(n):
        def position_at(s, q=q):
            return hermite(p0[q], p1[q], v0[q], v1[q], dt, s)
        ref_hit, ref_toi, ambiguous = reference_first_contact_sampled(position_at, edge_edge)
        if ambiguous:
            continue
        n_checked += 1
        assert hit[q] == ref_hit, f"query {q}: ccd {hit[q]} reference {ref_hit}"
        if ref_hit:
            n_hits += 1
            assert ref_toi - 1e-4 <= toi[q] <= ref_toi + 1e-9, f"query {q}: toi {toi[q]} reference {ref_toi}"
    assert n_checked > 0.6 * n and n_hits > 20


# ---------------------------------------------------------------------------- validation
def test_validation_messages():
    with pytest.raises(CCDInputError, match=r"shape \(n, 8, 3\)"):
        ccd.vertex_face(np.zeros((2, 4, 3)))
    bad = falling_vertex_query(0.3, -0.7)
    bad[0, 5, 1] = np.nan
    with pytest.raises(CCDInputError, match="non-finite"):
        ccd.edge_edge(bad)
    p = np.zeros((1, 4, 3))
    with pytest.raises(CCDInputError, match="dt must be"):
        ccd.vertex_face_spline(p, p, p, p, 0.0)
    with pytest.raises(CCDInputError, match="p1 has 2 queries"):
        ccd.vertex_face_spline(p, np.zeros((2, 4, 3)), p, p, 1.0)
    with pytest.raises(CCDInputError, match="tolerance must be > 0"):
        ccd.vertex_face(falling_vertex_query(0.3, -0.7), tolerance=0.0)


def test_budget_exhaustion_is_reported_as_conservative_hit():
    """With a budget of one box, an undecided query must come back as a hit at t = 0, flagged unresolved."""
    hit, toi, stats = ccd.vertex_face(falling_vertex_query(0.3, -0.7), max_boxes=1, return_stats=True)
    assert hit[0] and toi[0] == 0.0 and stats["unresolved"][0]

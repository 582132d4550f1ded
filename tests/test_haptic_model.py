"""Contact response and haptic rendering of the Contact FMU (model layer).

Known answers: a plain-numpy closest-point reference, a sampled segment-triangle reference, the
design equation F = -k dist n - b (v.n) n evaluated by hand, action-reaction and moment balance,
first-order extrapolation by hand, and a faceted tube whose facet planes are known exactly.
"""
import math

import numpy as np
import pytest

import haptic_helpers as helpers
from haptic_fmu import narrow_phase, penalty
from haptic_fmu.model import ContactModel, ContactParameters

RNG = np.random.default_rng(20260521)


# ---------------------------------------------------------------------------- references
def _closest_on_segments(p, a, b):
    ab = b - a
    t = np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
    return a + t[:, None] * ab


def reference_closest_points(p, a, b, c):
    """Plain numpy, points p (m,3) vs one triangle: the plane projection where it lies inside the
    triangle, else the nearest of the closest points on the three edges."""
    n = np.cross(b - a, c - a)
    n = n / np.linalg.norm(n)
    x = p - np.outer((p - a) @ n, n)
    inside = np.all([np.cross(v1 - v0, x - v0) @ n >= 0 for v0, v1 in ((a, b), (b, c), (c, a))], axis=0)
    edges = np.stack([_closest_on_segments(p, v0, v1) for v0, v1 in ((a, b), (b, c), (c, a))])
    nearest = edges[np.argmin(np.linalg.norm(edges - p, axis=2), axis=0), np.arange(len(p))]
    return np.where(inside[:, None], x, nearest)


def reference_closest_point(p, a, b, c):
    return reference_closest_points(np.atleast_2d(p), a, b, c)[0]


def flat_triangle(z=0.0):
    """Triangle in the plane z with outward normal +z (tissue below)."""
    return np.array([[-0.01, -0.01, z], [0.02, -0.01, z], [-0.01, 0.02, z]])


def tube_surface(radius=0.010, thickness=0.0015, length=0.04, n_around=32, n_along=9, walls="both"):
    """Faceted thick-walled tube along z (open ends), tissue between the two walls.

    Inner wall normals point to the axis (out of the tissue, into the lumen), outer wall normals
    away from it. Returns (positions (n,3), triangles (t,3))."""
    theta = np.arange(n_around) * 2 * np.pi / n_around
    z = np.linspace(-length / 2, length / 2, n_along)
    points, tris = [], []
    offset = 0
    radii = {"inner": [radius], "outer": [radius + thickness], "both": [radius, radius + thickness]}[walls]
    for r in radii:
        th, zz = np.meshgrid(theta, z, indexing="ij")
        points.append(np.stack([r * np.cos(th), r * np.sin(th), zz], axis=-1).reshape(-1, 3))
        for i in range(n_around):
            for j in range(n_along - 1):
                a = offset + i * n_along + j
                b = offset + ((i + 1) % n_around) * n_along + j
                c, d = b + 1, a + 1
                if r == radius and walls != "outer":   # inner wall: normal toward the axis
                    tris += [[a, d, c], [a, c, b]]
                else:
                    tris += [[a, b, c], [a, c, d]]
        offset += n_around * n_along
    return np.concatenate(points), np.array(tris, np.int64)


def facet_mid_direction(n_around, facet=0):
    """Unit radial direction through the middle of facet `facet` of a tube, and cos(pi/N)."""
    phi = (facet + 0.5) * 2 * np.pi / n_around
    return np.array([np.cos(phi), np.sin(phi), 0.0]), math.cos(math.pi / n_around)


# ---------------------------------------------------------------------------- geometry kernels
def test_closest_point_matches_plain_reference():
    n = 400
    tri = RNG.normal(size=(n, 3, 3))
    pts = RNG.normal(size=(n, 3)) * 1.5
    bary = np.zeros((n, 3))
    helpers.closest_point_triangle_batch(pts, tri[:, 0].copy(), tri[:, 1].copy(), tri[:, 2].copy(), bary)
    q = np.einsum("ij,ijk->ik", bary, tri)
    ref = np.array([reference_closest_point(pts[i], *tri[i]) for i in range(n)])
    assert np.all(bary >= -1e-12) and np.allclose(bary.sum(1), 1.0, atol=1e-12)
    np.testing.assert_allclose(q, ref, atol=1e-10)


def test_segment_triangle_distance_matches_sampled_reference():
    n = 150
    tri = RNG.normal(size=(n, 3, 3))
    p0 = RNG.normal(size=(n, 3)) * 1.5
    p1 = RNG.normal(size=(n, 3)) * 1.5
    s = np.zeros(n)
    bary = np.zeros((n, 3))
    dist = np.zeros(n)
    helpers.closest_segment_triangle_batch(p0, p1, tri[:, 0].copy(), tri[:, 1].copy(), tri[:, 2].copy(),
                                           s, bary, dist)
    samples = 4001
    u = np.linspace(0.0, 1.0, samples)
    hits = 0
    for i in range(n):
        seg = p0[i] + u[:, None] * (p1[i] - p0[i])
        ref = np.linalg.norm(seg - reference_closest_points(seg, *tri[i]), axis=1).min()
        length = np.linalg.norm(p1[i] - p0[i])
        # the sampled minimum is an upper bound, within half a sample spacing of the truth
        assert dist[i] <= ref + 1e-12
        assert ref - dist[i] <= 0.5 * length / (samples - 1) + 1e-12
        # the reported closest points realise the reported distance
        x = p0[i] + s[i] * (p1[i] - p0[i])
        assert abs(np.linalg.norm(x - bary[i] @ tri[i]) - dist[i]) < 1e-12
        hits += dist[i] == 0.0
    assert hits > 0  # some segments pierce their triangle


def test_capsule_through_penalty_api():
    tri = flat_triangle()
    d, s, w = helpers.segment_triangle_distance([-0.05, 0.0, 0.0004], [0.05, 0.0, 0.0004], tri)
    assert d == pytest.approx(0.0004, abs=1e-15)
    assert 0.0 < s < 1.0 and np.all(w >= 0)


# ---------------------------------------------------------------------------- penalty forces
@pytest.mark.parametrize("velocity", [(0.0, 0.0, -0.03), (0.01, -0.02, 0.05), (0.0, 0.0, 0.0)])
def test_flat_triangle_force_is_design_equation(velocity):
    k, b, depth = 800.0, 2.5, 0.0007
    p = np.array([0.0, 0.0, -depth])
    v = np.array(velocity)
    n = np.array([0.0, 0.0, 1.0])
    expected = -k * (-depth) * n - b * (v @ n) * n
    contact = helpers.facet_contact(p, flat_triangle(), v, stiffness=k, damping=b)
    np.testing.assert_allclose(contact.tool_force, expected, rtol=1e-14, atol=1e-15)
    assert contact.distance == pytest.approx(-depth, abs=1e-16)
    local = helpers.local_from_surface(0.0, flat_triangle(), np.zeros((3, 3)), [[0, 1, 2]], policy="hold")
    force, dist = helpers.probe_force(local, 0.01, p, v, stiffness=k, damping=b)
    np.testing.assert_allclose(force, expected, rtol=1e-14, atol=1e-15)
    assert dist == pytest.approx(-depth, abs=1e-16)


def test_no_force_outside():
    contact = helpers.facet_contact([0.0, 0.0, 1e-4], flat_triangle(), [0.0, 0.0, -1.0],
                                    stiffness=500.0, damping=10.0)
    assert np.all(contact.tool_force == 0.0) and contact.distance == pytest.approx(1e-4)
    local = helpers.local_from_surface(0.0, flat_triangle(), np.zeros((3, 3)), [[0, 1, 2]])
    force, dist = helpers.probe_force(local, 0.0, [0.0, 0.0, 1e-4], [0.0, 0.0, -1.0], stiffness=500.0, damping=10.0)
    assert np.all(force == 0.0) and dist is None


def test_tissue_gets_opposite_force_and_same_moment():
    for _ in range(50):
        tri = RNG.normal(size=(3, 3)) * 0.01
        n = helpers.face_normal(tri)
        w = RNG.dirichlet(np.ones(3))
        q = w @ tri
        p = q - RNG.uniform(1e-4, 2e-3) * n            # behind the facet, projecting inside it
        v = RNG.normal(size=3) * 0.05
        vv = RNG.normal(size=(3, 3)) * 0.02
        c = helpers.facet_contact(p, tri, v, vv, stiffness=700.0, damping=1.5)
        np.testing.assert_allclose(c.vertex_forces.sum(0), -c.tool_force, rtol=0, atol=1e-15)
        np.testing.assert_allclose(c.contact_point, q, atol=1e-15)
        # moment about the origin: tissue nodal forces == -F applied at q; and (p - q) x F = 0
        moment_tissue = np.cross(tri, c.vertex_forces).sum(0)
        np.testing.assert_allclose(moment_tissue, np.cross(q, -c.tool_force), atol=1e-16)
        np.testing.assert_allclose(np.cross(p - q, c.tool_force), 0.0, atol=1e-16)
        # damping uses the velocity relative to the surface point
        rel = v - w @ vv
        expected = (700.0 * np.linalg.norm(p - q) - 1.5 * (rel @ n)) * n
        np.testing.assert_allclose(c.tool_force, expected, rtol=1e-12, atol=1e-15)


def test_nonlinear_laws_by_hand_and_energy_is_the_work():
    k, b, d0, depth, rate = 600.0, 2.0, 1e-3, 4e-4, 0.02
    assert penalty.normal_force(depth, rate, "quadratic", k, b, d0) == pytest.approx(
        k * depth * (1 + depth / d0) + b * rate, rel=1e-14)
    assert penalty.normal_force(depth, rate, "hunt_crossley", k, b, d0) == pytest.approx(
        k * depth * math.sqrt(depth / d0) + b * depth / d0 * rate, rel=1e-14)
    # Hunt-Crossley never pulls; the linear law is the design equation verbatim (it can)
    assert penalty.normal_force(depth, -10.0, "hunt_crossley", k, b, d0) == 0.0
    assert penalty.normal_force(depth, -10.0, "linear", k, b, d0) == pytest.approx(k * depth - 10 * b)
    for law in ("linear", "quadratic", "hunt_crossley"):
        x = np.linspace(0.0, depth, 20001)
        f = np.array([penalty.normal_force(xi, 0.0, law, k, 0.0, d0) for xi in x])
        work = np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(x))
        assert penalty.penalty_energy(depth, law, k, d0) == pytest.approx(work, rel=1e-8)


# ---------------------------------------------------------------------------- local model
def test_extrapolate_vs_hold_on_moving_triangle():
    tri = flat_triangle()
    u = np.array([0.0, 0.0, 0.05])                     # the triangle moves up (out of the tissue)
    vel = np.tile(u, (3, 1))
    t_frame, t = 0.10, 0.10 + 0.02
    hold = helpers.local_from_surface(t_frame, tri, vel, [[0, 1, 2]], policy="hold")
    extra = helpers.local_from_surface(t_frame, tri, vel, [[0, 1, 2]], policy="extrapolate")
    np.testing.assert_array_equal(hold.positions_at(t), tri)
    np.testing.assert_allclose(extra.positions_at(t), tri + u * (t - t_frame), rtol=0, atol=1e-18)
    k, b = 500.0, 3.0
    p = np.array([0.0, 0.0, 0.0004])                   # outside the frame plane, inside the moved one
    v = np.array([0.0, 0.0, -0.01])
    force, dist = helpers.probe_force(hold, t, p, v, stiffness=k, damping=b)
    assert dist is None and np.all(force == 0.0)
    force, dist = helpers.probe_force(extra, t, p, v, stiffness=k, damping=b)
    depth = u[2] * (t - t_frame) - p[2]
    assert dist == pytest.approx(-depth, rel=1e-12)
    expected = k * depth + b * (u[2] - v[2])            # relative approach speed
    np.testing.assert_allclose(force, [0.0, 0.0, expected], rtol=1e-12)


# ---------------------------------------------------------------------------- contact model
@pytest.mark.parametrize("energy_consistent", [False, True])
def test_probe_pushed_into_tube_wall_gives_k_depth_along_inward_normal(energy_consistent):
    """k depth along the facet's normal; with the energy-consistent hold, k (depth + step / 2): the
    mean of the law over the depths of the coming hold interval at the probe's constant speed."""
    pos, tri = tube_surface(walls="inner")
    n_around = 32
    params = ContactParameters(stiffness=700.0, damping=0.0, tool="probe", local_model="hold",
                               energy_consistent=energy_consistent)
    model = ContactModel(tri, pos.shape[0], 1, params)
    model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
    e, cosine = facet_mid_direction(n_around, facet=5)
    plane = 0.010 * cosine                              # distance of the facet plane from the axis
    dt = 1e-3
    step = 0.0001 if energy_consistent else 0.0            # the depth change each sample predicts
    for i, depth in enumerate(np.linspace(-0.002, 0.0015, 36)):
        out = model.step(i * dt, dt, (plane + depth) * e + [0, 0, 0.001])
        if depth + step < -1e-12 or (not step and depth <= 0):
            assert out.contact_count == 0 and np.all(out.tool_force == 0.0)
        elif depth <= 1e-15 and step:                       # it will touch within the coming step: the law's
            mean = 700.0 * max(depth + step, 0.0) ** 2 / (2 * step)   # mean over it (the interval of first touch)
            np.testing.assert_allclose(out.tool_force, -mean * e, rtol=1e-6, atol=1e-15)
        else:
            np.testing.assert_allclose(out.tool_force, -700.0 * (depth + step / 2) * e, rtol=1e-9, atol=1e-15)
            assert out.penetration_depth == pytest.approx(depth, rel=1e-9)
            assert out.contact_count == 1
            # the wall and the tip (the probe's one point) get the law at the sampled depth: the
            # hold's prediction is the haptic port's (penalty_kernels.distribute, tip_response)
            np.testing.assert_allclose(out.tip_force, -700.0 * depth * e, rtol=1e-9, atol=1e-15)
            np.testing.assert_allclose(out.tissue_contact_force.sum(0), -out.tip_force, atol=1e-15)
            assert out.contact_energy == pytest.approx(0.5 * 700.0 * depth ** 2, rel=1e-9)


def test_contact_kept_deeper_than_the_margin():
    """A probe pushed slowly 3 margins deep keeps its contact face in the local model."""
    pos, tri = tube_surface(walls="inner", n_around=32)
    margin = 0.002
    model = ContactModel(tri, pos.shape[0], 1, ContactParameters(
        stiffness=500.0, damping=0.0, tool="probe", local_model="hold", energy_consistent=False,
        margin=margin))                                  # the geometry: the law at the sampled depth
    model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
    e, cosine = facet_mid_direction(32, facet=9)
    plane = 0.010 * cosine
    for i, depth in enumerate(np.arange(1, 61) * 1e-4):
        out = model.step(i * 1e-3, 1e-3, (plane + depth) * e)
        np.testing.assert_allclose(out.tool_force, -500.0 * depth * e, rtol=1e-9)
    assert depth > 2.9 * margin and model.local_refreshes > 3


def test_sphere_in_a_crease_is_pushed_back_continuously():
    """Issue 12: a catheter node (a 1 mm sphere) pressed 0.4 mm into the concave crease between two
    facets of a tube of 26 facets (13.8 degrees apart, as in the AAA sac) and moved across it. The
    force's direction blends the normals of the facets the sphere reaches: the force across the
    crease pushes it back toward the crease and changes by less than 0.3 % of the force between
    samples 10 um apart (measured 0.11 %). With the nearest facet's normal alone it jumped by 2 |F| sin(pi / 26) = 24 % of
    the force at the crease and pushed the node toward the other facet from either side: a relay
    that, delayed by one step, oscillated at 500 Hz and created energy at the port."""
    n_around, radius, k = 26, 0.010, 1000.0
    pos, tri = tube_surface(radius=radius, walls="inner", n_around=n_around)
    model = ContactModel(tri, pos.shape[0], 1, ContactParameters(
        stiffness=k, damping=0.0, tool="centerline", tool_radius=0.001, local_model="hold"))
    model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
    crease = 5 * 2 * np.pi / n_around                          # the angle of a vertex line
    gap = 0.0006                                               # sphere centre to the facet planes at the crease
    across = np.array([-math.sin(crease), math.cos(crease), 0.0])   # normal to the crease's bisector plane
    centre = (radius - gap / math.cos(math.pi / n_around)) * np.array([math.cos(crease), math.sin(crease), 0.0])
    offsets = np.linspace(-3e-4, 3e-4, 61)                     # +-0.3 mm across the crease, 10 um apart
    tangential, magnitude = [], []
    for i, y in enumerate(offsets):
        out = model.step(i * 1e-3, 1e-3, [centre + y * across + [0.0, 0.0, 0.001]])
        assert out.contact_count == 1
        f = out.tool_force
        tangential.append(f @ across)
        magnitude.append(np.linalg.norm(f))
        assert abs(f[2]) < 1e-12 * magnitude[-1]
    tangential, magnitude = np.array(tangential), np.array(magnitude)
    assert magnitude.min() > 0.35 and magnitude.max() < 0.45   # about k (1 mm - 0.6 mm)
    assert abs(tangential[30]) < 1e-12                          # on the crease: no side force
    assert np.all(tangential[:30] > 0.0) and np.all(tangential[31:] < 0.0)   # pushed back from both sides
    assert np.max(np.abs(np.diff(tangential))) < 0.003 * magnitude.min()
    # the nearest facet's normal alone: the direction would turn by 2 pi / 26 at the crease
    assert 2 * math.sin(math.pi / n_around) > 0.24


def test_sphere_on_a_flat_tessellated_wall_keeps_the_facet_normal():
    """The blend changes nothing where the reached facets are coplanar: a sphere moved across the
    diagonal and the edges of a flat grid gets k depth along the normal exactly."""
    xs = np.linspace(-0.01, 0.01, 5)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    pos = np.stack([X.ravel(), Y.ravel(), np.zeros(25)], axis=1)
    idx = np.arange(25).reshape(5, 5)
    tri = np.array([t for i in range(4) for j in range(4) for t in (
        [idx[i, j], idx[i + 1, j], idx[i + 1, j + 1]], [idx[i, j], idx[i + 1, j + 1], idx[i, j + 1]])])
    model = ContactModel(tri, 25, 1, ContactParameters(stiffness=800.0, damping=0.0, tool="centerline",
                                                       tool_radius=0.001, local_model="hold"))
    model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
    for i, (x, y) in enumerate(RNG.uniform(-0.004, 0.004, size=(40, 2))):
        out = model.step(i * 1e-3, 1e-3, [[x, y, 0.0006]])
        np.testing.assert_allclose(out.tool_force, [0.0, 0.0, 800.0 * 0.0004], rtol=1e-9, atol=1e-15)


def test_centerline_contacts_balance_and_capsule_force():
    pos, tri = tube_surface(walls="inner")
    params = ContactParameters(stiffness=500.0, damping=0.0, tool="centerline", tool_radius=0.001)
    model = ContactModel(tri, pos.shape[0], 5, params)
    model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
    e, cosine = facet_mid_direction(32, facet=3)
    # a bent centerline whose last nodes press into the wall
    s = np.linspace(0.0, 1.0, 5)
    tool = np.outer(0.004 + 0.0064 * s ** 2, e) + np.outer(np.linspace(-0.01, 0.01, 5), [0, 0, 1])
    out = model.step(0.0, 1e-3, tool)
    assert out.contact_count >= 1
    np.testing.assert_allclose(out.tissue_contact_force.sum(0), -out.tool_force, atol=1e-14)
    np.testing.assert_allclose(out.node_forces.sum(0), out.tool_force, atol=1e-15)
    # the tip node: a sphere of radius r at radial distance 0.0104 from a facet plane at R cos(pi/N)
    depth = 0.0104 + 0.001 - 0.010 * cosine
    assert out.penetration_depth == pytest.approx(depth, rel=1e-9)

    # capsule: a sloped segment passing over a small triangle, both ends far from it, so only the
    # segment interior touches: the axis point closest to the triangle's edge x = 0 is at
    # x* = -slope h / (1 + slope^2), at distance h / sqrt(1 + slope^2) from the edge
    small = np.array([[0.0, 0.0, 0.0], [0.002, 0.0, 0.0], [0.0, 0.002, 0.0]])
    k, r = 400.0, 0.001
    cap = ContactModel(np.array([[0, 1, 2]]), 3, 2,
                       ContactParameters(stiffness=k, damping=0.0, tool_radius=r, margin=0.01))
    cap.set_tissue_frame(0.0, small, np.zeros((3, 3)))
    h, slope, x0, x1 = 0.0006, 0.1, -0.004, 0.012
    seg = np.array([[x, 0.0005, h + slope * x] for x in (x0, x1)])
    out = cap.step(0.0, 1e-3, seg)
    x_star = -slope * h / (1 + slope ** 2)
    depth = r - h / math.sqrt(1 + slope ** 2)
    s_contact = (x_star - x0) / (x1 - x0)
    assert out.contact_count == 1
    assert out.penetration_depth == pytest.approx(depth, rel=1e-12)
    np.testing.assert_allclose(out.tool_force, [0.0, 0.0, k * depth], rtol=1e-12)
    np.testing.assert_allclose(out.node_forces[:, 2], [(1 - s_contact) * k * depth, s_contact * k * depth],
                               rtol=1e-9)
    np.testing.assert_allclose(out.tissue_contact_force.sum(0), -out.tool_force, atol=1e-16)
    # the reaction sits on the triangle's edge x = 0 at y = 0.0005: weights of vertices 0 and 2 only
    np.testing.assert_allclose(out.tissue_contact_force[:, 2], -k * depth * np.array([0.75, 0.0, 0.25]),
                               rtol=1e-9)


def reference_probe_contact(p, v, positions, triangles, k, b, trust=0.0015, side=None, hold=0.0):
    """Plain numpy: the nearest face over the whole surface (of the faces facing `side`, a
    remembered entry normal, when given), the sign from the angle-weighted pseudo-normal of the
    nearest feature, the normal blended over the faces within NORMAL_BLEND_LENGTH of the nearest;
    (force, tissue)."""
    if side is not None:
        tris = positions[triangles]
        facing = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]) @ side > 0
        force, tissue = reference_probe_contact(p, v, positions, triangles[facing], k, b, trust, hold=hold)
        return force, tissue
    tris = positions[triangles]
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    qs = np.array([reference_closest_point(p, *t) for t in tris])
    dist = np.linalg.norm(qs - p, axis=1)
    f = int(np.argmin(dist))
    q, d = qs[f], dist[f]
    pseudo = np.zeros(3)
    for g in np.flatnonzero(np.linalg.norm(qs - q, axis=1) <= 1e-12):
        corner = np.flatnonzero(np.linalg.norm(tris[g] - q, axis=1) <= 1e-12)
        weight = 1.0
        if corner.size:
            v0 = tris[g, corner[0]]
            e1, e2 = tris[g, (corner[0] + 1) % 3] - v0, tris[g, (corner[0] + 2) % 3] - v0
            weight = np.arccos(e1 @ e2 / np.linalg.norm(e1) / np.linalg.norm(e2))
        pseudo += weight * normals[g]
    tissue = np.zeros_like(positions)
    if (p - q) @ pseudo >= 0 or d > trust:
        return np.zeros(3), tissue
    reach = d + narrow_phase.NORMAL_BLEND_LENGTH
    blend = []                                  # (weight, normal), coplanar faces once
    for g in np.flatnonzero((dist < reach) & (normals @ normals[f] > 0)):
        same = [i for i, (_, n) in enumerate(blend) if n @ normals[g] > 1 - 1e-9]
        if same:
            blend[same[0]] = (max(blend[same[0]][0], reach - dist[g]), blend[same[0]][1])
        else:
            blend.append((reach - dist[g], normals[g]))
    n = sum(w * m for w, m in blend)
    n /= np.linalg.norm(n)
    rate = -(v @ n)
    ahead = rate * hold                         # the energy-consistent hold: the mean over [d, d + ahead]
    elastic = k * (d + 0.5 * ahead) if d + ahead >= 0 else k * d * d / (2 * -ahead)
    force = (elastic + b * rate) * n
    # barycentric weights of q by least squares on the triangle's edges
    a, bb, c = tris[f]
    w12 = np.linalg.lstsq(np.stack([bb - a, c - a], axis=1), q - a, rcond=None)[0]
    for w, vertex in zip((1 - w12.sum(), *w12), triangles[f]):
        tissue[vertex] -= w * force
    return force, tissue


def test_probe_matches_plain_reference_on_thick_tube():
    pos, tri = tube_surface(thickness=0.0015, n_around=16, n_along=5)
    k, b = 650.0, 1.7
    contacts = 0
    for _ in range(25):
        model = ContactModel(tri, pos.shape[0], 1, ContactParameters(
            stiffness=k, damping=b, tool="probe", local_model="hold"))
        model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
        phi = RNG.uniform(0, 2 * np.pi)
        r = RNG.uniform(0.0085, 0.0122)
        p = np.array([r * np.cos(phi), r * np.sin(phi), RNG.uniform(-0.015, 0.015)])
        v = RNG.normal(size=3) * 0.05
        out = model.step(0.0, 1e-3, p, v)
        force, _ = reference_probe_contact(p, v, pos, tri, k, b, hold=1e-3)     # the port: held
        _, tissue = reference_probe_contact(p, v, pos, tri, k, b)                 # the wall: the law
        np.testing.assert_allclose(out.tool_force, force, rtol=1e-9, atol=1e-14)
        np.testing.assert_allclose(out.tissue_contact_force, tissue, rtol=1e-9, atol=1e-14)
        contacts += out.contact_count
    assert 5 <= contacts <= 20   # both contacts (inside the wall) and free probes were checked


@pytest.mark.parametrize("detection", ["continuous", "discrete"])
def test_fast_probe_crossing_the_wall_in_one_step(detection):
    pos, tri = tube_surface(thickness=0.0015)
    params = ContactParameters(stiffness=500.0, damping=0.0, tool="probe", detection=detection,
                               local_model="hold", energy_consistent=False)   # the geometry: the sampled law
    model = ContactModel(tri, pos.shape[0], 1, params)
    model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
    e, cosine = facet_mid_direction(32, facet=7)
    inner = 0.010 * cosine
    dt = 1e-3
    start = (inner - 0.0005) * e
    model.step(0.0, dt, start)
    out = model.step(dt, dt, (inner + 0.0015 + 0.0006 / cosine + 0.0005) * e)   # beyond the outer wall
    if detection == "discrete":
        assert out.contact_count == 0 and np.all(out.tool_force == 0.0)
    else:
        depth = 0.0015 + 0.0006 / cosine + 0.0005
        assert out.contact_count == 1 and model.ccd_hits == 1
        np.testing.assert_allclose(out.tool_force, -500.0 * depth * e, rtol=1e-9)


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_wall_jumping_over_static_probe_between_frames(interpolation):
    pos, tri = tube_surface(thickness=0.0015, n_around=32)
    e, cosine = facet_mid_direction(32, facet=16)   # a facet on the -x side of the tube
    shift = np.array([0.003, 0.0, 0.0])
    frame_dt = 1.0 / 30.0
    vel = np.tile(shift / frame_dt, (pos.shape[0], 1))
    results = {}
    for detection in ("continuous", "discrete"):
        params = ContactParameters(stiffness=500.0, damping=0.0, tool="probe", detection=detection,
                                   interpolation=interpolation, local_model="hold")
        model = ContactModel(tri, pos.shape[0], 1, params)
        model.set_tissue_frame(0.0, pos, vel)
        probe = (0.010 * cosine - 0.0002) * e
        model.step(0.0, 1e-3, probe)
        model.set_tissue_frame(frame_dt, pos + shift, vel)
        results[detection] = model.step(1e-3, 1e-3, probe)
    assert results["discrete"].contact_count == 0
    out = results["continuous"]
    depth = shift @ -e - 0.0002                      # the inner facet plane moved past the probe
    assert out.contact_count == 1
    assert out.penetration_depth == pytest.approx(depth, rel=1e-12)
    # the probe remembers the inner side it was on (it is now beyond the outer wall): the force is
    # that of the inner faces, its direction blended with a neighbouring facet 0.083 mm farther
    force, _ = reference_probe_contact(probe, np.zeros(3), pos + shift, tri, 500.0, 0.0, trust=np.inf, side=-e)
    np.testing.assert_allclose(out.tool_force, force, rtol=1e-9, atol=1e-12)
    assert np.degrees(np.arccos(force @ -e / np.linalg.norm(force))) < 360 / 32


def test_get_state_set_state_replays_exactly():
    pos, tri = tube_surface(thickness=0.0015)
    model = ContactModel(tri, pos.shape[0], 4, ContactParameters())
    e, cosine = facet_mid_direction(32, facet=2)

    def tool_at(k):
        s = np.linspace(0, 1, 4)[:, None]
        return (0.006 + (0.0045 + 0.001 * math.sin(0.3 * k)) * s) * e + s * [0, 0, 0.004]

    def run(k0, k1):
        outs = []
        for k in range(k0, k1):
            if k % 33 == 0:
                model.set_tissue_frame(k * 1e-3, pos * (1 + 0.01 * math.sin(0.1 * k)),
                                       pos * 0.001 * math.cos(0.1 * k))
            out = model.step(k * 1e-3, 1e-3, tool_at(k))
            outs.append((out.tool_force.copy(), out.tissue_contact_force.copy(), out.passivity_energy))
        return outs

    run(0, 40)
    state = model.get_state()
    first = run(40, 100)
    model.set_state(state)
    again = run(40, 100)
    assert sum(np.any(f != 0) for f, _, _ in first) > 10      # the replay has contacts
    for (f1, t1, e1), (f2, t2, e2) in zip(first, again):
        np.testing.assert_array_equal(f1, f2)
        np.testing.assert_array_equal(t1, t2)
        assert e1 == e2


# ---------------------------------------------------------------------------- validation
@pytest.mark.parametrize("field, value", [
    ("stiffness", 0.0), ("stiffness", -3.0), ("damping", -0.1), ("penalty_law", "cubic"),
    ("detection", "sometimes"), ("interpolation", "quintic"), ("local_model", "predict"),
    ("tool", "needle"), ("tool_radius", -1e-3), ("margin", 0.0), ("penalty_length", float("nan")),
    ("passivity_controller", "yes"),
])
def test_bad_parameters_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        ContactParameters(**{field: value}).validate()
    pos, tri = tube_surface(walls="inner", n_along=3)
    with pytest.raises(ValueError, match=field):
        ContactModel(tri, pos.shape[0], 1, ContactParameters(**{"tool": "probe", field: value}))


def test_bad_inputs_raise_clear_errors():
    pos, tri = tube_surface(walls="inner", n_along=3)
    with pytest.raises(ValueError, match="surface_triangles"):
        ContactModel(tri + 1000, pos.shape[0], 3)
    model = ContactModel(tri, pos.shape[0], 3)
    with pytest.raises(ValueError, match="set_tissue_frame"):
        model.step(0.0, 1e-3, np.zeros((3, 3)))
    bad = pos.copy()
    bad[7, 1] = np.nan
    with pytest.raises(ValueError, match=r"tissue_positions.*\[7\]"):
        model.set_tissue_frame(0.0, bad, np.zeros_like(pos))
    with pytest.raises(ValueError, match="tissue_positions"):
        model.set_tissue_frame(0.0, pos[:-1], np.zeros_like(pos))
    model.set_tissue_frame(0.0, pos.ravel(), np.zeros(pos.size))    # flat arrays are accepted
    with pytest.raises(ValueError, match="tool_positions"):
        model.step(0.0, 1e-3, [[0.0, 0.0, np.nan], [0, 0, 0], [0, 0, 0]])
    with pytest.raises(ValueError, match="tool_positions"):
        model.step(0.0, 1e-3, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="dt"):
        model.step(0.0, 0.0, np.zeros((3, 3)))


def test_passivity_controller_is_refused_without_a_device_probe():
    """Its damping acts on a haptic device's point; on a catheter centerline (a kinematic chain that
    does not respond to it) the rendered force ran away to 1.3 kN on aaa_endovascular."""
    from haptic_fmu.model import ContactParameterError

    with pytest.raises(ContactParameterError, match="needs tool = 'probe'"):
        ContactParameters(passivity_controller=True, tool="centerline").validate()
    ContactParameters(passivity_controller=True, tool="probe").validate()

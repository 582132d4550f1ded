"""Tests of tissue_fmu.mesh: generators against analytic volumes/areas, conformity and
orientation against a slow plain-Python face count, quality against a per-tet linear-solve
reference, validation error messages and meshio round trips."""

from __future__ import annotations

import itertools
import logging
from collections import Counter

import meshio
import numpy as np
import pytest
import trimesh
from scipy.integrate import quad

from tissue_fmu.mesh import (
    MeshError,
    TetMesh,
    aaa_inner_radius,
    aaa_mesh,
    box_mesh,
    load_mesh,
    save_mesh,
    validate_mesh,
)

AAA_DEFAULTS = dict(aorta_radius=0.010, aneurysm_radius=0.025, aneurysm_length=0.060,
                    segment_length=0.130, wall_thickness=0.0015)


# ------------------------------------------------------------------------------ helpers


def slow_boundary_faces(tets: np.ndarray) -> tuple[set, Counter]:
    """Plain-Python reference: count each face by its node set; boundary faces appear once.

    Returns the boundary faces as cyclically normalised oriented triples and the counter.
    The orientation is taken from the tet's own geometry-free rule: for tet (a, b, c, d) the
    face opposite a, wound (b, c, d), has its normal pointing away from a when the tet is
    positively oriented, and likewise for the other three (with an odd permutation swap).
    """
    counter = Counter()
    oriented = {}
    for a, b, c, d in tets.tolist():
        for face in ((b, c, d), (a, d, c), (a, b, d), (a, c, b)):
            key = frozenset(face)
            counter[key] += 1
            oriented[key] = face
    boundary = set()
    for key, n in counter.items():
        if n == 1:
            f = oriented[key]
            i = f.index(min(f))  # rotate so the smallest id comes first (keeps the winding)
            boundary.add(f[i:] + f[:i])
    return boundary, counter


def normalise_triangles(triangles: np.ndarray) -> set:
    out = set()
    for f in triangles.tolist():
        i = f.index(min(f))
        out.add(tuple(f[i:] + f[:i]))
    return out


def surface_trimesh(mesh: TetMesh) -> trimesh.Trimesh:
    nodes, triangles = mesh.surface()
    return trimesh.Trimesh(mesh.points[nodes], triangles, process=False)


def triangle_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    p = points[triangles]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


# ------------------------------------------------------------------------------ box mesh


@pytest.mark.parametrize(
    "size, divisions, origin",
    [((1.0, 1.0, 1.0), (1, 1, 1), (0.0, 0.0, 0.0)),
     ((0.03, 0.02, 0.05), (3, 4, 5), (-0.01, 0.2, 1.0)),
     ((2.0, 0.5, 0.7), (7, 2, 3), (0.0, 0.0, 0.0))],
)
def test_box_volumes_area_and_conformity(size, divisions, origin):
    mesh = box_mesh(size, divisions, origin)
    lx, ly, lz = size
    nx, ny, nz = divisions
    assert mesh.n_tets == 6 * nx * ny * nz
    assert mesh.n_nodes == (nx + 1) * (ny + 1) * (nz + 1)
    volumes = mesh.volumes()
    # Every Kuhn tet of an hx x hy x hz cell has volume hx hy hz / 6.
    cell = lx * ly * lz / (nx * ny * nz)
    np.testing.assert_allclose(volumes, cell / 6.0, rtol=1e-12)
    assert volumes.sum() == pytest.approx(lx * ly * lz, rel=1e-13)

    # Conformity: a plain-Python face count says every face is shared by 1 or 2 tets, the
    # shared-once faces are exactly the 2 * 2 (nx ny + ny nz + nz nx) boundary triangles, and
    # they coincide (with winding) with what the vectorised surface() returns.
    boundary, counter = slow_boundary_faces(mesh.tets)
    assert set(counter.values()) <= {1, 2}
    assert len(boundary) == 4 * (nx * ny + ny * nz + nz * nx)
    nodes, triangles = mesh.surface()
    assert np.all(np.diff(nodes) > 0)
    assert normalise_triangles(nodes[triangles]) == boundary

    surf = surface_trimesh(mesh)
    assert surf.is_watertight and surf.is_winding_consistent
    assert surf.volume == pytest.approx(lx * ly * lz, rel=1e-12)
    assert surf.area == pytest.approx(2.0 * (lx * ly + ly * lz + lz * lx), rel=1e-12)


def test_box_outward_normals_and_node_sets():
    size, divisions, origin = (0.3, 0.2, 0.1), (3, 2, 4), np.array([1.0, -2.0, 0.5])
    mesh = box_mesh(size, divisions, tuple(origin))
    nodes, triangles = mesh.surface()
    global_tri = nodes[triangles]
    normals = triangle_normals(mesh.points, global_tri)
    centres = mesh.points[global_tri].mean(axis=1)
    lo, hi = origin, origin + np.array(size)
    for axis, name in enumerate("xyz"):
        for side, plane, sign in (("min", lo[axis], -1.0), ("max", hi[axis], 1.0)):
            on_face = np.isclose(centres[:, axis], plane, atol=1e-12)
            expected = np.zeros(3)
            expected[axis] = sign
            np.testing.assert_allclose(normals[on_face], np.broadcast_to(expected, (on_face.sum(), 3)),
                                       atol=1e-12)
            ids = mesh.node_sets[name + side]
            others = [d + 1 for i, d in enumerate(divisions) if i != axis]
            assert ids.size == others[0] * others[1]
            np.testing.assert_allclose(mesh.points[ids, axis], plane, atol=1e-15)
            # and no other node lies on that plane
            assert np.isclose(mesh.points[:, axis], plane, atol=1e-12).sum() == ids.size
    # each boundary triangle lies on exactly one face of the box
    on_any = sum(np.isclose(centres[:, a], v, atol=1e-12) for a in range(3) for v in (lo[a], hi[a]))
    assert np.all(on_any == 1)


# ------------------------------------------------------------------------------ quality


def slow_radius_ratio(p: np.ndarray) -> float:
    """Reference 3 r_in / r_circ for one tet: circumcentre from a 3x3 linear solve."""
    a, b, c = p[1] - p[0], p[2] - p[0], p[3] - p[0]
    rows = np.array([a, b, c])
    centre = np.linalg.solve(2.0 * rows, np.array([a @ a, b @ b, c @ c]))
    r_circ = np.linalg.norm(centre)
    volume = abs(np.linalg.det(rows)) / 6.0
    area = 0.0
    for i, j, k in itertools.combinations(range(4), 3):
        area += 0.5 * np.linalg.norm(np.cross(p[j] - p[i], p[k] - p[i]))
    return 3.0 * (3.0 * volume / area) / r_circ


def test_quality_regular_tet_is_one():
    points = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)
    tets = np.array([[0, 1, 2, 3]])
    if np.linalg.det(points[1:] - points[0]) < 0:
        tets = tets[:, [0, 1, 3, 2]]
    q = TetMesh(points, tets).quality()
    assert q["min_radius_ratio"] == pytest.approx(1.0, rel=1e-12)
    assert q["max_edge_ratio"] == pytest.approx(1.0, rel=1e-12)
    assert q["min_volume"] == pytest.approx(8.0 / 3.0, rel=1e-12)  # cube 8 minus 4 corners of 4/3


def test_quality_matches_slow_reference():
    mesh = aaa_mesh(n_circumferential=8, n_axial=6, n_radial=1)
    ratios = np.array([slow_radius_ratio(mesh.points[t]) for t in mesh.tets])
    edges = np.array([[np.linalg.norm(mesh.points[t[i]] - mesh.points[t[j]])
                       for i, j in itertools.combinations(range(4), 2)] for t in mesh.tets])
    q = mesh.quality()
    assert q["n_tets"] == mesh.n_tets and q["n_nodes"] == mesh.n_nodes
    assert q["min_radius_ratio"] == pytest.approx(ratios.min(), rel=1e-10)
    assert q["mean_radius_ratio"] == pytest.approx(ratios.mean(), rel=1e-10)
    assert q["max_edge_ratio"] == pytest.approx((edges.max(1) / edges.min(1)).max(), rel=1e-12)
    volumes = np.array([np.linalg.det(mesh.points[t[1:]] - mesh.points[t[0]]) / 6.0 for t in mesh.tets])
    assert q["min_volume"] == pytest.approx(volumes.min(), rel=1e-12)
    assert q["max_volume"] == pytest.approx(volumes.max(), rel=1e-12)
    assert 0.0 < q["min_radius_ratio"] <= 1.0


# ------------------------------------------------------------------------------ AAA mesh


def analytic_wall_volume(n_circumferential: int, p=AAA_DEFAULTS) -> float:
    """Wall volume of the faceted AAA: quadrature of pi ((r + h)^2 - r^2) dz, times the
    inscribed-polygon factor.

    The mesh's cross-section at height z is a regular n-gon inscribed in the circle of radius
    R, of area (n/2) R^2 sin(2 pi / n) = pi R^2 * sin(2 pi/n) / (2 pi/n).  That factor applies to
    both the outer and the inner polygon, so the faceted wall volume is the solid-of-revolution
    volume times sin(2 pi/n) / (2 pi/n) (0.955 for n = 12, 0.9936 for n = 32).
    """
    r = lambda z: aaa_inner_radius(z, p["aorta_radius"], p["aneurysm_radius"],
                                   p["aneurysm_length"], p["segment_length"])
    h = p["wall_thickness"]
    length, la = p["segment_length"], p["aneurysm_length"]
    ends = [0.5 * (length - la), 0.5 * length, 0.5 * (length + la)]  # kinks in r'' -> split there
    exact, _ = quad(lambda z: np.pi * ((r(z) + h) ** 2 - r(z) ** 2), 0.0, length, points=ends,
                    epsabs=0.0, epsrel=1e-13, limit=200)
    angle = 2.0 * np.pi / n_circumferential
    return exact * np.sin(angle) / angle


def axial_interpolation_bound(n_circumferential: int, n_axial: int, p=AAA_DEFAULTS) -> float:
    """Rigorous bound on |faceted volume - analytic_wall_volume|.

    Around the axis the faceting is exact (the factor above).  Along z the mesh follows the
    piecewise-linear interpolant r_pl of r between node rings (its trapezoidal faces are
    planar, so the cross-section at z is the n-gon of radius r_pl(z)).  The wall integrand
    pi((r+h)^2 - r^2) = pi(2 h r + h^2) is linear in r, so the error is factor * 2 pi h *
    int (r_pl - r) dz, and the trapezoid-rule bound gives |int (r_pl - r)| <= L dz^2/12 max|r''|
    with max|r''| = 2 pi^2 (R_a - R_0) / L_a^2 for the cos^2 bump.
    """
    angle = 2.0 * np.pi / n_circumferential
    dz = p["segment_length"] / n_axial
    max_r2 = 2.0 * np.pi ** 2 * (p["aneurysm_radius"] - p["aorta_radius"]) / p["aneurysm_length"] ** 2
    return (np.sin(angle) / angle * 2.0 * np.pi * p["wall_thickness"]
            * p["segment_length"] * dz ** 2 / 12.0 * max_r2)


# (n_circumferential, n_axial, n_radial): ~1k, default ~15k, ~40k and the >= 100k case once.
AAA_SIZES = [(12, 12, 1), (32, 40, 2), (24, 80, 3), (64, 132, 2)]


@pytest.fixture(scope="module", params=AAA_SIZES, ids=lambda s: "x".join(map(str, s)))
def aaa(request):
    nc, na, nr = request.param
    return (nc, na, nr), aaa_mesh(n_circumferential=nc, n_axial=na, n_radial=nr)


def test_aaa_counts_volumes_and_watertight_surface(aaa):
    (nc, na, nr), mesh = aaa
    assert mesh.n_tets == 6 * nc * na * nr
    assert mesh.n_nodes == nc * (na + 1) * (nr + 1)
    volumes = mesh.volumes()
    assert volumes.min() > 0.0
    surf = surface_trimesh(mesh)
    assert surf.is_watertight and surf.is_winding_consistent
    # The enclosed volume of the boundary equals the sum of the tets (round-off only) and is
    # positive, i.e. the surface is outward: an inward surface gives the negative volume.
    assert surf.volume > 0.0
    assert surf.volume == pytest.approx(volumes.sum(), rel=1e-10)
    # Against the analytic wall volume, with the faceting factor and the axial bound above.
    expected = analytic_wall_volume(nc)
    assert abs(surf.volume - expected) <= axial_interpolation_bound(nc, na) + 1e-12 * expected
    # Euler characteristic of a tube surface (torus-like) is 0; a hole or a stray patch breaks it.
    assert surf.euler_number == 0


def test_aaa_faceted_volume_is_exact_for_piecewise_linear_radius():
    """The tets fill exactly the stack of n-gon frusta through the node rings (round-off)."""
    nc, na = 16, 20
    mesh = aaa_mesh(n_circumferential=nc, n_axial=na, n_radial=2)
    z_nodes = np.linspace(0.0, AAA_DEFAULTS["segment_length"], na + 1)
    r_nodes = aaa_inner_radius(z_nodes)
    h = AAA_DEFAULTS["wall_thickness"]
    factor = np.sin(2 * np.pi / nc) / (2 * np.pi / nc)
    # Exact integral of the quadratic pi((r+h)^2 - r^2) = pi(2 h r + h^2) for linear r per interval.
    dz = np.diff(z_nodes)
    exact = factor * np.pi * np.sum(dz * (h * (r_nodes[1:] + r_nodes[:-1]) + h ** 2))
    assert mesh.volumes().sum() == pytest.approx(exact, rel=1e-12)


def test_aaa_faceting_correction_is_needed():
    """Fine in z, coarse around: the uncorrected solid-of-revolution volume misses the mesh by
    far more than the axial bound, the corrected one is within it."""
    nc, na = 16, 200
    mesh = aaa_mesh(n_circumferential=nc, n_axial=na, n_radial=1)
    volume = mesh.volumes().sum()
    corrected = analytic_wall_volume(nc)
    angle = 2 * np.pi / nc
    uncorrected = corrected / (np.sin(angle) / angle)
    bound = axial_interpolation_bound(nc, na)
    assert abs(volume - corrected) <= bound
    assert abs(volume - uncorrected) > 50 * bound


def test_aaa_node_and_element_sets(aaa):
    (nc, na, nr), mesh = aaa
    p = AAA_DEFAULTS
    pts = mesh.points
    radius = np.hypot(pts[:, 0], pts[:, 1])
    for name in ("inlet", "outlet", "inner", "outer"):
        assert mesh.node_sets[name].size > 0
    assert mesh.node_sets["inlet"].size == nc * (nr + 1)
    assert mesh.node_sets["outlet"].size == nc * (nr + 1)
    assert mesh.node_sets["inner"].size == nc * (na + 1)
    assert mesh.node_sets["outer"].size == nc * (na + 1)
    np.testing.assert_array_equal(pts[mesh.node_sets["inlet"], 2], 0.0)
    np.testing.assert_array_equal(pts[mesh.node_sets["outlet"], 2], p["segment_length"])
    assert np.sum(pts[:, 2] == 0.0) == mesh.node_sets["inlet"].size
    inner, outer = mesh.node_sets["inner"], mesh.node_sets["outer"]
    np.testing.assert_allclose(radius[inner], aaa_inner_radius(pts[inner, 2]), rtol=1e-12)
    np.testing.assert_allclose(radius[outer], aaa_inner_radius(pts[outer, 2]) + p["wall_thickness"],
                               rtol=1e-12)
    # Every node lies within the wall.
    r_in = aaa_inner_radius(pts[:, 2])
    assert np.all(radius >= r_in * (1 - 1e-12))
    assert np.all(radius <= (r_in + p["wall_thickness"]) * (1 + 1e-12))
    # The sac is exactly the elements whose centroid lies in the bulge, and it bulges.
    centroid = pts[mesh.tets].mean(axis=1)
    in_bulge = np.abs(centroid[:, 2] - 0.5 * p["segment_length"]) < 0.5 * p["aneurysm_length"]
    np.testing.assert_array_equal(mesh.element_sets["sac"], np.flatnonzero(in_bulge))
    assert mesh.element_sets["sac"].size > 0
    sac_radius = np.hypot(centroid[in_bulge, 0], centroid[in_bulge, 1])
    assert sac_radius.max() > p["aorta_radius"] + 0.5 * (p["aneurysm_radius"] - p["aorta_radius"])


def test_aaa_surface_orientation_by_region():
    """Outward means: outer wall points away from the axis, lumen wall towards it, inlet -z,
    outlet +z; every boundary triangle belongs to exactly one of these four regions."""
    mesh = aaa_mesh(n_circumferential=16, n_axial=20, n_radial=2)
    nodes, triangles = mesh.surface()
    tri = nodes[triangles]
    normals = triangle_normals(mesh.points, tri)
    centres = mesh.points[tri].mean(axis=1)
    radial = centres.copy()
    radial[:, 2] = 0.0
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    region = {name: np.isin(tri, ids).all(axis=1) for name, ids in mesh.node_sets.items()}
    # A triangle on the inlet ring edge may have all nodes in "inlet" and "inner"; classify
    # caps by normal-free geometry: cap triangles lie in the plane z = 0 or z = L.
    length = AAA_DEFAULTS["segment_length"]
    inlet = np.all(mesh.points[tri, 2] == 0.0, axis=1)
    outlet = np.all(mesh.points[tri, 2] == length, axis=1)
    inner = region["inner"] & ~inlet & ~outlet
    outer = region["outer"] & ~inlet & ~outlet
    assert np.all(inlet.astype(int) + outlet + inner + outer == 1)
    np.testing.assert_allclose(normals[inlet], [[0, 0, -1]] * inlet.sum(), atol=1e-12)
    np.testing.assert_allclose(normals[outlet], [[0, 0, 1]] * outlet.sum(), atol=1e-12)
    assert np.all(np.einsum("ij,ij->i", normals[outer], radial[outer]) > 0.5)
    assert np.all(np.einsum("ij,ij->i", normals[inner], radial[inner]) < -0.5)
    assert inlet.sum() == outlet.sum() == 2 * 16 * 2


@pytest.mark.parametrize(
    "kwargs, words",
    [(dict(wall_thickness=-1e-3), "wall_thickness must be finite and > 0"),
     (dict(aorta_radius=float("nan")), "aorta_radius must be finite"),
     (dict(n_circumferential=4), "n_circumferential must be >= 8"),
     (dict(n_axial=2.5), "n_axial must be an integer"),
     (dict(aneurysm_radius=0.005), "aneurysm_radius (0.005) must be >= aorta_radius"),
     (dict(aneurysm_length=0.2), "aneurysm_length (0.2) must be <= segment_length")],
)
def test_aaa_bad_parameters(kwargs, words):
    with pytest.raises(MeshError) as info:
        aaa_mesh(**kwargs)
    assert words in str(info.value)


def test_straight_tube_without_aneurysm():
    mesh = aaa_mesh(aneurysm_radius=0.010, n_circumferential=16, n_axial=10, n_radial=1)
    angle = 2 * np.pi / 16
    r, h, length = 0.010, 0.0015, 0.130
    # A straight faceted tube is exact: factor * pi ((r+h)^2 - r^2) L.
    expected = np.sin(angle) / angle * np.pi * ((r + h) ** 2 - r ** 2) * length
    assert mesh.volumes().sum() == pytest.approx(expected, rel=1e-12)


# ------------------------------------------------------------------------------ validation


def unit_cube_tets():
    mesh = box_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    return mesh.points.copy(), mesh.tets.copy()


def test_validate_accepts_generated_meshes():
    points, tets = unit_cube_tets()
    validate_mesh(points, tets)
    validate_mesh(points, tets.astype(np.int32))


@pytest.mark.parametrize(
    "corrupt, words",
    [(lambda p, t: (p[:, :2], t), ["points must have shape (n, 3)"]),
     (lambda p, t: (p, t[:, :3]), ["tets must have shape (m, 4)"]),
     (lambda p, t: (p, t.astype(float)), ["integer node ids", "float64"]),
     (lambda p, t: (p.astype(complex), t), ["real numbers"]),
     (lambda p, t: (np.where(np.arange(8)[:, None] == 5, np.nan, p), t), ["NaN", "[5]"]),
     (lambda p, t: (np.where(np.arange(8)[:, None] == 2, np.inf, p), t), ["Inf", "[2]"]),
     (lambda p, t: (p, np.where(np.arange(6)[:, None] == 3, t + 100, t)),
      ["outside [0, 7]", "1 element(s)", "[3]"]),
     (lambda p, t: (p, np.vstack([t, [[0, 1, 1, 2]]])), ["repeat a node", "[6]"]),
     (lambda p, t: (p, t[:, [0, 1, 3, 2]]), ["6 inverted", "[0, 1, 2, 3, 4, 5]",
                                               "swap two nodes", "fix_orientation=True"]),
     (lambda p, t: (p, np.vstack([t, [[0, 1, 2, 3]]])), ["degenerate", "[6]"]),  # coplanar face z=0
     (lambda p, t: (p, np.vstack([t, t[:1]])), ["non-manifold", "shared by more than two"])],
)
def test_validate_rejects_bad_input(corrupt, words):
    points, tets = unit_cube_tets()
    bad_points, bad_tets = corrupt(points, tets)
    with pytest.raises(MeshError) as info:
        validate_mesh(bad_points, bad_tets)
    for word in words:
        assert word in str(info.value)
    with pytest.raises(MeshError):  # the container refuses the same input
        TetMesh(bad_points, bad_tets)


def test_degenerate_threshold_is_relative():
    """A tiny but well-shaped tet (1e-5 m edges) is fine; a sliver flattened to 1e-13 of its
    size is degenerate whatever the scale."""
    base = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    tets = np.array([[0, 1, 2, 3]])
    for scale in (1e-5, 1.0, 1e4):
        validate_mesh(base * scale, tets)
        flat = base.copy()
        flat[3, 2] = 1e-13
        with pytest.raises(MeshError, match="degenerate"):
            validate_mesh(flat * scale, tets)


def test_unreferenced_nodes_warn_not_raise(caplog):
    points, tets = unit_cube_tets()
    points = np.vstack([points, [[5.0, 5.0, 5.0]]])
    with caplog.at_level(logging.WARNING, logger="tissue_fmu.mesh"):
        validate_mesh(points, tets)
    assert "not used by any tet" in caplog.text and "[8]" in caplog.text


def test_bad_node_set_rejected():
    points, tets = unit_cube_tets()
    with pytest.raises(MeshError, match="node set 'clamp' holds ids outside"):
        TetMesh(points, tets, {"clamp": np.array([0, 99])})


# ------------------------------------------------------------------------------ file I/O


@pytest.mark.parametrize("suffix", [".vtu", ".msh"])
def test_save_load_round_trip(tmp_path, suffix):
    mesh = aaa_mesh(n_circumferential=12, n_axial=10, n_radial=1)
    path = tmp_path / f"aaa{suffix}"
    save_mesh(mesh, path)
    back = load_mesh(path)
    np.testing.assert_array_equal(back.points, mesh.points)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    assert back.node_sets.keys() == mesh.node_sets.keys()
    for name in mesh.node_sets:
        np.testing.assert_array_equal(back.node_sets[name], mesh.node_sets[name])
    np.testing.assert_array_equal(back.element_sets["sac"], mesh.element_sets["sac"])


def test_msh_is_gmsh_readable_by_meshio(tmp_path):
    mesh = box_mesh(divisions=(2, 1, 1))
    save_mesh(mesh, tmp_path / "box.msh")
    raw = meshio.read(tmp_path / "box.msh", file_format="gmsh")
    np.testing.assert_array_equal(raw.cells_dict["tetra"], mesh.tets)


def test_load_fix_orientation_and_drop_unreferenced(tmp_path):
    mesh = box_mesh(divisions=(2, 2, 1))
    flipped = mesh.tets.copy()
    flipped[::3] = flipped[::3][:, [1, 0, 2, 3]]
    extra_points = np.vstack([[[9.0, 9.0, 9.0]], mesh.points])  # unused node 0 shifts all ids
    path = tmp_path / "flipped.vtu"
    meshio.write(path, meshio.Mesh(extra_points, [("tetra", flipped + 1),
                                                  ("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(MeshError, match="inverted"):
        load_mesh(path)
    fixed = load_mesh(path, fix_orientation=True)
    np.testing.assert_array_equal(fixed.points, mesh.points)
    assert fixed.volumes().min() > 0
    np.testing.assert_allclose(np.sort(fixed.volumes()), np.sort(mesh.volumes()), rtol=1e-14)
    assert fixed.volumes().sum() == pytest.approx(1.0, rel=1e-14)


def test_load_errors(tmp_path):
    with pytest.raises(MeshError, match="mesh file not found"):
        load_mesh(tmp_path / "missing.vtu")
    garbage = tmp_path / "garbage.vtu"
    garbage.write_text("this is not a VTU file")
    with pytest.raises(MeshError, match="could not read mesh file"):
        load_mesh(garbage)
    unknown = tmp_path / "mesh.unknownext"
    unknown.write_text("1 2 3")
    with pytest.raises(MeshError, match="could not read mesh file"):
        load_mesh(unknown)
    surface_only = tmp_path / "surface.vtu"
    meshio.write(surface_only, meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(MeshError, match=r"no linear tetrahedra.*\['triangle'\]"):
        load_mesh(surface_only)

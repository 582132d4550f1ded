"""Tests of anatomy.centerline against analytic centerlines and radii.

The surfaces are built here with plain numpy: rings of vertices swept along a known axis (two
triangles per quad, wound so the normals point out of the lumen), and a Y bifurcation as the zero
level of a union of capsules, triangulated by marching tetrahedra. Their axes and inscribed-sphere
radii are known in closed form (or by a dense 1-D minimisation of the profile), independently of
the voxels, sections and distance queries of the code under test.
"""
from __future__ import annotations

import itertools
import logging
import time

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from anatomy import centerline as centerline_module
from anatomy.centerline import Centerline, compute_centerline
from anatomy.ends import OpenEnd, capped, open_ends
from anatomy.errors import AnatomyError

MM = 1e-3
#: the centerline's contract: off the analytic axis by less than 5 % of the local radius
AXIS_TOLERANCE = 0.05
#: The radius is the distance to the faceted surface, whose polygons of 64 sides lie inside the
#: analytic circle by up to r (1 - cos(pi / 64)) = 0.12 % of r (and the rings' chords along the
#: axis by less): 1 % leaves room for that and nothing else.
RADIUS_TOLERANCE = 0.01


# ------------------------------------------------------------------------------ analytic surfaces


def swept_tube(centres: np.ndarray, tangents: np.ndarray, normals: np.ndarray, radii: np.ndarray,
               n_around: int = 64) -> trimesh.Trimesh:
    """Rings of ``n_around`` vertices of the given radii around ``centres``, open at both ends.

    The frame (e1, e2, t) is right-handed and the rings run along t, so the triangles (a, b, d)
    and (a, d, c) of each quad have normals pointing away from the axis: out of the lumen.
    """
    t = tangents / np.linalg.norm(tangents, axis=1, keepdims=True)
    e1 = normals - np.sum(normals * t, axis=1, keepdims=True) * t
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(t, e1)
    angle = 2 * np.pi * np.arange(n_around) / n_around
    rings = centres[:, None] + radii[:, None, None] * (np.cos(angle)[None, :, None] * e1[:, None]
                                                       + np.sin(angle)[None, :, None] * e2[:, None])
    k, j = np.meshgrid(np.arange(len(centres) - 1), np.arange(n_around), indexing="ij")
    a, b = k * n_around + j, k * n_around + (j + 1) % n_around
    c, d = a + n_around, b + n_around
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return trimesh.Trimesh(rings.reshape(-1, 3), faces, process=False)


def z_tube(z: np.ndarray, radii: np.ndarray, n_around: int = 64) -> trimesh.Trimesh:
    """A tube around the z axis with the radius profile ``radii`` at heights ``z``."""
    centres = np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1)
    return swept_tube(centres, np.tile([0.0, 0.0, 1.0], (len(z), 1)), np.tile([1.0, 0.0, 0.0], (len(z), 1)),
                      radii, n_around)


def straight_tube(radius: float = 10 * MM, length: float = 100 * MM) -> trimesh.Trimesh:
    z = np.linspace(0.0, length, 41)
    return z_tube(z, np.full(len(z), radius))


TORUS_MAJOR, TORUS_MINOR = 60 * MM, 10 * MM


def torus_segment() -> trimesh.Trimesh:
    """90 degrees of a torus in the xy plane: a curved tube whose axis is a circle of radius 60 mm."""
    phi = np.linspace(0.0, np.pi / 2, 91)
    centres = TORUS_MAJOR * np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)
    tangents = np.stack([-np.sin(phi), np.cos(phi), np.zeros_like(phi)], axis=1)
    return swept_tube(centres, tangents, centres, np.full(len(phi), TORUS_MINOR))


BULGE = dict(r0=10 * MM, ra=25 * MM, L=60 * MM, zc=65 * MM, length=130 * MM)


def bulge_radius(z: np.ndarray, r0: float, ra: float, L: float, zc: float, length: float) -> np.ndarray:
    """r(z) = r0 + (ra - r0) cos^2(pi (z - zc) / L) for |z - zc| < L / 2, else r0."""
    return np.where(np.abs(z - zc) < L / 2, r0 + (ra - r0) * np.cos(np.pi * (z - zc) / L) ** 2, r0)


def bulged_tube(n_around: int = 64, rings: int = 131, **shape) -> trimesh.Trimesh:
    z = np.linspace(0.0, shape["length"], rings)
    return z_tube(z, bulge_radius(z, **shape), n_around)


def inscribed_radius(z: np.ndarray, shape: dict) -> np.ndarray:
    """The largest sphere centred on the axis at z inside the surface of revolution r(z').

    Its radius is the distance to the nearest surface point, min over z' of sqrt(r(z')^2 + (z - z')^2),
    here by brute force over z' every micrometre: on the bulge's flanks it is well below r(z).
    """
    dense = np.linspace(0.0, shape["length"], int(round(shape["length"] / 1e-6)) + 1)
    r = bulge_radius(dense, **shape)
    return np.array([np.sqrt(r ** 2 + (zi - dense) ** 2).min() for zi in z])


def segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip((points - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - a - t[..., None] * ab, axis=-1)


def marching_tetrahedra(values: np.ndarray, origin: np.ndarray, spacing: float) -> trimesh.Trimesh:
    """The surface values == 0 of a sampled function, normals towards values > 0 (out of the region < 0).

    Each grid cube is split into the six tetrahedra around its main diagonal (consistent across
    neighbouring cubes); a crossing vertex is named by its grid edge, so the surface is closed
    wherever the region does not reach the grid's border, and open (a boundary loop) where it does.
    """
    flat = values.ravel()
    strides = np.array([values.shape[1] * values.shape[2], values.shape[2], 1])
    cubes = np.stack(np.meshgrid(*[np.arange(n - 1) for n in values.shape], indexing="ij"), -1).reshape(-1, 3)
    base = cubes @ strides
    corners = np.array(list(itertools.product((0, 1), repeat=3))) @ strides
    negative = flat[base[:, None] + corners] < 0
    base = base[negative.any(axis=1) & ~negative.all(axis=1)]

    def position(index):
        return origin + np.stack(np.unravel_index(index, values.shape), -1) * spacing

    # the crossing edges of a tetrahedron, its inside corners sorted first, by number inside
    cases = {1: [[(0, 1), (0, 2), (0, 3)]], 3: [[(3, 0), (3, 1), (3, 2)]],
             2: [[(0, 2), (0, 3), (1, 3)], [(0, 2), (1, 3), (1, 2)]]}
    edges, outward = [], []
    for order in itertools.permutations(range(3)):
        path = np.concatenate([[0], np.cumsum(np.eye(3, dtype=np.int64)[list(order)], axis=0) @ strides])
        tets = base[:, None] + path
        inside = flat[tets] < 0
        tets = np.take_along_axis(tets, np.argsort(~inside, axis=1, kind="stable"), axis=1)
        count = inside.sum(axis=1)
        for n_inside, triangles in cases.items():
            chosen = tets[count == n_inside]
            corner = position(chosen)
            for triangle in triangles:
                edges.append(np.stack([chosen[:, list(edge)] for edge in triangle], axis=1))
                outward.append(corner[:, n_inside:].mean(axis=1) - corner[:, :n_inside].mean(axis=1))
    edges = np.sort(np.concatenate(edges), axis=2)
    outward = np.concatenate(outward)
    keys, faces = np.unique(edges[..., 0] * flat.size + edges[..., 1], return_inverse=True)
    a, b = keys // flat.size, keys % flat.size
    t = flat[a] / (flat[a] - flat[b])
    vertices = position(a) + t[:, None] * (position(b) - position(a))
    faces = faces.reshape(-1, 3)
    corner = vertices[faces]
    normals = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])
    flip = np.sum(normals * outward, axis=1) < 0
    faces[flip] = faces[flip][:, ::-1]
    return trimesh.Trimesh(vertices, faces, process=False)


FORK = np.array([0.0, 0.0, 80 * MM])
#: The marching tetrahedra's facets (cells of 1 mm, slivers among them, on radii of 6 and 10 mm)
#: lie inside the capsules by up to about 1 % of the radius (measured 0.95 %): twice that.
Y_RADIUS_TOLERANCE = 0.02
AORTA = (np.array([0.0, 0.0, 200 * MM]), FORK, 10 * MM)
ILIACS = {side: (FORK, np.array([side * 50 * MM, 0.0, -20 * MM]), 6 * MM) for side in (-1, 1)}


def y_bifurcation(spacing: float = 1 * MM) -> trimesh.Trimesh:
    """An aorta (r 10 mm, along z) splitting at z = 80 mm into two iliacs (r 6 mm, 26.6 deg off the z axis).

    The union of three capsules, cut by the box z in [0, 150] mm: the aorta leaves through the
    top and each iliac through the bottom, obliquely; the grid is offset by an irrational fraction
    of its spacing so no sample is exactly on the surface.
    """
    low = np.array([-60 * MM, -16 * MM, 0.0]) + spacing / np.pi
    shape = np.ceil((np.array([60 * MM, 16 * MM, 150 * MM]) - low) / spacing).astype(int) + 1
    grid = np.stack(np.meshgrid(*[low[i] + spacing * np.arange(shape[i]) for i in range(3)], indexing="ij"), -1)
    capsules = [AORTA, *ILIACS.values()]
    values = np.min([segment_distance(grid, a, b) - r for a, b, r in capsules], axis=0)
    return marching_tetrahedra(values, low, spacing)


def polyline_distance(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Distance of each point from a polyline (the nearest of its segments)."""
    a, ab = polyline[:-1], np.diff(polyline, axis=0)
    t = np.clip(np.einsum("pkj,kj->pk", points[:, None] - a, ab) / np.sum(ab * ab, axis=1), 0.0, 1.0)
    return np.linalg.norm(points[:, None] - a - t[..., None] * ab, axis=2).min(axis=1)


def axis_deviation(points: np.ndarray) -> np.ndarray:
    """Distance of points from the z axis."""
    return np.hypot(points[:, 0], points[:, 1])


def end_nearest(surface: trimesh.Trimesh, point) -> OpenEnd:
    """The open end whose centre is nearest ``point``."""
    return min(open_ends(surface), key=lambda end: np.linalg.norm(end.center - point))


# ---------------------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def tube():
    surface = straight_tube()
    assert capped(surface).volume > 0
    return surface


@pytest.fixture(scope="module")
def tube_line(tube):
    return compute_centerline(tube, end_nearest(tube, [0, 0, 0]).center, end_nearest(tube, [0, 0, 0.1]).center)


@pytest.fixture(scope="module")
def y_surface():
    surface = y_bifurcation()
    assert capped(surface).volume > 0 and capped(surface).is_watertight
    assert len(open_ends(surface)) == 3
    return surface


@pytest.fixture(scope="module")
def y_lines(y_surface):
    aorta = end_nearest(y_surface, [0, 0, 0.15])
    return {side: compute_centerline(y_surface, aorta.center, end_nearest(y_surface, [side * 0.04, 0, 0]).center)
            for side in (-1, 1)}


# ----------------------------------------------------------------------------------- analytic shapes


def test_straight_tube_centerline_is_its_axis_to_round_off(tube_line):
    points = tube_line.points
    deviation = axis_deviation(points) / (10 * MM)
    print(f"straight tube: max deviation / r = {deviation.max():.2e}, "
          f"max radius error / r = {np.abs(tube_line.radius / (10 * MM) - 1).max():.2e}")
    assert deviation.max() < AXIS_TOLERANCE
    # sections of a prism are centred on its axis whatever their tilt: exact, not to the voxel size
    assert deviation.max() < 1e-9
    # the ends are the open ends' centres, the points evenly spaced in between
    np.testing.assert_allclose(points[[0, -1], 2], [0.0, 0.1], atol=1e-12)
    np.testing.assert_allclose(tube_line.length(), 0.1, rtol=1e-9)
    steps = np.diff(tube_line.arclength())
    assert steps.max() - steps.min() < 1e-9
    np.testing.assert_allclose(tube_line.radius, 10 * MM, rtol=RADIUS_TOLERANCE)


def test_a_rotated_straight_tube_gives_the_rotated_axis():
    """No alignment with the voxel grid helps: an arbitrarily turned and shifted tube is as exact."""
    rotation = Rotation.from_euler("xyz", [0.4, -1.1, 2.3])
    offset = np.array([0.31, -0.12, 0.05])
    surface = straight_tube()
    surface.vertices = rotation.apply(surface.vertices) + offset
    start, end = rotation.apply([[0, 0, 0], [0, 0, 0.1]]) + offset
    line = compute_centerline(surface, end_nearest(surface, start).center, end_nearest(surface, end).center)
    deviation = segment_distance(line.points, start, end) / (10 * MM)
    assert deviation.max() < 1e-9
    np.testing.assert_allclose(line.radius, 10 * MM, rtol=RADIUS_TOLERANCE)


def test_torus_segment_centerline_follows_the_circle():
    surface = torus_segment()
    assert capped(surface).volume > 0
    line = compute_centerline(surface, end_nearest(surface, [TORUS_MAJOR, 0, 0]).center,
                              end_nearest(surface, [0, TORUS_MAJOR, 0]).center)
    x, y, z = line.points.T
    deviation = np.hypot(np.hypot(x, y) - TORUS_MAJOR, z) / TORUS_MINOR
    # the axis circle is the locus of the largest inscribed spheres, of radius exactly the minor radius
    radius_error = np.abs(line.radius / TORUS_MINOR - 1)
    print(f"torus: max deviation / r = {deviation.max():.2e}, max radius error / r = {radius_error.max():.2e}")
    assert deviation.max() < AXIS_TOLERANCE
    assert radius_error.max() < RADIUS_TOLERANCE
    np.testing.assert_allclose(line.length(), TORUS_MAJOR * np.pi / 2, rtol=1e-3)
    assert np.all(np.diff(np.arctan2(y, x)) > 0)          # monotone from start to end


def test_bulged_tube_centerline_and_radius():
    surface = bulged_tube(**BULGE)
    assert capped(surface).volume > 0
    line = compute_centerline(surface, end_nearest(surface, [0, 0, 0]).center,
                              end_nearest(surface, [0, 0, BULGE["length"]]).center)
    z = line.points[:, 2]
    deviation = axis_deviation(line.points) / bulge_radius(z, **BULGE)
    # the radius is the distance to the wall, not the cross-section's r(z): on the bulge's flanks
    # (slope up to 0.79) the nearest wall is up the flank. The wall (the surface without its caps)
    # is what is measured, so the open ends need no exclusion zone.
    expected = inscribed_radius(z, BULGE)
    radius_error = np.abs(line.radius / expected - 1)
    print(f"bulge: max deviation / r = {deviation.max():.2e}, max radius error / r = {radius_error.max():.2e}")
    assert deviation.max() < AXIS_TOLERANCE
    assert radius_error.max() < RADIUS_TOLERANCE
    assert np.all(np.diff(z) > 0)


def test_a_closed_surface_without_open_ends_works_too():
    """Already capped: no open end gives the default voxel size, 2 V / A (a tube's radius) is used."""
    surface = capped(torus_segment())
    start = TORUS_MAJOR * np.array([1.0, 0.01, 0.0])
    end = TORUS_MAJOR * np.array([0.01, 1.0, 0.0])
    line = compute_centerline(surface, start, end)
    x, y, z = line.points.T
    assert (np.hypot(np.hypot(x, y) - TORUS_MAJOR, z) / TORUS_MINOR).max() < AXIS_TOLERANCE


# --------------------------------------------------------------------------------------- bifurcation


def test_bifurcation_each_iliac_end_picks_its_branch(y_surface, y_lines):
    for side, line in y_lines.items():
        target = end_nearest(y_surface, [side * 0.04, 0, 0])
        points = line.points
        assert np.linalg.norm(points[-1] - target.center) < target.radius
        assert np.linalg.norm(points[0] - end_nearest(y_surface, [0, 0, 0.15]).center) < 10 * MM
        # below the crotch (where the iliacs part, z = 68 mm) every point is in its own branch,
        # on the iliac's axis
        below = points[:, 2] < 62 * MM
        assert np.all(np.sign(points[below, 0]) == side)
        a, b, r = ILIACS[side]
        deviation = segment_distance(points[below], a, b) / r
        print(f"bifurcation, iliac {side:+d}: max deviation / r = {deviation.max():.2e}")
        assert deviation.max() < AXIS_TOLERANCE
        assert np.all(np.abs(line.radius[below] / r - 1) < Y_RADIUS_TOLERANCE)


def test_bifurcation_paths_share_the_aorta(y_lines):
    left, right = y_lines[-1].points, y_lines[1].points
    a, b, r = AORTA
    above = left[:, 2] > FORK[2] + r          # an aortic radius above the fork: the aorta, not the fork
    deviation = segment_distance(left[above], a, b) / r
    print(f"bifurcation, aorta: max deviation / r = {deviation.max():.2e}")
    assert deviation.max() < AXIS_TOLERANCE
    assert np.all(np.abs(y_lines[-1].radius[above] / r - 1) < Y_RADIUS_TOLERANCE)
    # each point of one path's aortic part lies on the other path
    assert polyline_distance(left[above], right).max() < 0.01 * r
    assert y_lines[-1].length() == pytest.approx(y_lines[1].length(), rel=1e-3)


def test_bifurcation_centerline_is_smooth_through_the_fork(y_lines):
    """Where the sections are not tube-like the voxel path is kept, corrected: no kink."""
    for line in y_lines.values():
        steps = np.diff(line.points, axis=0)
        cosine = np.sum(steps[1:] * steps[:-1], axis=1) / np.prod(np.linalg.norm([steps[1:], steps[:-1]], axis=2), 0)
        assert np.degrees(np.arccos(np.clip(cosine, -1, 1))).max() < 15.0


# ---------------------------------------------------------------------------------------- bad inputs


@pytest.mark.parametrize("start, words", [
    ([np.nan, 0.0, 0.0], ["start", "not finite", "open end"]),
    ([0.0, 0.0], ["start", "shape (2,)", "(3,)"]),
    ("aorta", ["start", "not numeric"]),
])
def test_malformed_points_are_refused(tube, start, words):
    with pytest.raises(AnatomyError) as error:
        compute_centerline(tube, start, [0.0, 0.0, 0.1])
    for word in words:
        assert word in str(error.value)


def test_a_point_far_outside_the_lumen_is_refused_with_the_ends_centres(tube):
    outer = end_nearest(tube, [0, 0, 0.1])
    with pytest.raises(AnatomyError) as error:
        compute_centerline(tube, [0.0, 0.0, 0.0], outer.center + 30 * MM * outer.normal)
    message = str(error.value)
    for words in ("end point", "30 mm outside the lumen", "radius", "open end's centre", "[0, 0, 0.1]"):
        assert words in message


def test_a_point_slightly_outside_is_taken_to_the_lumen(tube):
    """Less than a radius off (a click beside the cut) is fine: the path starts at the nearest inside."""
    outer = end_nearest(tube, [0, 0, 0.1])
    line = compute_centerline(tube, [0.0, 0.0, 0.0], outer.center + 3 * MM * outer.normal + [0.0, 2 * MM, 0.0])
    assert axis_deviation(line.points).max() < AXIS_TOLERANCE * 10 * MM
    assert line.points[-1, 2] > 0.095


def test_ends_of_two_separate_tubes_are_not_connected():
    surface = trimesh.util.concatenate([straight_tube(), straight_tube().apply_translation([30 * MM, 0, 0])])
    with pytest.raises(AnatomyError) as error:
        compute_centerline(surface, end_nearest(surface, [0, 0, 0]).center,
                           end_nearest(surface, [0.03, 0, 0.1]).center)
    assert "not connected inside the lumen" in str(error.value)
    assert "separate vessels" in str(error.value)


def test_a_sheet_encloses_no_volume():
    sheet = trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0]], [[0, 1, 2], [0, 2, 3]],
                            process=False)
    with pytest.raises(AnatomyError) as error:
        compute_centerline(sheet, [0.01, 0.01, 0.0], [0.09, 0.09, 0.0])
    assert "does not enclose a volume" in str(error.value)


def test_inward_normals_are_refused(tube):
    inverted = trimesh.Trimesh(tube.vertices, tube.faces[:, ::-1], process=False)
    with pytest.raises(AnatomyError) as error:
        compute_centerline(inverted, [0.0, 0.0, 0.0], [0.0, 0.0, 0.1])
    assert "normals point into the lumen" in str(error.value)
    assert "flip" in str(error.value)


def test_a_non_manifold_surface_is_refused(tube):
    # a second copy of a triangle away from the open ends: its edges are then shared by three triangles
    middle = len(tube.faces) // 4
    doubled = trimesh.Trimesh(tube.vertices, np.concatenate([tube.faces, tube.faces[middle:middle + 1]]),
                              process=False)
    with pytest.raises(AnatomyError) as error:
        compute_centerline(doubled, [0.0, 0.0, 0.0], [0.0, 0.0, 0.1])
    assert "not closed" in str(error.value)
    assert "shared by [3] triangles instead of 2" in str(error.value)


@pytest.mark.parametrize("resolution", [0.0, -1 * MM, np.nan])
def test_a_bad_resolution_is_refused(tube, resolution):
    with pytest.raises(AnatomyError) as error:
        compute_centerline(tube, [0.0, 0.0, 0.0], [0.0, 0.0, 0.1], resolution=resolution)
    assert "resolution must be a positive voxel size" in str(error.value)


def test_start_and_end_in_one_voxel_are_refused(tube):
    with pytest.raises(AnatomyError) as error:
        compute_centerline(tube, [0.0, 0.0, 0.0], [0.0, 0.0, 0.1 * MM])
    assert "fall in one" in str(error.value)


# ------------------------------------------------------------------------------- grid and log lines


def test_the_default_voxel_size_is_logged(tube, caplog):
    with caplog.at_level(logging.INFO, logger="anatomy.centerline"):
        compute_centerline(tube, [0.0, 0.0, 0.0], [0.0, 0.0, 0.1])
    # the end's radius is its 64-gon's area-equivalent radius, just under 10 mm
    radius = 10 * np.sqrt(64 * np.sin(2 * np.pi / 64) / (2 * np.pi))
    assert f"voxel size {radius / 8:.3g} mm (narrowest radius {radius:.3g} mm / 8)" in caplog.text


def test_the_grid_is_bounded_and_the_coarsening_logged(tube, caplog, monkeypatch):
    """A requested voxel size that would overflow the bound is coarsened, with a warning; the
    refinement on the surface keeps the centerline exact anyway."""
    monkeypatch.setattr(centerline_module, "MAX_INSIDE", 5_000)
    with caplog.at_level(logging.INFO, logger="anatomy.centerline"):
        line = compute_centerline(tube, [0.0, 0.0, 0.0], [0.0, 0.0, 0.1], resolution=0.5 * MM)
    assert any(record.levelno == logging.WARNING and "coarsened" in record.getMessage() for record in caplog.records)
    assert axis_deviation(line.points).max() < 1e-9


def test_a_200k_triangle_aorta_runs_within_its_budget(capsys):
    """30 cm of aorta (r 10 mm) with a 30 mm sac, 200 000 triangles; the time is printed, not asserted."""
    shape = dict(r0=10 * MM, ra=30 * MM, L=80 * MM, zc=150 * MM, length=300 * MM)
    surface = bulged_tube(n_around=400, rings=251, **shape)
    assert len(surface.faces) == 200_000
    began = time.perf_counter()
    line = compute_centerline(surface, [0.0, 0.0, 0.0], [0.0, 0.0, shape["length"]])
    elapsed = time.perf_counter() - began
    with capsys.disabled():
        print(f"\n200k-triangle aorta: centerline of {len(line.points)} points in {elapsed:.1f} s")
    z = line.points[:, 2]
    deviation = axis_deviation(line.points) / bulge_radius(z, **shape)
    radius_error = np.abs(line.radius / inscribed_radius(z, shape) - 1)
    with capsys.disabled():
        print(f"200k-triangle aorta: max deviation / r = {deviation.max():.2e}, "
              f"max radius error / r = {radius_error.max():.2e}")
    assert deviation.max() < AXIS_TOLERANCE
    assert radius_error.max() < RADIUS_TOLERANCE


# ------------------------------------------------------------------------------------ the dataclass


def test_centerline_length_arclength_and_resampling():
    # a right angle of two legs 3 and 4 m, radius rising linearly along it
    line = Centerline(np.array([[0.0, 0, 0], [3, 0, 0], [3, 4, 0]]), np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(line.arclength(), [0, 3, 7])
    assert line.length() == 7.0
    fine = line.resampled(0.5)
    assert len(fine.points) == 15
    np.testing.assert_allclose(np.diff(fine.arclength()), 0.5)
    np.testing.assert_allclose(fine.points[6], [3, 0, 0])
    np.testing.assert_allclose(fine.radius[[0, 6, 14]], [1, 2, 3])
    assert line.resampled(100.0).points.shape == (2, 3)


def test_centerline_is_immutable_and_checked():
    line = Centerline(np.zeros((2, 3)) + [[0, 0, 0], [0, 0, 1]], np.ones(2))
    with pytest.raises(ValueError):
        line.points[0, 0] = 1.0
    with pytest.raises(AnatomyError, match="positive length"):
        line.resampled(0.0)
    with pytest.raises(AnatomyError, match=r"\(n, 3\) points"):
        Centerline(np.zeros((3, 2)), np.ones(3))
    with pytest.raises(AnatomyError, match=r"\(n, 3\) points"):
        Centerline(np.zeros((3, 3)), np.ones(2))

"""Reading lumen surfaces as a surgeon's data arrive, and the broken ones: each gives a clear error or a
repaired surface with the repair reported, never a traceback and never a silently wrong wall."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from anatomy.ends import capped, open_ends
from anatomy.errors import AnatomyError
from anatomy.surface import MAX_TRIANGLES, check_surface, read_surface
from anatomy.wall import lumen_of
from tissue_fmu.mesh import aaa_mesh


@pytest.fixture(scope="module")
def lumen() -> trimesh.Trimesh:
    """Today's generated fusiform aneurysm as a segmentation would deliver its lumen."""
    return lumen_of(aaa_mesh())


def _copy(mesh, vertices=None, faces=None) -> trimesh.Trimesh:
    return trimesh.Trimesh(mesh.vertices.copy() if vertices is None else vertices,
                           mesh.faces.copy() if faces is None else faces, process=False)


@pytest.mark.parametrize("suffix", ["stl", "obj", "ply"])
def test_each_format_reads_the_same_surface_with_its_two_open_ends(lumen, tmp_path, suffix):
    path = tmp_path / f"lumen.{suffix}"
    lumen.export(path)
    surface = read_surface(path)
    assert surface.units == "m" and not surface.repairs
    assert len(surface.mesh.faces) == len(lumen.faces) == 2560
    assert surface.mesh.area == pytest.approx(lumen.area, rel=1e-6)
    assert sorted(round(float(e.center[2]), 6) for e in surface.ends) == [0.0, 0.13]
    # a 32-gon inscribed in the 10 mm circle: its area-equivalent radius
    polygon = 0.010 * np.sqrt(32 * np.sin(2 * np.pi / 32) / (2 * np.pi))
    assert [e.radius for e in surface.ends] == pytest.approx([polygon, polygon], rel=1e-6)
    assert capped(surface.mesh).volume > 0          # normals out of the lumen


def test_millimetres_are_detected_and_converted(lumen, tmp_path):
    _copy(lumen, vertices=lumen.vertices * 1000.0).export(tmp_path / "mm.stl")
    surface = read_surface(tmp_path / "mm.stl")
    assert surface.units == "mm" and "detected" in surface.report()
    assert surface.mesh.area == pytest.approx(lumen.area, rel=1e-9)
    assert read_surface(tmp_path / "mm.stl", units="mm").units_given


def test_units_that_make_no_vessel_are_refused(lumen, tmp_path):
    _copy(lumen, vertices=lumen.vertices * 1e6).export(tmp_path / "huge.stl")
    with pytest.raises(AnatomyError, match="in no unit of"):
        read_surface(tmp_path / "huge.stl")
    with pytest.raises(AnatomyError, match="check the units"):
        check_surface(lumen, units="mm")             # a 0.13 mm aorta


def test_inverted_normals_are_flipped_and_reported(lumen):
    inverted = _copy(lumen)
    inverted.invert()
    surface = check_surface(inverted, "m")
    assert any("flipped the normals" in r for r in surface.repairs)
    assert capped(surface.mesh).volume == pytest.approx(capped(lumen).volume, rel=1e-12)
    with pytest.raises(AnatomyError, match="normals point into the lumen"):
        check_surface(inverted, "m", repair=False)


def _sac_faces_near(mesh, point, radius):
    return np.linalg.norm(mesh.triangles_center - np.asarray(point), axis=1) < radius


def test_a_small_hole_in_the_sac_is_closed_and_reported(lumen):
    vertex = int(np.argmin(np.linalg.norm(lumen.vertices - [0.025, 0.0, 0.065], axis=1)))
    hole = (lumen.faces == vertex).any(axis=1)             # the triangles around one vertex: a clean hole
    assert hole.sum() == 6
    surface = check_surface(_copy(lumen, faces=lumen.faces[~hole]), "m")
    assert any("closed 1 small hole" in r for r in surface.repairs)
    assert len(surface.ends) == 2
    assert surface.mesh.is_winding_consistent and capped(surface.mesh).is_watertight


def test_a_large_hole_in_the_sac_is_refused_with_where_it_is(lumen):
    hole = _sac_faces_near(lumen, (0.025, 0.0, 0.065), 0.012)
    with pytest.raises(AnatomyError, match=r"a hole in the wall around \(0\.02.*mm across"):
        check_surface(_copy(lumen, faces=lumen.faces[~hole]), "m")


def test_holes_that_touch_at_a_vertex_are_refused_by_name(lumen):
    vertex = int(np.argmin(np.linalg.norm(lumen.vertices - [0.025, 0.0, 0.065], axis=1)))
    ring = np.flatnonzero((lumen.faces == vertex).any(axis=1))
    # two triangles of the ring that share only the centre vertex: a bow-tie of two holes
    first = ring[0]
    apart = next(f for f in ring[1:] if len(set(lumen.faces[f]) & set(lumen.faces[first])) == 1)
    keep = np.ones(len(lumen.faces), bool)
    keep[[first, apart]] = False
    with pytest.raises(AnatomyError, match="pinched at 1 vertex"):
        check_surface(_copy(lumen, faces=lumen.faces[keep]), "m")


def test_a_self_intersection_is_refused_with_where_it_is(lumen):
    vertices = lumen.vertices.copy()
    # push a patch of the sac through the opposite wall
    patch = (np.abs(vertices[:, 2] - 0.065) < 0.005) & (vertices[:, 0] > 0.02)
    vertices[patch, 0] -= 0.06
    with pytest.raises(AnatomyError, match="intersects itself around"):
        check_surface(_copy(lumen, vertices=vertices), "m")


def test_a_point_cloud_an_empty_file_and_garbage_are_refused(lumen, tmp_path):
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(lumen.vertices).export(cloud)
    with pytest.raises(AnatomyError, match="point cloud"):
        read_surface(cloud)
    (tmp_path / "empty.stl").write_bytes(b"")
    with pytest.raises(AnatomyError, match="empty"):
        read_surface(tmp_path / "empty.stl")
    (tmp_path / "garbage.stl").write_bytes(b"solid x\n this is not an stl\n")
    with pytest.raises(AnatomyError, match="no triangles|could not read"):
        read_surface(tmp_path / "garbage.stl")
    (tmp_path / "wall.vtu").write_text("x")
    with pytest.raises(AnatomyError, match="not a surface format"):
        read_surface(tmp_path / "wall.vtu")
    with pytest.raises(AnatomyError, match="no such file"):
        read_surface(tmp_path / "missing.stl")


def test_a_ten_million_triangle_file_is_refused_before_it_is_loaded(tmp_path):
    path = tmp_path / "huge.stl"
    count = 10_000_000
    with path.open("wb") as f:       # a binary STL's header and count; the rest a sparse hole of its size
        f.write(b"\0" * 80 + np.uint32(count).tobytes())
        f.truncate(84 + 50 * count)
    with pytest.raises(AnatomyError, match=f"10000000 triangles, more than MAX_TRIANGLES = {MAX_TRIANGLES}"):
        read_surface(path)


def test_a_closed_surface_two_vessels_and_a_non_manifold_edge_are_refused(lumen):
    with pytest.raises(AnatomyError, match="no open vessel end"):
        check_surface(capped(lumen), "m")
    second = _copy(lumen, vertices=lumen.vertices + [0.1, 0.0, 0.0])
    two = trimesh.util.concatenate([lumen, second])
    with pytest.raises(AnatomyError, match="2 separate surfaces"):
        check_surface(two, "m")
    vertices = lumen.vertices.copy()       # a third triangle on one edge: a fin
    extra = trimesh.Trimesh(np.vstack([vertices, [[0.0, 0.0, 0.065]]]),
                            np.vstack([lumen.faces, [[*lumen.faces[0, :2], len(vertices)]]]), process=False)
    with pytest.raises(AnatomyError, match="not manifold"):
        check_surface(extra, "m")


def test_specks_degenerate_and_duplicate_triangles_are_removed_and_reported(lumen):
    speck = trimesh.creation.icosphere(subdivisions=0, radius=0.0005)
    speck.apply_translation([0.05, 0.05, 0.05])
    faces = np.vstack([lumen.faces, lumen.faces[:3], [[0, 0, 1]]])    # duplicates and a degenerate one
    noisy = trimesh.util.concatenate([_copy(lumen, faces=faces), speck])
    surface = check_surface(noisy, "m")
    assert any("removed 4 degenerate or duplicate" in r for r in surface.repairs)
    assert any("dropped 1 speck" in r for r in surface.repairs)
    assert len(surface.mesh.faces) == len(lumen.faces)


def test_non_finite_coordinates_are_refused(lumen):
    vertices = lumen.vertices.copy()
    vertices[7, 1] = np.nan
    with pytest.raises(AnatomyError, match="NaN or infinite coordinates"):
        check_surface(_copy(lumen, vertices=vertices), "m")


def test_open_ends_point_out_of_the_vessel(lumen):
    ends = sorted(open_ends(lumen), key=lambda e: e.center[2])
    assert ends[0].normal == pytest.approx([0, 0, -1], abs=1e-12)
    assert ends[1].normal == pytest.approx([0, 0, 1], abs=1e-12)

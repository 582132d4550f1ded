"""The pipeline from a checked lumen to a scene's anatomy: ends, sac, thickness, the catheter's path."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from anatomy_shapes import tube_of_revolution

from anatomy.ends import capped, open_ends
from anatomy.errors import AnatomyError
from anatomy.pipeline import AIM_SHORT, WallOptions, build_anatomy
from anatomy.surface import check_surface
from anatomy.wall import lumen_of
from tissue_fmu.mesh import aaa_inner_radius, aaa_mesh


@pytest.fixture(scope="module")
def surface():
    return check_surface(lumen_of(aaa_mesh()), "m", source="generated fusiform")


@pytest.fixture(scope="module")
def anatomy(surface):
    return build_anatomy(surface, WallOptions(remesh="never"))


def test_the_fusiform_sac_and_the_path_are_the_default_scenes(anatomy):
    """The default scene's typed path: up the axis to z = 40 mm, then to (22, 0, 65) mm, 3 mm short of
    the sac wall on its +x side. The computed one: the same within millimetres."""
    assert (anatomy.access, anatomy.target) == (0, 1)
    # the sac's equator, +x (a section through the nearest centerline point, 1.25 mm apart)
    assert anatomy.wall_point == pytest.approx([0.025, 0.0, 0.065], abs=1e-3)
    assert anatomy.centerline.points[anatomy.sac_index][2] == pytest.approx(0.065, abs=2e-3)
    path = anatomy.path
    assert np.abs(path[:-1, :2]).max() < 1e-6                    # up the axis
    assert path[-2, 2] == pytest.approx(0.040, abs=2e-3)          # turns at one sac reach before the centre
    assert np.linalg.norm(anatomy.wall_point - path[-1]) == pytest.approx(AIM_SHORT, rel=1e-9)
    assert not anatomy.notes


def test_a_thinner_sac_wall_thins_smoothly_where_the_lumen_dilates(surface):
    anatomy = build_anatomy(surface, WallOptions(remesh="never", thickness=0.0015, sac_thickness=0.001))
    wall = anatomy.wall
    gap = np.linalg.norm(wall.points[wall.node_sets["outer"]] - wall.points[wall.node_sets["inner"]], axis=1)
    radius = aaa_inner_radius(wall.points[wall.node_sets["inner"], 2]) / 0.010
    assert gap[radius < 1.15] == pytest.approx(0.0015, rel=1e-9)        # the healthy aorta
    assert gap[radius > 1.55] == pytest.approx(0.001, rel=1e-9)         # the sac: 1.5x dilated and more
    between = (radius > 1.25) & (radius < 1.45)
    assert ((gap[between] < 0.0015) & (gap[between] > 0.001)).all()
    sac = wall.element_sets["sac"]
    centres = wall.points[wall.tets[sac]].mean(axis=1)
    assert len(sac) and (np.abs(centres[:, 2] - 0.065) < 0.03).all()


def test_ends_are_chosen_by_height_or_by_number(surface):
    anatomy = build_anatomy(surface, WallOptions(remesh="never"), access=1, target=0)
    assert anatomy.centerline.points[0][2] == pytest.approx(0.13, abs=1e-9)
    with pytest.raises(AnatomyError, match="numbered 0 to 1"):
        build_anatomy(surface, WallOptions(remesh="never"), access=2)
    with pytest.raises(AnatomyError, match="the same end"):
        build_anatomy(surface, WallOptions(remesh="never"), access=1, target=1)
    with pytest.raises(AnatomyError, match="remesh = 'sometimes'"):
        build_anatomy(surface, WallOptions(remesh="sometimes"))
    with pytest.raises(AnatomyError, match="edge_length = 3"):
        build_anatomy(surface, WallOptions(edge_length=3.0))


def _tube() -> trimesh.Trimesh:
    return tube_of_revolution(lambda z: 0.010, 0.1, 32, 34)


def test_a_straight_tube_has_no_aneurysm_and_says_so():
    anatomy = build_anatomy(check_surface(_tube(), "m"), WallOptions(remesh="never"))
    assert anatomy.notes and "no aneurysm on the path" in anatomy.notes[0]
    assert np.hypot(*anatomy.wall_point[:2]) == pytest.approx(0.010, rel=1e-6)


def test_a_vessel_with_one_open_end_has_no_path():
    tube = _tube()
    closed_top = trimesh.Trimesh(tube.vertices, tube.faces, process=False)
    top = max(open_ends(closed_top), key=lambda e: e.center[2])
    with pytest.raises(AnatomyError, match="1 open end"):
        build_anatomy(check_surface(capped(closed_top, [top]), "m"), WallOptions(remesh="never"))

"""Scenes from anatomy: the command line end to end, the round trip of the default scene's forces, and
every parametric aneurysm meshed and run with contact."""
from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from anatomy.family import FAMILY
from anatomy.remesh import gmsh_problem
from anatomy.surface import read_surface
from anatomy.wall import build_wall, lumen_of
from orchestration.observers.recorder import read_stream
from orchestration.run.simulation import run_scene
from orchestration.scene.loading import load_scene
from orchestration.scene.model import SceneError
from orchestration.scene.toml_writer import dumps
from project import SCENE_DIR, shipped_scenes
from tissue_fmu.mesh import aaa_inner_radius, aaa_mesh, save_mesh

REPO = Path(__file__).resolve().parent.parent

#: The round trip's tolerances on the default scene's haptic force, as measured: peak 0.5717 N against
#: 0.5728 N (0.2 %), largest difference of any sample 0.039 N (the rebuilt wall's compliance is
#: 1-3 % off, like its eigenfrequencies), the force the controller settles at equal to 1e-8 N.
PEAK_TOLERANCE = 0.01
SAMPLE_TOLERANCE = 0.05     # N
#: The scene written from the same lumen follows the computed centerline, not the typed path
#: (measured: peak 0.585 N, 2 % above the default scene's).
COMPUTED_PATH_PEAK_TOLERANCE = 0.05


def _cli(*args, cwd=REPO):
    return subprocess.run([sys.executable, "-m", "orchestration", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=900)


def _force(out: Path) -> tuple[np.ndarray, np.ndarray]:
    time, contact = read_stream(out / "contact.csv")
    return time, np.linalg.norm(np.stack([contact[f"tool_force[{i}]"] for i in range(3)], axis=1), axis=1)


@pytest.fixture(scope="module")
def default_run(fmus_in_repo, tmp_path_factory):
    out = tmp_path_factory.mktemp("default")
    summary, _ = run_scene(load_scene("aaa_endovascular"), out, progress=False, plots=False, vtu=False)
    assert summary["status"] == "completed", summary["error"]
    return _force(out)


@pytest.fixture(scope="module")
def lumen_stl(tmp_path_factory) -> Path:
    """The generator's fusiform aneurysm as a segmentation exports it: its lumen, in millimetres."""
    path = tmp_path_factory.mktemp("lumen") / "fusiform_mm.stl"
    lumen = lumen_of(aaa_mesh())
    lumen.apply_scale(1000.0)
    lumen.export(path)
    return path


def test_the_default_scene_on_the_rebuilt_wall_renders_the_same_force(default_run, lumen_stl, tmp_path):
    surface = read_surface(lumen_stl)
    z = surface.mesh.vertices[:, 2]
    dz = 1e-7
    slope = (aaa_inner_radius(z + dz) - aaa_inner_radius(z - dz)) / (2 * dz)
    # the generator's wall, radial: 1.5 mm across, 1.5 mm cos(slope) along the normal
    save_mesh(build_wall(surface, 0.0015 / np.sqrt(1 + slope ** 2), layers=2), tmp_path / "wall.vtu")
    scene = load_scene("aaa_endovascular", {"tissue.mesh_file": str(tmp_path / "wall.vtu"), "tissue.clamp": "ends"})
    summary, _ = run_scene(scene, tmp_path / "out", progress=False, plots=False, vtu=False)
    assert summary["status"] == "completed", summary["error"]
    time, force = _force(tmp_path / "out")
    expected_time, expected = default_run
    assert np.array_equal(time, expected_time)
    assert force.max() == pytest.approx(expected.max(), rel=PEAK_TOLERANCE)
    assert np.abs(force - expected).max() < SAMPLE_TOLERANCE
    assert force[-1] == pytest.approx(expected[-1], abs=1e-6)


def test_the_command_writes_a_scene_that_runs_like_the_default(default_run, lumen_stl, tmp_path):
    proc = _cli("scene-from-anatomy", lumen_stl, "--out", tmp_path / "scene", "--remesh", "never")
    assert proc.returncode == 0, proc.stderr
    assert "in mm (detected)" in proc.stdout and "run it: python -m orchestration run" in proc.stdout
    scene_file = tmp_path / "scene" / "fusiform_mm.toml"
    for name in ("fusiform_mm_wall.vtu", "fusiform_mm_lumen.stl", "fusiform_mm_centerline.csv"):
        assert (tmp_path / "scene" / name).is_file()
    data = tomllib.loads(scene_file.read_text())
    tissue = data["fmu"]["tissue"]["parameters"]
    assert tissue["mesh_file"] == {"file": "fusiform_mm_wall.vtu"}
    assert (tissue["n_surface_nodes"], tissue["n_surface_triangles"]) == (2688, 5376)   # the default wall's
    assert data["fmu"]["contact"]["parameters"]["n_surface_nodes"] == 2688
    # the computed path: up the axis, then across the sac to 3 mm short of its wall at z = 65 mm
    path = np.reshape(data["fmu"]["catheter"]["parameters"]["centerline_points"], (-1, 3))
    assert np.abs(path[:-1, :2]).max() < 1e-3 and path[0, 2] < 1e-3
    assert np.hypot(*path[-1, :2]) == pytest.approx(0.025 - 0.003 * 0.7, abs=1.5e-3)
    out = tmp_path / "results"
    proc = _cli("run", scene_file, "--out", out, "--quiet", "--no-vtu")
    assert proc.returncode == 0, proc.stderr
    _, force = _force(out)
    _, expected = default_run
    assert force.max() == pytest.approx(expected.max(), rel=COMPUTED_PATH_PEAK_TOLERANCE)
    assert force[-1] == pytest.approx(0.4, rel=1e-3)        # the controller's setpoint, as in the default scene

    again = _cli("scene-from-anatomy", lumen_stl, "--out", tmp_path / "scene", "--remesh", "never")
    assert again.returncode == 2 and "already exist" in again.stderr and "--force" in again.stderr
    assert _cli("scene-from-anatomy", lumen_stl, "--out", tmp_path / "scene", "--remesh", "never",
                "--force", "--quiet").returncode == 0


def test_a_broken_surface_is_a_usage_error_naming_it(tmp_path):
    (tmp_path / "empty.stl").write_bytes(b"")
    proc = _cli("scene-from-anatomy", tmp_path / "empty.stl", "--out", tmp_path / "scene")
    assert proc.returncode == 2 and proc.stderr.startswith("error: ") and "empty" in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "scene").exists()
    proc = _cli("scene-from-anatomy", "family:torus", "--out", tmp_path / "scene")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr


@pytest.mark.slow
@pytest.mark.parametrize("member", sorted(FAMILY))
def test_every_parametric_aneurysm_builds_meshes_and_runs_with_contact(member, fmus_in_repo, tmp_path):
    if gmsh_problem():                      # the bifurcation's marching surface is remeshed
        pytest.skip(gmsh_problem())
    proc = _cli("scene-from-anatomy", f"family:{member}", "--out", tmp_path, "--duration", 1, "--contact-time", 0.5)
    assert proc.returncode == 0, proc.stderr
    scene_file = tmp_path / f"aaa_{member}.toml"
    summary, _ = run_scene(load_scene(scene_file), tmp_path / "out", progress=False, plots=False, vtu=False)
    assert summary["status"] == "completed", summary["error"]
    time, force = _force(tmp_path / "out")
    touching = np.flatnonzero(force > 0.01)
    assert touching.size, f"{member}: the catheter never met the wall"
    assert time[touching[0]] < 0.9, f"{member}: contact at {time[touching[0]]} s, expected near 0.5 s"
    assert np.isfinite(force).all() and force.max() < 7.9, force.max()


def test_a_file_parameter_is_resolved_beside_the_scene_and_checked(fmus_in_repo, tmp_path):
    data = tomllib.loads((SCENE_DIR / "aaa_endovascular.toml").read_text())
    save_mesh(aaa_mesh(), tmp_path / "wall.vtu")
    data["fmu"]["tissue"]["parameters"]["mesh_file"] = {"file": "wall.vtu"}
    (tmp_path / "scene.toml").write_text(dumps(data))
    scene = load_scene(tmp_path / "scene.toml")
    assert scene.components["tissue"].parameters["mesh_file"] == str((tmp_path / "wall.vtu").resolve())
    data["fmu"]["tissue"]["parameters"]["mesh_file"] = {"file": "missing.vtu"}
    (tmp_path / "scene.toml").write_text(dumps(data))
    with pytest.raises(SceneError, match=r"parameters.mesh_file: the file 'missing.vtu' is not in the scene's folder"):
        load_scene(tmp_path / "scene.toml")
    data["fmu"]["tissue"]["parameters"]["mesh_file"] = {"path": "wall.vtu"}
    (tmp_path / "scene.toml").write_text(dumps(data))
    with pytest.raises(SceneError, match=r"a table value names a file"):
        load_scene(tmp_path / "scene.toml")


@pytest.mark.parametrize("name", shipped_scenes())
def test_the_toml_writer_round_trips_every_shipped_scene(name):
    data = tomllib.loads((SCENE_DIR / f"{name}.toml").read_text())
    assert tomllib.loads(dumps(data, "a comment\nof two lines")) == data

"""``scene-from-anatomy``: a runnable scene from a lumen surface (a patient's, or a parametric aneurysm).

The scene is the default scene (``scenes/aaa_endovascular.toml``) on another anatomy: the same
FMUs, connections, records and plots, with the Tissue FMU on the wall built from the surface (a
mesh file beside the scene), the structural sizes of that wall, the catheter on the computed path,
and the operator's insertion timed to that path. Written into a folder of its own: the scene, the
wall, the lumen it was built on and the centerline with its radius, so that a user can look at each.
"""
from __future__ import annotations

import logging
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fmu_build.paths import SCENE_DIR
from orchestration.scene.toml_writer import dumps

logger = logging.getLogger(__name__)

TEMPLATE = SCENE_DIR / "aaa_endovascular.toml"
#: The operator's motion, the default scene's: hold still for HOLD, then push at PUSH_SPEED until
#: OVERSHOOT past the insertion where the tip meets the wall, then hold.
HOLD = 0.2
PUSH_SPEED = 0.014 / 2.3
OVERSHOOT = 0.0058
#: The insertion at which the tip meets the wall, past the path's end (which stops AIM_SHORT before
#: the wall): the catheter's active section carries the tip off the path, so it is measured, on the
#: default scene (contact at 1.55 s: insertion 0.0782 m, its path 0.0733 m long).
TOUCH_PAST_PATH = 0.0049
#: the simulated region around the point of contact, as in the default scene
ACTIVE_RADIUS = 0.03
DEFAULT_DURATION = 4.0
DEFAULT_CONTACT_TIME = 1.5


@dataclass(frozen=True)
class AnatomyScene:
    """The files ``write_anatomy_scene`` wrote."""

    scene: Path
    wall: Path
    lumen: Path
    centerline: Path
    contact_time: float      # when the tip should meet the sac wall (s)


def _round(values, digits: int = 7) -> list[float]:
    """Coordinates to 0.1 um: readable, and far below any length that matters here."""
    return [round(float(v), digits) for v in np.ravel(values)]


def operator_script(path_length: float, contact_time: float, duration: float) -> tuple[list[float], list[float]]:
    """(times, insertion): the default scene's motion, timed so that the tip meets the wall at contact_time."""
    if not HOLD < contact_time < duration:
        raise ValueError(f"the contact time ({contact_time:g} s) must come after the operator's first {HOLD:g} s "
                         f"and before the end of the scene ({duration:g} s)")
    touch = path_length + TOUCH_PAST_PATH
    start = touch - PUSH_SPEED * (contact_time - HOLD)
    stop = touch + OVERSHOOT
    push_end = HOLD + (stop - start) / PUSH_SPEED
    if push_end < duration:
        return [0.0, HOLD, push_end, duration], [start, start, stop, stop]
    return [0.0, HOLD, duration], [start, start, start + PUSH_SPEED * (duration - HOLD)]


def scene_data(anatomy, name: str, wall_file: str, duration: float = DEFAULT_DURATION,
               contact_time: float = DEFAULT_CONTACT_TIME) -> dict:
    """The default scene's data with this anatomy in it."""
    with TEMPLATE.open("rb") as f:
        data = tomllib.load(f)
    nodes, triangles = anatomy.wall.surface()
    sizes = {"n_surface_nodes": int(len(nodes)), "n_surface_triangles": int(len(triangles))}
    data["scene"].update(name=name, duration=float(duration),
                         description=f"catheter into the aneurysm of {Path(anatomy.surface.source).name}: "
                                     "deformable wall, 1 kHz haptic force, active tip")
    tissue = data["fmu"]["tissue"]["parameters"]
    tissue.update(mesh_file={"file": wall_file}, clamp="ends", **sizes,
                  active_center=_round(anatomy.wall_point), active_radius=ACTIVE_RADIUS)
    data["fmu"]["contact"]["parameters"].update(sizes)
    catheter = data["fmu"]["catheter"]["parameters"]
    catheter.update(n_centerline_points=int(len(anatomy.path)), centerline_points=_round(anatomy.path))
    times, insertion = operator_script(anatomy.path_length, contact_time, duration)
    data["source"]["operator"].update(times=_round(times, 9), outputs={"insertion": _round(insertion),
                                                                       "rotation": [0.0] * len(times)})
    return data


def _comment(anatomy, name: str) -> str:
    surface, centerline = anatomy.surface, anatomy.centerline
    lines = [
        f"{name}: the default scene on the anatomy of {surface.source}",
        "written by `python -m orchestration scene-from-anatomy`; see docs/anatomy.md.",
        "",
        f"lumen: {len(surface.mesh.faces)} triangles in {surface.units}; "
        f"{len(surface.ends)} open ends (access {anatomy.access}, target {anatomy.target})",
        *[f"  {r}" for r in surface.repairs],
        f"wall: {anatomy.wall.n_nodes} nodes, {anatomy.wall.n_tets} tetrahedra (worst radius ratio "
        f"{anatomy.wall.quality()['min_radius_ratio']:.3f}); clamped at its ends (node set 'ends')",
        f"centerline: {centerline.length() * 1e3:.1f} mm, radius {centerline.radius.min() * 1e3:.1f}-"
        f"{centerline.radius.max() * 1e3:.1f} mm (inscribed); the sac reaches {anatomy.sac_reach * 1e3:.1f} mm from it "
        f"({anatomy.sac_reach / anatomy.reference_radius:.2f}x the neck's radius)",
        "the catheter follows the centerline to the sac's reach before its centre, then crosses the sac",
        "towards its farthest wall; n_surface_nodes and n_surface_triangles are the wall's (they size the",
        "Tissue and Contact FMUs' arrays): build the wall again with this command rather than editing them.",
        *[f"note: {n}" for n in anatomy.notes],
    ]
    return "\n".join(lines)


def write_anatomy_scene(anatomy, out_dir, name: str, *, duration: float = DEFAULT_DURATION,
                        contact_time: float = DEFAULT_CONTACT_TIME, force: bool = False) -> AnatomyScene:
    """Write ``<name>.toml``, ``<name>_wall.vtu``, ``<name>_lumen.stl`` and ``<name>_centerline.csv`` into
    ``out_dir``; files already there are kept unless ``force`` (they may be a user's edits)."""
    from tissue_fmu.mesh import save_mesh

    out = Path(out_dir)
    paths = AnatomyScene(scene=out / f"{name}.toml", wall=out / f"{name}_wall.vtu", lumen=out / f"{name}_lumen.stl",
                         centerline=out / f"{name}_centerline.csv", contact_time=contact_time)
    existing = [p for p in (paths.scene, paths.wall, paths.lumen, paths.centerline) if p.exists()]
    if existing and not force:
        raise FileExistsError(f"{', '.join(str(p) for p in existing)} already exist(s): choose another --out or "
                              "--name, or pass --force to replace them")
    data = scene_data(anatomy, name, paths.wall.name, duration, contact_time)
    out.mkdir(parents=True, exist_ok=True)
    save_mesh(anatomy.wall, paths.wall)
    anatomy.surface.mesh.export(paths.lumen)
    table = np.column_stack([anatomy.centerline.arclength(), anatomy.centerline.points, anatomy.centerline.radius])
    np.savetxt(paths.centerline, table, delimiter=",", fmt="%.7g", header="arclength_m,x_m,y_m,z_m,radius_m",
               comments="")
    paths.scene.write_text(dumps(data, _comment(anatomy, name)))
    return paths

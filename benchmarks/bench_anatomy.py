"""From a 200k-triangle lumen surface to a runnable scene, against the 60 s target; and the tissue step on
the wall it builds against the generated default wall.

Setting: a parametric aneurysm (default: the bifurcation, the hardest: a marching-cubes junction)
exported as a binary STL of about 200k triangles in millimetres, as a segmentation delivers it; then
`scene-from-anatomy`'s pipeline stage by stage (read and check, remesh to 3 mm with gmsh, check again,
centerline, wall, scene files). The tissue step: ETMM implicit at 30 Hz, viscosity 50 Pa s, 0.5 N on
the 4 surface nodes nearest the catheter's aim, whole wall active, median of the timed steps after 3
warm-up steps, on the built wall and on the generated default wall side by side in one run (this
2-core machine is shared: compare the ratio, not the absolute times, between runs).

Run: python benchmarks/bench_anatomy.py [--member bifurcation] [--triangles 200000] [--steps 10]
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from anatomy.family import lumen_surface
from anatomy.pipeline import WallOptions, build_anatomy
from anatomy.surface import read_surface
from orchestration.app.anatomy_scene import write_anatomy_scene
from tissue_fmu import TissueModel, TissueParameters, aaa_mesh

TARGET_S = 60.0
FRAME = 1.0 / 30.0


def _timed(label: str, stages: list, function, *args, **kwargs):
    start = time.perf_counter()
    result = function(*args, **kwargs)
    stages.append((label, time.perf_counter() - start))
    return result


def build_scene(member: str, triangles: int, folder: Path) -> tuple[list, object]:
    stages: list[tuple[str, float]] = []
    mesh = _timed(f"generate the {member} lumen ({triangles} triangles asked)", stages, lumen_surface, member,
                  triangles=triangles)
    mesh.apply_scale(1000.0)                       # millimetres, as segmentations export
    path = folder / f"{member}.stl"
    mesh.export(path)
    print(f"lumen surface: {len(mesh.faces)} triangles, {path.stat().st_size / 1e6:.1f} MB binary STL")
    work: list[tuple[str, float]] = []
    surface = _timed("read and check the surface", work, read_surface, path)
    anatomy = _timed("remesh, check, centerline, wall", work, build_anatomy, surface, WallOptions())
    _timed("write the scene, wall, lumen and centerline", work, write_anatomy_scene, anatomy, folder / "scene", member)
    return stages + work, anatomy


def step_cost(mesh, point: np.ndarray, steps: int, clamp: tuple[str, ...]) -> float:
    model = TissueModel(mesh, TissueParameters(law="etmm", integrator="implicit", viscosity=50.0, clamp=clamp))
    d = np.linalg.norm(model.surface_positions() - point, axis=1)
    force = np.zeros((model.n_surface, 3))
    nearest = np.argsort(d)[:4]
    normal = model.surface_positions()[nearest].mean(axis=0) - point
    force[nearest] = 0.5 / 4 * normal / max(np.linalg.norm(normal), 1e-12)
    times = []
    for k in range(steps + 3):
        model.set_contact_force(force)
        start = time.perf_counter()
        model.step(k * FRAME, FRAME)
        times.append(time.perf_counter() - start)
    return statistics.median(times[3:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--member", default="bifurcation")
    parser.add_argument("--triangles", type=int, default=200_000)
    parser.add_argument("--steps", type=int, default=10)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        stages, anatomy = build_scene(args.member, args.triangles, Path(tmp))
    pipeline = sum(seconds for label, seconds in stages if not label.startswith("generate"))
    for label, seconds in stages:
        print(f"  {label:<55} {seconds:7.2f} s")
    print(f"surface file to scene: {pipeline:.1f} s = {pipeline / TARGET_S:.2f} x the {TARGET_S:.0f} s target")
    wall = anatomy.wall
    print(f"built wall: {wall.n_nodes} nodes, {wall.n_tets} tetrahedra, worst radius ratio "
          f"{wall.quality()['min_radius_ratio']:.3f}")
    default = aaa_mesh()
    built = step_cost(wall, anatomy.wall_point, args.steps, ("ends",))
    generated = step_cost(default, np.array([0.025, 0.0, 0.065]), args.steps, ("inlet", "outlet"))
    print(f"tissue step (ETMM implicit, 0.5 N, whole wall): built wall {1e3 * built:.1f} ms, generated default "
          f"({default.n_tets} tetrahedra) {1e3 * generated:.1f} ms: ratio {built / generated:.2f} "
          f"(tetrahedra ratio {wall.n_tets / default.n_tets:.2f})")


if __name__ == "__main__":
    main()

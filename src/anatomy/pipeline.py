"""From a checked lumen surface to what a scene needs: the wall, the centerline and the catheter's path.

The steps, each its own module: remesh the surface to the wall's element size when its triangles
do not fit (:mod:`anatomy.remesh`), check it again (:mod:`anatomy.surface`), compute the centerline
from the access end to the target end (:mod:`anatomy.centerline`), find the sac on it, build the wall
(:mod:`anatomy.wall`), thinner in the sac when asked, and lay the catheter's path: up the centerline to
the sac's reach before the sac's centre, then across the sac to just short of its farthest wall, where
the catheter meets it as in the default scene.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from tissue_fmu.mesh import TetMesh

from .centerline import Centerline, compute_centerline, farthest_walls
from .distance import SurfaceDistance
from .errors import AnatomyError
from .remesh import remesh
from .surface import LumenSurface, check_surface
from .wall import build_wall

logger = logging.getLogger(__name__)

REMESH_CHOICES = ("auto", "always", "never")
#: "auto" keeps the surface's own triangles when their mean edge is within this factor of the wall's
#: element size and the worst of them is not a sliver
KEPT_EDGE_FACTOR = 1.6
KEPT_MIN_QUALITY = 0.2
#: An aneurysm is a permanent focal dilatation of at least 50 % of the normal diameter (Johnston et al.,
#: "Suggested standards for reporting on arterial aneurysms", J Vasc Surg 1991); the wall thins from
#: the healthy thickness to the sac's between 1.2x and 1.5x the neck's radius.
SAC_DILATION = (1.2, 1.5)
#: The catheter's path ends this far short of the sac wall: the tip starts free and meets the wall
#: when the operator pushes (as in the default scene).
AIM_SHORT = 0.003
#: A centerline point whose inscribed radius is below this fraction of the target end's is in a branch
#: (an iliac artery is about half the aorta's radius), not in the aorta where the sac is.
BRANCH_RADIUS = 0.75
#: The catheter's path keeps this far from the wall until it nears the point it aims at: a 6 Fr
#: catheter's radius (1 mm) and a margin.
PATH_CLEARANCE = 0.0015
#: The widest sections tried for a straight approach to the sac's wall, widest first.
MAX_SAC_CANDIDATES = 40
#: Spacing of the catheter path's vertices along the centerline (the catheter's link is 5 mm).
PATH_SPACING = 0.005


@dataclass(frozen=True)
class WallOptions:
    """How the wall is built from the lumen."""

    #: wall thickness in m (healthy aorta: about 1.5-2 mm)
    thickness: float = 0.0015
    #: thickness in the sac in m (AAA walls: about 1-2.5 mm), None: the same everywhere
    sac_thickness: float | None = None
    #: element layers across the wall
    layers: int = 2
    #: the wall's element size along the surface in m (the default wall's elements are 2-5 mm)
    edge_length: float = 0.003
    #: "auto" remeshes when the surface's triangles do not fit edge_length, "always", "never"
    remesh: str = "auto"

    def validate(self) -> None:
        if self.remesh not in REMESH_CHOICES:
            raise AnatomyError(f"remesh = {self.remesh!r} is not one of {', '.join(REMESH_CHOICES)}")
        for name in ("thickness", "edge_length") + (("sac_thickness",) if self.sac_thickness is not None else ()):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
                raise AnatomyError(f"{name} must be a length > 0 in metres (got {value!r})")
        if not 5e-4 <= self.edge_length <= 0.02:
            raise AnatomyError(f"edge_length = {self.edge_length!r} m: the wall's elements are 0.5-20 mm (the default "
                               "wall's are 2-5 mm); give it in metres, e.g. 0.003")


@dataclass
class Anatomy:
    """A patient's (or a generated) vessel, ready for a scene."""

    surface: LumenSurface        # the lumen the wall is built on (remeshed when it was)
    wall: TetMesh
    centerline: Centerline       # from the access end's centre to the target end's
    access: int                  # index into surface.ends
    target: int
    reference_radius: float      # the target end's radius (the healthy neck)
    sac_index: int               # centerline vertex whose cross-section reaches farthest
    sac_reach: float             # from there to the farthest wall of that section, m
    wall_point: np.ndarray       # where the catheter's path meets the sac wall
    path: np.ndarray             # (k, 3) the catheter's path, from the access end to AIM_SHORT before wall_point
    notes: list[str] = field(default_factory=list)

    @property
    def path_length(self) -> float:
        return float(np.linalg.norm(np.diff(self.path, axis=0), axis=1).sum())


def _triangle_quality(mesh) -> np.ndarray:
    """4 sqrt(3) area / sum of squared edges: 1 for an equilateral triangle, 0 for a sliver."""
    t = mesh.triangles
    edges = np.linalg.norm(np.roll(t, -1, axis=1) - t, axis=2)
    return 4.0 * np.sqrt(3.0) * mesh.area_faces / (edges ** 2).sum(axis=1)


def prepared_surface(surface: LumenSurface, options: WallOptions) -> LumenSurface:
    """The surface with triangles of the wall's element size: its own when they fit, else remeshed."""
    mean_edge = float(surface.mesh.edges_unique_length.mean())
    worst = float(_triangle_quality(surface.mesh).min())
    fits = (options.edge_length / KEPT_EDGE_FACTOR <= mean_edge <= options.edge_length * KEPT_EDGE_FACTOR
            and worst >= KEPT_MIN_QUALITY)
    if options.remesh == "never" or (options.remesh == "auto" and fits):
        return surface
    logger.info("remeshing %s (mean edge %.3g mm, worst triangle quality %.2f) at %.3g mm", surface.source,
                mean_edge * 1e3, worst, options.edge_length * 1e3)
    remeshed = check_surface(remesh(surface.mesh, options.edge_length), "m", source=surface.source)
    # repairs of gmsh's output (its patches' winding) are part of remeshing, not of the user's data
    return LumenSurface(mesh=remeshed.mesh, ends=remeshed.ends, units=surface.units, source=surface.source,
                        repairs=surface.repairs + [f"remeshed to {len(remeshed.mesh.faces)} triangles of about "
                                                   f"{options.edge_length * 1e3:.3g} mm (mean edge was "
                                                   f"{mean_edge * 1e3:.3g} mm, worst quality {worst:.2f})"],
                        units_given=surface.units_given)


def default_ends(surface: LumenSurface) -> tuple[int, int]:
    """(access, target): the lowest end along z (inferior: femoral access from below in the patient
    frames of 3D Slicer and DICOM) and the highest (the proximal aorta)."""
    heights = np.array([end.center[2] for end in surface.ends])
    return int(np.argmin(heights)), int(np.argmax(heights))


def _end_index(surface: LumenSurface, value, name: str) -> int:
    count = len(surface.ends)
    if not isinstance(value, (int, np.integer)) or not 0 <= value < count:
        raise AnatomyError(f"{name} = {value!r}: the surface has {count} open end(s), numbered 0 to {count - 1} (see "
                           "its report)")
    return int(value)


def _reach(centerline: Centerline, walls: np.ndarray) -> np.ndarray:
    """(n,) the distance from each centerline point to the farthest wall of its cross-section (the
    inscribed radius where the section has no loop around the point)."""
    reach = np.linalg.norm(walls - centerline.points, axis=1)
    return np.where(np.isfinite(reach), reach, centerline.radius)


def _sac_candidates(centerline: Centerline, reach: np.ndarray, guard: float, reference: float) -> np.ndarray:
    """Centerline vertices by how far their cross-section reaches, farthest first: where the sac is.

    Only in the aorta (inscribed radius at least BRANCH_RADIUS x the target end's) and away from the
    ends (where the cut shapes the section): in a branch, the section across the branch's axis cuts
    the aorta's junction obliquely and reaches far without a sac there.
    """
    s = centerline.arclength()
    inside = (s > guard) & (s < s[-1] - guard)
    aorta = inside & (centerline.radius >= BRANCH_RADIUS * reference)
    candidates = np.flatnonzero(aorta if aorta.any() else inside if inside.any() else np.ones_like(inside))
    return candidates[np.argsort(-reach[candidates], kind="stable")]


def _clear(start: np.ndarray, aim: np.ndarray, wall_point: np.ndarray, distance: SurfaceDistance) -> bool:
    """Whether the straight path start -> aim keeps PATH_CLEARANCE from the wall until it nears the wall
    point it is meant to meet (within AIM_SHORT + PATH_CLEARANCE). Starting inside, a path whose every
    sample (0.5 mm apart) is that far from the wall never crosses it."""
    length = float(np.linalg.norm(aim - start))
    samples = start + np.linspace(0.0, 1.0, max(2, int(length / 5e-4) + 1))[:, None] * (aim - start)
    far = np.linalg.norm(samples - wall_point, axis=1) > AIM_SHORT + PATH_CLEARANCE
    return bool((distance(samples[far]) > PATH_CLEARANCE).all()) if far.any() else True


def _catheter_path(centerline: Centerline, candidates: np.ndarray, reach: np.ndarray, walls: np.ndarray,
                   distance: SurfaceDistance) -> tuple[int, np.ndarray, np.ndarray]:
    """(sac index, wall point, path): up the centerline to the sac's reach before the sac, then straight to
    AIM_SHORT before the sac's farthest wall.

    The farthest-reaching section whose wall the catheter can reach in the lumen: the straight part
    starts later along the centerline where the sac's curve would make it graze the wall, and a section
    whose farthest wall no straight path reaches (seen past a fold of the lumen) gives way to the next.
    """
    s = centerline.arclength()
    for index in candidates[:MAX_SAC_CANDIDATES]:
        wall_point = walls[index]
        if not np.isfinite(wall_point).all():
            continue
        for branch in np.linspace(max(float(s[index] - reach[index]), 0.5 * float(s[index])), float(s[index]), 6):
            start = np.array([np.interp(branch, s, centerline.points[:, k]) for k in range(3)])
            gap = float(np.linalg.norm(wall_point - start))
            if gap <= 2 * AIM_SHORT:
                continue
            aim = start + (wall_point - start) * (1.0 - AIM_SHORT / gap)
            if _clear(start, aim, wall_point, distance):
                stations = np.append(np.arange(0.0, branch, PATH_SPACING), branch)
                along = np.stack([np.interp(stations, s, centerline.points[:, k]) for k in range(3)], axis=1)
                return int(index), wall_point, np.concatenate([along, aim[None, :]])
    raise AnatomyError("no straight approach from the centerline reaches the sac's wall inside the lumen (the "
                       f"{MAX_SAC_CANDIDATES} widest sections tried, each keeping {PATH_CLEARANCE * 1e3:g} mm from "
                       "the wall): is the surface a vessel with an aneurysm? (--access and --target choose the path)")


def _thickness(surface: LumenSurface, centerline: Centerline, reach: np.ndarray, reference: float,
               options: WallOptions) -> tuple[np.ndarray | float, dict]:
    """Per-vertex thickness, thinner in the sac when asked, and the ``sac`` element mask over triangles.

    A vertex's dilation is its distance from the nearest centerline point, over the healthy radius, but
    no more than that point's section reaches: the far vertices of another branch (the other iliac
    artery) are far from this centerline without being a sac.
    """
    distance, nearest = cKDTree(centerline.points).query(surface.mesh.vertices)
    dilation = np.minimum(distance, 1.05 * reach[nearest]) / reference
    low, high = SAC_DILATION
    x = np.clip((dilation - low) / (high - low), 0.0, 1.0)
    weight = x * x * (3.0 - 2.0 * x)      # smoothstep: no kink in the wall's thickness
    sac = weight[surface.mesh.faces].mean(axis=1) > 0.5
    if options.sac_thickness is None:
        return options.thickness, {"sac": sac}
    return options.thickness + (options.sac_thickness - options.thickness) * weight, {"sac": sac}


def build_anatomy(surface: LumenSurface, options: WallOptions | None = None, *, access: int | None = None,
                  target: int | None = None) -> Anatomy:
    """Everything a scene needs from a checked lumen surface (see the module's docstring)."""
    options = options or WallOptions()
    options.validate()
    surface = prepared_surface(surface, options)
    if len(surface.ends) < 2:
        raise AnatomyError(f"{surface.source}: {len(surface.ends)} open end: a catheter needs a vessel with an access "
                           "end and another end to follow it towards (cut the vessel open at both ends)")
    default_access, default_target = default_ends(surface)
    access = default_access if access is None else _end_index(surface, access, "access")
    target = default_target if target is None else _end_index(surface, target, "target")
    if access == target:
        raise AnatomyError(f"access and target are the same end ({access}): the catheter goes from one end to another")
    centerline = compute_centerline(surface.mesh, surface.ends[access].center, surface.ends[target].center)
    reference = surface.ends[target].radius
    walls = farthest_walls(surface.mesh, centerline)
    reach = _reach(centerline, walls)
    candidates = _sac_candidates(centerline, reach, 2.0 * max(surface.ends[access].radius, reference), reference)
    sac_index, wall_point, path = _catheter_path(centerline, candidates, reach, walls, SurfaceDistance(surface.mesh))
    notes = []
    dilation = float(reach[sac_index]) / reference
    if dilation < SAC_DILATION[1]:
        notes.append(f"no aneurysm on the path: the widest section reaches {dilation:.2f}x the target end's radius "
                     f"(an aneurysm is at least {SAC_DILATION[1]}x); the catheter aims at its farthest wall")
    thickness, element_sets = _thickness(surface, centerline, reach, reference, options)
    wall = build_wall(surface, thickness, options.layers, element_sets)
    for note in notes:
        logger.warning("%s: %s", surface.source, note)
    return Anatomy(surface=surface, wall=wall, centerline=centerline, access=access, target=target,
                   reference_radius=reference, sac_index=sac_index,
                   sac_reach=float(reach[sac_index]), wall_point=wall_point, path=path, notes=notes)

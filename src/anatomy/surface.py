"""Reading and checking a lumen surface (STL, OBJ, PLY): units, repairs that are safe, refusals that name the place.

A surface from segmentation is data from outside: it is parsed as data (trimesh's readers, no code),
its size is checked before it is loaded, and every property the wall depends on is checked. What can
be repaired without guessing the anatomy is repaired and reported (duplicate vertices, degenerate or
duplicate triangles, specks apart from the vessel, an inconsistent winding, normals pointing into the
lumen, small holes in the wall); what cannot is refused with where it is and what to do.
"""
from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .ends import OpenEnd, capped, open_ends
from .errors import AnatomyError
from .intersections import self_intersections

logger = logging.getLogger(__name__)

FORMATS = ("stl", "obj", "ply")
#: Most triangles read: a 30 cm aorta segmented at 0.2 mm is about 1M triangles; the wall is built
#: from a remeshed surface of a few thousand, so more only costs time and memory.
MAX_TRIANGLES = 2_000_000
#: Length units a surface may come in, in metres.
UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
#: The bounding-box diagonal of a vessel segment in metres: from a 1 cm piece of an iliac artery to
#: the whole aorta with the iliacs (about 0.6 m). Units are detected by which one puts it in here.
PLAUSIBLE_DIAGONAL = (0.01, 1.0)
#: The radius of a vessel's open end in metres: from a small iliac branch to a giant aneurysm.
PLAUSIBLE_END_RADIUS = (0.5e-3, 0.06)
#: Separate pieces of surface below this fraction of the whole area are segmentation specks.
SPECK_AREA_FRACTION = 0.01
#: An open boundary is a vessel's end when the triangles around it run along its normal (a tube
#: cut across): the mean |cos| between their normals and the loop's normal stays below this.
END_ALIGNMENT = 0.5
#: A hole in the wall up to this fraction of the smallest end's radius is closed (and reported): a flat
#: fan over a hole of radius a in a wall curved with radius R is off by a^2 / 2R, at most a quarter of
#: the hole's radius where the wall is as curved as the narrowest vessel.
FILLABLE_HOLE_FRACTION = 0.5


@dataclass
class LumenSurface:
    """A checked lumen surface in metres, normals out of the lumen, with its open ends."""

    mesh: trimesh.Trimesh
    ends: list[OpenEnd]
    units: str
    source: str
    repairs: list[str] = field(default_factory=list)
    #: whether the caller named the units (else they were detected from the size)
    units_given: bool = False

    @property
    def scale(self) -> float:
        """Metres per unit of the source."""
        return UNITS[self.units]

    def report(self) -> str:
        """What was read, in which units, what was repaired, and the ends."""
        lines = [f"{self.source}: {len(self.mesh.faces)} triangles, {len(self.mesh.vertices)} vertices, in "
                 f"{self.units} ({'given' if self.units_given else 'detected'})"]
        lines += [f"  repaired: {r}" for r in self.repairs]
        for i, end in enumerate(self.ends):
            lines.append(f"  end {i}: centre {place(end.center, self)}, radius {end.radius * 1e3:.2f} mm, "
                         f"{len(end.vertices)} boundary vertices")
        return "\n".join(lines)


def place(point, surface_or_scale) -> str:
    """A point as the user finds it in their tool: in the source's units."""
    scale = surface_or_scale.scale if isinstance(surface_or_scale, LumenSurface) else surface_or_scale
    unit = next(name for name, value in UNITS.items() if value == scale)
    return "(" + ", ".join(f"{x / scale:.4g}" for x in np.asarray(point, dtype=float)) + f") {unit}"


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------


def _declared_triangles(path: Path, kind: str) -> int | None:
    """The triangle count a file declares, read without loading it (None where a format does not say)."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(4096)
        if kind == "stl":
            if len(head) >= 84 and not head[:5].lower().startswith(b"solid"):
                return int(np.frombuffer(head[80:84], dtype="<u4")[0])
            return size // 200                   # ASCII: about 250 bytes per facet
        if kind == "ply":
            match = re.search(rb"element\s+face\s+(\d+)", head)
            return int(match.group(1)) if match else None
        count, tail = 0, b""                     # OBJ: face lines, counted in chunks
        f.seek(0)
        while chunk := f.read(1 << 24):
            block = tail + chunk
            count += block.count(b"\nf ") + block.count(b"\nf\t")
            tail = block[-2:]
        return count


def _load(path: Path, kind: str) -> trimesh.Trimesh:
    try:
        loaded = trimesh.load(str(path), file_type=kind, process=False, force=None)
    except Exception as exc:  # trimesh raises many types by format (ValueError, KeyError, struct.error...)
        raise AnatomyError(f"{path}: could not read it as {kind.upper()} ({type(exc).__name__}: {exc}): export the "
                           "lumen surface again from the segmentation tool as STL, OBJ or PLY") from None
    if isinstance(loaded, trimesh.Scene):
        meshes = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
        if not meshes:
            raise AnatomyError(f"{path}: holds no triangles (an empty file or only points or lines): export the "
                               "segmentation's surface (a triangle mesh), not its points")
        loaded = trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]
    if isinstance(loaded, trimesh.PointCloud) or not isinstance(loaded, trimesh.Trimesh) or not len(loaded.faces):
        raise AnatomyError(f"{path}: is a point cloud (vertices, no triangles): reconstruct the surface first (the "
                           "segmentation tool's surface export, or a surface reconstruction of the points)")
    return loaded


def read_surface(path, units: str = "auto", *, repair: bool = True) -> LumenSurface:
    """Read and check a lumen surface from an STL, OBJ or PLY file (see :func:`check_surface`)."""
    path = Path(os.fspath(path))
    kind = path.suffix.lower().lstrip(".")
    if kind not in FORMATS:
        raise AnatomyError(f"{path}: the extension {path.suffix or '(none)'!r} is not a surface format read here "
                           f"({', '.join('.' + f for f in FORMATS)}): export the lumen surface as one of them")
    if not path.is_file():
        raise AnatomyError(f"{path}: no such file (relative paths are from {os.getcwd()})")
    if path.stat().st_size == 0:
        raise AnatomyError(f"{path}: the file is empty: export the lumen surface again")
    declared = _declared_triangles(path, kind)
    if declared is not None and declared > MAX_TRIANGLES:
        raise AnatomyError(f"{path}: {declared} triangles, more than MAX_TRIANGLES = {MAX_TRIANGLES}: decimate the "
                           "surface first (3D Slicer: Surface Toolbox, Decimate; the wall is built from a few "
                           "thousand triangles anyway)")
    mesh = _load(path, kind)
    if len(mesh.faces) > MAX_TRIANGLES:
        raise AnatomyError(f"{path}: {len(mesh.faces)} triangles, more than MAX_TRIANGLES = {MAX_TRIANGLES}: "
                           "decimate the surface first")
    return check_surface(mesh, units, source=str(path), repair=repair)


# --------------------------------------------------------------------------------------
# Checking and repairing
# --------------------------------------------------------------------------------------


def _detect_units(mesh: trimesh.Trimesh, units: str, source: str) -> str:
    diagonal = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    low, high = PLAUSIBLE_DIAGONAL
    if units != "auto":
        if units not in UNITS:
            raise AnatomyError(f"units = {units!r} is not one of auto, {', '.join(UNITS)}")
        metres = diagonal * UNITS[units]
        if not low <= metres <= high:
            raise AnatomyError(f"{source}: in {units} the surface spans {metres:.4g} m (bounding-box diagonal), "
                               f"outside the {low}-{high} m of a vessel segment: check the units (auto detects them)")
        return units
    fitting = [name for name, scale in UNITS.items() if low <= diagonal * scale <= high]
    if not fitting:
        raise AnatomyError(f"{source}: the surface spans {diagonal:.4g} units (bounding-box diagonal); in no unit of "
                           f"{', '.join(UNITS)} is that a vessel segment ({low}-{high} m): check the export's scale")
    # the ranges overlap (a 5 cm piece in m is 5 in cm); segmentations are in mm, then m
    chosen = next(u for u in ("mm", "m", "cm") if u in fitting)
    if len(fitting) > 1:
        logger.warning("%s: %.4g units across could be %s; taking %s (give units= to choose)", source, diagonal,
                       " or ".join(fitting), chosen)
    return chosen


def _clean(mesh: trimesh.Trimesh, repairs: list[str], repair: bool, source: str) -> trimesh.Trimesh:
    """Merge duplicate vertices, drop degenerate and duplicate triangles and unused vertices."""
    n_vertices = len(mesh.vertices)
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    mesh.merge_vertices(digits_vertex=None)
    merged = n_vertices - len(mesh.vertices)
    n_faces = len(mesh.faces)
    keep = mesh.nondegenerate_faces(height=1e-12 * float(mesh.scale))
    keep &= mesh.unique_faces()
    removed = n_faces - int(keep.sum())
    if removed and not repair:
        raise AnatomyError(f"{source}: {removed} degenerate or duplicate triangle(s): repair them (repair=True)")
    mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()
    if merged:  # an STL stores each triangle's corners apart: merging them is reading it, not a repair
        logger.info("%s: merged %d coincident vertices", source, merged)
    if removed:
        repairs.append(f"removed {removed} degenerate or duplicate triangle(s)")
    return mesh


def _one_piece(mesh: trimesh.Trimesh, repairs: list[str], source: str, scale: float) -> trimesh.Trimesh:
    adjacency = mesh.face_adjacency
    graph = coo_matrix((np.ones(len(adjacency)), (adjacency[:, 0], adjacency[:, 1])),
                       shape=(len(mesh.faces), len(mesh.faces)))
    count, label = connected_components(graph, directed=False)
    if count <= 1:
        return mesh
    areas = np.bincount(label, weights=mesh.area_faces, minlength=count)
    order = np.argsort(areas)[::-1]
    small = areas[order[1:]].sum() / areas.sum()
    if small > SPECK_AREA_FRACTION:
        second = mesh.triangles_center[label == order[1]].mean(axis=0)
        raise AnatomyError(
            f"{source}: {count} separate surfaces; the second largest ({100 * areas[order[1]] / areas.sum():.1f} % "
            f"of the area) is around {place(second, scale)}: keep only the vessel's lumen in the "
            "segmentation (remove other structures), or connect the pieces")
    repairs.append(f"dropped {count - 1} speck(s) apart from the vessel ({100 * small:.2f} % of the area)")
    piece = trimesh.Trimesh(mesh.vertices, mesh.faces[label == order[0]], process=False)
    piece.remove_unreferenced_vertices()
    return piece


def _check_manifold(mesh: trimesh.Trimesh, source: str, scale: float) -> None:
    keys = np.sort(mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(keys, axis=0, return_counts=True)
    shared = unique[counts > 2]
    if len(shared):
        raise AnatomyError(f"{source}: not manifold: {len(shared)} edge(s) shared by more than two triangles, the "
                           f"first at {place(mesh.vertices[shared[0]].mean(axis=0), scale)}: separate the touching "
                           "parts of the surface (a vessel touching itself, or a double wall) in the segmentation")


def _orient(mesh: trimesh.Trimesh, repairs: list[str], source: str) -> trimesh.Trimesh:
    if not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
        if not mesh.is_winding_consistent:
            raise AnatomyError(f"{source}: the triangles cannot be wound consistently (a non-orientable surface): "
                               "export the lumen surface again")
        repairs.append("made the triangles' winding consistent")
    if capped(mesh).volume < 0.0:
        mesh.invert()
        repairs.append("flipped the normals to point out of the lumen (they pointed into it)")
    return mesh


def _ends_and_holes(mesh: trimesh.Trimesh, repairs: list[str], repair: bool, source: str,
                    scale: float) -> tuple[trimesh.Trimesh, list[OpenEnd]]:
    """Split the open boundaries into the vessel's ends and holes in its wall; close the small holes."""
    loops = open_ends(mesh)
    ends, holes = [], []
    normals = mesh.face_normals
    for loop in loops:
        beside = np.isin(mesh.faces, loop.vertices).any(axis=1)
        alignment = float(np.abs(normals[beside] @ loop.normal).mean())
        (ends if alignment < END_ALIGNMENT else holes).append(loop)
    if not ends:
        raise AnatomyError(
            f"{source}: the surface has no open vessel end ({'closed' if not loops else 'only holes in its wall'}): "
            "the simulation clamps the wall where the vessel was cut; export the lumen with its ends open "
            "(3D Slicer: cut the ends with planes and do not cap them)")
    smallest = min(end.radius for end in ends)
    too_big = [h for h in holes if h.radius > FILLABLE_HOLE_FRACTION * smallest or not repair]
    if too_big:
        hole = max(too_big, key=lambda h: h.radius)
        raise AnatomyError(
            f"{source}: a hole in the wall around {place(hole.center, scale)}, {2e3 * hole.radius:.2f} mm across "
            f"(not a vessel end: the wall around it faces across it){'' if repair else ' and repair=False'}: close it "
            f"in the segmentation tool (holes up to {FILLABLE_HOLE_FRACTION:g} x the smallest end's radius are "
            "closed here)")
    if holes:
        mesh = capped(mesh, holes)
        largest = max(holes, key=lambda h: h.radius)
        repairs.append(f"closed {len(holes)} small hole(s) in the wall (largest {2e3 * largest.radius:.2f} mm across, "
                       f"around {place(largest.center, scale)})")
        ends = open_ends(mesh)
    return mesh, ends


def _check_ends(ends: list[OpenEnd], source: str, scale: float) -> None:
    low, high = PLAUSIBLE_END_RADIUS
    for i, end in enumerate(ends):
        if not low <= end.radius <= high:
            raise AnatomyError(f"{source}: the open end {i} at {place(end.center, scale)} has a radius of "
                               f"{end.radius * 1e3:.3g} mm, outside the {low * 1e3:g}-{high * 1e3:g} mm of a vessel: "
                               "check the units or cut the vessel across, not along")


def check_surface(mesh: trimesh.Trimesh, units: str = "auto", *, source: str = "the surface",
                  repair: bool = True) -> LumenSurface:
    """Check a lumen surface; return it in metres, repaired where that is safe (each repair reported).

    Refused (AnatomyError, naming where and the fix): non-finite coordinates, implausible size in any
    unit, separate surfaces of comparable size, edges shared by more than two triangles, a surface that
    cannot be oriented, no open vessel end, holes in the wall larger than a quarter of the smallest
    end's radius, self-intersections, implausible end radii. ``repair=False`` refuses what would be
    repaired instead.
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if len(mesh.faces) == 0:
        raise AnatomyError(f"{source}: holds no triangles: export the lumen's surface (a triangle mesh)")
    bad = np.flatnonzero(~np.isfinite(vertices).all(axis=1))
    if bad.size:
        raise AnatomyError(f"{source}: {bad.size} vertex(es) with NaN or infinite coordinates (first id {bad[0]}): "
                           "export the surface again")
    repairs: list[str] = []
    chosen = _detect_units(mesh, units, source)
    scale = UNITS[chosen]
    if units == "auto" and chosen != "m":
        logger.info("%s: coordinates in %s (bounding-box diagonal %.4g %s)", source, chosen,
                    float(np.linalg.norm(np.ptp(vertices, axis=0))), chosen)
    mesh = trimesh.Trimesh(vertices * scale, np.asarray(mesh.faces, dtype=np.int64), process=False)
    mesh = _clean(mesh, repairs, repair, source)
    _check_manifold(mesh, source, scale)          # first: a fin on an edge is no neighbour of its triangles
    mesh = _one_piece(mesh, repairs, source, scale) if repair else mesh
    if repair:
        mesh = _orient(mesh, repairs, source)
    elif not mesh.is_winding_consistent or capped(mesh).volume < 0.0:
        raise AnatomyError(f"{source}: the winding is inconsistent or the normals point into the lumen: repair it "
                           "(repair=True)")
    mesh, ends = _ends_and_holes(mesh, repairs, repair, source, scale)
    crossing = self_intersections(mesh.vertices, mesh.faces, limit=1)
    if len(crossing):
        at = mesh.triangles_center[crossing[0]].mean(axis=0)
        raise AnatomyError(f"{source}: the surface intersects itself around {place(at, scale)} (triangles "
                           f"{crossing[0, 0]} and {crossing[0, 1]}): smooth or re-segment the lumen there (two walls "
                           "crossing have no inside to build a wall outside of)")
    _check_ends(ends, source, scale)
    for line in repairs:
        logger.warning("%s: %s", source, line)
    return LumenSurface(mesh=mesh, ends=ends, units=chosen, source=source, repairs=repairs, units_given=units != "auto")

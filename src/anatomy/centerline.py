"""The vessel's centerline and its radius, computed from the lumen surface (VMTK-style, numpy/scipy only).

The catheter is driven along the centerline and the wall's clearance is read from its radius, so
both must be accurate where the lumen is wide (an aneurysm sac) and where it is narrow (an iliac).
The method, in three stages:

1. Voxelize the capped (closed) lumen and take the Euclidean distance to the wall: its ridge is
   the medial axis. Inside/outside is decided by ray parity along the three grid axes with a
   majority vote, so a ray grazing an edge cannot flip a column.
2. The cheapest path through the inside voxels from the voxel nearest ``start`` to the one nearest
   ``end``, at a cost of 1/D^2 per unit length (D = distance to the wall): it keeps to the ridge
   and, at a bifurcation, goes into the branch of ``end``.
3. Refine the smoothed path off the voxel grid: each point moves to the centroid of the surface's
   section normal to the local tangent (the loop around the point), when that moves it deeper
   into the lumen; where it does not (a bifurcation's crotch), the correction is interpolated
   from the neighbours'. A straight tube's centerline is then exact to round-off, not to the
   voxel size, and an open end asked for as start or end is the centerline's first or last point.

The radius is the distance from each point to the wall (the surface without its caps: a cap is
not wall), i.e. the maximum inscribed sphere radius as VMTK defines it.
"""
from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from .ends import OpenEnd, capped, open_ends
from .distance import SurfaceDistance, chunks
from .errors import AnatomyError

logger = logging.getLogger(__name__)

#: The voxel grid's bound (its arrays take about 30 bytes per voxel)...
MAX_VOXELS = 4_000_000
#: ...and the bound on the voxels inside the lumen, from its volume: the path search's 26-neighbour
#: graph takes about 400 bytes per inside voxel. A large surface gets coarser voxels, never an
#: unbounded grid; the refinement on the surface keeps the accuracy.
MAX_INSIDE = 1_000_000
#: Default voxels per radius of the narrowest open end: enough for the distance ridge of the
#: narrowest vessel to be a few voxels wide, so the path does not hug its wall.
VOXELS_PER_RADIUS = 8
#: Section refinements; the second uses tangents of the refined (already centred) points.
REFINEMENTS = 2
#: Gaussian smoothing of the voxel path, in samples one voxel apart: removes the staircase.
SMOOTHING = 2.0

#: Sections whose farthest points are this close (relative) are round: the tie goes to +x, then +y
#: (the default scene meets its sac on the +x side).
FARTHEST_TIE = 2e-3


@dataclass(frozen=True, eq=False)
class Centerline:
    """A vessel's centerline from a start to an end point, with the lumen radius along it."""

    #: (n, 3) points from start to end, m, roughly evenly spaced
    points: np.ndarray
    #: (n,) lumen radius at each point, m: the distance to the wall (maximum inscribed sphere radius)
    radius: np.ndarray

    def __post_init__(self):
        points = np.array(self.points, dtype=np.float64)
        radius = np.array(self.radius, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) < 2 or radius.shape != (len(points),):
            raise AnatomyError(f"a centerline needs (n, 3) points and (n,) radii with n >= 2, got {points.shape} "
                               f"and {radius.shape}: pass matching arrays")
        # read-only, so a frozen centerline stays what it was computed to be
        points.setflags(write=False)
        radius.setflags(write=False)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "radius", radius)

    def arclength(self) -> np.ndarray:
        """(n,) distance along the centerline from its start, m: the catheter's insertion depth."""
        steps = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(steps)])

    def length(self) -> float:
        """The centerline's length, m: how far a catheter travels from start to end."""
        return float(self.arclength()[-1])

    def resampled(self, spacing: float) -> Centerline:
        """The same centerline at points ``spacing`` apart (as near as divides its length evenly).

        Points and radii are interpolated linearly: a finer spacing than the computed one adds no
        detail, it only gives a model the node spacing it wants.
        """
        if not (np.isfinite(spacing) and spacing > 0):
            raise AnatomyError(f"a centerline's spacing must be a positive length in m, got {spacing!r}")
        s = self.arclength()
        targets = np.linspace(0.0, s[-1], max(1, int(round(s[-1] / spacing))) + 1)
        points = np.stack([np.interp(targets, s, self.points[:, axis]) for axis in range(3)], axis=1)
        return Centerline(points, np.interp(targets, s, self.radius))


def compute_centerline(surface: trimesh.Trimesh, start, end, *, resolution: float | None = None) -> Centerline:
    """The centerline of the lumen from ``start`` to ``end``, with its radius.

    ``surface`` is the lumen (normals out of it, open ends allowed: they are capped here).
    ``start`` and ``end`` are points (3,) in m inside the lumen, or at most a lumen radius outside
    it; typically the centres of two open ends. At a bifurcation, ``end`` picks the branch.
    ``resolution`` is the voxel size of the path search, m; by default the narrowest open end's
    radius / 8, coarsened (with a log line) so the grid stays under :data:`MAX_VOXELS` and the
    lumen under :data:`MAX_INSIDE` voxels. It limits which passages are found, not the accuracy:
    the points are refined on the surface itself.
    """
    start, end = _point(start, "start"), _point(end, "end")
    ends = open_ends(surface)
    closed = capped(surface, ends)
    volume = _check_encloses(closed)
    grid = _Grid.around(closed, _pitch(closed, ends, volume, resolution))
    inside = _inside(closed.vertices[closed.faces], grid)
    cells = np.argwhere(inside)
    if len(cells) == 0:
        raise AnatomyError(f"no voxel of {grid.pitch * 1e3:.3g} mm fits inside the lumen: pass a smaller "
                           "resolution (about the narrowest radius / 8)")
    depth = ndimage.distance_transform_edt(inside, sampling=grid.pitch)
    first = _seed(start, "start", grid, cells, depth, closed, ends)
    last = _seed(end, "end", grid, cells, depth, closed, ends)
    path = grid.centres(cells[_ridge_path(inside, depth[inside], grid, first, last, start, end)])
    path, pinned = _pinned_to_open_ends(path, start, end, ends, grid.pitch)
    points = _smooth(_resample(path, grid.pitch), SMOOTHING)
    pinned = np.concatenate([pinned[:1], np.zeros(len(points) - 2, dtype=bool), pinned[1:]])
    wall = SurfaceDistance(surface)
    points = _resample(_refine(points, pinned, _Slicer(closed), wall), grid.pitch)
    return Centerline(points, wall(points))


# ------------------------------------------------------------------------------------- input checks


def farthest_walls(surface: trimesh.Trimesh, centerline: Centerline) -> np.ndarray:
    """(n, 3) for each centerline point, the farthest point of the lumen's cross-section around it (normal to
    the centerline; NaN where the section has no loop around the point).

    The inscribed radius does not see a saccular aneurysm, a dome on one side of a straight aorta; the
    farthest wall of the cross-section does: it is where a catheter crossing the sac meets its wall.
    """
    slicer = _Slicer(capped(surface))
    points = centerline.points
    return np.array([slicer.farthest(p, t) for p, t in zip(points, _tangents(points))])


def _point(value, name: str) -> np.ndarray:
    """A start or end point as (3,) floats, or an AnatomyError saying what is wrong with it."""
    advice = "pass a point (3,) in m inside the lumen, e.g. an open end's centre (anatomy.ends.open_ends)"
    try:
        point = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise AnatomyError(f"the centerline's {name} point {value!r} is not numeric: {advice}") from error
    if point.shape != (3,):
        raise AnatomyError(f"the centerline's {name} point has shape {point.shape}, not (3,): {advice}")
    if not np.isfinite(point).all():
        raise AnatomyError(f"the centerline's {name} point {point.tolist()} is not finite: {advice}")
    return point


def _format(point: np.ndarray) -> str:
    """A point for a message, to 0.1 um (round-off shown as 0)."""
    return "[" + ", ".join(f"{c:.7f}".rstrip("0").rstrip(".") for c in np.round(point, 7) + 0.0) + "]"


def _check_encloses(closed: trimesh.Trimesh) -> float:
    """The capped surface's volume, after checking it is closed, consistently wound and outward.

    The voxelization's inside/outside and the sections' loops are only defined for such a surface.
    """
    faces = np.asarray(closed.faces, dtype=np.int64)
    if len(faces) == 0:
        raise AnatomyError("the lumen surface has no triangles: read a segmented lumen surface")
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    _, counts = np.unique(_edge_keys(np.sort(directed, axis=1)), return_counts=True)
    if (counts != 2).any():
        raise AnatomyError(f"the lumen surface, with its open ends capped, is not closed: {int((counts != 2).sum())} "
                           f"edges are shared by {sorted(set(counts[counts != 2].tolist()))} triangles instead of 2 "
                           "(non-manifold or duplicated triangles); repair the surface in the segmentation tool "
                           "(merge duplicate vertices, remove overlapping triangles)")
    if len(np.unique(_edge_keys(directed))) != len(directed):
        raise AnatomyError("the lumen surface's triangles are not consistently wound (two neighbours traverse "
                           "their shared edge the same way): make the normals consistent (e.g. trimesh's "
                           "fix_normals) before computing the centerline")
    triangles = np.asarray(closed.vertices, dtype=np.float64)[faces]
    volume = float(np.einsum("ij,ij->i", triangles[:, 0], np.cross(triangles[:, 1], triangles[:, 2])).sum() / 6.0)
    area = 0.5 * float(np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0],
                                               triangles[:, 2] - triangles[:, 0]), axis=1).sum())
    # relative to the area's own volume scale, so a thin vessel is not mistaken for a flat sheet
    if abs(volume) <= 1e-6 * area ** 1.5:
        raise AnatomyError(f"the lumen surface does not enclose a volume even with its open ends capped "
                           f"(volume {volume:.3g} m^3 for an area of {area:.3g} m^2: a sheet, not a vessel); "
                           "export the lumen's closed surface (a tube) from the segmentation")
    if volume < 0:
        raise AnatomyError(f"the lumen surface's normals point into the lumen (enclosed volume {volume:.3g} m^3 "
                           "is negative): flip the triangles' winding so the normals point out of the lumen")
    return volume


def _edge_keys(edges: np.ndarray) -> np.ndarray:
    """One int64 per (k, 2) vertex pair: sorting integers is much faster than rows."""
    return edges[:, 0] * (int(edges.max()) + 1) + edges[:, 1]


def _pitch(closed: trimesh.Trimesh, ends: list[OpenEnd], volume: float, resolution: float | None) -> float:
    """The voxel size: the requested one or the narrowest end's radius / 8, within the grid's bound."""
    if resolution is None:
        # without open ends, a tube's radius is 2 V / A
        radius = min(e.radius for e in ends) if ends else 2.0 * volume / float(closed.area)
        pitch, why = radius / VOXELS_PER_RADIUS, f"narrowest radius {radius * 1e3:.3g} mm / {VOXELS_PER_RADIUS}"
    else:
        if not (np.isfinite(resolution) and resolution > 0):
            raise AnatomyError(f"the centerline's resolution must be a positive voxel size in m, got {resolution!r}; "
                               "leave it out for the default (the narrowest end's radius / 8)")
        pitch, why = float(resolution), "requested"
    extent = np.ptp(np.asarray(closed.vertices), axis=0)
    wanted = pitch
    pitch = max(pitch, (volume / MAX_INSIDE) ** (1 / 3))
    while np.prod(np.ceil(extent / pitch) + 6) > MAX_VOXELS:
        pitch *= 1.02
    if pitch > wanted:
        level = logging.WARNING if resolution is not None else logging.INFO
        logger.log(level, "centerline: voxel size %.3g mm (%s) coarsened to %.3g mm to keep the grid under %d voxels "
                   "and the lumen under %d", wanted * 1e3, why, pitch * 1e3, MAX_VOXELS, MAX_INSIDE)
    else:
        logger.info("centerline: voxel size %.3g mm (%s)", pitch * 1e3, why)
    return pitch


# ------------------------------------------------------------------------------------ voxel stage


@dataclass(frozen=True)
class _Grid:
    """Voxel centres ``origin + index * pitch`` for index in ``[0, shape)``."""

    origin: np.ndarray
    pitch: float
    shape: tuple[int, int, int]

    @classmethod
    def around(cls, mesh: trimesh.Trimesh, pitch: float) -> _Grid:
        """A grid two voxels wider than the mesh on every side, so the lumen never touches its border.

        The origin is shifted by an irrational fraction of a voxel so that the grid's rays do not
        run exactly through the vertices of a regularly built surface.
        """
        low, high = np.asarray(mesh.bounds, dtype=np.float64)
        origin = low - (2.0 - 1.0 / np.pi) * pitch
        shape = tuple(int(n) for n in np.ceil((high - origin) / pitch) + 3)
        return cls(origin, pitch, shape)

    def centres(self, index: np.ndarray) -> np.ndarray:
        return self.origin + np.asarray(index, dtype=np.float64) * self.pitch


def _inside(triangles: np.ndarray, grid: _Grid) -> np.ndarray:
    """Voxels whose centre is inside the closed surface: the majority of three rays' parities."""
    votes = sum(_parity(triangles, grid, axis).astype(np.uint8) for axis in range(3))
    return np.ascontiguousarray(votes >= 2)


def _parity(triangles: np.ndarray, grid: _Grid, axis: int) -> np.ndarray:
    """Inside by the parity of crossings along ``axis``, for every voxel centre at once.

    Each triangle toggles the voxels of the grid columns it covers beyond where it crosses them;
    an accumulated xor along the column then marks the inside.
    """
    u, v = (a for a in range(3) if a != axis)
    shape = grid.shape
    # vertex coordinates in voxel units, so a column's position is its integer index
    local = (triangles - grid.origin) / grid.pitch
    tu, tv, ta = local[:, :, u], local[:, :, v], local[:, :, axis]
    twice_area = (tu[:, 1] - tu[:, 0]) * (tv[:, 2] - tv[:, 0]) - (tu[:, 2] - tu[:, 0]) * (tv[:, 1] - tv[:, 0])
    i0 = np.maximum(np.ceil(tu.min(axis=1)), 0).astype(np.int64)
    i1 = np.minimum(np.floor(tu.max(axis=1)), shape[u] - 1).astype(np.int64)
    j0 = np.maximum(np.ceil(tv.min(axis=1)), 0).astype(np.int64)
    j1 = np.minimum(np.floor(tv.max(axis=1)), shape[v] - 1).astype(np.int64)
    nj = np.maximum(j1 - j0 + 1, 0)
    count = np.maximum(i1 - i0 + 1, 0) * nj
    count[twice_area == 0] = 0                        # seen edge-on: crossed by no column
    size = shape[u] * shape[v] * (shape[axis] + 1)
    toggles = np.zeros(size, dtype=bool)
    for lo, hi in chunks(count):
        t = np.repeat(np.arange(lo, hi), count[lo:hi])
        offset = np.arange(len(t)) - np.repeat(np.cumsum(count[lo:hi]) - count[lo:hi], count[lo:hi])
        ci, cj = i0[t] + offset // nj[t], j0[t] + offset % nj[t]
        du, dv = tu[t] - ci[:, None], tv[t] - cj[:, None]
        w = np.stack([du[:, 1] * dv[:, 2] - du[:, 2] * dv[:, 1],
                      du[:, 2] * dv[:, 0] - du[:, 0] * dv[:, 2],
                      du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0]], axis=1) / twice_area[t, None]
        hit = (w >= 0).all(axis=1)
        height = (w[hit] * ta[t[hit]]).sum(axis=1)
        k = np.clip(np.floor(height).astype(np.int64) + 1, 0, shape[axis])
        flat = (ci[hit] * shape[v] + cj[hit]) * (shape[axis] + 1) + k
        toggles ^= (np.bincount(flat, minlength=size) & 1).astype(bool)
    columns = np.logical_xor.accumulate(toggles.reshape(shape[u], shape[v], shape[axis] + 1)[:, :, :-1], axis=2)
    return np.transpose(columns, np.argsort([u, v, axis]))


def _ridge_radius(depth: np.ndarray, cell: np.ndarray) -> float:
    """The lumen's radius near a voxel: the distance to the wall at the ridge reached by ascent."""
    cell = np.asarray(cell)
    while True:
        low = np.maximum(cell - 1, 0)
        block = depth[low[0]:cell[0] + 2, low[1]:cell[1] + 2, low[2]:cell[2] + 2]
        best = np.array(np.unravel_index(np.argmax(block), block.shape)) + low
        if depth[tuple(best)] <= depth[tuple(cell)]:
            return float(depth[tuple(cell)])
        cell = best


def _seed(point: np.ndarray, name: str, grid: _Grid, cells: np.ndarray, depth: np.ndarray,
          closed: trimesh.Trimesh, ends: list[OpenEnd]) -> int:
    """The inside voxel nearest a start or end point, refusing a point far outside the lumen."""
    gaps = np.linalg.norm(grid.centres(cells) - point, axis=1)
    nearest = int(np.argmin(gaps))
    if gaps[nearest] <= grid.pitch:
        return nearest
    outside = float(SurfaceDistance(closed)(point[None])[0])
    radius = _ridge_radius(depth, cells[nearest])
    if outside > radius:
        centres = "; ".join(_format(e.center) for e in ends) or "none"
        raise AnatomyError(f"the centerline's {name} point {_format(point)} m is {outside * 1e3:.3g} mm outside "
                           f"the lumen, more than the lumen's radius there ({radius * 1e3:.3g} mm): pass a point "
                           f"inside the vessel, e.g. an open end's centre (the surface's open ends' centres, m: "
                           f"{centres})")
    return nearest


def _neighbour_graph(inside: np.ndarray, cost: np.ndarray, pitch: float) -> sparse.csr_matrix:
    """The inside voxels' 26-neighbour graph (each edge once), weighted by length x mean cost.

    Built row by row as CSR with int32 ids: the graph is the search's largest object. The inside
    never touches the grid's border, so a neighbour's flat index needs no bounds check.
    """
    steps = np.array(list(itertools.product((-1, 0, 1), repeat=3)))
    steps = steps[[tuple(s) > (0, 0, 0) for s in steps.tolist()]]      # half of the 26; edges are undirected
    flat = np.flatnonzero(inside)
    ids = np.full(inside.size, -1, dtype=np.int32)
    ids[flat] = np.arange(len(flat), dtype=np.int32)
    strides = np.array([inside.shape[1] * inside.shape[2], inside.shape[2], 1])      # of C-order flat indices
    neighbours = np.empty((len(flat), len(steps)), dtype=np.int32)
    for j, step in enumerate(steps):
        neighbours[:, j] = ids[flat + int(step @ strides)]
    valid = neighbours >= 0
    weights = (0.5 * pitch * np.linalg.norm(steps, axis=1)) * (cost[:, None] + cost[np.maximum(neighbours, 0)])
    indptr = np.concatenate([[0], np.cumsum(valid.sum(axis=1))])
    return sparse.csr_matrix((weights[valid], neighbours[valid], indptr), shape=(len(flat), len(flat)))


def _ridge_path(inside: np.ndarray, depth: np.ndarray, grid: _Grid, first: int, last: int, start: np.ndarray,
                end: np.ndarray) -> np.ndarray:
    """Inside-voxel ids of the cheapest path from ``first`` to ``last`` at 1/D^2 per unit length.

    ``depth`` holds D of the inside voxels in id order. The steep cost keeps the path on the
    distance ridge (the medial axis) rather than cutting a bend's inner corner.
    """
    if first == last:
        raise AnatomyError(f"the centerline's start {_format(start)} and end {_format(end)} m fall in one "
                           f"{grid.pitch * 1e3:.3g} mm voxel: pass two distinct open ends' centres")
    graph = _neighbour_graph(inside, 1.0 / depth ** 2, grid.pitch)
    distance, previous = csgraph.dijkstra(graph, directed=False, indices=first, return_predecessors=True)
    if not np.isfinite(distance[last]):
        raise AnatomyError(f"the centerline's start {_format(start)} and end {_format(end)} m are not connected "
                           f"inside the lumen (voxels of {grid.pitch * 1e3:.3g} mm): they are in separate vessels, "
                           "or a passage between them is narrower than the voxels; pick two ends of one vessel, "
                           "or pass a smaller resolution")
    path = [last]
    while path[-1] != first:
        path.append(int(previous[path[-1]]))
    return np.array(path[::-1])


# ----------------------------------------------------------------------------------- polyline tools


def _resample(points: np.ndarray, spacing: float) -> np.ndarray:
    """The polyline at evenly spaced points about ``spacing`` apart, keeping both ends."""
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    points = points[np.concatenate([[True], steps > 0])]
    s = np.concatenate([[0.0], np.cumsum(steps[steps > 0])])
    targets = np.linspace(0.0, s[-1], max(1, int(np.ceil(s[-1] / spacing))) + 1)
    return np.stack([np.interp(targets, s, points[:, axis]) for axis in range(3)], axis=1)


def _smooth(points: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing along the polyline that keeps its ends and its straight stretches.

    Padding by point reflection through each end (2 p0 - p_k) continues a straight line exactly,
    so the smoothing neither pulls the ends inward nor bends a straight centerline.
    """
    pad = min(len(points) - 1, int(np.ceil(4 * sigma)))
    if pad < 1:
        return points
    padded = np.concatenate([2 * points[0] - points[pad:0:-1], points, 2 * points[-1] - points[-2:-pad - 2:-1]])
    return ndimage.gaussian_filter1d(padded, sigma, axis=0, mode="nearest")[pad:len(padded) - pad]


def _tangents(points: np.ndarray) -> np.ndarray:
    """Unit tangents of a lightly smoothed copy: one off-centre point does not tilt its neighbours' sections."""
    gradient = np.gradient(_smooth(points, SMOOTHING), axis=0)
    return gradient / np.linalg.norm(gradient, axis=1, keepdims=True)


# --------------------------------------------------------------------------------- refinement stage


def _refine(path: np.ndarray, pinned: np.ndarray, slicer: _Slicer, wall: SurfaceDistance) -> np.ndarray:
    """The smoothed voxel path, moved onto the centroids of the sections normal to it.

    A move is measured only if it goes no farther than half the distance to the wall and does not
    bring the point nearer the wall: on a tube the section's centroid is the axis, the deepest
    point; where the section is not tube-like (the crotch of a bifurcation, an oblique cut through
    two branches, a cap cut at a slant) the centroid can lie off the ridge. There the correction
    to the voxel path is interpolated from the measured ones on either side, so the centerline
    stays smooth through the points that could not be refined. ``pinned`` points (open ends'
    centres) are exact already: their correction is zero.
    """
    correction = np.zeros_like(path)
    measured = pinned.copy()
    points = path
    for _ in range(REFINEMENTS):
        moved = np.array([slicer.centroid(p, t) for p, t in zip(points, _tangents(points))])
        found = np.isfinite(moved).all(axis=1)
        before = wall(points)
        after = np.zeros(len(points))
        after[found] = wall(moved[found])
        shift = np.linalg.norm(np.where(found[:, None], moved - points, 0.0), axis=1)
        keep = found & ~pinned & (shift <= 0.5 * before) & (after >= 0.99 * before)
        correction[keep] = moved[keep] - path[keep]
        measured |= keep
        points = path + _interpolated(correction, measured)
    return points


def _pinned_to_open_ends(path: np.ndarray, start: np.ndarray, end: np.ndarray, ends: list[OpenEnd],
                         pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """The path with its first/last point on the open end whose centre was asked for as start/end,
    and whether each of the two was so pinned.

    The voxel path begins and ends at inside voxels, up to a voxel off the axis and short of the
    cut, where a section would cross the cap; an end's centre is exactly on the axis at the cut.
    """
    path = path.copy()
    pinned = np.zeros(2, dtype=bool)
    for which, (index, asked) in enumerate(((0, start), (-1, end))):
        gaps = [float(np.linalg.norm(e.center - asked)) for e in ends]
        if gaps and min(gaps) <= pitch:
            path[index] = ends[int(np.argmin(gaps))].center
            pinned[which] = True
    return path, pinned


def _interpolated(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(n, 3) values, those not known linearly interpolated along the index (the nearest at the ends)."""
    if not known.any():
        return np.zeros_like(values)
    index = np.arange(len(values))
    return np.stack([np.interp(index, index[known], values[known, k]) for k in range(3)], axis=1)


class _Slicer:
    """Sections of a closed surface by planes, reduced to the area centroid of one loop."""

    def __init__(self, mesh: trimesh.Trimesh):
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.faces = np.asarray(mesh.faces, dtype=np.int64)
        triangles = self.vertices[self.faces]
        self.centroids = triangles.mean(axis=1)
        self.reach = np.linalg.norm(triangles - self.centroids[:, None], axis=2).max(axis=1)
        # edge k of a face runs from its vertex k to vertex k+1; a crossing point is named by its edge
        edges = np.sort(self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        self.edge_ids = np.unique(_edge_keys(edges), return_inverse=True)[1].reshape(-1, 3)

    def centroid(self, point: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """Area centroid of the section loop around ``point`` in the plane (point, normal); NaN if none.

        Area and winding number about the point are sums over the loop's oriented segments, so
        the loops need no chaining, only labelling.
        """
        found = self._loop(point, normal)
        if found is None:
            return np.full(3, np.nan)
        a, b, cross = found
        weights = 0.5 * cross
        return point + (weights[:, None] * (a + b)).sum(axis=0) / (3.0 * weights.sum())

    def farthest(self, point: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """The point of the section loop around ``point`` farthest from it; NaN if there is no loop.

        Ties within FARTHEST_TIE of the farthest (a round section) go to the largest x, then y.
        """
        found = self._loop(point, normal)
        if found is None:
            return np.full(3, np.nan)
        a = found[0]
        distance = np.linalg.norm(a, axis=1)
        near = np.flatnonzero(distance >= (1.0 - FARTHEST_TIE) * distance.max())
        candidates = point + a[near]
        return candidates[np.lexsort((candidates[:, 1], candidates[:, 0]))[-1]]

    def _loop(self, point: np.ndarray, normal: np.ndarray):
        """(tails - point, heads - point, (tail x head) . normal) of the innermost loop winding once
        around ``point``; None if no loop does."""
        tail, head, labels = self._segments(point, normal)
        if len(labels) == 0:
            return None
        a, b = tail - point, head - point
        cross = np.cross(a, b) @ normal
        turns = np.bincount(labels, np.arctan2(cross, np.einsum("ij,ij->i", a, b))) / (2 * np.pi)
        area = np.bincount(labels, 0.5 * cross)
        around = np.flatnonzero(np.round(turns) == 1)
        if len(around) == 0:
            return None
        mine = labels == around[np.argmin(area[around])]      # the innermost, if loops nest
        return a[mine], b[mine], cross[mine]

    def _segments(self, point: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(tails, heads, loop labels) of the section's segments, counter-clockwise about ``normal``.

        A vertex exactly on the plane counts as below it, so every loop closes. A crossing point is
        named by its edge, which joins the segments of one loop.
        """
        # (c - p) . n as c . n - p . n: no (faces, 3) temporary, several times faster
        near = np.flatnonzero(np.abs(self.centroids @ normal - point @ normal) <= self.reach)
        height = (self.vertices[self.faces[near]] - point) @ normal
        above = height > 0
        n_above = above.sum(axis=1)
        crossed = (n_above == 1) | (n_above == 2)
        faces, height, above, n_above = near[crossed], height[crossed], above[crossed], n_above[crossed]
        # the vertex alone on its side; the crossed edges are the two at it
        lone = np.where(n_above == 1, np.argmax(above, axis=1), np.argmin(above, axis=1))
        rows = np.arange(len(faces))
        corner = self.vertices[self.faces[faces]]

        def crossing(k):
            t = height[rows, lone] / (height[rows, lone] - height[rows, k])
            return corner[rows, lone] + t[:, None] * (corner[rows, k] - corner[rows, lone])

        prv = (lone + 2) % 3
        p, q = crossing((lone + 1) % 3), crossing(prv)
        ep, eq = self.edge_ids[faces, lone], self.edge_ids[faces, prv]
        # outward winding: a lone vertex above the plane gives the segment p -> q counter-clockwise
        up = n_above == 1
        tails, heads = np.where(up, ep, eq), np.where(up, eq, ep)
        labels = _components(tails, heads) if len(faces) else np.zeros(0, dtype=np.int64)
        return np.where(up[:, None], p, q), np.where(up[:, None], q, p), labels


def _components(tails: np.ndarray, heads: np.ndarray) -> np.ndarray:
    """Loop label of each segment, segments joined where they share a crossing point."""
    names, index = np.unique(np.concatenate([tails, heads]), return_inverse=True)
    m = len(tails)
    graph = sparse.coo_matrix((np.ones(m), (index[:m], index[m:])), shape=(len(names), len(names)))
    return csgraph.connected_components(graph, directed=False)[1][index[:m]]

"""Broad phase of collision detection: swept bounding boxes and an AABB tree.

Box makers return (lo, hi) arrays (m, 3). Swept boxes cover a primitive over the whole step; for
cubic Hermite trajectories the box of the Bezier control points contains the trajectory (convex
hull property). To keep the broad phase at least as conservative as the narrow phase, pass
`inflate` / `radius` >= the CCD contact margin (its min_distance, e.g. the tool radius).

The tree is built once (top-down median split) and refitted every step while the mesh topology
stays fixed (O(m)); queries return sorted (k, 2) int64 arrays of primitive index pairs.
"""
import logging

import numpy as np

from . import aabb_kernels

logger = logging.getLogger(__name__)

DEFAULT_LEAF_SIZE = 4


class AABBInputError(ValueError):
    """Invalid input to the bounding-box broad phase."""


def _points_array(name, points, meaning):
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise AABBInputError(f"{name} must have shape (n, 3) (got {points.shape}): {meaning}")
    if not np.all(np.isfinite(points)):
        raise AABBInputError(f"{name} has non-finite values: pass finite coordinates in m")
    return points


def _end_positions(positions_end, positions):
    if positions_end is None:
        return None
    end = _points_array("positions_end", positions_end, "positions at the end of the step, one row per point")
    if end.shape != positions.shape:
        raise AABBInputError(f"positions_end has shape {end.shape} but the start positions have {positions.shape}: "
                             f"pass the same points at the end of the step")
    return end


def _margin(name, value):
    value = float(value)
    if not (np.isfinite(value) and value >= 0.0):
        raise AABBInputError(f"{name} must be >= 0 (got {value}): give a margin in m, e.g. 0.001")
    return value


def _triangles_array(triangles, n_points):
    triangles = np.asarray(triangles)
    if triangles.ndim != 2 or triangles.shape[1] != 3 or not np.issubdtype(triangles.dtype, np.integer):
        raise AABBInputError(f"triangles must be an integer array of shape (m, 3) (got {triangles.dtype} "
                             f"{triangles.shape}): pass vertex indices per triangle")
    if triangles.size and (triangles.min() < 0 or triangles.max() >= n_points):
        raise AABBInputError(f"triangles index vertices outside [0, {n_points}) (range {triangles.min()}.."
                             f"{triangles.max()}): indices must refer to rows of positions")
    return triangles.astype(np.int64, copy=False)


def _boxes_of_groups(groups):
    """groups (m, k, 3) -> per-group min and max."""
    return groups.min(axis=1), groups.max(axis=1)


def _inflated(lo, hi, margin):
    if margin > 0.0:
        return lo - margin, hi + margin
    return lo, hi


def triangle_boxes(positions, triangles, positions_end=None, inflate=0.0):
    """Boxes (lo, hi) of triangles, swept over the step when positions_end is given (box of both ends).

    Validating wrapper of `aabb_kernels.triangle_boxes`, the kernel the contact model refits its
    tree with at every tissue frame."""
    positions = _points_array("positions", positions, "vertex positions, one row per vertex")
    triangles = _triangles_array(triangles, positions.shape[0])
    inflate = _margin("inflate", inflate)
    end = _end_positions(positions_end, positions)
    lo = np.empty((triangles.shape[0], 3))
    hi = np.empty((triangles.shape[0], 3))
    aabb_kernels.triangle_boxes(np.ascontiguousarray(positions),
                                positions if end is None else np.ascontiguousarray(end),
                                end is not None, np.ascontiguousarray(triangles), lo, hi)
    return _inflated(lo, hi, inflate)


def segment_boxes(points, positions_end=None, radius=0.0):
    """Boxes of the k-1 segments of a polyline (e.g. a tool centerline), inflated by its radius.

    Validating wrapper of `aabb_kernels.polyline_segment_boxes` (the kernel the contact model
    queries its tree with); swept to positions_end, the union of both ends' boxes."""
    points = np.ascontiguousarray(_points_array("points", points, "polyline vertices in order, one row per vertex"))
    if points.shape[0] < 2:
        raise AABBInputError(f"points must hold at least 2 polyline vertices (got {points.shape[0]})")
    radius = _margin("radius", radius)
    end = _end_positions(positions_end, points)
    lo, hi = np.empty((points.shape[0] - 1, 3)), np.empty((points.shape[0] - 1, 3))
    aabb_kernels.polyline_segment_boxes(points, radius, lo, hi)
    if end is not None:  # min(a - r, b - r) is min(a, b) - r exactly: rounding is monotonic
        end_lo, end_hi = np.empty_like(lo), np.empty_like(hi)
        aabb_kernels.polyline_segment_boxes(np.ascontiguousarray(end), radius, end_lo, end_hi)
        np.minimum(lo, end_lo, out=lo)
        np.maximum(hi, end_hi, out=hi)
    return lo, hi


def point_boxes(points, positions_end=None, radius=0.0):
    """Boxes of points (swept to positions_end when given), inflated by radius.

    Validating wrapper of `aabb_kernels.swept_point_boxes` (the kernel the contact model queries
    its tree with), with no point reaching back."""
    points = np.ascontiguousarray(_points_array("points", points, "point positions, one row per point"))
    radius = _margin("radius", radius)
    end = _end_positions(positions_end, points)
    end = points if end is None else np.ascontiguousarray(end)
    k = points.shape[0]
    lo, hi = np.empty((k, 3)), np.empty((k, 3))
    aabb_kernels.swept_point_boxes(points, end, radius, np.zeros(k, np.int8), points, np.zeros(k), lo, hi)
    return lo, hi


def spline_swept_boxes(p0, p1, v0, v1, dt, triangles, inflate=0.0):
    """Conservative boxes of triangles whose vertices follow cubic Hermite trajectories over [0, dt].

    Each vertex trajectory lies in the convex hull of its Bezier control points
    p0, p0 + v0 dt/3, p1 - v1 dt/3, p1 (the same points the spline CCD uses).
    """
    p0 = _points_array("p0", p0, "vertex positions at the start of the step")
    p1 = _points_array("p1", p1, "vertex positions at the end of the step")
    v0 = _points_array("v0", v0, "vertex velocities at the start of the step (m/s)")
    v1 = _points_array("v1", v1, "vertex velocities at the end of the step (m/s)")
    for name, a in (("p1", p1), ("v0", v0), ("v1", v1)):
        if a.shape != p0.shape:
            raise AABBInputError(f"{name} has shape {a.shape} but p0 has {p0.shape}: pass one row per vertex in all")
    dt = float(dt)
    if not (np.isfinite(dt) and dt > 0.0):
        raise AABBInputError(f"dt must be > 0 (got {dt}): give the step length in s, e.g. 0.001")
    triangles = _triangles_array(triangles, p0.shape[0])
    inflate = _margin("inflate", inflate)
    control = np.stack([p0, p0 + v0 * (dt / 3.0), p1 - v1 * (dt / 3.0), p1], axis=1)
    vertex_lo, vertex_hi = _boxes_of_groups(control)
    lo = vertex_lo[triangles].min(axis=1)
    hi = vertex_hi[triangles].max(axis=1)
    return _inflated(lo, hi, inflate)


def _boxes_pair(lo, hi, what):
    lo = np.ascontiguousarray(lo, dtype=np.float64)
    hi = np.ascontiguousarray(hi, dtype=np.float64)
    if lo.ndim != 2 or lo.shape[1] != 3 or lo.shape != hi.shape:
        raise AABBInputError(f"{what}: lo and hi must both have shape (m, 3) (got {lo.shape} and {hi.shape})")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise AABBInputError(f"{what}: boxes have non-finite bounds: pass finite coordinates in m")
    if np.any(lo > hi):
        bad = int(np.argwhere(np.any(lo > hi, axis=1))[0, 0])
        raise AABBInputError(f"{what}: box {bad} has lo > hi ({lo[bad]} > {hi[bad]}): pass (min corner, max corner)")
    return lo, hi


def _sorted_pairs(pairs):
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    return pairs[order]


def _collect(run, initial_capacity, sort=True):
    """Run a counting kernel into a buffer, growing it once if the first one was too small."""
    out = np.empty((max(initial_capacity, 16), 2), dtype=np.int64)
    found = run(out)
    if found > out.shape[0]:
        out = np.empty((found, 2), dtype=np.int64)
        found = run(out)
    return _sorted_pairs(out[:found]) if sort else out[:found]


class AABBTree:
    """Bounding-box tree over m primitive boxes (flat arrays, see aabb_kernels)."""

    def __init__(self, lo, hi, order, node_lo, node_hi, left, right, start, count, n_nodes, leaf_size):
        self.lo = lo
        self.hi = hi
        self.order = order
        self.node_lo = node_lo
        self.node_hi = node_hi
        self.left = left
        self.right = right
        self.start = start
        self.count = count
        self.n_nodes = n_nodes
        self.leaf_size = leaf_size

    @classmethod
    def build(cls, lo, hi, leaf_size=DEFAULT_LEAF_SIZE):
        """Top-down median split on the widest axis of the box centres."""
        lo, hi = _boxes_pair(lo, hi, "AABBTree.build")
        if int(leaf_size) < 1:
            raise AABBInputError(f"leaf_size must be >= 1 (got {leaf_size}): e.g. 4 primitives per leaf")
        m = lo.shape[0]
        size = max(2 * m, 1)
        order = np.empty(m, dtype=np.int64)
        node_lo = np.empty((size, 3))
        node_hi = np.empty((size, 3))
        left = np.empty(size, dtype=np.int64)
        right = np.empty(size, dtype=np.int64)
        start = np.empty(size, dtype=np.int64)
        count = np.empty(size, dtype=np.int64)
        n_nodes = aabb_kernels.build_tree(lo, hi, int(leaf_size), order, node_lo, node_hi, left, right, start, count)
        return cls(lo.copy(), hi.copy(), order, node_lo, node_hi, left, right, start, count, n_nodes, int(leaf_size))

    @property
    def n_primitives(self):
        return self.lo.shape[0]

    def refit(self, lo, hi):
        """New boxes for the same primitives (same topology), bottom-up in O(m)."""
        lo, hi = _boxes_pair(lo, hi, "AABBTree.refit")
        if lo.shape[0] != self.n_primitives:
            raise AABBInputError(f"AABBTree.refit got {lo.shape[0]} boxes but the tree has {self.n_primitives}: "
                                 f"refit needs the same primitives; build a new tree if the mesh changed")
        self.lo[...] = lo
        self.hi[...] = hi
        self.refit_in_place()

    def query_tree(self, other):
        """(k, 2) int64 pairs (i of self, j of other) whose primitive boxes overlap, sorted."""
        if not isinstance(other, AABBTree):
            raise AABBInputError(f"query_tree needs another AABBTree (got {type(other).__name__}): "
                                 f"build one with AABBTree.build(lo, hi), or use query_boxes")
        if self.n_primitives == 0 or other.n_primitives == 0:
            return np.empty((0, 2), dtype=np.int64)

        def run(out):
            return aabb_kernels.query_tree_tree(
                self.lo, self.hi, self.order, self.node_lo, self.node_hi, self.left, self.right, self.start,
                self.count, other.lo, other.hi, other.order, other.node_lo, other.node_hi, other.left,
                other.right, other.start, other.count, out)

        return _collect(run, 4 * (self.n_primitives + other.n_primitives))

    def refit_in_place(self):
        """`refit` for boxes written straight into ``self.lo``, ``self.hi`` (no copy, no check: the
        contact model makes them from validated positions at every tissue frame)."""
        aabb_kernels.refit_tree(self.lo, self.hi, self.order, self.n_nodes, self.node_lo, self.node_hi,
                                self.left, self.right, self.start, self.count)

    def query_boxes(self, lo, hi, check=True, sort=True):
        """(k, 2) int64 pairs (i primitive of self, j query box) whose boxes overlap, sorted.

        check=False skips the validation for boxes the caller made from validated positions
        ((k, 3) C-contiguous float64, finite lo <= hi). sort=False: the same pairs in the
        traversal's order (for a caller that groups them itself)."""
        if check:
            lo, hi = _boxes_pair(lo, hi, "AABBTree.query_boxes")
        if self.n_primitives == 0 or lo.shape[0] == 0:
            return np.empty((0, 2), dtype=np.int64)

        def run(out):
            return aabb_kernels.query_tree_boxes(self.lo, self.hi, self.order, self.node_lo, self.node_hi,
                                                 self.left, self.right, self.start, self.count, lo, hi, out)

        # A few boxes (a tool's) meet a few primitives each: a buffer sized by the query, not by
        # the tree (a tree-sized one costs more to allocate than the query itself); grown if short.
        return _collect(run, 16 * lo.shape[0] + 64, sort)

"""Exact distances from points to a triangle surface, for many points at once.

A k-d tree of the triangles' centroids bounds the search: a few nearest centroids give an upper
bound, and only the triangles whose centroid lies within that bound plus their own reach can be
nearer; those are measured exactly (Ericson's closest point on a triangle, by Voronoi region).
"""
from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

#: pairs (point, triangle) or (triangle, grid column) handled at once: bounds the memory
CHUNK = 1 << 18


class SurfaceDistance:
    """Distance from points to a triangle surface, exact, with a k-d tree of triangle centroids."""

    def __init__(self, mesh: trimesh.Trimesh):
        self.triangles = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)]
        self.centroids = self.triangles.mean(axis=1)
        # every point of a triangle lies within its reach of its centroid
        self.reach = np.linalg.norm(self.triangles - self.centroids[:, None], axis=2).max(axis=1)
        self.tree = cKDTree(self.centroids)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(m,) distances of (m, 3) points to the surface."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        k = min(8, len(self.triangles))
        nearest = self.tree.query(points, k)[1].reshape(len(points), k)
        # an upper bound from a few near triangles; the nearest triangle's centroid is within it + reach
        bound = _point_triangle_distance(np.repeat(points, k, axis=0),
                                         self.triangles[nearest.ravel()]).reshape(-1, k).min(axis=1)
        # (with a margin for round-off, so the nearest triangle is never left out)
        bound = bound * (1 + 1e-9) + 1e-12
        radius = bound + self.reach.max()
        # counted first, listed a chunk at a time: a sac's centre is equally far from thousands of triangles
        counts = self.tree.query_ball_point(points, radius, return_length=True)
        result = np.empty(len(points))
        for lo, hi in chunks(counts):
            listed = self.tree.query_ball_point(points[lo:hi], radius[lo:hi], return_sorted=False)
            faces = np.concatenate([np.asarray(c, dtype=np.int64) for c in listed])
            owner = np.repeat(np.arange(lo, hi), counts[lo:hi])
            # only triangles that can beat the bound: most of a tube's wall is farther by its own reach
            near = (np.linalg.norm(points[owner] - self.centroids[faces], axis=1) - self.reach[faces]
                    <= bound[owner])
            d = np.full(len(faces), np.inf)
            d[near] = _point_triangle_distance(points[owner[near]], self.triangles[faces[near]])
            result[lo:hi] = np.minimum.reduceat(d, np.cumsum(counts[lo:hi]) - counts[lo:hi])
        return result


def chunks(count: np.ndarray):
    """(lo, hi) ranges of items whose counts add up to at most :data:`CHUNK` (a larger item alone)."""
    total = np.cumsum(count)
    lo = 0
    while lo < len(count):
        before = total[lo - 1] if lo else 0
        hi = max(lo + 1, int(np.searchsorted(total, before + CHUNK, side="right")))
        yield lo, hi
        lo = hi


def _point_triangle_distance(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(m,) distance from each point to its triangle (Ericson's closest point, by Voronoi region)."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    ab, ac, ap = b - a, c - a, points - a
    bp, cp = points - b, points - c

    def dot(x, y):
        return np.einsum("ij,ij->i", x, y)

    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    # barycentric (v, w) of the closest point as a + v ab + w ac, by region in increasing priority
    # (Ericson's order reversed: on a shared boundary the regions agree, on degenerate ones his wins)
    v, w = _ratio(vb, va + vb + vc), _ratio(vc, va + vb + vc)               # the face
    t = _ratio(d4 - d3, (d4 - d3) + (d5 - d6))
    zero, one = np.zeros_like(v), np.ones_like(v)
    regions = [
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), 1.0 - t, t),            # edge bc
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), zero, _ratio(d2, d2 - d6)),        # edge ac
        ((d6 >= 0) & (d5 <= d6), zero, one),                                   # vertex c
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), _ratio(d1, d1 - d3), zero),        # edge ab
        ((d3 >= 0) & (d4 <= d3), one, zero),                                   # vertex b
        ((d1 <= 0) & (d2 <= 0), zero, zero),                                   # vertex a
    ]
    for region, rv, rw in regions:
        v, w = np.where(region, rv, v), np.where(region, rw, w)
    return np.linalg.norm(ap - v[:, None] * ab - w[:, None] * ac, axis=1)


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den, 0 where den is 0 (a degenerate triangle or edge, whose region then does not matter)."""
    return np.where(den != 0, num, 0.0) / np.where(den != 0, den, 1.0)

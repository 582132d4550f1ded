"""Exact distances from points to a triangle surface, for many points at once.

A k-d tree of the triangles' centroids bounds the search: a few nearest centroids give an upper
bound, and only the triangles whose centroid lies within that bound plus their own reach can be
nearer; those are measured exactly by the narrow phase's closest point on a triangle
(:func:`haptic_fmu.geometry.closest_point_triangle`, Ericson's, by Voronoi region).
"""
from __future__ import annotations

import math

import numpy as np
import trimesh
from numba import njit
from scipy.spatial import cKDTree

from haptic_fmu.geometry import closest_point_triangle

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


@njit(cache=True)
def _point_triangle_distance(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(m,) distance from each point to its triangle: the narrow phase's closest point (Ericson's, by
    Voronoi region), one pair at a time."""
    out = np.empty(points.shape[0])
    for i in range(points.shape[0]):
        a, b, c = triangles[i, 0], triangles[i, 1], triangles[i, 2]
        wa, wb, wc = closest_point_triangle(points[i, 0], points[i, 1], points[i, 2], a, b, c)
        dx = points[i, 0] - (wa * a[0] + wb * b[0] + wc * c[0])
        dy = points[i, 1] - (wa * a[1] + wb * b[1] + wc * c[1])
        dz = points[i, 2] - (wa * a[2] + wb * b[2] + wc * c[2])
        out[i] = math.sqrt(dx * dx + dy * dy + dz * dz)
    return out

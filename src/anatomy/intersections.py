"""Self-intersections of a triangle surface: pairs of triangles that cross each other.

Two triangles in general position intersect exactly when an edge of one crosses the other, so the
test is edges against triangles: a k-d tree of the triangles' centres finds, for each edge, the
triangles whose bounding spheres its own bounding sphere overlaps; a vectorised segment-triangle
test (Moller-Trumbore) decides. Triangles that share a vertex with the edge are neighbours, not an
intersection. Touching within a relative tolerance is not counted: a segmentation surface is
closed to round-off, and a crossing that matters is a fold, far beyond it.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: relative margin (of the barycentric and edge parameters) under which a contact is a touch
TOUCH = 1e-9
#: candidate pairs tested at once (bounds the memory of the vectorised test)
_CHUNK = 2_000_000


def _segment_crosses_triangle(p, q, a, b, c) -> np.ndarray:
    """(k,) bool: segment p-q crosses triangle a-b-c strictly inside both (all arrays (k, 3))."""
    d = q - p
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    scale = np.linalg.norm(d, axis=1) * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    usable = np.abs(det) > 1e-12 * scale          # not parallel to the triangle's plane
    inv = np.where(usable, 1.0 / np.where(usable, det, 1.0), 0.0)
    s = p - a
    u = np.einsum("ij,ij->i", s, h) * inv
    qv = np.cross(s, e1)
    v = np.einsum("ij,ij->i", d, qv) * inv
    t = np.einsum("ij,ij->i", e2, qv) * inv
    return usable & (u > TOUCH) & (v > TOUCH) & (u + v < 1 - TOUCH) & (t > TOUCH) & (t < 1 - TOUCH)


def self_intersections(vertices: np.ndarray, faces: np.ndarray, limit: int = 10) -> np.ndarray:
    """Up to ``limit`` pairs (triangle of the edge, crossed triangle) of a self-intersecting surface.

    An empty (0, 2) array means the surface does not cross itself.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    edges = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    edge_face = np.repeat(np.arange(len(faces)), 3)
    keys = np.sort(edges, axis=1)
    _, first = np.unique(keys, axis=0, return_index=True)
    edges, edge_face = edges[first], edge_face[first]

    triangles = vertices[faces]
    centres = triangles.mean(axis=1)
    tri_radius = np.linalg.norm(triangles - centres[:, None, :], axis=2).max(axis=1)
    p, q = vertices[edges[:, 0]], vertices[edges[:, 1]]
    mid = 0.5 * (p + q)
    half = 0.5 * np.linalg.norm(q - p, axis=1)
    tree = cKDTree(centres)
    found = []
    # edges in batches: query_ball_point returns Python lists, bounded per batch
    batch = max(1, _CHUNK // 64)
    for start in range(0, len(edges), batch):
        stop = min(start + batch, len(edges))
        near = tree.query_ball_point(mid[start:stop], half[start:stop] + tri_radius.max(), workers=-1)
        counts = np.fromiter((len(n) for n in near), dtype=np.int64, count=stop - start)
        if counts.sum() == 0:
            continue
        e = np.repeat(np.arange(start, stop), counts)
        f = np.fromiter((i for n in near for i in n), dtype=np.int64, count=int(counts.sum()))
        close = np.linalg.norm(mid[e] - centres[f], axis=1) <= half[e] + tri_radius[f]
        shares = (faces[f] == edges[e, :1]).any(axis=1) | (faces[f] == edges[e, 1:]).any(axis=1)
        e, f = e[close & ~shares], f[close & ~shares]
        tri = triangles[f]
        crossing = _segment_crosses_triangle(p[e], q[e], tri[:, 0], tri[:, 1], tri[:, 2])
        if crossing.any():
            found.append(np.stack([edge_face[e[crossing]], f[crossing]], axis=1))
            if sum(len(x) for x in found) >= limit:
                break
    if not found:
        return np.empty((0, 2), dtype=np.int64)
    return np.concatenate(found)[:limit]

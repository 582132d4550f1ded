"""The open ends of a lumen surface: the boundary loops where the segmentation cut the vessel.

An end is where the wall is clamped in the simulation and where a catheter enters or aims; capping
the ends closes the lumen, so that inside and outside are defined (for the centerline's distance
field and for the surface checks).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from .errors import AnatomyError


@dataclass(frozen=True)
class OpenEnd:
    """One boundary loop of a lumen surface."""

    #: vertex ids of the loop, in the order of the surface's winding (each consecutive pair is a
    #: boundary edge as one triangle traverses it)
    vertices: np.ndarray
    #: the centroid of the loop's polygon (area-weighted), m
    center: np.ndarray
    #: unit normal of the loop's plane pointing out of the vessel (away from the lumen it closes)
    normal: np.ndarray
    #: radius of the circle with the loop's area, m
    radius: float


def boundary_edges(mesh: trimesh.Trimesh) -> np.ndarray:
    """(k, 2) directed edges used by exactly one triangle, as that triangle traverses them."""
    directed = mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    keys = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return directed[counts[inverse.reshape(-1)] == 1]


def _loops(edges: np.ndarray) -> list[np.ndarray]:
    """Chain directed boundary edges into closed loops; refuse a vertex where loops touch."""
    starts, counts = np.unique(edges[:, 0], return_counts=True)
    if (counts > 1).any():
        pinched = starts[counts > 1]
        raise AnatomyError(
            f"the surface's open boundary is pinched at {pinched.size} vertex(es) (first ids "
            f"{pinched[:5].tolist()}), where two holes touch: not a vessel's open end; close the "
            "holes or cut the vessel cleanly in the segmentation tool")
    following = dict(zip(edges[:, 0].tolist(), edges[:, 1].tolist()))
    loops = []
    while following:
        first = next(iter(following))
        loop = [first]
        current = following.pop(first)
        while current != first:
            if current not in following:
                raise AnatomyError("the surface's open boundary does not close into loops (an edge is used by "
                                   "one triangle in an inconsistent direction): fix the winding with the "
                                   "repair (read_surface repairs it) or in the segmentation tool")
            loop.append(current)
            current = following.pop(current)
        loops.append(np.array(loop, dtype=np.int64))
    return loops


def _polygon_area_normal(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(area vector (3,), area-weighted centroid (3,)) of a closed polygon, by a fan from its mean."""
    anchor = points.mean(axis=0)
    a = points - anchor
    b = np.roll(points, -1, axis=0) - anchor
    cross = 0.5 * np.cross(a, b)                     # the fan triangles' area vectors
    area_vector = cross.sum(axis=0)
    weights = cross @ area_vector
    centroids = anchor + (a + b) / 3.0
    total = weights.sum()
    center = (weights[:, None] * centroids).sum(axis=0) / total if total > 0 else anchor
    return area_vector, center


def open_ends(mesh: trimesh.Trimesh) -> list[OpenEnd]:
    """The surface's open ends, each with its centre, outward normal and radius.

    The loops follow the winding of the triangles next to them. Where the normals point out of the
    lumen, the loop's area vector (by the right-hand rule) points into the vessel; the normal is
    flipped to point out of it either way, checked against the triangles beside the loop.
    """
    edges = boundary_edges(mesh)
    if edges.size == 0:
        return []
    ends = []
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    for loop in _loops(edges):
        points = vertices[loop]
        area_vector, center = _polygon_area_normal(points)
        area = float(np.linalg.norm(area_vector))
        if area == 0.0 or len(loop) < 3:
            raise AnatomyError(f"an open boundary of {len(loop)} vertices around {points.mean(axis=0).tolist()} m "
                               "encloses no area: remove the degenerate sliver of triangles there")
        normal = area_vector / area
        beside = mesh.faces[np.isin(mesh.faces, loop).any(axis=1)]
        inward = vertices[beside].reshape(-1, 3).mean(axis=0) - center
        if float(normal @ inward) > 0.0:
            normal = -normal
        ends.append(OpenEnd(vertices=loop, center=center, normal=normal, radius=float(np.sqrt(area / np.pi))))
    return ends


def capped(mesh: trimesh.Trimesh, ends: list[OpenEnd] | None = None) -> trimesh.Trimesh:
    """The surface with every open end closed by a fan of triangles around the end's centre.

    The cap's triangles traverse each boundary edge against its triangle, so the winding stays
    consistent and a surface that was watertight but for its ends becomes watertight.
    """
    ends = open_ends(mesh) if ends is None else ends
    vertices = [np.asarray(mesh.vertices, dtype=np.float64)]
    faces = [np.asarray(mesh.faces, dtype=np.int64)]
    n = len(vertices[0])
    for end in ends:
        a = end.vertices
        b = np.roll(a, -1)
        faces.append(np.stack([b, a, np.full_like(a, n)], axis=1))
        vertices.append(end.center[None, :])
        n += 1
    return trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), process=False)

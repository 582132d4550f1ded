"""Lumen surfaces of revolution for the anatomy tests: rings of vertices about the z axis, two triangles per
quad, wound so that the normals point out of the lumen, the two ends open."""
from __future__ import annotations

import numpy as np
import trimesh


def tube_of_revolution(radius_of_z, length: float, n_around: int, n_along: int) -> trimesh.Trimesh:
    """The lumen r = radius_of_z(z) about the z axis, z in [0, length]."""
    theta = np.arange(n_around) * 2 * np.pi / n_around
    z = np.linspace(0.0, length, n_along + 1)
    r = np.broadcast_to(np.asarray(radius_of_z(z), dtype=np.float64), z.shape)
    points = np.stack([np.outer(np.cos(theta), r), np.outer(np.sin(theta), r),
                       np.broadcast_to(z, (n_around, n_along + 1))], axis=-1).reshape(-1, 3)
    ids = np.arange(n_around * (n_along + 1)).reshape(n_around, n_along + 1)
    a, b = ids[:, :-1], np.roll(ids, -1, axis=0)[:, :-1]
    c, d = np.roll(ids, -1, axis=0)[:, 1:], ids[:, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return trimesh.Trimesh(points, faces, process=False)

"""Vessel centerline: an arc-length parametrised polyline the catheter is pushed along.

Conventions: SI units (m), arc length ``s`` measured from the first vertex (the entry point,
``s = 0``). The curve is extended by straight rays beyond both ends: ``s < 0`` lies outside
the body along the entry direction (where the not-yet-inserted catheter waits), ``s > length``
continues along the last segment direction.

Two tangents exist on a polyline: the segment direction (piecewise constant, what positions
move along) and a *smoothed tangent* that blends linearly between vertex tangents (the mean
of the adjacent segment directions). The smoothed tangent is continuous in ``s``, so an
active tip whose base frame follows it does not jump when its base crosses a vertex. Frames
(tangent, e1, e2) are parallel-transported (rotation-minimising) from the entry, so the
operator's ``rotation`` angle means the same thing all along the vessel.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np

from . import kernels

logger = logging.getLogger(__name__)

__all__ = ["CenterlineError", "CenterlineCurve", "AAA_CENTERLINE_LENGTH"]

# The built-in AAA mesh (tissue_fmu.mesh.aaa_mesh) has its aorta axis on +z from z = 0 to 0.13 m.
AAA_CENTERLINE_LENGTH = 0.13

# A vertex may turn the centerline by less than this; a sharper corner has no meaningful
# smoothed tangent (the mean of two opposite directions vanishes): resample the curve.
MAX_TURN_ANGLE_DEG = 90.0


class CenterlineError(ValueError):
    """Invalid centerline; the message names the problem and the fix."""


def _cross(a, b) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross costs ~15 us per call on single vectors)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def _rotate_min(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Apply the minimal rotation taking unit vector a to unit vector b to vector x.

    Rodrigues form without trigonometry: R = I + [v]x + [v]x^2 / (1 + c), v = a x b, c = a.b;
    valid for c > -1 (guaranteed by the turning-angle limit).
    """
    v = _cross(a, b)
    c = float(a @ b)
    vx = _cross(v, x)
    return x + vx + _cross(v, vx) / (1.0 + c)


class CenterlineCurve:
    """Arc-length parametrised polyline with straight extensions and parallel-transported frames.

    ``CenterlineCurve(points)`` takes any (k, 3) array, k >= 2, of finite vertices with no
    repeated consecutive vertex and turning angles below 90 degrees per vertex.
    """

    def __init__(self, points) -> None:
        try:
            pts = np.array(points, dtype=np.float64, order="C")
        except (TypeError, ValueError):
            raise CenterlineError(
                f"centerline must be a (k, 3) array of vertices in m (got {type(points).__name__}):"
                " e.g. [[0, 0, 0], [0, 0, 0.13]]"
            ) from None
        if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 2:
            raise CenterlineError(
                f"centerline must have shape (k, 3) with k >= 2 (got {pts.shape}):"
                " e.g. [[0, 0, 0], [0, 0, 0.13]]"
            )
        if not np.isfinite(pts).all():
            bad = np.flatnonzero(~np.isfinite(pts).all(axis=1))[:10].tolist()
            raise CenterlineError(f"centerline has non-finite vertices {bad}: give finite coordinates in m")
        seg = np.diff(pts, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        scale = float(np.max(seg_len))
        short = np.flatnonzero(seg_len <= 1e-12 * max(scale, 1e-300))
        if scale <= 0.0 or short.size:
            raise CenterlineError(
                f"centerline has zero-length segments after vertices {short[:10].tolist()}:"
                " remove repeated consecutive vertices"
            )
        directions = seg / seg_len[:, None]
        cos_turn = np.einsum("ij,ij->i", directions[:-1], directions[1:])
        limit = math.cos(math.radians(MAX_TURN_ANGLE_DEG))
        sharp = np.flatnonzero(cos_turn <= limit)
        if sharp.size:
            angles = np.degrees(np.arccos(np.clip(cos_turn[sharp], -1.0, 1.0)))
            raise CenterlineError(
                f"centerline turns by {angles[0]:.1f} deg at vertex {int(sharp[0]) + 1}"
                f" (vertices {(sharp[:10] + 1).tolist()}): the turn per vertex must be <"
                f" {MAX_TURN_ANGLE_DEG:g} deg; resample the curve more finely"
            )

        self.vertices = pts
        self.directions = directions
        self.segment_lengths = seg_len
        self.arc = np.concatenate([[0.0], np.cumsum(seg_len)])
        self.length = float(self.arc[-1])

        tangents = np.empty_like(pts)
        tangents[0] = directions[0]
        tangents[-1] = directions[-1]
        mid = directions[:-1] + directions[1:]
        tangents[1:-1] = mid / np.linalg.norm(mid, axis=1)[:, None]
        self.vertex_tangents = tangents

        # First normal: the global axis least aligned with the entry tangent, made orthogonal.
        ref = np.eye(3)[int(np.argmin(np.abs(tangents[0])))]
        e1 = ref - (ref @ tangents[0]) * tangents[0]
        e1 /= np.linalg.norm(e1)
        frames = np.empty_like(pts)
        frames[0] = e1
        for i in range(1, pts.shape[0]):
            e1 = _rotate_min(e1, tangents[i - 1], tangents[i])
            e1 -= (e1 @ tangents[i]) * tangents[i]
            e1 /= np.linalg.norm(e1)
            frames[i] = e1
        self.vertex_normals = frames

    # ----------------------------------------------------------------------------------
    # Constructors
    # ----------------------------------------------------------------------------------

    @classmethod
    def aaa_default(cls) -> "CenterlineCurve":
        """Aorta axis of the built-in AAA mesh: straight on +z from (0,0,0) to (0,0,0.13)."""
        return cls([[0.0, 0.0, 0.0], [0.0, 0.0, AAA_CENTERLINE_LENGTH]])

    @classmethod
    def from_function(
        cls, curve: Callable[[np.ndarray], np.ndarray], t_start: float, t_end: float, n_samples: int = 200
    ) -> "CenterlineCurve":
        """Sample a parametric curve ``curve(t) -> (m, 3)`` at n_samples values of t into a polyline.

        The polyline is re-parametrised by its own arc length; sample finely enough that the
        chord error (about L kappa^2 h^2 / 8 for spacing h) is negligible.
        """
        if not isinstance(n_samples, (int, np.integer)) or n_samples < 2:
            raise CenterlineError(f"n_samples must be an integer >= 2 (got {n_samples!r}): e.g. 200")
        t = np.linspace(float(t_start), float(t_end), int(n_samples))
        return cls(np.asarray(curve(t), dtype=np.float64).reshape(int(n_samples), 3))

    # ----------------------------------------------------------------------------------
    # Evaluation (scalars in the hot path use plain floats: numpy scalar calls cost ~1 us each)
    # ----------------------------------------------------------------------------------

    def segment_index(self, s: float) -> int:
        """Index of the polyline segment holding arc length s (end segments extend to infinity)."""
        return kernels.segment_index(self.arc, float(s))

    def points(self, s) -> np.ndarray:
        """Positions (m, 3) at arc lengths s (array-like); beyond the ends, straight extensions."""
        s = np.asarray(s, dtype=np.float64)
        idx = np.clip(np.searchsorted(self.arc, s, side="right") - 1, 0, self.directions.shape[0] - 1)
        return self.vertices[idx] + (s - self.arc[idx])[..., None] * self.directions[idx]

    def point(self, s: float) -> np.ndarray:
        out = np.empty(3)
        kernels.point(self.vertices, self.directions, self.arc, float(s), out)
        return out

    def frame(self, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Smoothed unit tangent t and the parallel-transported normals (e1, e2) at arc length s."""
        out = np.empty((3, 3))
        kernels.frame(self.arc, self.segment_lengths, self.vertex_tangents, self.vertex_normals, float(s), out, 0)
        return out[0], out[1], out[2]

    def chain_back(self, s_start: float, n_points: int, spacing: float) -> np.ndarray:
        """Points (n_points, 3) on the curve walking back from c(s_start), each exactly
        ``spacing`` (Euclidean) from the previous one.

        Inside one straight segment the chord equals the arc step, so runs of points are placed
        directly; only where the chain crosses a vertex is a sphere-segment intersection solved
        (first crossing going backward, which is continuous in s_start). A root landing exactly
        on a vertex is clamped to it (see ``kernels.chain_back``).
        """
        out = np.empty((int(n_points), 3))
        kernels.chain_back(
            self.vertices, self.directions, self.arc, self.segment_lengths, float(s_start), float(spacing), out
        )
        return out

"""Catheter shape: a chain of equal rigid links that follows the vessel centerline, with a
distal active section bent as a discrete constant-curvature arc.

Shape model (``n_segments`` links of length ``l``, the last ``n_active`` of them active):

- The inserted length ``s = insertion`` is measured along the centerline from the entry
  point. The active section's base sits on the centerline at ``s_b = s - n_active * l``; the
  proximal links hang back from it along the curve, each joint on the curve and exactly ``l``
  from the next (sphere-curve intersection, see ``CenterlineCurve.chain_back``). Joints with
  ``s < 0`` lie outside the body on the entry ray.
- The active section starts at the base with the curve's smoothed tangent ``t`` and bends by a
  total angle ``beta`` toward the unit direction ``d`` in the normal plane (``d`` from the bend
  vector given in the base frame (e1, e2)). Link ``j = 1..n_active`` points along
  ``cos((j - 1/2) phi) t + sin((j - 1/2) phi) d`` with ``phi = beta / n_active``: every joint lies
  on the circular arc of curvature ``kappa = beta / (n_active l)`` through the base (a regular
  inscribed polygon), every link keeps length ``l`` exactly, and the tip tangent is turned by
  ``beta - phi / 2`` (the arc tangent by ``beta``).
- Small-bend tip displacement: lateral ``L beta / 2``, axial shortening ``L beta^2 / 6`` with
  ``L = n_active l`` (same as the continuous arc to first order).

The tip position is continuous in (insertion, rotation, bend): positions and the smoothed
tangent are continuous in ``s`` and the parallel-transported frame is continuous too.
"""

from __future__ import annotations

import logging

import numpy as np

from . import kernels
from .geometry import CenterlineCurve

logger = logging.getLogger(__name__)

__all__ = ["CatheterKinematics"]


class CatheterKinematics:
    """Positions of the ``n_segments + 1`` joints (proximal end first, tip last).

    Inputs are trusted (validated by ``CatheterModel``); arrays are preallocated once.
    """

    def __init__(self, curve: CenterlineCurve, n_segments: int, segment_length: float, n_active: int) -> None:
        self.curve = curve
        self.n_segments = int(n_segments)
        self.segment_length = float(segment_length)
        self.n_active = int(n_active)
        self.active_length = self.n_active * self.segment_length
        self.positions = np.zeros((self.n_segments + 1, 3))
        # Rows (base point, t, e1, e2) of the latest ``fill_base_frame``.
        self.frame = np.zeros((4, 3))
        # Link angles (j - 1/2) / n_active in units of the total bend angle.
        self._link_fraction = (np.arange(1, self.n_active + 1) - 0.5) / self.n_active
        # Kernel arguments looked up once (attribute lookups add up at 1 kHz).
        self._polyline = (curve.vertices, curve.directions, curve.arc, curve.segment_lengths)
        self._frame_data = self._polyline + (curve.vertex_tangents, curve.vertex_normals)

    def fill_base_frame(self, insertion: float) -> np.ndarray:
        """Fill and return ``self.frame`` (4, 3): rows (base point, t, e1, e2) for this insertion (m).

        The buffer is reused by the next call; ``base_frame`` returns fresh arrays.
        """
        kernels.base_frame(*self._frame_data, insertion - self.active_length, self.frame)
        return self.frame

    def fill_shape(self, insertion: float, b1: float, b2: float, frame: np.ndarray,
                   out: np.ndarray | None = None) -> np.ndarray:
        """Fill and return ``self.positions`` (or ``out``, a C-contiguous (n_segments + 1, 3)
        float64 array) from a (4, 3) frame array (``fill_base_frame``) and the bend vector
        (b1, b2) (rad)."""
        positions = self.positions if out is None else out
        kernels.catheter_shape(
            *self._polyline,
            frame,
            insertion - self.active_length,
            b1,
            b2,
            self._link_fraction,
            self.segment_length,
            positions,
        )
        return positions

    @property
    def link_fraction(self) -> np.ndarray:
        """(n_active,) link angles (j - 1/2) / n_active in units of the total bend angle."""
        return self._link_fraction

    def fill_tip_jacobian(self, frame: np.ndarray, b1: float, b2: float, out: np.ndarray) -> np.ndarray:
        """Fill and return ``out`` (3, 2): d tip / d (b1, b2) (m/rad) of the active section bent by
        (b1, b2) on a (4, 3) frame array (``fill_base_frame``)."""
        kernels.tip_jacobian(frame, b1, b2, self._link_fraction, self.segment_length, out)
        return out

    def base_frame(self, insertion: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(base point, tangent t, e1, e2) of the active section for this insertion."""
        out = np.empty((4, 3))
        kernels.base_frame(*self._frame_data, float(insertion) - self.active_length, out)
        return out[0], out[1], out[2], out[3]

    def active_chain(
        self, base: np.ndarray, t: np.ndarray, e1: np.ndarray, e2: np.ndarray, bend_vector: tuple[float, float]
    ) -> np.ndarray:
        """Joints (n_active, 3) after the base for bend vector (b1, b2) in the (e1, e2) frame (rad)."""
        b1, b2 = bend_vector
        frame = np.array([base, t, e1, e2], dtype=np.float64)
        out = np.empty((self.n_active, 3))
        kernels.active_chain(frame, float(b1), float(b2), self._link_fraction, self.segment_length, out)
        return out

    def shape(self, insertion: float, bend_vector: tuple[float, float], frame=None) -> np.ndarray:
        """Fill and return ``self.positions`` for this insertion (m) and bend vector (rad).

        ``frame`` may pass a precomputed ``base_frame(insertion)`` to avoid recomputing it.
        """
        insertion = float(insertion)
        frame = self.fill_base_frame(insertion) if frame is None else np.array(frame, dtype=np.float64)
        b1, b2 = bend_vector
        return self.fill_shape(insertion, float(b1), float(b2), frame)

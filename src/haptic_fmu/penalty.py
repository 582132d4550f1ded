"""Penalty contact response: signed distance to a facet, penalty laws, force distribution.

The haptic force on the tool (design eq. 5, law "linear"):

    F_c = -k dist n - b (v . n) n    if dist < 0, else 0

with n the facet's outward unit normal (triangle (a, b, c) wound so that (b-a) x (c-a) points out
of the tissue), dist = (p - q) . n the signed distance of the tool point p (q: the closest point
of the facet, so dist is the plane distance; dist < 0 is penetration) and v the velocity of the
tool relative to the surface at q. The tissue receives exactly -F_c, applied at q and split over
the facet's three vertices by the barycentric weights of q (so the nodal forces sum to -F_c and
their moment about any point equals that of -F_c applied at q).

Penalty laws (delta = -dist > 0, rate = d delta/dt = -(v.n); d0 = `penalty_length`):
- "linear":        f = k delta + b rate                            energy k delta^2 / 2
- "quadratic":     f = k delta (1 + delta/d0) + b rate             energy k delta^2/2 + k delta^3/(3 d0)
- "hunt_crossley": f = max(0, k delta (delta/d0)^0.5 + b (delta/d0) rate)   energy 0.4 k delta^2.5/d0^0.5
  (k keeps units of N/m: it is the secant stiffness at delta = d0; damping grows with depth so the
  force starts from zero at first contact and never pulls the tool in.)
"""
from dataclasses import dataclass

import numpy as np

from . import kernels

PENALTY_LAWS = {"linear": kernels.LAW_LINEAR, "quadratic": kernels.LAW_QUADRATIC,
                "hunt_crossley": kernels.LAW_HUNT_CROSSLEY}


class PenaltyInputError(ValueError):
    """Invalid input to a penalty computation."""


def law_code(name: str) -> int:
    """Kernel code of a penalty law name; ValueError naming the choices otherwise."""
    try:
        return PENALTY_LAWS[name]
    except (KeyError, TypeError):
        raise PenaltyInputError(
            f"penalty_law must be one of {sorted(PENALTY_LAWS)} (got {name!r})") from None


def _triangle_array(name, value, rows):
    arr = np.ascontiguousarray(value, dtype=np.float64)
    if arr.shape != (rows, 3):
        raise PenaltyInputError(f"{name} must have shape ({rows}, 3) (got {arr.shape})")
    if not np.isfinite(arr).all():
        raise PenaltyInputError(f"{name} contains NaN or inf: give finite coordinates in m")
    return arr


def _vector(name, value):
    arr = np.ascontiguousarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,):
        raise PenaltyInputError(f"{name} must be a 3-vector (got shape {np.shape(value)})")
    if not np.isfinite(arr).all():
        raise PenaltyInputError(f"{name} contains NaN or inf")
    return arr


def face_normal(triangle) -> np.ndarray:
    """Outward unit normal of a (3,3) triangle (rows a, b, c)."""
    tri = _triangle_array("triangle", triangle, 3)
    n = np.array(kernels.face_normal(tri[0], tri[1], tri[2]))
    if not n.any():
        raise PenaltyInputError("triangle is degenerate (zero area): it has no normal")
    return n


def closest_point(point, triangle):
    """(q, barycentric weights (3,)) of the point of `triangle` (3,3) closest to `point`."""
    p = _vector("point", point)
    tri = _triangle_array("triangle", triangle, 3)
    w = np.array(kernels.closest_point_triangle(p[0], p[1], p[2], tri[0], tri[1], tri[2]))
    return w @ tri, w


def signed_distance(point, triangle) -> float:
    """Signed distance (p - q) . n of a point to a facet: < 0 inside the tissue."""
    q, _ = closest_point(point, triangle)
    return float((_vector("point", point) - q) @ face_normal(triangle))


def segment_triangle_distance(p0, p1, triangle):
    """(distance, segment parameter s, barycentric weights) of segment [p0, p1] to a triangle."""
    a0 = _vector("p0", p0)
    a1 = _vector("p1", p1)
    tri = _triangle_array("triangle", triangle, 3)
    s, wa, wb, wc, d2 = kernels.closest_segment_triangle(a0, a1, tri[0], tri[1], tri[2])
    return float(np.sqrt(d2)), float(s), np.array([wa, wb, wc])


def normal_force(depth, rate, law="linear", stiffness=500.0, damping=0.0, penalty_length=1e-3) -> float:
    """Force magnitude along the outward normal for penetration `depth` (m) and rate d depth/dt."""
    return float(kernels.penalty_magnitude(float(depth), float(rate), law_code(law), float(stiffness),
                                           float(damping), float(penalty_length)))


def penalty_energy(depth, law="linear", stiffness=500.0, penalty_length=1e-3) -> float:
    """Elastic potential energy (J) stored by the penalty law at penetration `depth`."""
    return float(kernels.penalty_energy(float(depth), law_code(law), float(stiffness), float(penalty_length)))


@dataclass
class FacetContact:
    """Result of one tool point against one facet."""

    tool_force: np.ndarray      # (3,) force on the tool
    vertex_forces: np.ndarray   # (3,3) forces on the facet's vertices a, b, c (sum = -tool_force)
    distance: float             # signed distance (< 0: penetration)
    normal: np.ndarray          # (3,) outward unit normal
    contact_point: np.ndarray   # (3,) closest point q on the facet
    barycentric: np.ndarray     # (3,) weights of q


def facet_contact(point, triangle, tool_velocity=(0.0, 0.0, 0.0), vertex_velocities=None, *,
                  stiffness=500.0, damping=0.0, law="linear", penalty_length=1e-3,
                  radius=0.0) -> FacetContact:
    """Penalty contact of a tool point (sphere of `radius`) with one facet (plain reference API).

    The relative velocity is the tool velocity minus the facet velocity at the contact point,
    interpolated barycentrically from `vertex_velocities` (3,3) (zero if None).
    """
    p = _vector("point", point)
    tri = _triangle_array("triangle", triangle, 3)
    vt = _vector("tool_velocity", tool_velocity)
    vv = np.zeros((3, 3)) if vertex_velocities is None else _triangle_array(
        "vertex_velocities", vertex_velocities, 3)
    n = face_normal(tri)
    q, w = closest_point(p, tri)
    dist = float((p - q) @ n) - float(radius)
    rate = -float((vt - w @ vv) @ n)
    f = normal_force(-dist, rate, law, stiffness, damping, penalty_length) if dist < 0 else 0.0
    force = f * n
    return FacetContact(tool_force=force, vertex_forces=-np.outer(w, force), distance=dist,
                        normal=n, contact_point=q, barycentric=w)

"""Test-only helpers of the Contact model (moved out of `haptic_fmu`): plain references and small
drivers the tests check the package against.

- `local_from_surface`, `probe_force`: a local model over a whole small surface and the force on
  one probe point against it (the narrow phase and response kernels, memoryless).
- `closest_point_triangle_batch`, `closest_segment_triangle_batch`: row-wise geometry kernels.
- `face_normal`, `closest_point`, `signed_distance`, `segment_triangle_distance`, `facet_contact`:
  the penalty contact of one point with one facet, in plain Python around the geometry kernels.
- `PassivityObserver`, `controller_damping`: the plain-Python passivity observer and controller
  gain that `haptic_fmu.passivity.PassiveRenderer` computes in one kernel.
"""
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from haptic_fmu import geometry, narrow_phase, penalty_kernels
from haptic_fmu.penalty import law_code, normal_force
from haptic_fmu.rendering import LocalModel


# ---------------------------------------------------------------------------- local model drivers
def local_from_surface(t_frame, positions, velocities, triangles, policy="extrapolate", n_nodes=1):
    """A local model holding a whole (small) surface, every face a candidate of every node."""
    positions = np.asarray(positions, np.float64)
    velocities = np.asarray(velocities, np.float64)
    triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
    model = LocalModel(policy)
    nodes, faces = np.meshgrid(np.arange(n_nodes), np.arange(triangles.shape[0]), indexing="ij")
    model.capture(t_frame, positions, velocities, triangles,
                  np.stack([nodes.ravel(), faces.ravel()], axis=1), n_nodes)
    return model


def probe_force(local, t, point, velocity=(0.0, 0.0, 0.0), *, stiffness=500.0, damping=0.0,
                law="linear", penalty_length=1e-3, radius=0.0):
    """Force (3,) on one probe point at time t against a local model (memoryless: the nearest
    facet decides the side). Returns (force, signed distance or None if no contact)."""
    p = np.asarray(point, np.float64).reshape(1, 3)
    v = np.asarray(velocity, np.float64).reshape(1, 3)
    pos = local.positions_at(t)
    face, w, n = np.full(1, -1, np.int64), np.zeros((1, 3)), np.zeros((1, 3))
    depth, rate, s, q, near = np.zeros(1), np.zeros(1), np.zeros(1), np.zeros((1, 3)), np.zeros(1)
    narrow_phase.proximity(pos, local.velocities, local.triangles, local.node_ptr[:2], local.node_faces,
                           np.zeros(1, np.int64), local.seg_faces, p, v, float(radius), 0.0, np.full(1, np.inf),
                           np.zeros(1, np.int8), np.zeros((1, 3)), face, w, n, depth, rate, s, q, near,
                           np.zeros((max(local.node_faces.size, 1), narrow_phase.WORK_COLUMNS)))
    fmag = np.zeros(1)
    code = law_code(law)
    penalty_kernels.penalty_forces(face, depth, rate, np.zeros(1), code, float(stiffness), float(damping),
                                   float(penalty_length), fmag)
    node_force = np.zeros((1, 3))
    tissue = np.zeros((local.vertices.size, 3))
    penalty_kernels.distribute(fmag, fmag, face, w, n, s, depth, local.triangles, np.arange(local.vertices.size), 1,
                               code, float(stiffness), float(penalty_length), node_force, tissue, np.zeros((0, 3)))
    return node_force[0], (None if face[0] < 0 else -float(depth[0]))


# ---------------------------------------------------------------------------- geometry
@njit(cache=True)
def closest_point_triangle_batch(points, a, b, c, bary_out):
    """Row-wise closest points: bary_out[i] = weights of the point of triangle i closest to point i."""
    for i in range(points.shape[0]):
        wa, wb, wc = geometry.closest_point_triangle(points[i, 0], points[i, 1], points[i, 2], a[i], b[i], c[i])
        bary_out[i, 0] = wa
        bary_out[i, 1] = wb
        bary_out[i, 2] = wc


@njit(cache=True)
def closest_segment_triangle_batch(p0, p1, a, b, c, s_out, bary_out, dist_out):
    """Row-wise segment-triangle closest points (see geometry.closest_segment_triangle)."""
    for i in range(p0.shape[0]):
        s, wa, wb, wc, d2 = geometry.closest_segment_triangle(p0[i], p1[i], a[i], b[i], c[i])
        s_out[i] = s
        bary_out[i, 0] = wa
        bary_out[i, 1] = wb
        bary_out[i, 2] = wc
        dist_out[i] = math.sqrt(d2)


def face_normal(triangle) -> np.ndarray:
    """Outward unit normal of a (3,3) triangle (rows a, b, c)."""
    tri = np.asarray(triangle, np.float64)
    return np.array(geometry.face_normal(tri[0], tri[1], tri[2]))


def closest_point(point, triangle):
    """(q, barycentric weights (3,)) of the point of `triangle` (3,3) closest to `point`."""
    p = np.asarray(point, np.float64)
    tri = np.asarray(triangle, np.float64)
    w = np.array(geometry.closest_point_triangle(p[0], p[1], p[2], tri[0], tri[1], tri[2]))
    return w @ tri, w


def segment_triangle_distance(p0, p1, triangle):
    """(distance, segment parameter s, barycentric weights) of segment [p0, p1] to a triangle."""
    tri = np.asarray(triangle, np.float64)
    s, wa, wb, wc, d2 = geometry.closest_segment_triangle(np.asarray(p0, np.float64), np.asarray(p1, np.float64),
                                                          tri[0], tri[1], tri[2])
    return float(np.sqrt(d2)), float(s), np.array([wa, wb, wc])


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
                  stiffness=500.0, damping=0.0, law="linear", penalty_length=1e-3, radius=0.0) -> FacetContact:
    """Penalty contact of a tool point (sphere of `radius`) with one facet (plain reference).

    The relative velocity is the tool velocity minus the facet velocity at the contact point,
    interpolated barycentrically from `vertex_velocities` (3,3) (zero if None)."""
    p = np.asarray(point, np.float64)
    tri = np.asarray(triangle, np.float64)
    vt = np.asarray(tool_velocity, np.float64)
    vv = np.zeros((3, 3)) if vertex_velocities is None else np.asarray(vertex_velocities, np.float64)
    n = face_normal(tri)
    q, w = closest_point(p, tri)
    dist = float((p - q) @ n) - float(radius)
    rate = -float((vt - w @ vv) @ n)
    f = normal_force(-dist, rate, law, stiffness, damping, penalty_length) if dist < 0 else 0.0
    force = f * n
    return FacetContact(tool_force=force, vertex_forces=-np.outer(w, force), distance=dist,
                        normal=n, contact_point=q, barycentric=w)


# ---------------------------------------------------------------------------- passivity

class PassivityObserver:
    """Energy that has flowed into the environment through the haptic port (>= 0 when passive)."""

    def __init__(self):
        self.energy = 0.0
        self.min_energy = 0.0
        self._force = None       # force held since the previous sample (on the tool)
        self._position = None

    def reset(self) -> None:
        self.__init__()

    def update(self, position, force) -> float:
        """Record sample n: the tool position x(n) and the force F(n) that will be held until the
        next sample. Adds the work of the previously held force over x(n) - x(n-1); returns E(n)."""
        x = np.asarray(position, np.float64)
        f = np.asarray(force, np.float64)
        if self._position is not None:
            self.energy -= float(np.sum(self._force * (x - self._position)))
            self.min_energy = min(self.min_energy, self.energy)
        self._position = x.copy()
        self._force = f.copy()
        return self.energy

    def observe(self, position) -> float:
        """E(n) including the work of the held force up to `position`, without recording a sample."""
        if self._position is None:
            return self.energy
        return self.energy - float(np.sum(self._force * (np.asarray(position, np.float64) - self._position)))


def controller_damping(energy: float, velocity, period: float, max_damping: float = math.inf) -> float:
    """Passivity controller gain alpha = min(-E / (T v.v), max_damping) when E < 0, else 0 (N s/m)."""
    if period <= 0.0:
        raise ValueError(f"period must be > 0 (got {period}): give the haptic sample time in s")
    vv = float(np.sum(np.square(velocity)))
    if energy >= 0.0 or vv <= 0.0:
        return 0.0
    return min(-energy / (period * vv), max_damping)


# ---------------------------------------------------------------------------- device limit, contact cycles
# Plain references of `haptic_fmu.device.limit_force` and of the per-contact-cycle judgement that
# `haptic_fmu.passivity.port_step` computes in one kernel.

def limit_force_reference(force, prev, max_force, max_force_rate, dt):
    """The device limit in plain numpy: (rendered node forces (n,3), rate limited, magnitude limited).

    The port's total force moves at most max_force_rate * dt from the previous rendered total (every
    node blended toward its request by the same factor), then is scaled into |F| <= max_force
    (every node by the same factor)."""
    f = np.array(force, np.float64).reshape(-1, 3)
    p = np.array(prev, np.float64).reshape(-1, 3)
    change = np.linalg.norm(f.sum(axis=0) - p.sum(axis=0))
    rate = bool(change > max_force_rate * dt)
    if rate:
        f = p + (max_force_rate * dt / change) * (f - p)
    magnitude = np.linalg.norm(f.sum(axis=0))
    clamp = bool(magnitude > max_force)
    if clamp:
        f = f * (max_force / magnitude)
    return f, rate, clamp


class ContactCycles:
    """Contact cycles of a haptic port in plain Python: feed every sample's position, contact force
    (before the controller and the device limit) and rendered force (held until the next sample).

    A cycle opens at a sample with a nonzero contact force and closes at the first sample where the
    contact force and the rendered force are both zero; over it the work of each held force,
    w = -F(j-1) . (x(j) - x(j-1)), is energy in (w > 0) or out. `closed` lists the cycles as dicts
    (t_start, t_end, energy_in, energy_out, abs_work, samples, active); active when
    out - in > tolerance (in + out) + 2 (3 n + samples + 1) 2^-53 abs_work."""

    def __init__(self, tolerance=1e-6):
        self.tolerance = tolerance
        self.closed = []
        self.open = None
        self._x = None
        self._f = None

    def update(self, t, position, contact_force, rendered_force):
        x = np.array(position, np.float64).reshape(-1, 3)
        if self.open is not None and self._x is not None:
            products = self._f * (x - self._x)
            w = -float(products.sum())
            if w > 0:
                self.open["energy_in"] += w
            else:
                self.open["energy_out"] -= w
            self.open["abs_work"] += float(np.abs(products).sum())
            self.open["samples"] += 1
        contact = bool(np.any(np.asarray(contact_force) != 0))
        held = bool(np.any(np.asarray(rendered_force) != 0))
        if self.open is not None and not contact and not held:
            c = self.open
            floor = 2.0 * (3 * x.shape[0] + c["samples"] + 1) * 2.0 ** -53 * c["abs_work"]
            c["threshold"] = self.tolerance * (c["energy_in"] + c["energy_out"]) + floor
            c["active"] = c["energy_out"] - c["energy_in"] > c["threshold"]
            c["t_end"] = t
            self.closed.append(c)
            self.open = None
        elif self.open is None and contact:
            self.open = dict(t_start=t, energy_in=0.0, energy_out=0.0, abs_work=0.0, samples=0)
        self._x = x
        self._f = np.array(rendered_force, np.float64).reshape(-1, 3)

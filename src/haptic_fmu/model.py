"""Contact model of the Contact FMU: tissue frames at ~30 Hz, haptic steps at ~1 kHz (no FMI).

Data flow
- `set_tissue_frame(t, positions, velocities)`: refits the AABB tree of the surface triangles
  (built once, on the first frame; never rebuilt), runs the frame-level continuous detection of
  the tool against the tissue's motion since the previous frame, and refreshes the local model.
- `step(t, dt, tool_positions, tool_velocities=None)`: one haptic step, evaluated at t + dt with
  the tool at `tool_positions` (the previous call's positions start the swept interval). Broad
  phase against the local model only (its candidate pairs), optional CCD over the step, narrow
  phase and penalty forces in one numba kernel, then the passivity observer/controller.

Tool
- "centerline": n_tool points of the catheter centerline; nodes are spheres and segments capsules
  of `tool_radius`.
- "probe": one point (radius 0) driven by a haptic device.

Contact side memory: a tool node that enters the tissue remembers the outward normal of the face
it entered through and, while inside, measures its penetration only against faces facing the
same way. This keeps the force on the side it came from when a thin wall is crossed (both the
discrete and the continuous detection use it). Continuous detection adds the CCD of every node
that crosses a face plane during the step (linear motion; the local model's motion over a step
is linear for both policies) and, at each new tissue frame, of the tool against the tissue's motion
between frames (linear, or cubic Hermite trajectories from the frame velocities when
interpolation="cubic"), so a fast tool or wall cannot tunnel. Segment interiors are checked
discretely only (the catheter's nodes carry the CCD). The interpolation parameter only affects
that frame-level detection.

Real time: every kernel (and the CCD) is loaded or compiled at construction, not in the first
steps; the hot path allocates only small per-step arrays; the broad phase runs against the local
model's candidate pairs, re-queried from the tree only at frames and when the tool has moved
more than margin/2 since the last query.
"""
import copy
import logging
import math
import numbers
from dataclasses import dataclass, fields

import numpy as np

from . import kernels
from .local_model import LOCAL_POLICIES, LocalModel
from .passivity import PassiveRenderer
from .penalty import PENALTY_LAWS, law_code

logger = logging.getLogger(__name__)

#: Energy (J) below which the active-contact warning stays silent (noise, one-sample transients,
#: a moving tissue surface: the AAA scene creates about 1 mJ).
ACTIVE_ENERGY_FLOOR = 0.01

DETECTIONS = ("continuous", "discrete")
INTERPOLATIONS = ("linear", "cubic")
TOOLS = ("centerline", "probe")


class ContactParameterError(ValueError):
    """A contact parameter is out of range or unknown."""


class ContactInputError(ValueError):
    """A run-time input (tissue frame, tool positions, step) is invalid."""


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


@dataclass
class ContactParameters:
    """Parameters of the Contact FMU (SI units)."""

    stiffness: float = 500.0           # k, N/m
    damping: float = 0.1               # b, N s/m
    penalty_law: str = "linear"        # "linear" | "quadratic" | "hunt_crossley" (see penalty.py)
    penalty_length: float = 1e-3       # d0, m (non-linear laws)
    detection: str = "continuous"      # "continuous" | "discrete"
    interpolation: str = "linear"      # tissue trajectories between frames for CCD: "linear" | "cubic"
    local_model: str = "extrapolate"   # "hold" | "extrapolate"
    tool: str = "centerline"           # "centerline" | "probe"
    tool_radius: float = 0.001         # m (centerline capsules; a probe is a point)
    passivity_controller: bool = False
    passivity_max_damping: float = 20.0  # N s/m, cap of the controller's damping (keep < 2 m_device / dt)
    margin: float = 0.003              # m, broad-phase margin of the local model
    frame_period: float = 1.0 / 30.0   # s, expected tissue frame period (extent of extrapolated boxes)

    def validate(self) -> "ContactParameters":
        def positive(name, example):
            value = getattr(self, name)
            if not (_is_real(value) and math.isfinite(value) and value > 0):
                raise ContactParameterError(f"{name} must be a finite number > 0 (got {value!r}): {example}")

        def choice(name, options):
            value = getattr(self, name)
            if value not in options:
                raise ContactParameterError(f"{name} must be one of {list(options)} (got {value!r})")

        positive("stiffness", "give the penalty stiffness k in N/m, e.g. 500")
        if not (_is_real(self.damping) and math.isfinite(self.damping) and self.damping >= 0):
            raise ContactParameterError(
                f"damping must be a finite number >= 0 (got {self.damping!r}): give b in N s/m, e.g. 0.1")
        positive("penalty_length", "give the non-linear penalty length d0 in m, e.g. 1e-3")
        positive("margin", "give the broad-phase margin in m, e.g. 0.003 (more than the deepest expected penetration)")
        positive("frame_period", "give the tissue frame period in s, e.g. 1/30")
        positive("passivity_max_damping", "give the cap of the passivity controller's damping in N s/m, "
                                          "below 2 m/T for the device mass m and step T, e.g. 20")
        if not (_is_real(self.tool_radius) and math.isfinite(self.tool_radius)
                and self.tool_radius >= 0):
            raise ContactParameterError(
                f"tool_radius must be a finite number >= 0 (got {self.tool_radius!r}): e.g. 0.001 m for 6 Fr")
        choice("penalty_law", tuple(PENALTY_LAWS))
        choice("detection", DETECTIONS)
        choice("interpolation", INTERPOLATIONS)
        choice("local_model", LOCAL_POLICIES)
        choice("tool", TOOLS)
        if not isinstance(self.passivity_controller, (bool, np.bool_)):
            raise ContactParameterError(
                f"passivity_controller must be True or False (got {self.passivity_controller!r})")
        return self


@dataclass
class ContactOutputs:
    """Outputs of one haptic step. Arrays are the model's buffers: copy them to keep them.

    tissue_contact_force sums to -tool_force exactly (action-reaction), except for the damping the
    passivity controller adds on the tool side when it is on (a device-side element, not a contact).
    """

    tool_force: np.ndarray             # (3,) total force on the tool, N
    tip_force: np.ndarray              # (3,) force on the last tool point, N
    tissue_contact_force: np.ndarray   # (n_surface,3) nodal forces on the surface, N
    node_forces: np.ndarray            # (n_tool,3) force on each tool point, N
    penetration_depth: float           # max over contacts, m
    contact_count: int                 # tool primitives (nodes, segments) in contact
    contact_energy: float              # penalty potential energy, J
    passivity_energy: float            # energy into the environment through the port, J (>= 0 passive)


def _float_array(name, value, n, fix):
    arr = np.asarray(value, dtype=np.float64)
    if arr.size != n * 3:
        raise ContactInputError(
            f"{name} must hold {n} points ({n}x3 = {n * 3} values, flat or (n,3)) (got shape {arr.shape}): {fix}")
    arr = arr.reshape(n, 3)
    if not np.isfinite(arr).all():
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        raise ContactInputError(f"{name} contains NaN or inf at points {bad[:10].tolist()}: {fix}")
    return arr


_WARMED = set()


def _warm_up(ccd, interpolation) -> None:
    """Load (or compile) every kernel of the hot path once per process, at construction, so the
    first haptic steps do not pay it (it takes up to seconds: a haptic loop cannot absorb that)."""
    key = ("ccd", interpolation)
    if key in _WARMED:
        return
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    local = LocalModel.from_surface(0.0, tri, np.zeros((3, 3)), [[0, 1, 2]], policy="extrapolate")
    local.probe_force(0.0, [0.2, 0.2, -0.1], [0.0, 0.0, -1.0])
    p0 = np.array([[[0.2, 0.2, 1.0], *tri]])
    p1 = np.array([[[0.2, 0.2, -1.0], *tri]])
    kernels.ccd_candidates(tri, tri, np.array([[0, 1, 2]]), np.array([0, 1]), np.array([0]),
                           p0[:, 0].copy(), p1[:, 0].copy(), 0.0, np.zeros(1, np.int8),
                           np.zeros((1, 8, 3)), np.zeros(1, np.int64), np.zeros(1, np.int64))
    kernels.max_displacement(tri, tri)
    PassiveRenderer(1e-3, True).render(tri, tri, tri)
    kernels.triangle_boxes(tri, tri, True, np.array([[0, 1, 2]]), np.zeros((1, 3)), np.zeros((1, 3)))
    ccd.vertex_face(np.concatenate([p0, p1], axis=1))
    if interpolation == "cubic":
        ccd.vertex_face_spline(p0, p1, p1 - p0, p1 - p0, 1.0)
    _WARMED.add(key)


def _import_broad_phase():
    from . import aabb, ccd  # the AABB tree and CCD modules of this package
    return aabb, ccd


class ContactModel:
    """Penalty contact and haptic rendering of a tool against the tissue surface."""

    def __init__(self, surface_triangles, n_surface: int, n_tool: int, params: ContactParameters | None = None):
        self.params = (params or ContactParameters()).validate()
        if not (isinstance(n_surface, (int, np.integer)) and n_surface >= 3):
            raise ContactParameterError(f"n_surface must be an integer >= 3 (got {n_surface!r})")
        if not (isinstance(n_tool, (int, np.integer)) and n_tool >= 1):
            raise ContactParameterError(f"n_tool must be an integer >= 1 (got {n_tool!r})")
        if self.params.tool == "probe" and n_tool != 1:
            raise ContactParameterError(f"n_tool must be 1 for tool='probe' (got {n_tool}); "
                                        "use tool='centerline' for several points")
        tri = np.asarray(surface_triangles)
        if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] == 0:
            raise ContactParameterError(f"surface_triangles must have shape (t,3), t >= 1 (got {tri.shape})")
        if not np.issubdtype(tri.dtype, np.integer):
            if not np.all(np.asarray(tri, np.float64) == np.round(tri)):
                raise ContactParameterError("surface_triangles must hold integer vertex ids")
        tri = np.ascontiguousarray(tri, dtype=np.int64)
        if tri.min() < 0 or tri.max() >= n_surface:
            raise ContactParameterError(
                f"surface_triangles must index surface nodes 0..{n_surface - 1} "
                f"(got ids {tri.min()}..{tri.max()}): give local surface ids")
        self.aabb, self.ccd = _import_broad_phase()
        _warm_up(self.ccd, self.params.interpolation)
        self.triangles = tri
        self.n_surface = int(n_surface)
        self.n_tool = int(n_tool)
        p = self.params
        self.radius = float(p.tool_radius) if p.tool == "centerline" else 0.0
        self.n_segments = self.n_tool - 1 if p.tool == "centerline" else 0
        self._law = law_code(p.penalty_law)
        self.local = LocalModel(p.local_model)
        self.tree = None
        # tissue frames
        self._frame_t = None
        self._frame_pos = None
        self._frame_vel = None
        # tool state
        self._tool_prev = None          # tool positions at the last step
        self._tunnel_warned = False     # the discrete-detection tunnelling warning is given once
        self._peak_potential = 0.0      # largest penalty energy held so far (J)
        self._active_warned = False     # the active-contact warning is given once
        self._tool_at_frame = None      # tool positions when the last frame arrived
        self._built_at = None           # tool positions when the local model was last queried
        self._inside = np.zeros(self.n_tool, np.int8)
        self._entry_normal = np.zeros((self.n_tool, 3))
        # output buffers (allocation-light hot path)
        self._node_force = np.zeros((self.n_tool, 3))
        self._tissue_force = np.zeros((self.n_surface, 3))
        self._contact_face = np.full(self.n_tool + self.n_segments, -1, np.int64)
        self._contact_depth = np.zeros(self.n_tool + self.n_segments)
        self._pos0 = np.zeros((0, 3))
        self._box_lo = np.zeros((tri.shape[0], 3))
        self._box_hi = np.zeros((tri.shape[0], 3))
        self._ccd_buffers = None
        self._renderer = None
        self.ccd_hits = 0               # diagnostics: contacts started by CCD
        self.local_refreshes = 0

    # ------------------------------------------------------------------ tissue frames
    def set_tissue_frame(self, t, positions, velocities=None) -> None:
        """New tissue frame: positions/velocities (n_surface,3) or flat, at time t (s)."""
        if not (_is_real(t) and math.isfinite(t)):
            raise ContactInputError(f"t must be a finite time in s (got {t!r})")
        fix = "give surface node positions in m for all surface nodes, in the order of surface_triangles"
        pos = _float_array("tissue_positions", positions, self.n_surface, fix).copy()
        vel = (np.zeros_like(pos) if velocities is None else
               _float_array("tissue_velocities", velocities, self.n_surface, "give velocities in m/s").copy())
        if self._frame_t is not None and not float(t) > self._frame_t:
            raise ContactInputError(f"tissue frame time must increase (got {t} after {self._frame_t})")
        # boxes cover the motion the local model may extrapolate to before the next frame
        extrapolate = self.params.local_model == "extrapolate"
        end = pos + vel * self.params.frame_period if extrapolate else pos
        kernels.triangle_boxes(pos, end, extrapolate, self.triangles, self._box_lo, self._box_hi)
        if self.tree is None:
            self.tree = self.aabb.AABBTree.build(self._box_lo, self._box_hi)
            logger.debug("AABB tree built over %d surface triangles", self.triangles.shape[0])
        else:
            self.tree.refit(self._box_lo, self._box_hi)
        previous = (self._frame_t, self._frame_pos, self._frame_vel)
        self._frame_t, self._frame_pos, self._frame_vel = float(t), pos, vel
        if self._tool_prev is not None:
            # the query covers the tool's sweep since the last frame (for the frame-level CCD)
            self._refresh_local(self._tool_at_frame, self._tool_prev)
            if self.params.detection == "continuous" and previous[0] is not None:
                self._frame_ccd(previous, self._tool_at_frame, self._tool_prev)
            self._tool_at_frame = self._tool_prev.copy()

    def _refresh_local(self, tool0, tool1) -> None:
        """Query the tree with boxes around the tool's sweep from tool0 to tool1 (plus margin).

        A node inside the tissue also reaches back along its entry normal by its last depth, so
        the faces it entered through stay in the local model however deep it has gone."""
        reach = self.params.margin + self.radius
        lo, hi = self.aabb.point_boxes(tool0, positions_end=tool1, radius=reach)
        inside = np.flatnonzero(self._inside)
        if inside.size:
            back = tool1[inside] + self._entry_normal[inside] * self._contact_depth[inside, None]
            lo[inside] = np.minimum(lo[inside], back - reach)
            hi[inside] = np.maximum(hi[inside], back + reach)
        node_pairs = self.tree.query_boxes(lo, hi)[:, ::-1]
        seg_pairs = None
        if self.n_segments:
            lo, hi = self.aabb.segment_boxes(tool1, radius=reach)
            seg_pairs = self.tree.query_boxes(lo, hi)[:, ::-1]
        self.local.capture(self._frame_t, self._frame_pos, self._frame_vel, self.triangles,
                           node_pairs, self.n_tool, seg_pairs, self.n_segments)
        self._built_at = tool1.copy()
        self._pos0 = np.zeros_like(self.local.positions)
        cap = self.local.node_faces.size
        self._ccd_buffers = (np.zeros((cap, 8, 3)), np.zeros(cap, np.int64), np.zeros(cap, np.int64))
        self.local_refreshes += 1

    def _mark_entries(self, hit, toi, q_node, q_face, normals) -> None:
        """Nodes whose CCD found a crossing become inside, with the crossed face's normal."""
        best = {}
        for j in np.flatnonzero(hit):
            node = int(q_node[j])
            if node not in best or toi[j] < toi[best[node]]:
                best[node] = j
        for node, j in best.items():
            self._inside[node] = 1
            self._entry_normal[node] = normals[q_face[j]]
            self.ccd_hits += 1
            logger.debug("CCD: tool node %d entered face %d at toi %.3g", node,
                         int(self.local.faces[q_face[j]]), float(toi[j]))

    def _local_normals(self, pos) -> np.ndarray:
        tri = self.local.triangles
        n = np.cross(pos[tri[:, 1]] - pos[tri[:, 0]], pos[tri[:, 2]] - pos[tri[:, 0]])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)

    def _frame_ccd(self, previous, tool0, tool1) -> None:
        """CCD of the tool's motion against the tissue's motion between the last two frames."""
        t0, p_prev, v_prev = previous
        verts = self.local.vertices
        pos0 = np.ascontiguousarray(p_prev[verts])
        pos1 = np.ascontiguousarray(self._frame_pos[verts])
        queries, q_node, q_face = self._ccd_buffers
        count = kernels.ccd_candidates(pos0, pos1, self.local.triangles, self.local.node_ptr,
                                       self.local.node_faces, tool0, tool1, self.radius, self._inside,
                                       queries, q_node, q_face)
        if count == 0:
            return
        q, q_node, q_face = queries[:count], q_node[:count], q_face[:count]
        if self.params.interpolation == "cubic":
            period = self._frame_t - t0
            tri = self.local.triangles[q_face]
            tool_vel = (tool1[q_node] - tool0[q_node]) / period
            v0 = np.concatenate([tool_vel[:, None], v_prev[verts][tri]], axis=1)
            v1 = np.concatenate([tool_vel[:, None], self._frame_vel[verts][tri]], axis=1)
            hit, toi = self.ccd.vertex_face_spline(q[:, :4], q[:, 4:], v0, v1, period)
        else:
            hit, toi = self.ccd.vertex_face(q)
        self._mark_entries(hit, toi, q_node, q_face, self._local_normals(pos1))

    # ------------------------------------------------------------------ haptic step
    def step(self, t, dt, tool_positions, tool_velocities=None) -> ContactOutputs:
        """One haptic step over [t, t+dt]; the contact is evaluated at t + dt."""
        if self._frame_t is None:
            raise ContactInputError("no tissue frame yet: call set_tissue_frame(t, positions, velocities) "
                                    "before step()")
        if not (_is_real(dt) and math.isfinite(dt) and dt > 0):
            raise ContactInputError(f"dt must be a finite number > 0 (got {dt!r}): e.g. 0.001 s")
        if not (_is_real(t) and math.isfinite(t)):
            raise ContactInputError(f"t must be a finite time in s (got {t!r})")
        tool1 = _float_array("tool_positions", tool_positions, self.n_tool,
                             "give the tool point positions in m")
        tool0 = tool1 if self._tool_prev is None else self._tool_prev
        if tool_velocities is None:
            tool_vel = (tool1 - tool0) / dt
        else:
            tool_vel = _float_array("tool_velocities", tool_velocities, self.n_tool,
                                    "give the tool point velocities in m/s, or None to difference positions")
        if self.params.detection == "discrete" and not self._tunnel_warned:
            # Discrete detection sees only where the tool is at each sample: a tool that moves
            # farther than the margin in one step can pass through a thin wall unseen (measured by
            # the extremes study: a probe at 10 m/s crossed the 1.5 mm AAA wall without a contact).
            jump = kernels.max_displacement(tool1, tool0)
            if jump > self.params.margin:
                self._tunnel_warned = True
                logger.warning(
                    "the tool moved %.3g mm in one %.3g ms step (t = %.6g s), more than the margin %.3g mm: with "
                    "detection = 'discrete' a contact can be missed (tunnelling); use detection = 'continuous'",
                    1e3 * jump, 1e3 * dt, t, 1e3 * self.params.margin)
        if self._built_at is None or kernels.max_displacement(tool1, self._built_at) > 0.5 * self.params.margin:
            self._refresh_local(tool0, tool1)
        if self._tool_at_frame is None:
            self._tool_at_frame = tool1.copy()
        t_eval = float(t) + float(dt)
        local = self.local
        pos1 = local.positions_at(t_eval)
        if self.params.detection == "continuous" and local.node_faces.size:
            pos0 = pos1
            if local.extrapolate:
                pos0 = self._pos0
                kernels.local_positions(local.frame_positions, local.frame_velocities,
                                        t_eval - dt - local.t_frame, True, pos0)
            queries, q_node, q_face = self._ccd_buffers
            count = kernels.ccd_candidates(pos0, pos1, local.triangles, local.node_ptr, local.node_faces,
                                           tool0, tool1, self.radius, self._inside, queries, q_node, q_face)
            if count:
                hit, toi = self.ccd.vertex_face(queries[:count])
                self._mark_entries(hit, toi, q_node[:count], q_face[:count], self._local_normals(pos1))
        p = self.params
        max_depth, count, energy = kernels.contact_step(
            pos1, local.velocities, local.triangles, local.vertices,
            local.node_ptr, local.node_faces, local.seg_ptr, local.seg_faces,
            tool1, tool_vel, self.radius, p.stiffness, p.damping, self._law, p.penalty_length,
            self._inside, self._entry_normal,
            self._node_force, self._tissue_force, self._contact_face, self._contact_depth)
        if self._renderer is None:
            self._renderer = PassiveRenderer(dt, p.passivity_controller, p.passivity_max_damping)
        self._renderer.period = float(dt)
        node_force = self._renderer.render(tool1, tool_vel, self._node_force)
        self._node_force[:] = node_force
        self._warn_if_active(float(energy), t)
        self._tool_prev = tool1.copy()
        return ContactOutputs(
            tool_force=node_force.sum(axis=0), tip_force=node_force[-1].copy(),
            tissue_contact_force=self._tissue_force, node_forces=self._node_force,
            penetration_depth=float(max_depth), contact_count=int(count), contact_energy=float(energy),
            passivity_energy=self._renderer.energy)

    def _warn_if_active(self, potential: float, t: float) -> None:
        """Warn once when the contact has given back more energy than it ever stored.

        The observer's energy alone is no verdict: a sampled penalty wall always creates some
        energy (about K T / 2 v^2 per unit time) that the device's own damping is meant to take
        out, which the contact model does not know. A wall that has returned more than the largest
        penalty energy it ever held is active whatever the device (measured by the extremes study:
        0.375 J created against 0.09 J stored at 20 kN/m; 0.03 J against 0.06 J at a passive
        800 N/m with b_dev = 1 N s/m).
        """
        self._peak_potential = max(self._peak_potential, potential)
        created = -self._renderer.energy
        if created > max(self._peak_potential, ACTIVE_ENERGY_FLOOR) and not self._active_warned:
            self._active_warned = True
            logger.warning(
                "passivity observer: the contact has created %.3g J by t = %.6g s, more than the %.3g J it ever "
                "stored: the rendered contact is active (a sampled-data instability); lower stiffness or damping, "
                "raise the device damping (passive while b_dev > K T / 2 + |B|)%s",
                created, t, self._peak_potential,
                "" if self.params.passivity_controller else ", or set passivity_controller = true")

    # ------------------------------------------------------------------ state (FMU rollback)
    _STATELESS = ("aabb", "ccd", "tree", "triangles", "params", "n_surface", "n_tool", "radius",
                  "n_segments", "_law")

    def get_state(self) -> dict:
        """A deep copy of everything that changes at run time (frames, local model, contact side
        memory, passivity energy, previous tool positions), for set_state (rollback)."""
        return copy.deepcopy({k: v for k, v in self.__dict__.items() if k not in self._STATELESS})

    def set_state(self, state: dict) -> None:
        """Restore a get_state() snapshot; the AABB tree is refitted to the restored frame."""
        self.__dict__.update(copy.deepcopy(state))
        if self._frame_pos is not None:
            extrapolate = self.params.local_model == "extrapolate"
            end = self._frame_pos + self._frame_vel * self.params.frame_period if extrapolate else self._frame_pos
            kernels.triangle_boxes(self._frame_pos, end, extrapolate, self.triangles, self._box_lo, self._box_hi)
            self.tree.refit(self._box_lo, self._box_hi)

    # ------------------------------------------------------------------ diagnostics
    @property
    def inside(self) -> np.ndarray:
        """(n_tool,) bool: tool nodes currently remembered inside the tissue."""
        return self._inside.astype(bool)

    @property
    def contact_faces(self) -> np.ndarray:
        """Global face id per primitive (nodes then segments) of the last step, -1 when none."""
        out = np.full(self._contact_face.shape, -1, np.int64)
        ok = self._contact_face >= 0
        out[ok] = self.local.faces[self._contact_face[ok]]
        return out


def parameters_from_dict(values: dict) -> ContactParameters:
    """ContactParameters from a dict (e.g. a scene file), rejecting unknown names."""
    known = {f.name for f in fields(ContactParameters)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ContactParameterError(f"unknown contact parameters {unknown}: known are {sorted(known)}")
    return ContactParameters(**values).validate()

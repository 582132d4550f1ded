"""Contact model of the Contact FMU: tissue frames at ~30 Hz, haptic steps at ~1 kHz (no FMI).

Organised by role, as SOFA's collision and haptics pipeline:

| stage | module | what |
|---|---|---|
| broad phase | `aabb` (+ `aabb_kernels`) | AABB tree of the surface triangles (built on the first frame, refitted at every frame), queried with boxes around the tool's sweep: the local model's candidate pairs |
| narrow phase | `narrow_phase`, `ccd` (+ `ccd_kernels`) | CCD of the tool nodes crossing a face plane (frame-level against the tissue's motion, step-level against the local model's), then the depth of every tool primitive as a signed distance to the wall (continuous in the tool's configuration) and the depth change its motion predicts for the hold |
| response | `penalty` (+ `penalty_kernels`) | penalty laws held energy-consistently over the step, forces on the tool nodes and the tissue nodes |
| rendering | `rendering` (+ `rendering_kernels`) | local models between frames: `compliance` (the wall yields through W from Tissue; the contact is solved against it), `hold`, `extrapolate` |
| haptic port | `passivity`, `device` | passivity observer (per contact cycle too) and controller, and the device's force and rate limits |

Data flow
- `set_tissue_frame(t, positions, velocities, compliance=None, compliance_nodes=None,
  applied_force=None)`: refits the AABB tree, runs the frame-level CCD of the tool against the
  tissue's motion since the previous frame, refreshes the local model, and (local_model =
  "compliance") takes the compliance W of the patch nodes the tissue used (see `rendering`).
- `step(t, dt, tool_positions, tool_velocities=None)`: one haptic step evaluated at t + dt with the
  tool at `tool_positions` (the previous call's positions start the swept interval):
  tool inputs -> broad phase (re-query only when the tool moved more than margin/2) -> rendered
  geometry (free motion + the wall's yielding) -> narrow phase -> response (rigid penalty, or the
  penalty solved against the yielding wall) -> patch naming -> passivity.

Tool
- "centerline": n_tool points of the catheter centerline; nodes are spheres and segments capsules
  of `tool_radius`.
- "probe": one point (radius 0) driven by a haptic device.

Contact side memory: a tool node that enters the tissue remembers the outward normal of the face
it entered through and, while inside, measures its penetration only against faces facing the
same way. This keeps the force on the side it came from when a thin wall is crossed (both the
discrete and the continuous detection use it). Continuous detection adds the CCD of every node
that crosses a face plane during the step (linear motion; the local model's free motion over a
step is linear for every policy; the compliance model's yielding within a step is not swept) and,
at each new tissue frame, of the tool against the tissue's motion between frames (linear, or
cubic Hermite trajectories from the frame velocities when interpolation="cubic"), so a fast tool
or wall cannot tunnel. Segment interiors are checked discretely only (the catheter's nodes carry
the CCD). The interpolation parameter only affects that frame-level detection.

Real time: every kernel (and the CCD) is loaded or compiled at construction (and after
unpickling), not in the first steps; the kernels of the hot path write into buffers allocated at
construction, at frames or at local-model refreshes; the broad phase runs against the local
model's candidate pairs, re-queried from the tree only at frames and when the tool has moved
more than margin/2 since the last query.

State: a ContactModel holds only numpy arrays, numbers and plain objects, so `copy.deepcopy` and
pickle give a model that continues bit-identically (frames, W, AABB tree, local model, contact
side memory, passivity energy, previous tool positions); `get_state`/`set_state` snapshot the
run-time part for rollback.
"""
import copy
import logging
from dataclasses import dataclass, fields

import numpy as np

from . import aabb, aabb_kernels, ccd, narrow_phase, penalty_kernels
from . import rendering_kernels
from ._checks import is_finite_real, is_integer
from ._coupling import PATCH_NODES
from .geometry import all_finite, difference_velocity, max_displacement, max_displacement_rows
from .device import DEFAULT_MAX_FORCE_RATE, PHANTOM_DESKTOP_MAX_FORCE, DeviceSpec, ForceLimiter
from .passivity import DEFAULT_CYCLE_TOLERANCE, PassiveRenderer
from .penalty import PENALTY_LAWS, law_code
from .rendering import (FREE_MOTIONS, LOCAL_POLICIES, ComplianceError, LocalModel, WallCompliance,
                        check_compliance)

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


@dataclass
class ContactParameters:
    """Parameters of the Contact FMU (SI units)."""

    stiffness: float = 500.0           # k, N/m
    damping: float = 0.1               # b, N s/m
    penalty_law: str = "linear"        # "linear" | "quadratic" | "hunt_crossley" (see penalty.py)
    penalty_length: float = 1e-3       # d0, m (non-linear laws)
    energy_consistent: bool = True     # hold the law's mean over the step's predicted depth change (penalty.py)
    detection: str = "continuous"      # "continuous" | "discrete"
    interpolation: str = "linear"      # tissue trajectories between frames for CCD: "linear" | "cubic"
    local_model: str = "compliance"    # "compliance" | "hold" | "extrapolate" (see rendering.py)
    tool: str = "centerline"           # "centerline" | "probe"
    tool_radius: float = 0.001         # m (centerline capsules; a probe is a point)
    passivity_controller: bool = False
    passivity_max_damping: float = 20.0  # N s/m, cap of the controller's damping (keep < 2 m_device / dt)
    margin: float = 0.003              # m, broad-phase margin of the local model
    frame_period: float = 1.0 / 30.0   # s, expected tissue frame period (extent of extrapolated boxes)
    max_patch_nodes: int = PATCH_NODES          # N, most surface nodes the contact names for the compliance (structural)
    compliance_free_motion: str = "hold"  # the wall's free motion between frames: "hold" | "extrapolate"
    compliance_force_lag: int = 2      # frames between the haptic interval whose mean force the tissue applied
    #                                    and the frame showing it, when the tissue does not report the force
    #                                    (2: jacobi + average, the shipped scenes; 1: gauss-seidel + average)
    max_force: float = PHANTOM_DESKTOP_MAX_FORCE       # N, the haptic device's maximum force (device.py)
    max_force_rate: float = DEFAULT_MAX_FORCE_RATE     # N/s, the fastest change of the rendered force (device.py)
    passivity_cycle_tolerance: float = DEFAULT_CYCLE_TOLERANCE  # share of a contact cycle's exchanged energy it
    #                                    may create before the observer calls it active (passivity.py)

    def validate(self) -> "ContactParameters":
        def positive(name, example):
            value = getattr(self, name)
            if not (is_finite_real(value) and value > 0):
                raise ContactParameterError(f"{name} must be a finite number > 0 (got {value!r}): {example}")

        def choice(name, options):
            value = getattr(self, name)
            if value not in options:
                raise ContactParameterError(f"{name} must be one of {list(options)} (got {value!r})")

        positive("stiffness", "give the penalty stiffness k in N/m, e.g. 500")
        if not (is_finite_real(self.damping) and self.damping >= 0):
            raise ContactParameterError(
                f"damping must be a finite number >= 0 (got {self.damping!r}): give b in N s/m, e.g. 0.1")
        positive("penalty_length", "give the non-linear penalty length d0 in m, e.g. 1e-3")
        positive("margin", "give the broad-phase margin in m, e.g. 0.003 (more than the deepest expected penetration)")
        positive("frame_period", "give the tissue frame period in s, e.g. 1/30")
        positive("passivity_max_damping", "give the cap of the passivity controller's damping in N s/m, "
                                          "below 2 m/T for the device mass m and step T, e.g. 20")
        positive("max_force", "give the haptic device's maximum force in N, e.g. 7.9 for a PHANTOM Desktop / "
                              "Touch X (a larger value for a stronger device)")
        positive("max_force_rate", "give the fastest change of the rendered force in N/s, e.g. 10000 (10 N per "
                                   "1 ms step, twice a 10 kN/m wall under a hand at 0.5 m/s)")
        tolerance = self.passivity_cycle_tolerance
        if not (is_finite_real(tolerance) and tolerance >= 0):
            raise ContactParameterError(
                f"passivity_cycle_tolerance must be a finite number >= 0 (got {tolerance!r}): the share of a contact "
                "cycle's exchanged energy it may create before it is reported active, e.g. 1e-3")
        if not (is_finite_real(self.tool_radius) and self.tool_radius >= 0):
            raise ContactParameterError(
                f"tool_radius must be a finite number >= 0 (got {self.tool_radius!r}): e.g. 0.001 m for 6 Fr")
        choice("penalty_law", tuple(PENALTY_LAWS))
        choice("detection", DETECTIONS)
        choice("interpolation", INTERPOLATIONS)
        choice("local_model", LOCAL_POLICIES)
        choice("tool", TOOLS)
        choice("compliance_free_motion", FREE_MOTIONS)
        for name, low, example in (("max_patch_nodes", 1, "16 surface nodes"),
                                   ("compliance_force_lag", 1, "2 frames (jacobi + average)")):
            value = getattr(self, name)
            if not is_integer(value) or value < low:
                raise ContactParameterError(f"{name} must be an integer >= {low} (got {value!r}): e.g. {example}")
        if not isinstance(self.energy_consistent, (bool, np.bool_)):
            raise ContactParameterError(
                f"energy_consistent must be True or False (got {self.energy_consistent!r})")
        if not isinstance(self.passivity_controller, (bool, np.bool_)):
            raise ContactParameterError(
                f"passivity_controller must be True or False (got {self.passivity_controller!r})")
        if self.passivity_controller and self.tool != "probe":
            # Its damping -alpha v acts on a haptic device's probe (a mass the operator holds). On a
            # catheter centerline it brakes every point of a kinematic chain that does not respond to
            # it: on aaa_endovascular the rendered force runs away to 1.3 kN.
            raise ContactParameterError(
                "passivity_controller = true needs tool = 'probe' (the haptic device's point): with tool = "
                f"{self.tool!r} there is no device to damp; set passivity_controller = false")
        return self


@dataclass
class ContactOutputs:
    """Outputs of one haptic step. Arrays are the model's buffers: copy them to keep them.

    The haptic port (tool_force, node_forces) renders the held force: the law's mean over the
    depths the tool's motion predicts for the next millisecond (energy_consistent), limited to the
    device (`force_limited`, device.py), with the passivity controller's damping when it is on. The
    wall (tissue_contact_force) and the catheter's tip (tip_force, tip_stiffness, tip_gap) get the
    law's force at the sampled depths (penalty_kernels.distribute, tip_response): the prediction,
    the device limit and the controller belong to the port, as CHAI3D limits only what it sends to
    the device. So tissue_contact_force sums to -tool_force where the tool rests and nothing is
    limited, and differs from it by the prediction's share, k v dt / 2 per contact, while it moves.
    """

    tool_force: np.ndarray             # (3,) total force on the tool as the device renders it, N
    tip_force: np.ndarray              # (3,) the wall's law on the last tool point, N (penalty_kernels.tip_response)
    tip_stiffness: np.ndarray          # (3,3) -d tip_force / d (last tool point), N/m (penalty_kernels.tip_stiffness)
    tip_gap: np.ndarray                # (3,) clearance g n of a tip near the wall carrying no force, m (penalty_kernels.tip_gap)
    tissue_contact_force: np.ndarray   # (n_surface,3) nodal forces on the surface, N
    node_forces: np.ndarray            # (n_tool,3) force on each tool point as rendered (sums to tool_force), N
    penetration_depth: float           # max over contacts, m
    contact_count: int                 # tool primitives (nodes, segments) in contact
    contact_energy: float              # penalty potential energy, J
    passivity_energy: float            # energy into the environment through the port, J (>= 0 passive)
    force_limited: bool = False        # the device limit (max_force, max_force_rate) engaged at this step
    force_limited_steps: int = 0       # steps whose rendered force was limited, since the start
    contact_cycles: int = 0            # closed contact cycles (passivity.py)
    active_cycles: int = 0             # closed contact cycles that created energy (passivity.py)
    last_cycle_energy: float = 0.0     # energy into the environment over the last closed contact cycle, J (>= 0 passive)


def _float_array(name, value, n, fix):
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape == (n, 3) and arr.flags.c_contiguous and all_finite(arr):   # the common case
        return arr
    if arr.size != n * 3:
        raise ContactInputError(
            f"{name} must hold {n} points ({n}x3 = {n * 3} values, flat or (n,3)) (got shape {arr.shape}): {fix}")
    arr = arr.reshape(n, 3)
    if not np.isfinite(arr).all():
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        raise ContactInputError(f"{name} contains NaN or inf at points {bad[:10].tolist()}: {fix}")
    return arr


#: Newton iterations (then the Gauss-Seidel fallback) and relative tolerance of the compliance solve
#: (the linear law needs 1-2 on a fixed contact set).
COMPLIANCE_MAX_ITERATIONS = 8
COMPLIANCE_TOLERANCE = 1e-13

#: m: the step of the central differences of the tip's contact normal (narrow_phase.normal_jacobian):
#: far below the 0.1 mm over which the blended normal turns, far above round-off of the positions.
NORMAL_JACOBIAN_STEP = 1e-6

_WARMED = set()


def _warm_up(interpolation) -> None:
    """Load (or compile) every kernel of the hot path once per process, at construction, so the
    first haptic steps do not pay it (it takes up to seconds: a haptic loop cannot absorb that).
    Runs a tiny scene through every stage: each policy, both detections, the frame-level CCD."""
    key = ("contact", interpolation)
    if key in _WARMED:
        return
    _WARMED.add(key)
    pos = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [0.01, 0.01, 0.0]])
    tri = np.array([[0, 1, 2], [1, 3, 2]])
    W = np.eye(12) * 1e-4
    centerline = [np.array([[0.003, 0.003, 0.004], [0.003, 0.003, 0.002], [0.003, 0.003, -0.0005 * k]])
                  for k in range(3)]
    centerline += [np.array([[0.003, 0.003, 0.004], [0.003, 0.004, 0.001], [0.003, 0.003, -0.001]])] * 3
    for policy in LOCAL_POLICIES:
        for detection in DETECTIONS:
            # a catheter centerline, and a device probe with the passivity controller on
            for tool, passivity, path in (("centerline", False, centerline),
                                          ("probe", True, [points[-1:] for points in centerline])):
                params = ContactParameters(local_model=policy, detection=detection, interpolation=interpolation,
                                           passivity_controller=passivity, tool=tool, margin=0.003)
                model = ContactModel(tri, 4, len(path[0]), params)
                if policy == "compliance" and detection == "continuous":  # outputs into an FMU's buffers
                    model.write_outputs_into(np.zeros(3), np.zeros(3), np.zeros((4, 3)),
                                             np.zeros(params.max_patch_nodes, np.int32))
                model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
                for k in range(3):
                    model.step(k * 1e-3, 1e-3, path[k])
                model.set_tissue_frame(0.01, pos + [0.0, 0.0, 0.001], np.full_like(pos, 0.1),
                                       compliance=W, compliance_nodes=np.arange(4))
                for k in range(3, 6):
                    model.step(k * 1e-3, 1e-3, path[k])


def _checked_surface(surface_triangles, n_surface, n_tool, tool: str) -> np.ndarray:
    """The surface's triangles as a C-contiguous int64 (t, 3) array, after the sizes' checks;
    ContactParameterError naming the problem otherwise."""
    if not (isinstance(n_surface, (int, np.integer)) and n_surface >= 3):
        raise ContactParameterError(f"n_surface must be an integer >= 3 (got {n_surface!r})")
    if not (isinstance(n_tool, (int, np.integer)) and n_tool >= 1):
        raise ContactParameterError(f"n_tool must be an integer >= 1 (got {n_tool!r})")
    if tool == "probe" and n_tool != 1:
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
    return tri


class ContactModel:
    """Penalty contact and haptic rendering of a tool against the tissue surface."""

    def __init__(self, surface_triangles, n_surface: int, n_tool: int, params: ContactParameters | None = None):
        self.params = (params or ContactParameters()).validate()
        tri = _checked_surface(surface_triangles, n_surface, n_tool, self.params.tool)
        _warm_up(self.params.interpolation)
        self.triangles = tri
        self.n_surface = int(n_surface)
        self.n_tool = int(n_tool)
        p = self.params
        self.radius = float(p.tool_radius) if p.tool == "centerline" else 0.0
        self.n_segments = self.n_tool - 1 if p.tool == "centerline" else 0
        n_prim = self.n_tool + self.n_segments
        self._law = law_code(p.penalty_law)
        self.local = LocalModel(p.local_model, p.compliance_free_motion)
        self.compliance = (WallCompliance(self.n_surface, n_prim, p.max_patch_nodes, p.compliance_force_lag)
                           if p.local_model == "compliance" else None)
        self.tree = None
        self._init_run_state()
        self._init_contact_buffers(n_prim)
        self._init_output_buffers()

    def _init_run_state(self) -> None:
        """No tissue frame and no tool position yet."""
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
        self._tool_vel = np.zeros((self.n_tool, 3))   # differenced tool velocities (buffer)
        self._inside = np.zeros(self.n_tool, np.int8)
        self._entry_normal = np.zeros((self.n_tool, 3))

    def _init_contact_buffers(self, n_prim: int) -> None:
        """The narrow phase's and the response's buffers: the contact data per primitive (nodes,
        then segments), the hold's prediction and the forces the response gives the contacts."""
        p = self.params
        self._contact_face = np.full(n_prim, -1, np.int64)     # local face, -1 when none
        self._contact_w = np.zeros((n_prim, 3))
        self._contact_n = np.zeros((n_prim, 3))
        self._contact_depth = np.zeros(n_prim)
        self._contact_rate = np.zeros(n_prim)
        self._contact_s = np.zeros(n_prim)
        self._contact_point = np.zeros((n_prim, 3))
        self._trust = np.zeros(self.n_tool)            # how deep behind the wall a node may be found (narrow phase)
        self._contact_ahead = np.zeros(n_prim)        # depth change predicted over the hold (energy_consistent)
        self._ahead_before = np.zeros(n_prim)         # last step's prediction (narrow_phase.approach)
        self._tool_older = None                       # tool positions two steps back (the hold's prediction)
        self._tool_vel_older = np.zeros((self.n_tool, 3))   # the tool's velocity over the step before
        self._older_dt = 0.0
        self._near_dist = np.zeros(self.n_tool)
        self._blend_work = np.zeros((1, narrow_phase.WORK_COLUMNS))
        self._fmag = np.zeros(n_prim)                 # the haptic port's held force per contact
        self._fmag_wall = np.zeros(n_prim)            # the law's force per contact (the wall, the tip)
        self._no_ahead = np.zeros(n_prim)
        self._bind_contacts()
        # the penalty law as the compliance kernels take it (rendering_kernels.penalty_law)
        self._penalty = rendering_kernels.penalty_law(self._law, p.stiffness, p.damping, p.penalty_length)

    def _init_output_buffers(self) -> None:
        """The step's outputs, the tip's and the passivity observer's, and the broad phase's boxes."""
        self._node_force = np.zeros((self.n_tool, 3))
        self._tip_stiffness = np.zeros((3, 3))
        self._tip_gap = np.zeros(3)
        self._tip_dn = np.zeros((3, 3))               # d (the tip's contact normal) / d (its position)
        self._band = 0.0                              # the narrow phase's band at the last step
        self._tip_force = np.zeros(3)                 # the law's force on the tip (penalty_kernels.tip_response)
        self._no_slot = np.zeros(0, np.int64)
        self._no_W = np.zeros((0, 0))
        self._tip_near = np.zeros(4)                 # the free tip's (clearance, normal) (narrow_phase.clearance)
        self._tissue_force = np.zeros((self.n_surface, 3))
        self._outputs = None            # (tool force, tip force, patch nodes) arrays of write_outputs_into
        self._no_patch = np.zeros(0, np.int64)
        self._no_record = np.zeros((0, 3))
        self._pos0 = np.zeros((0, 3))
        # the broad phase's query boxes: tool nodes, tool segments
        self._query_boxes = (np.zeros((self.n_tool, 3)), np.zeros((self.n_tool, 3)),
                             np.zeros((self.n_segments, 3)), np.zeros((self.n_segments, 3)))
        self._ccd_buffers = None
        self._renderer = None
        self.ccd_hits = 0               # diagnostics: contacts started by CCD
        self.local_refreshes = 0

    def _bind_contacts(self) -> None:
        """The contact state as the compliance kernels take it (rendering_kernels.contact_state): the
        per-primitive arrays above, made again whenever they are replaced (a restored state)."""
        self._contacts = rendering_kernels.contact_state(
            self._contact_face, self._contact_w, self._contact_n, self._contact_depth, self._contact_rate,
            self._contact_s, self._contact_ahead, self._fmag, self._fmag_wall)

    # ------------------------------------------------------------------ pickling
    def __getstate__(self) -> dict:
        """The attributes but the contact state tuple, made again from them when restored (a
        serialized state stores each reference to an array as an array of its own)."""
        state = self.__dict__.copy()
        del state["_contacts"]
        return state

    def __setstate__(self, state) -> None:
        """Unpickled (or deep-copied): the kernels are loaded in this process before any step."""
        self.__dict__.update(state)
        self._bind_contacts()
        _warm_up(self.params.interpolation)

    # ------------------------------------------------------------------ tissue frames
    def set_tissue_frame(self, t, positions, velocities=None, compliance=None, compliance_nodes=None,
                         applied_force=None) -> None:
        """New tissue frame at time t (s): positions/velocities (n_surface,3) or flat.

        compliance_nodes: the surface node ids the tissue computed the compliance for (the patch
        this model named, -1 padded, at most max_patch_nodes valid); compliance: their W (m/N),
        (3n x 3n) or flat, n = len(compliance_nodes) or the number of valid ids (see
        `rendering.check_compliance`). applied_force (optional, N, (n,3) or flat like the ids):
        the contact force the tissue applied on those nodes over the step that produced this
        frame; None: the model's own record (`compliance_force_lag`). Both None: no compliance
        for this frame (renders as hold). Ignored by the hold and extrapolate local models.
        """
        if not is_finite_real(t):
            raise ContactInputError(f"t must be a finite time in s (got {t!r})")
        fix = "give surface node positions in m for all surface nodes, in the order of surface_triangles"
        pos = _float_array("tissue_positions", positions, self.n_surface, fix).copy()
        vel = (np.zeros_like(pos) if velocities is None else
               _float_array("tissue_velocities", velocities, self.n_surface, "give velocities in m/s").copy())
        if self._frame_t is not None and not float(t) > self._frame_t:
            raise ContactInputError(f"tissue frame time must increase (got {t} after {self._frame_t})")
        patch = self._check_patch(compliance, compliance_nodes, applied_force)
        # broad phase: boxes cover the motion the local model may extrapolate to before the next frame
        extrapolate = self.local.extrapolate
        end = pos + vel * self.params.frame_period if extrapolate else pos
        self._fit_tree(pos, end, extrapolate)
        previous = (self._frame_t, self._frame_pos, self._frame_vel)
        self._frame_t, self._frame_pos, self._frame_vel = float(t), pos, vel
        if self.compliance is not None:
            self._take_compliance(*(patch or ()))
        if self._tool_prev is not None:
            # the query covers the tool's sweep since the last frame (for the frame-level CCD)
            self._refresh_local(self._tool_at_frame, self._tool_prev)
            if self.params.detection == "continuous" and previous[0] is not None:
                self._frame_ccd(previous, self._tool_at_frame, self._tool_prev)
            self._tool_at_frame = self._tool_prev.copy()
        elif self.compliance is not None:
            self.compliance.map_local(self.local.vertices)

    def _check_patch(self, compliance, compliance_nodes, applied_force):
        """Validated (ids, W, applied (p,3) or None), or None when the frame brings no compliance."""
        if compliance is None and compliance_nodes is None:
            if applied_force is not None:
                raise ContactInputError("applied_force was given without compliance and compliance_nodes: "
                                        "give the force together with the W and the node ids it belongs to")
            return None
        if compliance is None or compliance_nodes is None:
            missing = "compliance" if compliance is None else "compliance_nodes"
            raise ContactInputError(f"{missing} is missing: give the compliance W together with the node ids "
                                    "it was computed for (compliance_nodes), or neither")
        try:
            ids, W, where = check_compliance(compliance, compliance_nodes, self.n_surface,
                                             self.params.max_patch_nodes)
        except ComplianceError as exc:
            raise ContactInputError(str(exc)) from None
        applied = None
        if applied_force is not None:
            raw = np.asarray(applied_force, np.float64).reshape(-1)
            n_given = int(np.asarray(compliance_nodes).size)
            if raw.size == 3 * n_given:
                applied = raw.reshape(n_given, 3)[where]
            elif raw.size == 3 * ids.size:
                applied = raw.reshape(-1, 3)
            else:
                raise ContactInputError(f"applied_force must hold 3 values per compliance node ({3 * n_given} or "
                                        f"{3 * ids.size} values) (got {raw.size}): the force in N the tissue "
                                        "applied on those nodes over its step")
            if not np.isfinite(applied).all():
                raise ContactInputError("applied_force contains NaN or inf: give the force the tissue applied in N")
        return ids, W, applied

    def _take_compliance(self, ids=None, W=None, applied=None) -> None:
        c = self.compliance
        c.close_interval()
        if ids is None or ids.size == 0:
            c.clear()
        else:
            c.set_frame(ids, W, applied, self._tissue_force)
        logger.debug("frame t = %.6g s: compliance of %d patch nodes", self._frame_t, c.ids.size)

    def _refresh_local(self, tool0, tool1) -> None:
        """Broad phase: query the tree with boxes around the tool's sweep from tool0 to tool1 (plus
        margin) and capture the local model.

        A node inside the tissue also reaches back along its entry normal by its last depth, so
        the faces it entered through stay in the local model however deep it has gone."""
        # The tool positions were validated when they came in: no second check in the 1 kHz loop.
        reach = self.params.margin + self.radius
        lo, hi, seg_lo, seg_hi = self._query_boxes
        aabb_kernels.swept_point_boxes(tool0, tool1, reach, self._inside, self._entry_normal, self._contact_depth,
                                       lo, hi)
        # unsorted: capture groups the pairs by tool primitive itself
        node_pairs = self.tree.query_boxes(lo, hi, check=False, sort=False)[:, ::-1]
        seg_pairs = None
        if self.n_segments:
            aabb_kernels.polyline_segment_boxes(tool1, reach, seg_lo, seg_hi)
            seg_pairs = self.tree.query_boxes(seg_lo, seg_hi, check=False, sort=False)[:, ::-1]
        self.local.capture(self._frame_t, self._frame_pos, self._frame_vel, self.triangles,
                           node_pairs, self.n_tool, seg_pairs, self.n_segments)
        if self.compliance is not None:
            self.compliance.map_local(self.local.vertices)
        self._built_at = tool1.copy()
        self._pos0 = np.zeros_like(self.local.positions)
        cap = self.local.node_faces.size
        self._ccd_buffers = (np.zeros((cap, 8, 3)), np.zeros(cap, np.int64), np.zeros(cap, np.int64))
        most = max(rendering_kernels.longest_row(self.local.node_ptr), rendering_kernels.longest_row(self.local.seg_ptr))
        if most > self._blend_work.shape[0]:
            self._blend_work = np.zeros((most, narrow_phase.WORK_COLUMNS))   # the narrow phase's scratch
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
        count = narrow_phase.ccd_candidates(pos0, pos1, self.local.triangles, self.local.node_ptr,
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
            hit, toi = ccd.vertex_face_spline(q[:, :4], q[:, 4:], v0, v1, period)
        else:
            hit, toi = ccd.vertex_face(q)
        self._mark_entries(hit, toi, q_node, q_face, self._local_normals(pos1))

    # ------------------------------------------------------------------ haptic step
    def step(self, t, dt, tool_positions, tool_velocities=None) -> ContactOutputs:
        """One haptic step over [t, t+dt]; the contact is evaluated at t + dt."""
        tool0, tool1, tool_vel = self._tool_inputs(t, dt, tool_positions, tool_velocities)
        if self._built_at is None or max_displacement(tool1, self._built_at) > 0.5 * self.params.margin:
            self._refresh_local(tool0, tool1)                        # broad phase
        if self._tool_at_frame is None:
            self._tool_at_frame = tool1.copy()
        pos0, pos1 = self._render_geometry(float(t) + float(dt), float(dt))   # rendering: where the wall is
        self._narrow_phase(pos0, pos1, tool0, tool1, tool_vel)
        max_depth, count, energy = self._response(float(dt))
        self._tip_response(pos1, tool1, float(dt))
        if self.compliance is not None:
            self._name_patch(tool1)
        node_force = self._passivity(tool1, tool_vel, float(dt), float(t) + float(dt))
        self._warn_if_active(float(energy), t)
        self._tool_older, self._older_dt = self._tool_prev, float(dt)
        self._tool_prev = tool1.copy()
        renderer = self._renderer
        limited = renderer.force_limited
        if self._outputs is None:
            tool_force, tip_force = node_force.sum(axis=0), self._tip_force.copy()
        else:  # write_outputs_into
            self._publish(node_force)
            tool_force, tip_force = self._outputs[0], self._outputs[1]
        return ContactOutputs(
            tool_force=tool_force, tip_force=tip_force, tip_stiffness=self._tip_stiffness, tip_gap=self._tip_gap,
            tissue_contact_force=self._tissue_force, node_forces=self._node_force,
            penetration_depth=float(max_depth), contact_count=int(count), contact_energy=float(energy),
            passivity_energy=renderer.energy, force_limited=limited,
            force_limited_steps=renderer.limiter.limited_steps, contact_cycles=renderer.cycles,
            active_cycles=renderer.active_cycles, last_cycle_energy=renderer.last_cycle_energy)

    def _tool_inputs(self, t, dt, tool_positions, tool_velocities):
        """Validated (tool0, tool1, tool velocities); warns once about tunnelling (discrete)."""
        if self._frame_t is None:
            raise ContactInputError("no tissue frame yet: call set_tissue_frame(t, positions, velocities) "
                                    "before step()")
        if not (is_finite_real(dt) and dt > 0):
            raise ContactInputError(f"dt must be a finite number > 0 (got {dt!r}): e.g. 0.001 s")
        if not is_finite_real(t):
            raise ContactInputError(f"t must be a finite time in s (got {t!r})")
        tool1 = _float_array("tool_positions", tool_positions, self.n_tool,
                             "give the tool point positions in m")
        tool0 = tool1 if self._tool_prev is None else self._tool_prev
        if tool_velocities is None:
            tool_vel = self._tool_vel
            difference_velocity(tool1, tool0, float(dt), tool_vel)
            if self._tool_older is None:
                self._tool_vel_older[...] = tool_vel
            else:   # the step before's velocity: the prediction limits the two (narrow_phase.approach)
                difference_velocity(tool0, self._tool_older, self._older_dt, self._tool_vel_older)
        else:
            tool_vel = _float_array("tool_velocities", tool_velocities, self.n_tool,
                                    "give the tool point velocities in m/s, or None to difference positions")
            self._tool_vel[...] = tool_vel      # the velocity the prediction reads (narrow_phase.approach)
            self._tool_vel_older[...] = tool_vel
        if self.params.detection == "discrete" and not self._tunnel_warned:
            # Discrete detection sees only where the tool is at each sample: a tool that moves
            # farther than the margin in one step can pass through a thin wall unseen (in the
            # extremes study a probe at 10 m/s crosses the 1.5 mm AAA wall without a contact).
            jump = max_displacement(tool1, tool0)
            if jump > self.params.margin:
                self._tunnel_warned = True
                logger.warning(
                    "the tool moved %.3g mm in one %.3g ms step (t = %.6g s), more than the margin %.3g mm: with "
                    "detection = 'discrete' a contact can be missed (tunnelling); use detection = 'continuous'",
                    1e3 * jump, 1e3 * dt, t, 1e3 * self.params.margin)
        return tool0, tool1, tool_vel

    def _render_geometry(self, t_eval, dt):
        """Local model positions at the step start and end: free motion, plus the wall's yielding
        under the last step's patch force (compliance; the response corrects it for this step)."""
        local = self.local
        pos1 = local.positions_at(t_eval)
        c = self.compliance
        if c is not None and c.active:
            rendering_kernels.add_displacement(pos1, c.slot, c.u)
        pos0 = pos1
        if local.extrapolate and self.params.detection == "continuous":
            pos0 = self._pos0
            rendering_kernels.local_positions(local.frame_positions, local.frame_velocities,
                                              t_eval - dt - local.t_frame, True, pos0)
            if c is not None and c.active:
                rendering_kernels.add_displacement(pos0, c.slot, c.u)
        return pos0, pos1

    def _narrow_phase(self, pos0, pos1, tool0, tool1, tool_vel) -> None:
        """CCD of the nodes crossing a face plane during the step, then the closest facets."""
        local = self.local
        if self.params.detection == "continuous" and local.node_faces.size:
            queries, q_node, q_face = self._ccd_buffers
            count = narrow_phase.ccd_candidates(pos0, pos1, local.triangles, local.node_ptr, local.node_faces,
                                                tool0, tool1, self.radius, self._inside, queries, q_node, q_face)
            if count:
                hit, toi = ccd.vertex_face(queries[:count])
                self._mark_entries(hit, toi, q_node[:count], q_face[:count], self._local_normals(pos1))
        c = self.compliance
        band = c.band if c is not None and c.active else 0.0
        if self.params.energy_consistent:
            # a primitive that this step's motion, continued, brings into contact within the next
            # step gets its share of the held force already (penalty.py: the interval of first touch)
            band = max(band, max_displacement(tool1, tool0))
        # the candidates are complete within margin / 2 of the tool's sphere (the broad phase queries
        # boxes of margin + radius, and again whenever the tool has moved margin / 2); a node found
        # behind the wall may also have crossed it within this step's motion
        self._band = band
        trust = self._trust
        max_displacement_rows(tool1, tool0, trust)
        trust += self.radius + 0.5 * self.params.margin
        narrow_phase.proximity(pos1, local.velocities, local.triangles, local.node_ptr, local.node_faces,
                               local.seg_ptr, local.seg_faces, tool1, tool_vel, self.radius, band, trust,
                               self._inside, self._entry_normal, self._contact_face, self._contact_w,
                               self._contact_n, self._contact_depth, self._contact_rate, self._contact_s,
                               self._contact_point, self._near_dist, self._blend_work)

    def _response(self, dt):
        """Penalty forces: against the rigid local model, or solved against the yielding wall
        (one kernel: solve, distribution, the tip's stiffness, the patch's new load and
        displacement)."""
        p = self.params
        c = self.compliance
        ahead = self._contact_ahead
        if p.energy_consistent:
            # the depth change the tool's motion predicts over the step the force will be held
            # (penalty.py), from its last two steps' approach speeds, limited (narrow_phase.approach)
            narrow_phase.approach(self._contact_face, self._contact_w, self._contact_n, self._contact_s,
                                  self._contact_depth, self.local.triangles, self.local.velocities,
                                  self._tool_vel, self._tool_vel_older, self.n_tool, dt, ahead, self._ahead_before)
        else:
            ahead.fill(0.0)
        if c is not None and c.active:
            rendering_kernels.compliance_response(
                self._contacts, self._no_ahead, self.local.triangles, self.local.vertices, self.n_tool, c.wall,
                self._penalty, dt, COMPLIANCE_MAX_ITERATIONS, COMPLIANCE_TOLERANCE, c.work, self._node_force,
                self._tissue_force, c.out)
            c.record_steps[c.current] += 1
            max_depth, count, energy, iterations, c.band = c.out.tolist()
            c.iterations = int(iterations)
            if c.iterations < 0:
                c.unconverged += 1
                if c.unconverged == 1:
                    logger.warning("compliance solve did not converge (%d Newton iterations, then %d Gauss-Seidel "
                                   "sweeps; kept the last iterate); reported once", COMPLIANCE_MAX_ITERATIONS,
                                   rendering_kernels.GAUSS_SEIDEL_SWEEPS)
            return max_depth, count, energy
        record = self._no_record
        if c is not None:
            record = c.record[c.current]
            c.record_steps[c.current] += 1
        return penalty_kernels.rigid_response(
            self._contact_face, self._contact_w, self._contact_n, self._contact_s, self._contact_depth,
            self._contact_rate, self.local.triangles, self.local.vertices, self.n_tool, self._law, p.stiffness,
            p.damping, p.penalty_length, ahead, self._no_ahead, self._fmag, self._fmag_wall, self._node_force,
            self._tissue_force, record)

    def _tip_response(self, pos1, tool1, dt) -> None:
        """What the catheter's tip meets (penalty_kernels.tip_response): the law's force on it, its
        stiffness, and the wall where it does not press (its clearance, narrow_phase.clearance, when
        its node has no contact), so that its passive bend meets the wall in the step it reaches it."""
        p = self.params
        local = self.local
        tip = self.n_tool - 1
        self._tip_near[0] = np.inf
        if self.n_segments and self._contact_face[tip] < 0:
            narrow_phase.clearance(pos1, local.triangles, local.node_ptr, local.node_faces, tool1, tip, self.radius,
                                   self._inside, self._entry_normal, self._blend_work, self._tip_near)
        c = self.compliance
        slot, W = (c.slot, c.W) if c is not None and c.active else (self._no_slot, self._no_W)
        if self._contact_face[tip] >= 0 and self._fmag_wall[tip] > 0.0:
            narrow_phase.normal_jacobian(pos1, local.triangles, local.node_ptr, local.node_faces, tool1, tip,
                                         self.radius + self._band, self._inside, self._entry_normal,
                                         NORMAL_JACOBIAN_STEP, self._blend_work, self._tip_dn)
        else:
            self._tip_dn.fill(0.0)
        penalty_kernels.tip_response(
            self._fmag_wall, self._contact_face, self._contact_w, self._contact_n, self._contact_s,
            self._contact_depth, self._contact_rate, self._contact_point, tool1, local.triangles, slot, W, self.n_tool,
            self.n_segments, self._law, p.stiffness, p.damping, p.penalty_length, dt, self._tip_near, self._tip_dn,
            self._tip_force, self._tip_stiffness, self._tip_gap)

    def _name_patch(self, tool1) -> None:
        c = self.compliance
        local = self.local
        c.patch_count = rendering_kernels.name_patch(
            local.positions, local.vertices, local.triangles, self._contact_face, self._contact_point, tool1,
            self._near_dist, self.params.margin + self.radius, c.max_nodes, c._key_class, c._key_dist,
            c._key_id, c.patch)

    def _passivity(self, tool1, tool_vel, dt, t_sample) -> np.ndarray:
        """The haptic port (one kernel, passivity.port_step): observer, contact cycles, controller and
        the device limit; node forces become the rendered ones in place."""
        p = self.params
        if self._renderer is None:
            limiter = ForceLimiter(DeviceSpec(float(p.max_force), float(p.max_force_rate)))
            self._renderer = PassiveRenderer(dt, p.passivity_controller, p.passivity_max_damping, limiter,
                                             float(p.passivity_cycle_tolerance))
        self._renderer.period = dt
        self._renderer.render_in_place(tool1, tool_vel, self._node_force, t_sample)
        return self._node_force

    def _warn_if_active(self, potential: float, t: float) -> None:
        """Warn once when the contact has given back more energy than it ever stored.

        The observer's energy alone is no verdict: a sampled penalty wall always creates some
        energy (about K T / 2 v^2 per unit time) that the device's own damping is meant to take
        out, which the contact model does not know. A wall that has returned more than the largest
        penalty energy it ever held is active whatever the device (in the extremes study a 20 kN/m
        wall creates 0.375 J against 0.09 J stored; a passive 800 N/m wall with b_dev = 1 N s/m
        creates 0.03 J against 0.06 J stored).

        Each contact cycle is also judged on its own, relative to the energy it exchanged, in the
        passivity kernel (passivity.py: contact_cycles, active_cycles, last_cycle_energy, its own log
        line); this warning is for a run's balance, e.g. a contact that never ends.
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
                ", or set passivity_controller = true" if self.params.tool == "probe"
                and not self.params.passivity_controller else "")

    # ------------------------------------------------------------------ state (FMU rollback)
    _STATELESS = ("tree", "triangles", "params", "n_surface", "n_tool", "radius", "n_segments", "_law",
                  "_penalty", "_no_record", "_no_patch", "_contacts")

    def get_state(self) -> dict:
        """A deep copy of everything that changes at run time (frames, local model, compliance,
        contact side memory, passivity energy, previous tool positions), for set_state (rollback)."""
        return copy.deepcopy({k: v for k, v in self.__dict__.items() if k not in self._STATELESS})

    def set_state(self, state: dict) -> None:
        """Restore a get_state() snapshot; the AABB tree is refitted to the restored frame."""
        self.__dict__.update(copy.deepcopy(state))
        self._bind_contacts()
        if self._frame_pos is not None:
            extrapolate = self.local.extrapolate
            end = self._frame_pos + self._frame_vel * self.params.frame_period if extrapolate else self._frame_pos
            self._fit_tree(self._frame_pos, end, extrapolate)

    def _fit_tree(self, pos, end, extrapolate) -> None:
        """The AABB tree over the surface triangles at this frame (built at the first)."""
        if self.tree is None:
            lo, hi = np.empty((self.triangles.shape[0], 3)), np.empty((self.triangles.shape[0], 3))
            aabb_kernels.triangle_boxes(pos, end, extrapolate, self.triangles, lo, hi)
            self.tree = aabb.AABBTree.build(lo, hi)
            logger.debug("AABB tree built over %d surface triangles", self.triangles.shape[0])
        else:  # the boxes go straight into the tree's own: no copy of two (t, 3) arrays per frame
            aabb_kernels.triangle_boxes(pos, end, extrapolate, self.triangles, self.tree.lo, self.tree.hi)
            self.tree.refit_in_place()

    # ------------------------------------------------------------------ the patch (compliance)
    def patch_nodes(self) -> np.ndarray:
        """(max_patch_nodes,) int64: the surface nodes this model names for the compliance, in or
        near the contact, ascending ids, padded with -1 (all -1 with the hold and extrapolate
        local models, or when the tool is farther than margin + tool radius from the surface).
        Updated by every step: the tissue reads it and sends W back for these ids."""
        if self.compliance is None:
            return np.full(self.params.max_patch_nodes, -1, np.int64)
        return self.compliance.patch.copy()

    def write_outputs_into(self, tool_force: np.ndarray, tip_force: np.ndarray, tissue_contact_force: np.ndarray,
                           patch_nodes: np.ndarray) -> None:
        """Let every step write its outputs into these arrays (e.g. an FMU's output buffers, which
        then need no copy) instead of new ones: ``tool_force``, ``tip_force`` (3,) and
        ``tissue_contact_force`` (n_surface, 3) float64, ``patch_nodes`` (max_patch_nodes,) of an
        integer type; writable and C-contiguous. They take the current values now (the last
        step's outputs); ``step`` returns them, overwritten by the next step. The same numbers
        as without: the tool force is summed point after point, as ``node_forces.sum(axis=0)``
        does. A copy of the model (deepcopy, pickle, ``set_state``) writes into arrays of its own
        again."""
        arrays = dict(tool_force=(tool_force, (3,)), tip_force=(tip_force, (3,)),
                      tissue_contact_force=(tissue_contact_force, (self.n_surface, 3)),
                      patch_nodes=(patch_nodes, (self.params.max_patch_nodes,)))
        for name, (array, shape) in arrays.items():
            kind = "i" if name == "patch_nodes" else "f"
            if not (isinstance(array, np.ndarray) and array.shape == shape and array.dtype.kind == kind
                    and (kind == "i" or array.dtype == np.float64) and array.flags.c_contiguous
                    and array.flags.writeable):
                raise ValueError(f"{name} goes into a writable C-contiguous {shape} "
                                 f"{'integer' if kind == 'i' else 'float64'} array (got "
                                 f"{getattr(array, 'dtype', type(array).__name__)} {getattr(array, 'shape', '')})")
        if tissue_contact_force is not self._tissue_force:
            tissue_contact_force[...] = self._tissue_force
            self._tissue_force = tissue_contact_force
        if self.compliance is None:
            patch_nodes.fill(-1)
        self._outputs = (tool_force, tip_force, patch_nodes)
        self._publish(self._node_force)

    def _publish(self, node_force):
        """The bound outputs of this step: tool and tip force, and the patch."""
        tool_force, tip_force, patch_nodes = self._outputs
        patch = self.compliance.patch if self.compliance is not None else self._no_patch
        rendering_kernels.publish(node_force, self._tip_force, tool_force, tip_force, patch, patch_nodes)

    @property
    def patch_count(self) -> int:
        """Number of valid ids in patch_nodes()."""
        return 0 if self.compliance is None else int(self.compliance.patch_count)

    @property
    def compliance_nodes(self) -> np.ndarray:
        """The node ids of the compliance in use (those of the last frame's W), empty when none."""
        return np.zeros(0, np.int64) if self.compliance is None else self.compliance.ids.copy()

    @property
    def wall_displacement(self) -> np.ndarray:
        """(p,3) the yielding of the compliance nodes after the last step, W (g - g_applied), m."""
        if self.compliance is None:
            return np.zeros((0, 3))
        return self.compliance.u.reshape(-1, 3).copy()

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

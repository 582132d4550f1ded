"""Haptic rendering between tissue frames: the local models of the 1 kHz loop.

At each tissue frame (about 30 Hz) the facets near the tool (found by the AABB tree with a
margin) are copied with their vertex positions and velocities (`LocalModel`). Between frames the
1 kHz loop renders the contact against this copy only, moved by one of three local models:

- "compliance" (default): the wall yields at once under the contact force through the compliance
  of the patch from Tissue (`WallCompliance`, as SOFA's LCPForceFeedback hands its haptic thread
  the constraint compliance W of the last simulation step):
      x = x_free + W (g - g_applied)
  x_free the frame positions (held, or extrapolated with compliance_free_motion = "extrapolate"),
  g the force this haptic step puts on the patch nodes, g_applied the force the tissue applied
  over the step that produced the frame (already contained in the frame positions: the frame is
  x_free + W g_applied, so the yielding is counted once). The contact is solved with the penalty
  law against the yielding wall (`rendering_kernels.compliance_forces`). Until a frame brings a
  compliance it renders exactly as "hold".
- "hold":        p(t) = p_frame,                        surface velocity 0
- "extrapolate": p(t) = p_frame + v_frame (t - t_frame), surface velocity v_frame (first order)
  (frozen facets, kept for the stability studies)

The surface velocity is that of the geometry the force is computed against, so the damping term
of F = -k dist n - b (v . n) n always uses the tool velocity relative to the rendered surface (with
compliance, plus the wall's yielding velocity over the step).

Candidate pairs are stored per tool primitive (CSR: for node i, faces node_faces[node_ptr[i]:
node_ptr[i+1]], local face ids), so the narrow phase of a haptic step visits only the faces the
broad phase found near that primitive.

The patch (compliance only). The contact model names, at every haptic step, the surface nodes in
or near the contact: at most `max_patch_nodes` N, ascending ids padded with -1
(`ContactModel.patch_nodes()`; ranking in `rendering_kernels.name_patch`). The tissue computes
the compliance W of the nodes it last read and sends them back with W (compliance_nodes): W is
always used for the ids it was computed for, whatever the contact names now. So
- a node that dropped out of the contact's naming but is in W keeps its compliance for the frame;
- a contact-face vertex that came in after the tissue read the patch has no compliance until the
  next frame: it is rendered rigid (held at the frame position), and a contact none of whose
  vertices is in W renders exactly as "hold";
- a frame without compliance (None, or no valid id) renders as "hold" until the next frame.
"""
import logging

import numpy as np

from . import rendering_kernels as kernels

logger = logging.getLogger(__name__)

LOCAL_POLICIES = ("compliance", "hold", "extrapolate")
FREE_MOTIONS = ("hold", "extrapolate")

#: W may be asymmetric by this fraction of its largest entry (the tissue's triangular solves).
SYMMETRY_TOLERANCE = 1e-6
#: W's smallest eigenvalue may be negative by this fraction of its largest one (round-off).
PSD_TOLERANCE = 1e-9


class LocalModelError(ValueError):
    """Invalid input to the local model."""


class ComplianceError(ValueError):
    """An invalid compliance block W or patch node list from the tissue."""


class LocalModel:
    """Facets near the tool, captured at a tissue frame; their free motion between frames."""

    def __init__(self, policy: str = "compliance", free_motion: str = "hold"):
        if policy not in LOCAL_POLICIES:
            raise LocalModelError(f"local_model must be one of {LOCAL_POLICIES} (got {policy!r})")
        if free_motion not in FREE_MOTIONS:
            raise LocalModelError(f"compliance_free_motion must be one of {FREE_MOTIONS} (got {free_motion!r})")
        self.policy = policy
        self.extrapolate = policy == "extrapolate" or (policy == "compliance" and free_motion == "extrapolate")
        self.t_frame = 0.0
        self.faces = np.zeros(0, np.int64)            # global face ids
        self.vertices = np.zeros(0, np.int64)         # global (surface) vertex ids, ascending
        self.triangles = np.zeros((0, 3), np.int64)   # local vertex ids
        self.frame_positions = np.zeros((0, 3))
        self.frame_velocities = np.zeros((0, 3))
        self.positions = np.zeros((0, 3))             # rendered at the last positions_at(t) (+ yielding)
        self.velocities = np.zeros((0, 3))
        self.node_ptr = np.zeros(1, np.int64)
        self.node_faces = np.zeros(0, np.int64)
        self.seg_ptr = np.zeros(1, np.int64)
        self.seg_faces = np.zeros(0, np.int64)

    _scratch = None  # capture's work arrays, sized by the surface (not part of the state)

    def __getstate__(self):
        state = self.__dict__.copy()
        state.pop("_scratch", None)
        return state

    def capture(self, t_frame, positions, velocities, triangles, node_pairs, n_nodes,
                seg_pairs=None, n_segments=0) -> None:
        """Copy the facets named by the candidate pairs out of a tissue frame.

        positions, velocities (n_surface,3) at t_frame; triangles (t,3) surface triangles;
        node_pairs (k,2) (tool node, global face); seg_pairs (k2,2) (tool segment, global face).
        """
        node_pairs = np.ascontiguousarray(np.asarray(node_pairs, np.int64).reshape(-1, 2))
        seg_pairs = np.zeros((0, 2), np.int64) if seg_pairs is None else np.ascontiguousarray(
            np.asarray(seg_pairs, np.int64).reshape(-1, 2))
        scratch = self._scratch
        if scratch is None or scratch[0].size != triangles.shape[0] or scratch[1].size != positions.shape[0]:
            # face and vertex maps (-1 between captures) and room for every face and vertex
            scratch = self._scratch = (np.full(triangles.shape[0], -1, np.int64),
                                       np.full(positions.shape[0], -1, np.int64),
                                       np.empty(triangles.shape[0], np.int64), np.empty(positions.shape[0], np.int64),
                                       np.empty((triangles.shape[0], 3), np.int64))
        face_map, vertex_map, faces, vertices, local_tri = scratch
        node_ptr, seg_ptr = np.empty(n_nodes + 1, np.int64), np.empty(n_segments + 1, np.int64)
        node_faces, seg_faces = np.empty(node_pairs.shape[0], np.int64), np.empty(seg_pairs.shape[0], np.int64)
        n_faces, n_vertices = kernels.capture_topology(
            np.ascontiguousarray(triangles, dtype=np.int64), node_pairs, seg_pairs, face_map, vertex_map, faces,
            vertices, local_tri, node_ptr, node_faces, seg_ptr, seg_faces)
        self.t_frame = float(t_frame)
        self.faces = faces[:n_faces].copy()
        self.vertices = vertices[:n_vertices].copy()
        self.triangles = local_tri[:n_faces].copy()
        self.frame_positions = np.ascontiguousarray(positions[self.vertices], dtype=np.float64)
        self.frame_velocities = np.ascontiguousarray(velocities[self.vertices], dtype=np.float64)
        self.positions = self.frame_positions.copy()
        self.velocities = (self.frame_velocities.copy() if self.extrapolate
                           else np.zeros_like(self.frame_velocities))
        self.node_ptr, self.node_faces = node_ptr, node_faces
        self.seg_ptr, self.seg_faces = seg_ptr, seg_faces

    @property
    def n_faces(self) -> int:
        return int(self.faces.size)

    def positions_at(self, t, out=None) -> np.ndarray:
        """Free-motion vertex positions at time t (hold or first-order extrapolation)."""
        out = self.positions if out is None else out
        kernels.local_positions(self.frame_positions, self.frame_velocities, float(t) - self.t_frame,
                                self.extrapolate, out)
        return out


def _node_ids(nodes, n_surface, max_nodes):
    """(valid ids (p,), their positions in the given array) from a -1 padded id list."""
    raw = np.asarray(nodes)
    if raw.ndim != 1:
        raw = raw.reshape(-1)
    if raw.size and not np.issubdtype(raw.dtype, np.integer):
        as_float = np.asarray(raw, np.float64)
        if not (np.isfinite(as_float).all() and np.all(as_float == np.round(as_float))):
            raise ComplianceError(f"compliance_nodes must hold integer surface node ids (-1 for unused slots) "
                                  f"(got {raw[:8].tolist()}...)")
    ids = np.ascontiguousarray(raw, dtype=np.int64)
    status = kernels.patch_id_status(ids, n_surface, max_nodes, np.empty(ids.size, np.int64))
    where = np.flatnonzero(ids >= 0)
    valid = ids[where]
    if status == 1:
        bad = np.flatnonzero((ids < -1) | (ids >= n_surface))
        raise ComplianceError(f"compliance_nodes must be surface node ids 0..{n_surface - 1} or -1 (unused) "
                              f"(got {ids[bad[:5]].tolist()} at slots {bad[:5].tolist()})")
    if status == 2:
        raise ComplianceError(f"compliance_nodes names {valid.size} nodes, more than max_patch_nodes = {max_nodes}")
    if status == 3:
        raise ComplianceError(f"compliance_nodes repeats node ids ({np.sort(valid).tolist()}): each node once")
    return valid, where


def check_compliance(compliance, nodes, n_surface, max_nodes):
    """Validated (ids (p,) int64, W (3p,3p) symmetrised, slots used) from the tissue's outputs.

    nodes: the patch node ids W was computed for, -1 padded (any length >= p). compliance: W as
    (3n,3n) or flat (3n)^2 for n = len(nodes) (rows/columns of the -1 slots are ignored) or for
    n = p, the valid ids only. W must be finite, symmetric within SYMMETRY_TOLERANCE of its largest
    entry and positive semi-definite within PSD_TOLERANCE (ComplianceError otherwise).
    """
    ids, where = _node_ids(nodes, n_surface, max_nodes)
    p = ids.size
    n_given = int(np.asarray(nodes).size)
    w = np.asarray(compliance, dtype=np.float64)
    size = w.size
    if size == (3 * n_given) ** 2:
        w = w.reshape(3 * n_given, 3 * n_given)
        cols = (3 * where[:, None] + np.arange(3)).reshape(-1)
    elif size == (3 * p) ** 2:
        w = w.reshape(3 * p, 3 * p)
        cols = np.arange(3 * p)
    else:
        raise ComplianceError(
            f"compliance must be a (3n x 3n) matrix for the n = {n_given} compliance_nodes slots "
            f"({(3 * n_given) ** 2} values) or for the {p} valid ids ({(3 * p) ** 2} values) (got shape "
            f"{np.shape(compliance)}): give W in m/N, rows and columns (x, y, z) per node in the order of the ids")
    # One pass over the block in a kernel (extraction, finiteness, symmetry, symmetric part): this
    # runs at every tissue frame inside the 1 kHz loop, where a dozen numpy calls cost 100 us.
    block = np.empty((cols.size, cols.size))
    bad, scale, asym = kernels.compliance_block(w, cols, block)
    if bad >= 0:
        raise ComplianceError(f"compliance contains NaN or inf (first at row {bad // cols.size}, column "
                              f"{bad % cols.size}): the tissue's solve for W failed")
    if p == 0:
        return ids, np.zeros((0, 0)), where
    if asym > SYMMETRY_TOLERANCE * scale:
        raise ComplianceError(f"compliance is not symmetric: max |W - W^T| = {asym:.3g} m/N, more than "
                              f"{SYMMETRY_TOLERANCE:g} of its largest entry {scale:.3g} m/N (a compliance of a "
                              "conservative linear system is symmetric): check the node order of rows and columns")
    w = block
    if scale > 0.0:
        # Smallest eigenvalue >= -shift exactly when W + shift I has a Cholesky factor (up to its
        # round-off): a few us in a kernel, where eigvalsh would take about 100 us of each tissue
        # frame's intake in the 1 kHz loop. eigvalsh decides, and measures, only where the factor fails.
        shift = PSD_TOLERANCE * scale * w.shape[0]
        if not kernels.cholesky_succeeds(w, shift, np.empty_like(w)):
            lowest = float(np.linalg.eigvalsh(w)[0])
            if lowest < -shift:
                raise ComplianceError(f"compliance is not positive semi-definite: smallest eigenvalue {lowest:.3g} "
                                      f"m/N (largest entry {scale:.3g} m/N): a wall cannot move against the force "
                                      "on it")
    return ids, w, where


class WallCompliance:
    """State of the compliance local model: the patch's W, forces and the named patch.

    ids (p,) the nodes W belongs to; W (3p,3p); g_applied (3p) the force the tissue applied over
    the step that produced the frame; g (3p) the patch force of the last haptic step; u (3p) the
    wall's displacement W (g - g_applied); slot (local vertex -> index in ids or -1).
    The record: the mean tissue force per frame interval (the last `lag + 1` intervals), used as
    g_applied when the tissue does not report it.

    ``wall`` holds (slot, W, g, g_new, u, the current interval's record) as the response kernel takes
    them (`rendering_kernels.patch_state`): made again whenever one of them changes, and left out of
    the state (a serialized state stores each reference to an array as an array of its own), so
    that it always holds the arrays the attributes name. ``work`` holds the solve's work arrays
    (`rendering_kernels.solve_work`), made once.
    """

    def __init__(self, n_surface: int, n_primitives: int, max_nodes: int, lag: int):
        self.max_nodes = int(max_nodes)
        self.lag = int(lag)
        self.ids = np.zeros(0, np.int64)
        self.W = np.zeros((0, 0))
        self.g_applied = np.zeros(0)
        self.g = np.zeros(0)
        self.g_new = np.zeros(0)
        self.u = np.zeros(0)
        self.slot = np.zeros(0, np.int64)
        self.active = False
        self.band = 0.0                 # largest yielding |u| of a node: how far the wall may come back
        self.iterations = 0             # Newton iterations of the last solve (-1: not converged)
        self.unconverged = 0            # diagnostics: solves that hit the iteration cap
        # the named patch (output) and its work arrays
        self.patch = np.full(self.max_nodes, -1, np.int64)
        self.patch_count = 0
        self._key_class = np.zeros(self.max_nodes, np.int64)
        self._key_dist = np.zeros(self.max_nodes)
        self._key_id = np.zeros(self.max_nodes, np.int64)
        # Newton work arrays (sized for every primitive in contact at once)
        m = int(n_primitives)
        self.work = kernels.solve_work(np.zeros(m, np.int64), np.zeros((m, 3 * self.max_nodes)), np.zeros((m, m)),
                                       np.zeros((m, m)), np.zeros((3, m)))
        self.out = np.zeros(5)                   # max depth, contact count, energy, iterations, largest |u|
        # record of the force sent to the tissue, per frame interval
        self.record = np.zeros((self.lag + 1, n_surface, 3))
        self.record_steps = np.zeros(self.lag + 1, np.int64)
        self.current = 0
        self._bind_wall()

    def _bind_wall(self) -> None:
        self.wall = kernels.patch_state(self.slot, self.W, self.g, self.g_new, self.u, self.record[self.current])

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        del state["wall"]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._bind_wall()

    def close_interval(self) -> None:
        """A frame arrived: the current interval's record is complete; start the next one."""
        self.current = (self.current + 1) % (self.lag + 1)
        self.record[self.current] = 0.0
        self.record_steps[self.current] = 0
        self._bind_wall()

    def recorded_force(self, ids) -> np.ndarray:
        """Mean tissue force at `ids` over the interval `lag` frames back, (p,3)."""
        index = (self.current - self.lag) % (self.lag + 1)
        steps = self.record_steps[index]
        if steps == 0:
            return np.zeros((ids.size, 3))
        return self.record[index][ids] / steps

    def set_frame(self, ids, W, applied, last_tissue_force) -> None:
        """New W for nodes `ids`; g_applied from `applied` (p,3) or None (the record)."""
        self.ids = ids
        self.W = W
        p = ids.size
        self.active = p > 0
        g_applied = self.recorded_force(ids) if applied is None else applied
        self.g_applied = np.ascontiguousarray(g_applied, np.float64).reshape(-1)
        self.g = np.ascontiguousarray(last_tissue_force[ids], np.float64).reshape(-1)
        self.g_new = np.zeros(3 * p)
        self.u = np.zeros(3 * p)
        self.band = 0.0
        self._bind_wall()
        if self.active:
            self.band = kernels.patch_displacement(self.W, self.g, self.g_applied, self.u)

    def clear(self) -> None:
        """A frame without compliance: render as hold until the next one."""
        self.set_frame(np.zeros(0, np.int64), np.zeros((0, 0)), np.zeros((0, 3)), np.zeros((0, 3)))

    def map_local(self, local_vertices) -> None:
        """slot of every local model vertex (its index in ids, -1 when it has no compliance)."""
        self.slot = np.empty(local_vertices.size, np.int64)
        self._bind_wall()
        kernels.patch_slots(self.ids, local_vertices, self.slot)

"""Local model of the haptic loop (seed paper): a small copy of the surface around the tool.

At each tissue frame (about 30 Hz) the facets near the tool (found by the AABB tree with a
margin) are copied with their vertex positions and velocities. Between frames the 1 kHz loop
renders the contact against this copy only, updated by one of two policies:

- "hold":        p(t) = p_frame,                        surface velocity 0
- "extrapolate": p(t) = p_frame + v_frame (t - t_frame), surface velocity v_frame (first order)

The surface velocity is that of the geometry the force is computed against, so the damping term
of F = -k dist n - b (v . n) n always uses the tool velocity relative to the rendered surface.

Candidate pairs are stored per tool primitive (CSR: for node i, faces node_faces[node_ptr[i]:
node_ptr[i+1]], local face ids), so the narrow phase of a haptic step visits only the faces the
broad phase found near that primitive.
"""
import numpy as np

from . import kernels
from .penalty import law_code

LOCAL_POLICIES = ("hold", "extrapolate")


class LocalModelError(ValueError):
    """Invalid input to the local model."""


def _csr(pairs: np.ndarray, n_rows: int, face_map: np.ndarray):
    """CSR (ptr, local faces) of (k,2) pairs (row, global face) with faces mapped to local ids."""
    if pairs.shape[0] == 0:
        return np.zeros(n_rows + 1, np.int64), np.zeros(0, np.int64)
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    rows = pairs[order, 0]
    faces = face_map[pairs[order, 1]]
    ptr = np.zeros(n_rows + 1, np.int64)
    np.cumsum(np.bincount(rows, minlength=n_rows), out=ptr[1:])
    return ptr, np.ascontiguousarray(faces, dtype=np.int64)


class LocalModel:
    """Facets near the tool, captured at a tissue frame and held or extrapolated between frames."""

    def __init__(self, policy: str = "extrapolate"):
        if policy not in LOCAL_POLICIES:
            raise LocalModelError(f"local_model must be one of {LOCAL_POLICIES} (got {policy!r})")
        self.policy = policy
        self.extrapolate = policy == "extrapolate"
        self.t_frame = 0.0
        self.faces = np.zeros(0, np.int64)            # global face ids
        self.vertices = np.zeros(0, np.int64)         # global (surface) vertex ids
        self.triangles = np.zeros((0, 3), np.int64)   # local vertex ids
        self.frame_positions = np.zeros((0, 3))
        self.frame_velocities = np.zeros((0, 3))
        self.positions = np.zeros((0, 3))             # evaluated at the last positions_at(t)
        self.velocities = np.zeros((0, 3))
        self.node_ptr = np.zeros(1, np.int64)
        self.node_faces = np.zeros(0, np.int64)
        self.seg_ptr = np.zeros(1, np.int64)
        self.seg_faces = np.zeros(0, np.int64)

    # ------------------------------------------------------------------ capture
    def capture(self, t_frame, positions, velocities, triangles, node_pairs, n_nodes,
                seg_pairs=None, n_segments=0) -> None:
        """Copy the facets named by the candidate pairs out of a tissue frame.

        positions, velocities (n_surface,3) at t_frame; triangles (t,3) surface triangles;
        node_pairs (k,2) (tool node, global face); seg_pairs (k2,2) (tool segment, global face).
        """
        node_pairs = np.asarray(node_pairs, np.int64).reshape(-1, 2)
        seg_pairs = np.zeros((0, 2), np.int64) if seg_pairs is None else np.asarray(
            seg_pairs, np.int64).reshape(-1, 2)
        faces = np.unique(np.concatenate([node_pairs[:, 1], seg_pairs[:, 1]]))
        face_map = np.full(triangles.shape[0], -1, np.int64)
        face_map[faces] = np.arange(faces.size)
        vertices, local_tri = np.unique(triangles[faces].reshape(-1), return_inverse=True)
        self.t_frame = float(t_frame)
        self.faces = faces
        self.vertices = vertices
        self.triangles = np.ascontiguousarray(local_tri.reshape(-1, 3), dtype=np.int64)
        self.frame_positions = np.ascontiguousarray(positions[vertices], dtype=np.float64)
        self.frame_velocities = np.ascontiguousarray(velocities[vertices], dtype=np.float64)
        self.positions = self.frame_positions.copy()
        self.velocities = (self.frame_velocities.copy() if self.extrapolate
                           else np.zeros_like(self.frame_velocities))
        self.node_ptr, self.node_faces = _csr(node_pairs, n_nodes, face_map)
        self.seg_ptr, self.seg_faces = _csr(seg_pairs, n_segments, face_map)

    @classmethod
    def from_surface(cls, t_frame, positions, velocities, triangles, policy="extrapolate", n_nodes=1):
        """A local model holding a whole (small) surface, every face a candidate of every node."""
        positions = np.asarray(positions, np.float64)
        velocities = np.asarray(velocities, np.float64)
        triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
        if positions.shape != velocities.shape or positions.ndim != 2 or positions.shape[1] != 3:
            raise LocalModelError(
                f"positions and velocities must both be (n,3) (got {positions.shape} and {velocities.shape})")
        if not (np.isfinite(positions).all() and np.isfinite(velocities).all()):
            raise LocalModelError("positions/velocities contain NaN or inf")
        if triangles.size and (triangles.min() < 0 or triangles.max() >= positions.shape[0]):
            raise LocalModelError("triangles index vertices outside 0..n-1")
        model = cls(policy)
        nodes, faces = np.meshgrid(np.arange(n_nodes), np.arange(triangles.shape[0]), indexing="ij")
        model.capture(t_frame, positions, velocities, triangles,
                      np.stack([nodes.ravel(), faces.ravel()], axis=1), n_nodes)
        return model

    # ------------------------------------------------------------------ evaluation
    @property
    def n_faces(self) -> int:
        return int(self.faces.size)

    def positions_at(self, t, out=None) -> np.ndarray:
        """Vertex positions of the local model at time t (hold or first-order extrapolation)."""
        out = self.positions if out is None else out
        kernels.local_positions(self.frame_positions, self.frame_velocities, float(t) - self.t_frame,
                                self.extrapolate, out)
        return out

    def probe_force(self, t, point, velocity=(0.0, 0.0, 0.0), *, stiffness=500.0, damping=0.0,
                    law="linear", penalty_length=1e-3, radius=0.0):
        """Force (3,) on one probe point at time t against the local model (memoryless: the
        nearest facet decides the side). Returns (force, signed distance or None if no contact)."""
        p = np.asarray(point, np.float64).reshape(1, 3)
        v = np.asarray(velocity, np.float64).reshape(1, 3)
        if not (np.isfinite(p).all() and np.isfinite(v).all()):
            raise LocalModelError("point/velocity contain NaN or inf")
        pos = self.positions_at(t)
        node_force = np.zeros((1, 3))
        tissue = np.zeros((self.vertices.size, 3))
        face = np.full(1, -1, np.int64)
        depth = np.zeros(1)
        kernels.contact_step(pos, self.velocities, self.triangles, np.arange(self.vertices.size),
                             self.node_ptr[:2], self.node_faces, np.zeros(1, np.int64), self.seg_faces,
                             p, v, float(radius), float(stiffness), float(damping), law_code(law),
                             float(penalty_length), np.zeros(1, np.int8), np.zeros((1, 3)),
                             node_force, tissue, face, depth)
        return node_force[0], (None if face[0] < 0 else -float(depth[0]))

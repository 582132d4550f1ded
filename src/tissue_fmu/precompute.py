"""Rest-state precomputation of the tensor-mass model (vectorised numpy, no loops over elements).

Per tet with shape-function gradients g_j (j = 0..3, constant over a linear tet) and volume V,
the 3x3 block coupling local vertices j and k is (docs/design.md section 6)

    K_jk = lam A_jk + mu B_jk,   A_jk = V g_j (x) g_k,   B_jk = V (g_k (x) g_j + (g_j . g_k) I).

These blocks are summed over the tets of each vertex (K_ii) and of each edge (K_ij for i < j,
K_ji = K_ij^T), so the elastic force is ``f_i = -K_ii u_i - sum_j K_ij u_j``.  ``A`` and ``B`` are
the lambda- and mu-parts; :func:`tensor_mass_parts` returns their vertex/edge sums.  The run-time
non-linear correction never needs them stored: ``sum_k (dlam A_jk + dmu B_jk) u_k =
V (dlam tr(H) I + dmu (H + H^T)) g_j`` with ``H = sum_k u_k (x) g_k`` (see kernels.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = [
    "signed_volumes",
    "TensorMassTensors",
    "shape_gradients",
    "element_pair_blocks",
    "tensor_mass_tensors",
    "remove_element_tensors",
    "tensor_mass_parts",
    "tensors_to_csr",
    "lumped_masses",
    "edge_strain_bound_factors",
    "edge_element_adjacency",
    "edge_screen_limits",
]

# Local vertex pairs: the four diagonal pairs, then the six edges of a tet.
_DIAG_PAIRS = np.array([[0, 0], [1, 1], [2, 2], [3, 3]], dtype=np.int64)
_EDGE_PAIRS = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)


@dataclass
class TensorMassTensors:
    """Vertex and edge 3x3 tensors of a symmetric operator (stiffness or damping).

    vertex: (n, 3, 3) K_ii; edges: (e, 2) int32 node pairs with edges[:, 0] < edges[:, 1],
    sorted; edge_tensors: (e, 3, 3) K_ij for (i, j) = edges[k] (K_ji = K_ij^T).
    """

    vertex: np.ndarray
    edges: np.ndarray
    edge_tensors: np.ndarray
    element_edges: np.ndarray | None = None  # (m, 6) edge id of each tet's local edge (_EDGE_PAIRS order)

    @property
    def n_nodes(self) -> int:
        return int(self.vertex.shape[0])

    def scaled(self, factor: float) -> "TensorMassTensors":
        return TensorMassTensors(self.vertex * factor, self.edges, self.edge_tensors * factor)


def signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(m,) signed volumes det[p1 - p0, p2 - p0, p3 - p0] / 6 (> 0: positively oriented)."""
    p0 = points[tets[:, 0]]
    a = points[tets[:, 1]] - p0
    b = points[tets[:, 2]] - p0
    c = points[tets[:, 3]] - p0
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def shape_gradients(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(grads (m, 4, 3), volumes (m,)) of linear tets; grads[e, j] = grad N_j (constant).

    Correct for any vertex order: the gradient of N_j belongs to the vertex listed j whatever the
    orientation, and the volume is |det| / 6 (a signed volume would give a negatively oriented tet
    a stiffness and mass of the wrong sign).
    """
    p0 = points[tets[:, 0]]
    d = np.stack([points[tets[:, 1]] - p0, points[tets[:, 2]] - p0, points[tets[:, 3]] - p0], axis=2)
    # d has columns p_k - p_0; x = p0 + d xi, so grad xi_k = row k of d^-1 and N_k = xi_k.
    volumes = np.abs(np.linalg.det(d)) / 6.0
    inv = np.linalg.inv(d)
    grads = np.empty((tets.shape[0], 4, 3))
    grads[:, 1:, :] = inv
    grads[:, 0, :] = -inv.sum(axis=1)
    return grads, volumes


def element_pair_blocks(grads, volumes, lam, mu, pairs) -> np.ndarray:
    """(m, p, 3, 3) blocks K_jk for the local pairs (p, 2); lam, mu scalars or (m,)."""
    gj = grads[:, pairs[:, 0], :]
    gk = grads[:, pairs[:, 1], :]
    lam_v = (np.broadcast_to(lam, volumes.shape) * volumes)[:, None, None, None]
    mu_v = (np.broadcast_to(mu, volumes.shape) * volumes)[:, None, None, None]
    outer_jk = gj[..., :, None] * gk[..., None, :]
    blocks = lam_v * outer_jk + mu_v * np.swapaxes(outer_jk, -1, -2)
    dots = np.einsum("mpi,mpi->mp", gj, gk)
    idx = np.arange(3)
    blocks[..., idx, idx] += (mu_v[..., 0, 0] * dots)[..., None]
    return blocks


def _reduce_blocks(keys: np.ndarray, blocks: np.ndarray, n_out: int) -> np.ndarray:
    """Sum (k, 3, 3) blocks into (n_out, 3, 3) by integer key (bincount per component: fast)."""
    flat = blocks.reshape(-1, 9)
    out = np.empty((n_out, 9))
    for c in range(9):
        out[:, c] = np.bincount(keys, weights=flat[:, c], minlength=n_out)
    return out.reshape(n_out, 3, 3)


def tensor_mass_tensors(points, tets, lam, mu, grads=None, volumes=None) -> TensorMassTensors:
    """Vertex and edge tensors of ``sum_T (lam_T A_T + mu_T B_T)`` (inputs assumed valid)."""
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    n = points.shape[0]
    if grads is None or volumes is None:
        grads, volumes = shape_gradients(points, tets)

    diag = element_pair_blocks(grads, volumes, lam, mu, _DIAG_PAIRS)
    vertex = _reduce_blocks(tets.reshape(-1), diag, n)

    blocks = element_pair_blocks(grads, volumes, lam, mu, _EDGE_PAIRS)
    a = tets[:, _EDGE_PAIRS[:, 0]]
    b = tets[:, _EDGE_PAIRS[:, 1]]
    # The stored block couples the lower global id (row) to the higher one (column):
    # where the local order is reversed, K_ab = K_kj = K_jk^T.
    flip = a > b
    blocks[flip] = np.swapaxes(blocks[flip], -1, -2)
    lo = np.minimum(a, b).reshape(-1)
    hi = np.maximum(a, b).reshape(-1)
    keys = lo * np.int64(n) + hi
    unique_keys, inverse = np.unique(keys, return_inverse=True)
    edge_tensors = _reduce_blocks(inverse.reshape(-1), blocks.reshape(-1, 3, 3), unique_keys.size)
    edges = np.stack([unique_keys // n, unique_keys % n], axis=1).astype(np.int32)
    return TensorMassTensors(np.ascontiguousarray(vertex), edges, np.ascontiguousarray(edge_tensors),
                             inverse.reshape(-1, 6))


def remove_element_tensors(t: TensorMassTensors, tets, grads, volumes, lam, mu, ids) -> None:
    """Take the blocks of elements ``ids`` (rows of ``tets``, the tets ``t`` was built from) out of
    its vertex and edge tensors, in place: the tensor-mass model's local topology change (Cotin,
    Delingette and Ayache 2000), which touches only the elements' own vertices and edges, never a
    global precomputation. An edge left without elements keeps a zero tensor."""
    ids = np.asarray(ids, dtype=np.int64)
    if ids.size == 0:
        return
    if t.element_edges is None:
        raise ValueError("these tensors do not record their elements' edges (element_edges)")
    removed = tets[ids]
    lam = np.broadcast_to(lam, volumes.shape)[ids]
    mu = np.broadcast_to(mu, volumes.shape)[ids]
    diag = element_pair_blocks(grads[ids], volumes[ids], lam, mu, _DIAG_PAIRS)
    np.subtract.at(t.vertex, removed.reshape(-1), diag.reshape(-1, 3, 3))
    blocks = element_pair_blocks(grads[ids], volumes[ids], lam, mu, _EDGE_PAIRS)
    flip = removed[:, _EDGE_PAIRS[:, 0]] > removed[:, _EDGE_PAIRS[:, 1]]  # stored lower id first
    blocks[flip] = np.swapaxes(blocks[flip], -1, -2)
    np.subtract.at(t.edge_tensors, t.element_edges[ids].reshape(-1), blocks.reshape(-1, 3, 3))


def tensor_mass_parts(points, tets, lam, mu):
    """(K, K_lambda, K_mu): full tensors and their lambda- and mu-parts (lam A and mu B sums)."""
    grads, volumes = shape_gradients(np.asarray(points, float), np.asarray(tets, np.int64))
    zero = np.zeros_like(volumes)
    k_lam = tensor_mass_tensors(points, tets, lam, zero, grads, volumes)
    k_mu = tensor_mass_tensors(points, tets, zero, mu, grads, volumes)
    full = TensorMassTensors(k_lam.vertex + k_mu.vertex, k_lam.edges, k_lam.edge_tensors + k_mu.edge_tensors)
    return full, k_lam, k_mu


def tensors_to_csr(t: TensorMassTensors) -> sp.csr_matrix:
    """The same operator as a 3n x 3n CSR matrix (node-major dofs)."""
    n = t.n_nodes
    r = np.arange(3)
    # Block entry (a, b) of node pair (i, j) sits at row 3 i + a, column 3 j + b.
    vi = np.arange(n)
    rows_v = (3 * vi[:, None, None] + r[None, :, None]).repeat(3, axis=2)
    cols_v = (3 * vi[:, None, None] + r[None, None, :]).repeat(3, axis=1)
    i = t.edges[:, 0].astype(np.int64)
    j = t.edges[:, 1].astype(np.int64)
    rows_e = np.broadcast_to(3 * i[:, None, None] + r[None, :, None], t.edge_tensors.shape)
    cols_e = np.broadcast_to(3 * j[:, None, None] + r[None, None, :], t.edge_tensors.shape)
    rows = np.concatenate([rows_v.ravel(), rows_e.ravel(), cols_e.ravel()])
    cols = np.concatenate([cols_v.ravel(), cols_e.ravel(), rows_e.ravel()])
    vals = np.concatenate([t.vertex.ravel(), t.edge_tensors.ravel(), t.edge_tensors.ravel()])
    k = sp.coo_matrix((vals, (rows, cols)), shape=(3 * n, 3 * n)).tocsr()
    k.sum_duplicates()
    k.sort_indices()
    return k


def lumped_masses(tets, volumes, density, n_nodes: int) -> np.ndarray:
    """(n,) lumped nodal masses: a quarter of each tet's mass to each of its nodes."""
    share = np.broadcast_to(np.asarray(density, dtype=np.float64) * volumes / 4.0, volumes.shape)
    return np.bincount(tets.reshape(-1), weights=np.repeat(share, 4), minlength=n_nodes)


def edge_strain_bound_factors(points, tets) -> np.ndarray:
    """(m,) C_T with  max |principal Green strain| <= C_T * max_edges |edge Green strain|.

    A linear tet's Green strain E is fixed by its six edge strains eps_e = n_e . E n_e (n_e unit
    rest edge directions): E = sum_e eps_e M_e with M_e the columns of the inverse of the 6x6 map
    Q: E -> eps.  Hence |E|_2 <= |E|_F <= max|eps_e| sum_e |M_e|_F =: max|eps_e| C_T.
    """
    d = points[tets[:, _EDGE_PAIRS[:, 1]]] - points[tets[:, _EDGE_PAIRS[:, 0]]]
    n = d / np.linalg.norm(d, axis=2, keepdims=True)
    # eps_e = n0^2 E00 + n1^2 E11 + n2^2 E22 + 2 n0 n1 E01 + 2 n0 n2 E02 + 2 n1 n2 E12
    q = np.stack([n[..., 0] ** 2, n[..., 1] ** 2, n[..., 2] ** 2,
                  2 * n[..., 0] * n[..., 1], 2 * n[..., 0] * n[..., 2], 2 * n[..., 1] * n[..., 2]], axis=2)
    cols = np.linalg.inv(q)  # (m, 6 components, 6 edges)
    weights = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])[None, :, None]
    return np.sqrt((weights * cols**2).sum(axis=1)).sum(axis=1)


def edge_element_adjacency(element_edges: np.ndarray, n_edges: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR (ptr (e+1,), element ids) of the tets around each edge."""
    flat = element_edges.reshape(-1)
    order = np.argsort(flat, kind="stable")
    ptr = np.zeros(n_edges + 1, dtype=np.int64)
    np.cumsum(np.bincount(flat, minlength=n_edges), out=ptr[1:])
    return ptr, (order // 6).astype(np.int64)


def edge_screen_limits(points, tets, edges, element_edges, threshold: float) -> np.ndarray:
    """(e, 4) float32 screen data of each edge: (d, 1/2) / (limit_e L_e^2), limit_e =
    threshold / max_{T around e} C_T, so |s . du + s3 |du|^2| > 1 <=> |edge Green strain| > limit_e.
    An edge below its limit cannot belong to a tet whose principal Green strain exceeds the
    threshold.  float32 rounding (1e-7 relative) is covered by a 1e-4 safety factor on the limit."""
    inv_c = 1.0 / edge_strain_bound_factors(points, tets)
    limit = np.full(edges.shape[0], np.inf)
    np.minimum.at(limit, element_edges.reshape(-1), np.repeat(inv_c, 6))
    d = points[edges[:, 1]] - points[edges[:, 0]]
    scale = 1.0 / ((1.0 - 1e-4) * threshold * limit * np.einsum("ij,ij->i", d, d))
    screen = np.empty((edges.shape[0], 4), dtype=np.float32)
    screen[:, :3] = d * scale[:, None]
    screen[:, 3] = 0.5 * scale
    return screen

"""The implicit step's preconditioner: a sparse factorisation of the step matrix, kept exact.

The implicit step solves ``A dv = b`` with ``A = M + h C + h^2 K_t`` (lumped mass, Kelvin-Voigt
damping, tangent stiffness).  :class:`TangentFactorization` factorises the rest matrix
``A_0 = M + h C + h^2 K_0`` once per step size (CHOLMOD: the system's SuiteSparse through
scikit-sparse when installed, else cholespy's; else SuperLU with a symmetric fill-reducing ordering
and no pivoting; :data:`BACKENDS`) and keeps the
preconditioner equal to the CURRENT ``A`` wherever that is affordable, so the step is one
application of it (accepted on the true residual; see ``BackwardEuler``):

* no element above the ETMM threshold (the linear law, small loads): ``A = A_0``, exact;
* a few super-threshold elements (``k`` free dofs on their nodes, ``k <= max_lowrank_dofs``):
  ``A = A_0 + U C U^T`` with ``C`` the assembled consistent-tangent correction (k x k) on those
  dofs; Woodbury, ``A^-1 = A_0^-1 - Z (I + C G)^-1 C U^T A_0^-1`` with ``Z = A_0^-1 U`` cached per
  node (solved once, when a node first joins the set, at most ``max_new_lowrank_dofs`` new
  columns per step) and ``G = U^T Z``: one factor solve, a k x k dense solve and an n x k product
  per application, exact to round-off;
* many (the whole wall stiffening): the assembled consistent tangent ``A`` is factorised
  (SuperLU: it is not symmetric) and reused as the preconditioner of GMRES while it stays good;
  it is refactorised at the next step when a solve needed more than ``refactor_iterations``
  iterations or the iterations beyond the first since the last factorisation reach
  ``refactor_budget`` (about the cost of one factorisation in solves: ski rental).  The choice
  depends only on iteration counts, never on timing, so runs are deterministic.

Hyperelastic (no assembled tangent): the rest factorisation only.  The choices are compared in
``benchmarks/bench_tissue_step.py``.  Fixed dofs are filtered out (the factors cover the free
dofs only), so the preconditioner returns 0 there.

State: the SuperLU/CHOLMOD factors cannot be pickled; :meth:`__getstate__` drops them and
:meth:`__setstate__` refactorises the same matrices (the rest matrix from ``h``, the tangent
from its stored values), which reproduces the factors bit for bit.

Why a maintained factorisation: on the rest factor alone a stiffened wall needs a dozen or more
GMRES iterations per step; kept exact, a step is one solve.  At 10k+ nodes the factor solve is
most of every step, which is why the fastest CHOLMOD installed is taken (docs/performance.md
has the figures).
"""

from __future__ import annotations

import importlib
import logging
from typing import Callable, NamedTuple

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from . import kernels
from .precompute import tensors_to_csr

logger = logging.getLogger(__name__)

__all__ = ["BACKENDS", "RestFactorization", "TangentFactorization", "backend_available", "default_backend",
           "sparse_lu"]

#: Woodbury (low-rank) correction up to this many free dofs on the super-threshold elements'
#: nodes; above it the tangent is assembled and factorised (compared in bench_tissue_step.py).
MAX_LOWRANK_DOFS = 600
#: ... and while a step needs at most this many new columns of A_0^-1 (one multi-right-hand-side
#: solve; more cost about as much as factorising the tangent, which then serves the next steps).
MAX_NEW_LOWRANK_DOFS = 150
#: Refactorise the assembled tangent at the next step once a solve needs more iterations, or once
#: the iterations beyond the first since the last factorisation add up to REFACTOR_BUDGET.
REFACTOR_ITERATIONS = 6
REFACTOR_BUDGET = 24


class _CholespyFactor:
    """CHOLMOD (supernodal, through the self-contained ``cholespy`` wheel, over the reference BLAS)
    of an SPD matrix given as CSR arrays; ``solve`` takes (n,) or (n, k) right-hand sides like
    SuperLU's."""

    def __init__(self, indptr, indices, data):
        import cholespy

        n = indptr.size - 1
        self._solver = cholespy.CholeskySolverD(n, np.ascontiguousarray(indptr, dtype=np.int32),
                                                np.ascontiguousarray(indices, dtype=np.int32),
                                                np.ascontiguousarray(data, dtype=np.float64), cholespy.MatrixType.CSR)

    def solve(self, rhs, trans="N"):
        rhs = np.ascontiguousarray(rhs, dtype=np.float64)
        x = np.empty_like(rhs)
        self._solver.solve(rhs, x)
        return x


class _SuiteSparseFactor:
    """CHOLMOD (supernodal) of the system's SuiteSparse through scikit-sparse, over the system's
    BLAS (OpenBLAS where installed), of an SPD matrix given as CSR arrays; ``solve`` like SuperLU's.

    Preferred to cholespy's CHOLMOD over the reference BLAS: its factorisations and its
    single-vector solves are faster (on the 10k+ node walls a solve is bound by reading the
    factor; bench_tissue_step.py compares them)."""

    def __init__(self, indptr, indices, data):
        cholmod, self._one_blas_thread = _load_system_cholmod()
        n = indptr.size - 1
        # symmetric: the CSR arrays are the CSC arrays of the same matrix
        matrix = sp.csc_matrix((np.asarray(data, dtype=np.float64), indices, indptr), shape=(n, n))
        with self._one_blas_thread():
            self._factor = cholmod.cholesky(matrix, mode="supernodal")

    def solve(self, rhs, trans="N"):
        rhs = np.asarray(rhs, dtype=np.float64)
        with self._one_blas_thread():
            return self._factor(rhs)


_system_cholmod = None

#: The system BLAS libraries CHOLMOD may run on (threadpoolctl's names); numpy's and scipy's own
#: OpenBLAS (``libscipy_openblas``) are other libraries and are left alone.
_SYSTEM_BLAS = ["libopenblas", "libblas", "libflexiblas", "libblis", "libmkl_rt"]


def _load_system_cholmod():
    """scikit-sparse's CHOLMOD and a context manager that runs the system BLAS on one thread
    (ImportError when scikit-sparse or threadpoolctl is not installed).

    One BLAS thread for every CHOLMOD call, restored afterwards: the factor and its solves then
    have the same bits in every process, whatever its CPU count or its importer's settings (two
    OpenBLAS threads round differently), and an importer that uses the same OpenBLAS keeps its own
    thread count. A second thread gains little, and the 1 kHz loop has the other CPU.

    OpenMP: CHOLMOD 3 (SuiteSparse 5) runs parts of a factorisation on 4 threads whatever
    ``OMP_NUM_THREADS`` says (with the same bits as one). Only ``OMP_THREAD_LIMIT`` caps them, read
    once when libgomp loads and process-wide: this module does not set it, since it runs inside
    other people's FMU importers too; the orchestrator sets it in its own processes
    (``orchestration.native_threads``), where one thread factorises faster."""
    global _system_cholmod
    if _system_cholmod is None:
        from sksparse import cholmod
        from threadpoolctl import ThreadpoolController

        system_blas = ThreadpoolController().select(prefix=_SYSTEM_BLAS)

        def one_blas_thread():
            return system_blas.limit(limits=1)

        _system_cholmod = cholmod, one_blas_thread
    return _system_cholmod


class _Backend(NamedTuple):
    package: str                 # what provides it (for messages)
    load: Callable[[], object]   # imports it; ImportError when it is not installed
    factor: type | None          # the rest factor's class; None: SuperLU (``sparse_lu``)


#: The rest factor's backends, fastest first (``auto`` takes the first one installed).
BACKENDS = {
    "scikit-sparse": _Backend("scikit-sparse (the cholmod extra)", _load_system_cholmod, _SuiteSparseFactor),
    "cholespy": _Backend("cholespy", lambda: importlib.import_module("cholespy"), _CholespyFactor),
    "superlu": _Backend("scipy", lambda: importlib.import_module("scipy.sparse.linalg"), None),
}


def backend_available(name: str) -> bool:
    """Whether the rest factor's backend ``name`` (a key of :data:`BACKENDS`) can be imported here."""
    try:
        BACKENDS[name].load()
    except ImportError:
        return False
    return True


def default_backend() -> str:
    """The fastest backend installed here (what ``backend="auto"`` takes)."""
    return next(name for name in BACKENDS if backend_available(name))


def sparse_lu(matrix_csc):
    """SuperLU of a structurally symmetric, diagonally dominant-ish matrix: symmetric fill-reducing
    ordering and no pivoting (fewer nonzeros and faster solves than scipy's default COLAMD with
    partial pivoting on these matrices)."""
    from scipy.sparse.linalg import splu

    return splu(matrix_csc, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})


class _ColumnCache:
    """Rows of Z^T = (A_0^-1 U)^T for the free dofs of nodes, solved in one multi-right-hand-side
    call per request for the nodes not cached yet (rows: one per free dof, node-major)."""

    def __init__(self, free_index: np.ndarray, n_free: int):
        self._free_index = free_index
        self.rows = np.zeros((0, n_free))
        self.count = 0
        self.node_row: dict[int, int] = {}

    def _free(self, v: int) -> np.ndarray:
        d = self._free_index[3 * v: 3 * v + 3]
        return d[d >= 0]

    def missing_dofs(self, nodes) -> int:
        return sum(self._free(int(v)).size for v in nodes if int(v) not in self.node_row)

    def ensure(self, nodes, factor) -> tuple[np.ndarray, np.ndarray]:
        """(free dof ids, cached rows) of ``nodes``; solves the missing ones with ``factor``."""
        new = [int(v) for v in nodes if int(v) not in self.node_row and self._free(int(v)).size]
        if new:
            new_dofs = np.concatenate([self._free(v) for v in new])
            rhs = np.zeros((self.rows.shape[1], new_dofs.size))
            rhs[new_dofs, np.arange(new_dofs.size)] = 1.0
            columns = factor.solve(rhs, trans="T")
            r = self.count
            if r + new_dofs.size > self.rows.shape[0]:
                grown = np.zeros((max(2 * self.rows.shape[0], r + new_dofs.size, 24), self.rows.shape[1]))
                grown[:r] = self.rows[:r]
                self.rows = grown
            self.rows[r: r + new_dofs.size] = columns.T
            for v in new:
                self.node_row[v] = r
                r += self._free(v).size
            self.count = r
        dofs, rows = [], []
        for v in nodes:
            v = int(v)
            free = self._free(v)
            if free.size:
                r = self.node_row[v]
                dofs.extend(free.tolist())
                rows.extend(range(r, r + free.size))
        return np.asarray(dofs, dtype=np.int64), np.asarray(rows, dtype=np.int64)


def _chosen_backend(backend: str) -> str:
    """The backend ``backend`` names ('auto': the fastest installed); ValueError when it is unknown
    or not installed here."""
    if backend != "auto" and backend not in BACKENDS:
        raise ValueError(f"backend must be 'auto' or one of {', '.join(BACKENDS)} (got {backend!r})")
    if backend == "auto":
        return default_backend()
    if not backend_available(backend):
        raise ValueError(f"backend {backend!r} needs {BACKENDS[backend].package}, which is not installed here "
                         "(see the README's install; backend='auto' takes the fastest one installed)")
    return backend


def _element_block_offsets(indptr: np.ndarray, indices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(m, 4, 4) element block offsets in the full pattern: the position of (3 t_j, 3 t_k) minus
    indptr[3 t_j]."""
    row0 = 3 * tets[:, :, None]
    col0 = 3 * tets[:, None, :]
    starts = indptr[row0]
    lengths = indptr[row0 + 1] - starts
    offsets = np.empty(tets.shape[:1] + (4, 4), dtype=np.int64)
    for j in range(4):  # searchsorted per row segment, vectorised over elements and k
        for k in range(4):
            s, ln, c = starts[:, j, 0], lengths[:, j, 0], col0[:, 0, k]
            lo = s.copy()
            hi = s + ln
            while True:  # vectorised binary search of column c in indices[lo:hi]
                active = lo < hi
                if not active.any():
                    break
                mid = (lo + hi) // 2
                go_right = active & (indices[np.minimum(mid, indices.size - 1)] < c)
                lo = np.where(go_right, mid + 1, lo)
                hi = np.where(active & ~go_right, mid, hi)
            offsets[:, j, k] = lo - s
    return offsets


class TangentFactorization:
    """Preconditioner ``z ~ (M + h C + h^2 K_t)^-1 r``, exact except for a large non-linear set
    (module docstring).  ``update(h)`` after the force field's ``add_forces``; ``__call__(r, out)``;
    ``record_iterations(n)`` after each solve (refactorisation policy)."""

    name = "factorized"

    def __init__(self, force_field, masses: np.ndarray, fixed: np.ndarray, *,
                 max_lowrank_dofs: int = MAX_LOWRANK_DOFS, max_new_lowrank_dofs: int = MAX_NEW_LOWRANK_DOFS,
                 refactor_iterations: int = REFACTOR_ITERATIONS,
                 refactor_budget: int = REFACTOR_BUDGET, backend: str = "auto"):
        ff = self.force_field = force_field
        n = ff.n_nodes
        #: the rest (SPD) matrix's factorisation: CHOLMOD (the system's through scikit-sparse, else
        #: cholespy's; faster solves than SuperLU on these matrices), else SuperLU; the tangent
        #: is always SuperLU (it is not symmetric).
        self.backend = _chosen_backend(backend)
        self._factor_class = BACKENDS[self.backend].factor
        self.max_lowrank_dofs = int(max_lowrank_dofs)
        self.max_new_lowrank_dofs = int(max_new_lowrank_dofs)
        self.refactor_iterations = int(refactor_iterations)
        self.refactor_budget = int(refactor_budget)
        self._extra_iterations = 0  # iterations beyond the first since the tangent was factorised
        fixed = np.asarray(fixed, dtype=bool)
        dof_free = np.repeat(~fixed, 3)
        self._free_dofs = np.flatnonzero(dof_free)
        nf = self._free_dofs.size
        rows = self._set_pattern(ff, masses, n)
        self._set_free_block(dof_free, rows, n, nf)
        self._offsets = _element_block_offsets(self._indptr, self._indices, ff.active_tets)
        self._n = n
        self._set_initial_state(nf)

    def _set_pattern(self, ff, masses: np.ndarray, n: int) -> np.ndarray:
        """The full-size (3n) pattern of K0 and C, their data, the diagonal's positions and the
        dofs' masses; returns the row of every pattern entry."""
        # K0 and C share the tets, so they share the edge pattern.
        k0 = tensors_to_csr(ff.stiffness)
        damping = ff.damping_tensors()
        c0 = None if damping is None else tensors_to_csr(damping)
        if c0 is not None and not (np.array_equal(c0.indptr, k0.indptr) and np.array_equal(c0.indices, k0.indices)):
            c0 = (k0 * 0.0 + c0).tocsr()
            k0 = (k0 + c0 * 0.0).tocsr()
            k0.sort_indices()
            c0.sort_indices()
        self._indptr = k0.indptr.astype(np.int64)
        self._indices = k0.indices.astype(np.int64)
        self._k_data = k0.data.copy()
        self._c_data = None if c0 is None else c0.data.copy()
        rows = np.repeat(np.arange(3 * n), np.diff(self._indptr))
        diag = np.flatnonzero(rows == self._indices)
        if diag.size != 3 * n:
            raise ValueError("stiffness pattern lacks a diagonal entry")  # cannot happen: every node has K_ii
        self._diag_pos = diag
        self._mass_dofs = np.repeat(np.where(masses > 0.0, masses, 1.0), 3)
        return rows

    def _set_free_block(self, dof_free: np.ndarray, rows: np.ndarray, n: int, nf: int) -> None:
        """The free-free block: entry selection and its CSR structure in free numbering."""
        keep = dof_free[rows] & dof_free[self._indices]
        self._keep = np.flatnonzero(keep)
        free_index = np.full(3 * n, -1, dtype=np.int64)
        free_index[self._free_dofs] = np.arange(nf)
        self._free_index = free_index
        self._f_indices = free_index[self._indices[self._keep]].astype(np.int32)
        self._f_indptr = np.zeros(nf + 1, dtype=np.int64)
        np.cumsum(np.bincount(free_index[rows[self._keep]], minlength=nf), out=self._f_indptr[1:])
        self._f_indptr = self._f_indptr.astype(np.int32)

    def _set_initial_state(self, nf: int) -> None:
        """No step size, factor or Woodbury set yet."""
        self._h = None
        self._rest_data = None      # full-pattern data of M + h C + h^2 K0
        self._lu_rest = None
        self.mode = "rest"          # "rest", "lowrank" or "tangent" (what the last update chose)
        self.factorizations = 0     # counters for benchmarks
        self.refactor_pending = False
        self._tangent_data = None   # free-block data of the factorised tangent
        self._lu_tangent = None
        # Woodbury cache: rows of Z^T (one per free dof of a cached node), node -> first row.
        self._z = _ColumnCache(self._free_index, nf)   # the steps' Woodbury columns
        self._zc = _ColumnCache(self._free_index, nf)  # compliance requests' own (never read by a step)
        self._dofs = np.zeros(0, dtype=np.int64)      # free dof ids of the current set
        self._rows = np.zeros(0, dtype=np.int64)      # their rows in the Woodbury cache
        self._small_lu = None
        self._small_c = None
        self._rhs = np.zeros(nf)

    # ------------------------------------------------------------------------------------
    # pickling: SuperLU objects are rebuilt from the stored matrices
    # ------------------------------------------------------------------------------------
    def __getstate__(self):
        state = self.__dict__.copy()
        state["_lu_rest"] = None
        state["_lu_tangent"] = None
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        if self._rest_data is not None:
            self._lu_rest = self._factor_rest(self._rest_data[self._keep])
        if self._tangent_data is not None:
            self._lu_tangent = sparse_lu(self._free_matrix(self._tangent_data))

    # ------------------------------------------------------------------------------------
    def _free_matrix(self, free_data):
        """CSC of A^T from the free block's CSR data (A^T: solved with trans='T')."""
        nf = self._free_dofs.size
        return sp.csc_matrix((free_data, self._f_indices, self._f_indptr), shape=(nf, nf))

    def _factor_rest(self, free_data):
        if self._factor_class is not None:
            return self._factor_class(self._f_indptr, self._f_indices, free_data)
        return sparse_lu(self._free_matrix(free_data))

    def _set_step(self, h: float) -> None:
        data = (h * h) * self._k_data
        if self._c_data is not None:
            data += h * self._c_data
        data[self._diag_pos] += self._mass_dofs
        self._rest_data = data
        self._lu_rest = self._factor_rest(data[self._keep])
        self.factorizations += 1
        self._h = h
        # Everything derived from A_0 is stale.
        self._z = _ColumnCache(self._free_index, self._free_dofs.size)
        self._zc = _ColumnCache(self._free_index, self._free_dofs.size)
        self._tangent_data = None
        self._lu_tangent = None
        logger.debug("factorised M + h C + h^2 K0 for h = %.4g s: %d free dofs", h, self._free_dofs.size)

    def prepare(self, h: float) -> None:
        """Factorise the rest matrix for step ``h`` now, if it is not yet (before the first frame,
        not in it)."""
        if h != self._h:
            self._set_step(h)

    def update(self, h: float) -> None:
        """Prepare for a solve with step ``h`` at the force field's current state."""
        self.prepare(h)
        ids = self.force_field.nonlinear_element_ids()
        # None: a law whose tangent is not assembled (hyperelastic); the rest factor only
        # preconditions it.
        self._approximate = ids is None
        if ids is None or ids.size == 0:
            self.mode = "rest"
            return
        nodes = np.unique(self.force_field.active_tets[ids])
        dofs = self._free_index[(3 * nodes[:, None] + np.arange(3)).ravel()]
        n_free = np.count_nonzero(dofs >= 0)
        if n_free == 0:  # every super-threshold element sits on fixed nodes: nothing to correct
            self.mode = "rest"
            return
        # hysteresis: an assembled tangent is left for the Woodbury form only once the set is half
        # the size limit (each entry into the tangent mode costs a factorisation)
        limit = self.max_lowrank_dofs if self.mode != "tangent" else self.max_lowrank_dofs // 2
        if n_free <= limit and self._z.missing_dofs(nodes) <= self.max_new_lowrank_dofs:
            self._update_lowrank(h, nodes)
            self.mode = "lowrank"
            return
        if self.mode != "tangent" or self._lu_tangent is None or self.refactor_pending:
            self._factor_tangent(h)
        self.mode = "tangent"

    @property
    def exact(self) -> bool:
        """True when the preconditioner equals the current step matrix to round-off (rest factor
        or its Woodbury correction): one application solves the step."""
        return self.mode != "tangent" and not self._approximate

    _approximate = False

    def record_iterations(self, iterations: int) -> None:
        """After a solve: schedule a refactorisation of a tangent that has gone stale."""
        if self.mode != "tangent":
            return
        self._extra_iterations += max(iterations - 1, 0)
        self.refactor_pending = (iterations > self.refactor_iterations
                                 or self._extra_iterations >= self.refactor_budget)

    def _factor_tangent(self, h: float) -> None:
        ids, blocks = self.force_field.tangent_blocks()
        data = self._rest_data.copy()
        kernels.scatter_element_blocks(self.force_field.active_tets, ids, ids.shape[0], blocks, h * h,
                                       self._indptr, self._offsets, data)
        self._tangent_data = data[self._keep]
        self._lu_tangent = sparse_lu(self._free_matrix(self._tangent_data))
        self.factorizations += 1
        self.refactor_pending = False
        self._extra_iterations = 0
        logger.debug("factorised the assembled tangent: %d super-threshold elements", ids.shape[0])

    def _update_lowrank(self, h: float, nodes: np.ndarray) -> None:
        # Current set: free dofs and their cached rows, node-major.
        dofs, rows = self._z.ensure(nodes, self._lu_rest)
        self._dofs = dofs
        self._rows = rows
        k = self._dofs.size
        # C (k x k): h^2 times the consistent correction on the set's free dofs.
        ids, blocks = self.force_field.tangent_blocks()
        local = np.full(3 * self._n, -1, dtype=np.int64)
        local[self._free_dofs[self._dofs]] = np.arange(k)
        tets = self.force_field.active_tets[ids]
        dof = local[(3 * tets[:, :, None] + np.arange(3)).reshape(ids.size, 12)]  # (count, 12)
        values = blocks.transpose(0, 1, 3, 2, 4).reshape(ids.size, 12, 12)  # (j, a) x (k, b)
        r_idx = np.broadcast_to(dof[:, :, None], values.shape)
        c_idx = np.broadcast_to(dof[:, None, :], values.shape)
        ok = (r_idx >= 0) & (c_idx >= 0)
        small_c = np.zeros((k, k))
        np.add.at(small_c, (r_idx[ok], c_idx[ok]), (h * h) * values[ok])
        g = self._z.rows[np.ix_(self._rows, self._dofs)].T  # G[a, b] = Z[D[a], b] = z_row(D[b])[D[a]]
        self._small_c = small_c
        self._small_lu = sla.lu_factor(np.eye(k) + small_c @ g, check_finite=False)

    def __call__(self, r: np.ndarray, out: np.ndarray) -> None:
        np.take(r.reshape(-1), self._free_dofs, out=self._rhs)
        if self.mode == "tangent":
            x = self._lu_tangent.solve(self._rhs, trans="T")
        else:
            x = self._lu_rest.solve(self._rhs, trans="T")
            if self.mode == "lowrank":
                t = self._small_c @ x[self._dofs]
                s = sla.lu_solve(self._small_lu, t, check_finite=False)
                kernels.rows_transpose_subtract(self._z.rows, self._rows, s, x)
        out.reshape(-1)[self._free_dofs] = x

    def inverse_block(self, nodes) -> np.ndarray | None:
        """(A^-1)[d, d] for the free dofs d of ``nodes`` (node-major), from the cached columns of
        A_0^-1 and the Woodbury correction: O(k p) once the nodes' columns are cached; None when
        the preconditioner is an assembled tangent factor (not exact)."""
        if not self.exact:
            return None
        dofs, rows = self._zc.ensure(nodes, self._lu_rest)
        y = self._zc.rows[np.ix_(rows, dofs)]  # (A_0^-1)[d, d] (symmetric)
        if self.mode == "lowrank":
            y_set = self._zc.rows[np.ix_(rows, self._dofs)].T          # (A_0^-1)[D, d]
            s = sla.lu_solve(self._small_lu, self._small_c @ y_set, check_finite=False)
            y = y - y_set.T @ s                                         # (A_0^-1)[d, D] = y_set^T
        return y

    def solve_matrix(self, rhs_free: np.ndarray) -> np.ndarray:
        """Apply the preconditioner to the columns of an (n_free, p) array (free numbering)."""
        if self.mode == "tangent":
            return self._lu_tangent.solve(rhs_free, trans="T")
        x = self._lu_rest.solve(rhs_free, trans="T")
        if self.mode == "lowrank":
            t = self._small_c @ x[self._dofs]
            s = sla.lu_solve(self._small_lu, t, check_finite=False)
            x -= self._z.rows[self._rows].T @ s
        return x

    @property
    def free_dofs(self) -> np.ndarray:
        return self._free_dofs


class RestFactorization(TangentFactorization):
    """The frame-budgeted step's preconditioner: the rest factor ``A_0 = M + h C + h^2 K_0`` only.

    It never factorises nor adds Woodbury columns inside a frame, so a budgeted step costs its
    iterations and nothing else: one factor solve and one system product each. It is the step matrix
    while no element is above the ETMM threshold (``exact``: the step is then the exact one); above
    it the Krylov solve it preconditions is cut at the budget and the residual left is reported.

    Why the rest factor and not the tangent refactorised in the background (Courtecuisse et al.'s
    asynchronous preconditioner): measured on the default wall under 5 N (bench_tissue_step.py
    section 0, docs/performance.md), a SuperLU tangent factor 8-15 frames old bought no fewer
    iterations than the rest factor (the loaded wall's tangent changes every frame), its solves cost
    1.6x the rest factor's CHOLMOD solves, and its factorisation took the other core from the 1 kHz
    loop; at four iterations the rest factor gave the same error in 25.6 ms at worst against 40.3 ms.
    """

    name = "rest"

    def update(self, h: float) -> None:
        """Prepare for the solve of the next frame with step ``h`` at the force field's state."""
        self.prepare(h)
        self.mode = "rest"
        ids = self.force_field.nonlinear_element_ids()
        # None: no assembled tangent (hyperelastic), the rest factor only approximates it
        self._approximate = ids is None or (
            ids.size > 0 and bool((self._free_index[3 * self.force_field.active_tets[ids]] >= 0).any()))

    def record_iterations(self, iterations: int) -> None:
        """Nothing to schedule: the factor never changes."""

    def rest_inverse_block(self, nodes) -> np.ndarray:
        """(A_0^-1)[d, d] for the free dofs d of ``nodes`` (node-major), from cached columns: the
        compliance of the wall at rest stiffness (the step matrix's own below the ETMM threshold)."""
        dofs, rows = self._zc.ensure(nodes, self._lu_rest)
        return self._zc.rows[np.ix_(rows, dofs)]

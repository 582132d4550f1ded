"""Krylov solvers on (n, 3) node arrays with a fixed-dof filter: CG, BiCGSTAB and GMRES.

Each solver sees only ``apply_matrix(p, out)`` (``out = A p``) and ``precondition(r, out)``
(``out ~ A^-1 r``), takes its initial guess in ``x`` (warm start), works on the free dofs
(``free``: 1.0 free, 0.0 fixed) and stops on the TRUE residual ``||b - A x|| <= tol ||b||``.
They never raise on non-convergence: they return (iterations, relative residual, converged).
Preallocated workspaces keep the hot loop free of allocations.
"""

from __future__ import annotations

import logging
import math
from typing import Callable

import numpy as np

logger = logging.getLogger(__name__)

__all__ = [
    "CGWorkspace",
    "preconditioned_cg",
    "BiCGStabWorkspace",
    "preconditioned_bicgstab",
    "GMRESWorkspace",
    "preconditioned_gmres",
    "masked_dot",
    "true_residual",
]


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """Dot product of two (n, 3) arrays without BLAS.

    np.vdot / np.dot go to a multi-threaded BLAS, whose threads spin-wait for cores that other
    processes hold: on a busy machine a dot then takes milliseconds where einsum takes
    microseconds.  CG does three per iteration, so this keeps the step time predictable.
    """
    return float(np.einsum("ij,ij->", a, b))


def masked_dot(a: np.ndarray, b: np.ndarray, free: np.ndarray) -> float:
    """sum(a * b * free) of (n, 3) arrays: a dot product over the free dofs (einsum, no BLAS)."""
    return float(np.einsum("ij,ij,ij->", a, b, free))


def true_residual(apply_matrix, b: np.ndarray, x: np.ndarray, free: np.ndarray, r: np.ndarray,
                   scratch: np.ndarray) -> float:
    """r = free * (b - A x); returns ||r||."""
    apply_matrix(x, scratch)
    np.subtract(b, scratch, out=r)
    np.multiply(r, free, out=r)
    return math.sqrt(_dot(r, r))


class CGWorkspace:
    """Preallocated vectors for :func:`preconditioned_cg` on an (n, 3) unknown."""

    def __init__(self, n_nodes: int):
        shape = (n_nodes, 3)
        self.r = np.zeros(shape)  # residual b - A x
        self.z = np.zeros(shape)  # preconditioned residual
        self.p = np.zeros(shape)  # search direction
        self.q = np.zeros(shape)  # A p
        self.t = np.zeros(shape)  # scratch for axpy updates


def preconditioned_cg(
    apply_matrix: Callable[[np.ndarray, np.ndarray], None],
    b: np.ndarray,
    x: np.ndarray,
    precondition: Callable[[np.ndarray, np.ndarray], None],
    free: np.ndarray,
    tolerance: float,
    max_iterations: int,
    work: CGWorkspace,
) -> tuple[int, float, bool]:
    """Solve a symmetric positive definite ``A x = b`` on the free dofs by preconditioned CG.

    ``apply_matrix(p, out)`` writes ``A p`` into ``out``; ``precondition(r, out)`` writes an
    approximation of ``A^-1 r`` (symmetric positive definite, zero on fixed dofs).  ``x`` holds
    the initial guess (warm start) and is overwritten with the solution.  ``free`` is an (n, 3) array of 1.0 on free and
    0.0 on fixed dofs: residuals and search directions are multiplied by it (the Baraff-Witkin
    filter), so fixed dofs keep ``x = 0`` and the iteration is plain PCG on the free subspace.
    Stops when the TRUE residual ``||b - A x|| <= tolerance ||b||`` (2-norms, unpreconditioned,
    over the free dofs).

    Returns (iterations, relative residual, converged).  Does not raise on non-convergence:
    the caller decides what to do with an inexact answer.
    """
    r, z, p, q, t = work.r, work.z, work.p, work.q, work.t
    np.multiply(x, free, out=x)
    b_norm = math.sqrt(masked_dot(b, b, free))
    if b_norm == 0.0:
        x.fill(0.0)
        return 0, 0.0, True
    target = tolerance * b_norm
    iterations = 0
    while True:
        # The recurrence residual drifts from b - A x in round-off: convergence is only
        # declared on the true residual, and a drifted iteration restarts from it.
        r_norm = true_residual(apply_matrix, b, x, free, r, q)
        if r_norm <= target:
            return iterations, r_norm / b_norm, True
        if iterations >= max_iterations or not math.isfinite(r_norm):
            return iterations, r_norm / b_norm, False
        precondition(r, z)
        np.copyto(p, z)
        rz = _dot(r, z)
        while iterations < max_iterations:
            apply_matrix(p, q)
            np.multiply(q, free, out=q)
            p_q = _dot(p, q)
            if not p_q > 0.0:
                # A is not positive definite along p (an indefinite non-linear tangent) or p is
                # NaN: CG cannot continue, return what we have.
                logger.warning("conjugate gradients broke down: p^T A p = %g after %d iterations",
                               p_q, iterations)
                r_norm = true_residual(apply_matrix, b, x, free, r, q)
                return iterations, r_norm / b_norm, False
            alpha = rz / p_q
            np.multiply(p, alpha, out=t)
            np.add(x, t, out=x)
            np.multiply(q, alpha, out=t)
            np.subtract(r, t, out=r)
            iterations += 1
            if math.sqrt(_dot(r, r)) <= target:
                break
            precondition(r, z)
            rz_new = _dot(r, z)
            beta = rz_new / rz
            rz = rz_new
            np.multiply(p, beta, out=p)
            np.add(p, z, out=p)


class BiCGStabWorkspace:
    """Preallocated vectors for :func:`preconditioned_bicgstab` on an (n, 3) unknown."""

    def __init__(self, n_nodes: int):
        shape = (n_nodes, 3)
        self.r = np.zeros(shape)
        self.r_hat = np.zeros(shape)
        self.p = np.zeros(shape)
        self.v = np.zeros(shape)
        self.y = np.zeros(shape)
        self.s = np.zeros(shape)
        self.z = np.zeros(shape)
        self.t = np.zeros(shape)
        self.tmp = np.zeros(shape)


def preconditioned_bicgstab(
    apply_matrix: Callable[[np.ndarray, np.ndarray], None],
    b: np.ndarray,
    x: np.ndarray,
    precondition: Callable[[np.ndarray, np.ndarray], None],
    free: np.ndarray,
    tolerance: float,
    max_iterations: int,
    work: BiCGStabWorkspace,
) -> tuple[int, float, bool]:
    """Solve a NON-symmetric ``A x = b`` on the free dofs by preconditioned BiCGSTAB (van der Vorst).

    Same contract as :func:`preconditioned_cg` (warm start in ``x``, ``free`` filter, stop at
    ``||b - A x|| <= tolerance ||b||``, returns (iterations, relative residual, converged)).
    Needed for the consistent ETMM tangent, which is not symmetric.
    """
    r, r_hat, tmp = work.r, work.r_hat, work.tmp
    np.multiply(x, free, out=x)
    b_norm = math.sqrt(masked_dot(b, b, free))
    if b_norm == 0.0:
        x.fill(0.0)
        return 0, 0.0, True
    target = tolerance * b_norm
    iterations = 0
    while True:
        # Convergence only on the true residual; a drifted recurrence restarts from it.
        r_norm = true_residual(apply_matrix, b, x, free, r, tmp)
        if r_norm <= target:
            return iterations, r_norm / b_norm, True
        if iterations >= max_iterations or not math.isfinite(r_norm):
            return iterations, r_norm / b_norm, False
        np.copyto(r_hat, r)
        iterations, broke_down = _bicgstab_cycle(apply_matrix, x, precondition, free, target, max_iterations,
                                                 iterations, work)
        if broke_down:
            r_norm = true_residual(apply_matrix, b, x, free, r, tmp)
            return iterations, r_norm / b_norm, False


def _bicgstab_cycle(apply_matrix, x, precondition, free, target: float, max_iterations: int, iterations: int,
                    work: BiCGStabWorkspace) -> tuple[int, bool]:
    """BiCGSTAB iterations from the residual in ``work.r`` (and ``work.r_hat``, its shadow) until
    the recurrence residual is below ``target`` or ``max_iterations`` are done; returns (the
    iteration count, whether it broke down, logged)."""
    r, r_hat, p, v, y, s, z, t, tmp = (work.r, work.r_hat, work.p, work.v, work.y, work.s, work.z,
                                        work.t, work.tmp)
    p.fill(0.0)
    v.fill(0.0)
    rho = alpha = omega = 1.0
    while iterations < max_iterations:
        rho_new = _dot(r_hat, r)
        if rho_new == 0.0 or omega == 0.0 or not math.isfinite(rho_new):
            logger.warning("BiCGSTAB broke down (rho = %g, omega = %g) after %d iterations",
                           rho_new, omega, iterations)
            return iterations, True
        beta = (rho_new / rho) * (alpha / omega)
        rho = rho_new
        # p = r + beta (p - omega v)
        np.multiply(v, omega, out=tmp)
        np.subtract(p, tmp, out=p)
        np.multiply(p, beta, out=p)
        np.add(p, r, out=p)
        precondition(p, y)
        apply_matrix(y, v)
        np.multiply(v, free, out=v)
        r_hat_v = _dot(r_hat, v)
        if r_hat_v == 0.0 or not math.isfinite(r_hat_v):
            logger.warning("BiCGSTAB broke down (r_hat . v = %g) after %d iterations", r_hat_v, iterations)
            return iterations, True
        alpha = rho / r_hat_v
        # half step: s = r - alpha v, x += alpha y
        np.multiply(v, alpha, out=tmp)
        np.subtract(r, tmp, out=s)
        np.multiply(y, alpha, out=tmp)
        np.add(x, tmp, out=x)
        iterations += 1
        if math.sqrt(_dot(s, s)) <= target:
            break
        precondition(s, z)
        apply_matrix(z, t)
        np.multiply(t, free, out=t)
        t_t = _dot(t, t)
        if t_t == 0.0 or not math.isfinite(t_t):
            logger.warning("BiCGSTAB broke down (t . t = %g) after %d iterations", t_t, iterations)
            return iterations, True
        omega = _dot(t, s) / t_t
        # x += omega z;  r = s - omega t
        np.multiply(z, omega, out=tmp)
        np.add(x, tmp, out=x)
        np.multiply(t, omega, out=tmp)
        np.subtract(s, tmp, out=r)
        if math.sqrt(_dot(r, r)) <= target:
            break
    return iterations, False


class GMRESWorkspace:
    """Preallocated Krylov basis for :func:`preconditioned_gmres` (restart length ``restart``)."""

    def __init__(self, n_nodes: int, restart: int = 30):
        self.restart = restart
        self.V = np.zeros((restart + 1, n_nodes, 3))  # orthonormal Arnoldi basis
        self.Z = np.zeros((restart, n_nodes, 3))  # preconditioned basis: x = x0 + Z y
        self.w = np.zeros((n_nodes, 3))
        self.r = np.zeros((n_nodes, 3))
        self.tmp = np.zeros((n_nodes, 3))
        self.H = np.zeros((restart + 1, restart))
        self.g = np.zeros(restart + 1)
        self.cs = np.zeros(restart)
        self.sn = np.zeros(restart)


def preconditioned_gmres(
    apply_matrix: Callable[[np.ndarray, np.ndarray], None],
    b: np.ndarray,
    x: np.ndarray,
    precondition: Callable[[np.ndarray, np.ndarray], None],
    free: np.ndarray,
    tolerance: float,
    max_iterations: int,
    work: GMRESWorkspace,
) -> tuple[int, float, bool]:
    """Solve a NON-symmetric ``A x = b`` on the free dofs by right-preconditioned (flexible) GMRES.

    Same contract as :func:`preconditioned_cg`.  One preconditioner application and one
    matrix product per iteration (BiCGSTAB needs two of each), and the minimised residual is the
    true one; restarted every ``work.restart`` iterations.  Needed for the consistent ETMM
    tangent, which is not symmetric.
    """
    V, Z, w, r, tmp, H, g, cs, sn = (work.V, work.Z, work.w, work.r, work.tmp, work.H, work.g,
                                     work.cs, work.sn)
    restart = work.restart
    np.multiply(x, free, out=x)
    b_norm = math.sqrt(masked_dot(b, b, free))
    if b_norm == 0.0:
        x.fill(0.0)
        return 0, 0.0, True
    target = tolerance * b_norm
    iterations = 0
    while True:
        beta = true_residual(apply_matrix, b, x, free, r, tmp)
        if beta <= target:
            return iterations, beta / b_norm, True
        if iterations >= max_iterations or not math.isfinite(beta):
            return iterations, beta / b_norm, False
        np.multiply(r, 1.0 / beta, out=V[0])
        H.fill(0.0)
        g.fill(0.0)
        g[0] = beta
        k = 0
        for j in range(restart):
            precondition(V[j], Z[j])
            apply_matrix(Z[j], w)
            np.multiply(w, free, out=w)
            for i in range(j + 1):  # modified Gram-Schmidt
                H[i, j] = _dot(w, V[i])
                np.multiply(V[i], H[i, j], out=tmp)
                np.subtract(w, tmp, out=w)
            h_next = math.sqrt(_dot(w, w))
            H[j + 1, j] = h_next
            if h_next > 0.0:
                np.multiply(w, 1.0 / h_next, out=V[j + 1])
            for i in range(j):  # previous Givens rotations
                hij = cs[i] * H[i, j] + sn[i] * H[i + 1, j]
                H[i + 1, j] = -sn[i] * H[i, j] + cs[i] * H[i + 1, j]
                H[i, j] = hij
            denominator = math.hypot(H[j, j], H[j + 1, j])
            if denominator == 0.0 or not math.isfinite(denominator):
                logger.warning("GMRES broke down after %d iterations", iterations)
                break
            cs[j] = H[j, j] / denominator
            sn[j] = H[j + 1, j] / denominator
            H[j, j] = denominator
            H[j + 1, j] = 0.0
            g[j + 1] = -sn[j] * g[j]
            g[j] = cs[j] * g[j]
            iterations += 1
            k = j + 1
            if abs(g[j + 1]) <= target or iterations >= max_iterations or h_next == 0.0:
                break
        if k == 0:
            return iterations, beta / b_norm, False
        # x += Z y with H[:k, :k] y = g[:k] (upper triangular after the rotations)
        y = np.zeros(k)
        for i in range(k - 1, -1, -1):
            y[i] = (g[i] - H[i, i + 1:k] @ y[i + 1:k]) / H[i, i]
        for i in range(k):
            np.multiply(Z[i], y[i], out=tmp)
            np.add(x, tmp, out=x)

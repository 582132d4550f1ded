"""Time integrators for the tensor-mass tissue, separate from the force field and the linear solver.

As in SOFA, an ODE solver only talks to the force field through a small matrix-free interface
(:class:`ForceField`): it never sees element data, so the same integrator runs the linear,
ETMM and hyperelastic laws, and the linear solver (:func:`preconditioned_cg`) only sees a
matrix-vector product.

State is the displacement ``u = x - x0`` and the velocity ``v``, both (n, 3) float64, updated in
place.  Lumped masses ``m`` (n,).  ``fixed`` (n,) bool marks nodes that never move (clamped
boundary, nodes outside the active region): their displacement and velocity stay at zero.

* :class:`SymplecticEuler` -- explicit, ``v += h M^-1 (f(u, v) + f_ext); u += h v`` with
  ``h = dt / substeps``.  Stable only for ``h <= 2 / omega_max``; it refuses a larger step with
  :class:`StabilityError` instead of blowing up, and ``substeps="auto"`` picks the smallest safe
  count.
* :class:`BackwardEuler` -- implicit, one linearised (Baraff-Witkin) step
  ``(M + h C + h^2 K_t) dv = h (f(u, v) + f_ext - h K_t v)``, ``v += dv``, ``u += h v``, solved
  matrix-free by preconditioned conjugate gradients (GMRES or BiCGSTAB for the non-symmetric
  consistent ETMM tangent) with fixed dofs filtered out.
  Unconditionally stable for the linear law; it damps a mode of angular frequency omega by
  ``1 / sqrt(1 + (omega h)^2)`` per step (its known numerical dissipation).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .errors import StabilityError, TissueError
from .forcefield import TensorMassForceField
from .solvers import (
    BiCGStabWorkspace,
    CGWorkspace,
    GMRESWorkspace,
    masked_dot,
    preconditioned_bicgstab,
    preconditioned_cg,
    preconditioned_gmres,
    true_residual,
)

logger = logging.getLogger(__name__)

__all__ = [
    "ForceField",
    "StepStatistics",
    "JacobiPreconditioner",
    "FactorizedPreconditioner",
    "SymplecticEuler",
    "BackwardEuler",
]

# substeps="auto" keeps this margin below the critical step: the bound is exact only for the
# rest tensors, and a step right at the limit leaves the highest mode undamped on the edge.
AUTO_SUBSTEP_SAFETY = 0.9


class ForceField(Protocol):
    """What an integrator needs from a force field (see tissue_fmu.forcefield)."""

    n_nodes: int

    def add_forces(self, u: np.ndarray, v: np.ndarray, out: np.ndarray) -> None: ...
    def tangent_matvec(self, du: np.ndarray, out: np.ndarray) -> None: ...
    # Optional: consistent_tangent_matvec(du, out), the exact (possibly non-symmetric) tangent.
    def damping_matvec(self, dv: np.ndarray, out: np.ndarray) -> None: ...
    def stiffness_diagonal(self) -> np.ndarray: ...


@dataclass
class StepStatistics:
    """What one integrator step did.  For the explicit integrator the solver fields stay 0."""

    substeps: int = 0
    iterations: int = 0
    relative_residual: float = 0.0
    converged: bool = True


# --------------------------------------------------------------------------------------
# Preconditioners (the Krylov solvers are in solvers.py)
# --------------------------------------------------------------------------------------


class JacobiPreconditioner:
    """``z = r / (m + h^2 diag K_t)``: cheap, matrix-free, but weak on thin stiff walls.

    (The viscous term is left out of the diagonal: the force field exposes no damping
    diagonal, and leaving it out keeps the preconditioner symmetric positive definite.)
    """

    name = "jacobi"

    def __init__(self, force_field: ForceField, masses: np.ndarray, fixed: np.ndarray):
        self.force_field = force_field
        self.mass = np.repeat(np.where(masses > 0.0, masses, 1.0)[:, None], 3, axis=1)
        self.free = np.repeat((~np.asarray(fixed, dtype=bool))[:, None], 3, axis=1).astype(np.float64)
        self.inverse_diagonal = np.zeros_like(self.mass)

    def update(self, h: float) -> None:
        """Refresh for step ``h`` at the current tangent (call after add_forces)."""
        diagonal = self.force_field.stiffness_diagonal() * (h * h)
        diagonal += self.mass
        np.divide(self.free, diagonal, out=self.inverse_diagonal)

    def __call__(self, r: np.ndarray, out: np.ndarray) -> None:
        np.multiply(r, self.inverse_diagonal, out=out)


class FactorizedPreconditioner:
    """``z = (M + h C + h^2 K_0)^-1 r`` by a sparse factorisation of the rest-state system.

    ``K_0`` is the assembled rest (linear) stiffness and ``C`` the damping matrix, both 3n x 3n
    scipy sparse.  For the linear law (and ETMM below its strain threshold) this is the exact
    system matrix and CG converges in one iteration; for non-linear laws it misses the
    stiffening of deformed elements (on the default AAA under 5 N, half the elements corrected,
    GMRES needs about a dozen iterations for 1e-6).  The factorisation is redone only when ``h``
    changes (a fixed communication step factors once).  Factors the free-dof block only, so
    fixed dofs get z = 0.
    """

    name = "factorized"

    def __init__(self, stiffness, masses: np.ndarray, fixed: np.ndarray, damping=None):
        import scipy.sparse as sp

        masses = np.asarray(masses, dtype=np.float64)
        free = self._free_dofs = np.flatnonzero(np.repeat(~np.asarray(fixed, dtype=bool), 3))
        self._stiffness = sp.csr_matrix(stiffness)[free][:, free].tocsc()
        self._damping = None if damping is None else sp.csr_matrix(damping)[free][:, free].tocsc()
        self._mass = sp.diags(np.repeat(masses, 3)[free]).tocsc()
        self._rhs = np.zeros(free.size)
        self._h = None
        self._lu = None

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_lu"] = None  # SuperLU cannot be pickled: refactorised (bit for bit) on load
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        if self._h is not None:
            h, self._h = self._h, None
            self.update(h)

    def update(self, h: float) -> None:
        if h == self._h:
            return
        from scipy.sparse.linalg import splu

        system = self._mass + (h * h) * self._stiffness
        if self._damping is not None:
            system = system + h * self._damping
        system = system.tocsc()
        # M + h C + h^2 K is symmetric positive definite: a symmetric fill-reducing ordering and
        # no pivoting (fewer nonzeros and faster solves than scipy's default COLAMD with partial
        # pivoting on these matrices).
        self._lu = splu(system, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                        options={"SymmetricMode": True})
        self._h = h
        logger.debug("factorised M + h^2 K for h = %.4g s: %d dofs, %d nonzeros in L+U",
                     h, system.shape[0], self._lu.L.nnz + self._lu.U.nnz)

    def __call__(self, r: np.ndarray, out: np.ndarray) -> None:
        np.take(r.reshape(-1), self._free_dofs, out=self._rhs)
        out.reshape(-1)[self._free_dofs] = self._lu.solve(self._rhs)


# --------------------------------------------------------------------------------------
# Explicit symplectic Euler
# --------------------------------------------------------------------------------------


class SymplecticEuler:
    """Explicit symplectic (semi-implicit) Euler with substeps.

    Per substep of size ``h = dt / substeps``::

        v += h M^-1 (f(u, v) + f_ext);   u += h v      (fixed nodes stay at rest)

    ``critical_time_step`` is the force field's safe bound (``2 / omega_max`` from Gershgorin,
    shortened for viscous damping and the stiffening of non-linear laws); pass
    ``critical_time_step`` to override it (tests use this to show what happens without the check).
    """

    def __init__(
        self,
        force_field: ForceField,
        masses: np.ndarray,
        fixed: np.ndarray,
        substeps: int | str = "auto",
        *,
        critical_time_step: float | None = None,
    ):
        n = force_field.n_nodes
        self.force_field = force_field
        self.substeps = substeps
        self.free = np.repeat((~np.asarray(fixed, dtype=bool))[:, None], 3, axis=1).astype(np.float64)
        masses = np.asarray(masses, dtype=np.float64)
        # Fixed nodes get inverse mass 0, so no force can ever move them.
        self.inverse_mass = np.zeros((n, 3))
        movable = (masses > 0.0) & ~np.asarray(fixed, dtype=bool)
        self.inverse_mass[movable] = (1.0 / masses[movable])[:, None]
        if critical_time_step is None:
            critical_time_step = force_field.critical_time_step(np.where(masses > 0.0, masses, 1.0))
        self.critical_time_step = float(critical_time_step)
        self._force = np.zeros((n, 3))
        self._last_auto_substeps = 0

    def substeps_for(self, dt: float) -> int:
        """Substep count used for a communication step ``dt``; raises StabilityError if unsafe."""
        critical = self.critical_time_step
        if self.substeps == "auto":
            count = max(1, math.ceil(dt / (AUTO_SUBSTEP_SAFETY * critical)))
            if count != self._last_auto_substeps:
                logger.info(
                    "explicit integrator: %d substeps of %.3g s for dt = %.4g s (critical step %.3g s, safety %.2f)",
                    count, dt / count, dt, critical, AUTO_SUBSTEP_SAFETY,
                )
                self._last_auto_substeps = count
            return count
        count = int(self.substeps)
        h = dt / count
        if h > critical:
            needed = math.ceil(dt / critical)
            raise StabilityError(
                f"explicit step h = dt/substeps = {dt:.6g}/{count} = {h:.4g} s exceeds the critical time step "
                f"{critical:.4g} s of this mesh and material: use at least {needed} substeps "
                f"(substeps='auto' picks {math.ceil(dt / (AUTO_SUBSTEP_SAFETY * critical))}) "
                f"or the implicit integrator"
            )
        return count

    def step(self, u: np.ndarray, v: np.ndarray, f_ext: np.ndarray, dt: float) -> StepStatistics:
        """Advance ``u``, ``v`` in place by ``dt`` with ``f_ext`` held constant."""
        count = self.substeps_for(dt)
        h = dt / count
        f = self._force
        ff = self.force_field
        v *= self.free
        for _ in range(count):
            np.copyto(f, f_ext)
            ff.add_forces(u, v, f)
            np.multiply(f, self.inverse_mass, out=f)
            f *= h
            v += f
            np.multiply(v, h, out=f)
            u += f
        return StepStatistics(substeps=count)


# --------------------------------------------------------------------------------------
# Implicit backward Euler
# --------------------------------------------------------------------------------------


class BackwardEuler:
    """Linearised implicit (backward) Euler, one Krylov solve per step (Baraff and Witkin 1998).

    Backward Euler asks ``M dv = h f(u + h (v + dv), v + dv) + h f_ext``; linearising the force at
    the current state (``df/du = -K_t``, ``df/dv = -C``) gives::

        (M + h C + h^2 K_t) dv = h (f(u, v) + f_ext - h K_t v)
        v += dv;   u += h v

    For the linear law this is exactly backward Euler.  The system is solved matrix-free,
    warm started from the previous ``dv`` extrapolated linearly from the one before, with
    :class:`JacobiPreconditioner` (default), :class:`FactorizedPreconditioner` (the rest matrix) or
    :class:`~tissue_fmu.factorization.TangentFactorization` (the model's choice: the step matrix
    kept exact; needed for thin walls at 30 Hz, where Jacobi-CG takes
    thousands of iterations).

    Tangent: ``K_t`` is the force field's symmetric ``tangent_matvec`` (linear: K; ETMM: the
    secant stiffness; hyperelastic: the exact tangent), solved by :func:`preconditioned_cg`.
    With ``consistent_tangent=True`` and a force field that offers ``consistent_tangent_matvec``,
    steps in which non-linear elements are active (``nonlinear_fraction > 0``) use the exact,
    non-symmetric ETMM derivative instead, solved by :func:`preconditioned_gmres` (default) or
    :func:`preconditioned_bicgstab` (``nonsymmetric_solver``).  Why: with
    the secant the quasi-static limit of the step is the fixed-point iteration
    ``u <- K_s(u)^-1 f_ext``, which diverges into a limit cycle once the material stiffens
    faster than ``K_c > 2 K_s`` (a cantilever under 20 N keeps oscillating with a force residual
    of 200 %); the consistent tangent makes it a Newton step and it converges.

    Non-convergence within ``max_iterations`` is logged and reported in the statistics; a NaN
    raises TissueError.  ``budgeted=True`` makes ``max_iterations`` the frame's work budget (the
    frame-budgeted step, with :class:`~tissue_fmu.factorization.RestFactorization`; docs/tissue.md):
    stopping there is the design, so it is reported in the statistics only, and each solve starts
    from zero.
    """

    def __init__(
        self,
        force_field: ForceField,
        masses: np.ndarray,
        fixed: np.ndarray,
        tolerance: float = 1e-6,
        max_iterations: int = 1000,
        *,
        viscous: bool = True,
        preconditioner=None,
        consistent_tangent: bool = True,
        nonsymmetric_solver: str = "gmres",
        budgeted: bool = False,
    ):
        n = force_field.n_nodes
        self.budgeted = bool(budgeted)
        self.force_field = force_field
        self.tolerance = float(tolerance)
        self.max_iterations = int(max_iterations)
        self.viscous = viscous
        self.consistent_tangent = bool(consistent_tangent) and hasattr(force_field, "consistent_tangent_matvec")
        fixed = np.asarray(fixed, dtype=bool)
        self.free = np.repeat((~fixed)[:, None], 3, axis=1).astype(np.float64)
        masses = np.asarray(masses, dtype=np.float64)
        # Fixed dofs are filtered out of the solve; give them unit mass so the preconditioner
        # stays finite where a frozen node has no mass.
        self.mass = np.repeat(np.where(masses > 0.0, masses, 1.0)[:, None], 3, axis=1)
        self.dv = np.zeros((n, 3))  # previous solution: the warm start of the next solve
        self._dv_prev = np.zeros((n, 3))
        self._direct_r = np.zeros((n, 3))
        # Initial guess of each solve: the last solution extrapolated linearly from the one before
        # (on the default AAA under 5 N steady steps then need 1 GMRES iteration, not 2).
        self.extrapolate = True
        self._b = np.zeros((n, 3))
        self._tmp = np.zeros((n, 3))
        self._apply_tmp = np.zeros((n, 3))
        if preconditioner is None:
            preconditioner = JacobiPreconditioner(force_field, masses, fixed)
        self.preconditioner = preconditioner
        self._cg_work = CGWorkspace(n)
        if nonsymmetric_solver not in ("gmres", "bicgstab"):
            raise TissueError(f"nonsymmetric_solver must be 'gmres' or 'bicgstab' (got {nonsymmetric_solver!r})")
        self.nonsymmetric_solver = nonsymmetric_solver
        self._nonsymmetric_work = None
        self._tangent = force_field.tangent_matvec
        self._consistent = False
        self._h = 0.0
        self.last_solver = "cg"

    def _apply_system(self, p: np.ndarray, out: np.ndarray) -> None:
        """out = (M + h C + h^2 K_t) p."""
        h = self._h
        tmp = self._apply_tmp
        system = getattr(self.force_field, "system_matvec", None)
        if system is not None:
            system(p, h * h, h if self.viscous else 0.0, out, self._consistent)
        else:
            self._tangent(p, out)
            out *= h * h
            if self.viscous:
                self.force_field.damping_matvec(p, tmp)
                tmp *= h
                out += tmp
        np.multiply(self.mass, p, out=tmp)
        out += tmp

    def _direct_solve(self, b: np.ndarray):
        """When the preconditioner IS the step matrix (to round-off): dv = P^-1 b, accepted on the
        true residual (one iteration's worth, without the Krylov bookkeeping: two system products
        fewer than a 1-iteration CG/GMRES); None lets the Krylov solver continue from dv."""
        free = self.free
        b_norm = math.sqrt(masked_dot(b, b, free))
        self.preconditioner(b, self.dv)
        if b_norm == 0.0:
            return 0, 0.0, True
        r_norm = true_residual(self._apply_system, b, self.dv, free, self._direct_r, self._tmp)
        if r_norm <= self.tolerance * b_norm:
            return 1, r_norm / b_norm, True
        return None

    def step(self, u: np.ndarray, v: np.ndarray, f_ext: np.ndarray, dt: float) -> StepStatistics:
        """Advance ``u``, ``v`` in place by one backward-Euler step of size ``dt``."""
        h = float(dt)
        self._h = h
        v *= self.free
        nonsymmetric = self._right_hand_side(u, v, f_ext, h)
        self.preconditioner.update(h)
        if self.budgeted:
            # A budgeted solve starts from zero: its dv is then a polynomial in P^-1 A applied to
            # P^-1 b (with one iteration, the step with the preconditioner's matrix), whereas a warm
            # start carries the residual a budget leaves into the next frame (at 5 N on the default
            # wall one iteration diverged from the extrapolated start and from the last dv, two from
            # the extrapolated one).
            self.dv.fill(0.0)
        elif self.extrapolate:
            # initial guess: linear extrapolation of the last two solutions
            tmp = self._tmp
            np.subtract(self.dv, self._dv_prev, out=tmp)
            np.copyto(self._dv_prev, self.dv)
            self.dv += tmp
        iterations, residual, converged = self._solve(self._b, nonsymmetric, u.shape[0])
        record = getattr(self.preconditioner, "record_iterations", None)
        if record is not None:
            record(iterations)
        self._check_solution(iterations, residual, converged, dt)
        v += self.dv
        np.multiply(v, h, out=self._tmp)
        u += self._tmp
        return StepStatistics(substeps=1, iterations=iterations, relative_residual=residual, converged=converged)

    def _right_hand_side(self, u: np.ndarray, v: np.ndarray, f_ext: np.ndarray, h: float) -> bool:
        """``self._b`` = h (f(u, v) + f_ext - h K_t v), and the tangent the solve takes; returns
        whether it is the non-symmetric (consistent) one."""
        ff = self.force_field
        b, tmp = self._b, self._tmp
        # add_forces first: it sets the state the tangent is taken at.  With K_t = K_0 + correction,
        # -h K_0 v is folded into the force's rest-stiffness pass (one product over the rest tensors
        # fewer per step).  Only for the tensor-mass force field itself (a wrapper may replace its
        # tangent_matvec).
        fused = isinstance(ff, TensorMassForceField) and ff.splits_rest_stiffness
        np.copyto(b, f_ext)
        if fused:
            ff.add_forces(u, v, b, rest_v_scale=h)
        else:
            ff.add_forces(u, v, b)
        nonsymmetric = self.consistent_tangent and getattr(ff, "nonlinear_fraction", 0.0) > 0.0
        self._tangent = ff.consistent_tangent_matvec if nonsymmetric else ff.tangent_matvec
        self._consistent = nonsymmetric
        if fused:
            ff.add_tangent_correction(v, -h, b, nonsymmetric)
        else:
            self._tangent(v, tmp)
            tmp *= h
            b -= tmp
        b *= h
        return nonsymmetric

    def _solve(self, b: np.ndarray, nonsymmetric: bool, n: int) -> tuple[int, float, bool]:
        """``self.dv`` from its warm start: one application of an exact preconditioner, else the
        Krylov solver of the tangent; returns (iterations, relative residual, converged)."""
        direct = self._direct_solve(b) if getattr(self.preconditioner, "exact", False) else None
        if direct is not None:
            # labelled with the Krylov method it stands for (its first iteration, exact here)
            self.last_solver = self.nonsymmetric_solver if nonsymmetric else "cg"
            return direct
        if nonsymmetric:
            if self.nonsymmetric_solver == "gmres":
                if self._nonsymmetric_work is None:
                    self._nonsymmetric_work = GMRESWorkspace(n)
                solve = preconditioned_gmres
            else:
                if self._nonsymmetric_work is None:
                    self._nonsymmetric_work = BiCGStabWorkspace(n)
                solve = preconditioned_bicgstab
            self.last_solver = self.nonsymmetric_solver
            return solve(
                self._apply_system, b, self.dv, self.preconditioner, self.free,
                self.tolerance, self.max_iterations, self._nonsymmetric_work,
            )
        self.last_solver = "cg"
        return preconditioned_cg(
            self._apply_system, b, self.dv, self.preconditioner, self.free,
            self.tolerance, self.max_iterations, self._cg_work,
        )

    def _check_solution(self, iterations: int, residual: float, converged: bool, dt: float) -> None:
        """A NaN or infinity raises TissueError (u and v untouched); an inexact solve is logged."""
        if not (math.isfinite(residual) and np.isfinite(self.dv).all()):
            # Leave u and v untouched and the warm start usable for a retry.
            self.dv.fill(0.0)
            raise TissueError(
                f"implicit solve produced NaN/Inf after {iterations} {self.last_solver} iterations "
                f"(dt = {dt:.4g} s): check the contact forces and material parameters, or reduce dt"
            )
        if not converged and not self.budgeted:
            logger.warning(
                "implicit step: %s did not reach tolerance %.2g in %d iterations (relative residual %.3g); "
                "raise cg_max_iterations or cg_tolerance",
                self.last_solver, self.tolerance, iterations, residual,
            )

"""Tensor-mass force field (linear, Extended Tensor-Mass, hyperelastic reference).

Python layer: validates the inputs, precomputes the rest-state tensors (precompute.py) and calls
the numba kernels (kernels.py).  The material derivations are in materials.py.

Laws
- ``linear``: f = -K u with the vertex/edge tensors of DESIGN.md section 6.
- ``etmm``: linear plus the per-element secant correction ``-(dlam A + dmu B) u_T`` on elements
  whose extreme Green strain (axisymmetric-equivalent, from the strain invariants; materials.py)
  exceeds ``nonlinear_strain_threshold`` (ramped in over [t, 2t] so the force is continuous),
  reproducing the Raghavan-Vorp uniaxial response exactly once fully on.  Only the candidate
  tets (``nonlinear_elements``, default all) are examined; when most tets are candidates an edge
  strain pre-screen fused into the linear pass selects the few that need the exact check.
- ``hyperelastic``: finite-strain FEM internal force of the compressible Raghavan-Vorp law
  ``W = a (I1bar - 3) + b (I1bar - 3)^2 + kappa/2 (J - 1)^2`` (slow accuracy reference).
  Per element ``a = mu0 / 2``, ``b = a rv_beta / rv_alpha``, ``kappa = lam0 + 2 mu0 / 3`` so its
  small-strain moduli equal the element's (young_modulus, poisson_ratio); with
  young_modulus = 6 rv_alpha and poisson_ratio -> 0.5 it is the Raghavan-Vorp law.
Viscosity (all laws): Kelvin-Voigt with the linear viscous tensors, ``-C v``.
"""

from __future__ import annotations

import logging

import numpy as np

from . import kernels
from .materials import (
    LAWS,
    MaterialError,
    element_array,
    lame_parameters,
    rv_stiffening_ratio,
    viscous_lame_parameters,
)
from .precompute import (
    TensorMassTensors,
    assemble_stiffness,
    edge_element_adjacency,
    edge_screen_limits,
    lumped_masses,
    shape_gradients,
    tensor_mass_tensors,
    tensors_to_csr,
)

logger = logging.getLogger(__name__)

# lame_parameters and assemble_stiffness are re-exported here (agreed interface).
__all__ = ["ForceFieldError", "TensorMassForceField", "lame_parameters", "assemble_stiffness"]

# Explicit-step stiffening margin for non-linear laws: the time step stays a bound while every
# element's principal Green strains stay within +-STIFFENING_REFERENCE_STRAIN.
STIFFENING_REFERENCE_STRAIN = 0.1

# ETMM: above this fraction of candidate (non-linear-capable) tets, candidates are pre-screened
# by edge strains fused into the linear pass instead of checking every candidate tet.
SCREEN_MIN_CANDIDATE_FRACTION = 0.3


class ForceFieldError(ValueError):
    """Invalid force-field input (shape, law, mask); the message names the problem and the fix."""


def _check_node_array(name: str, x, n: int) -> np.ndarray:
    if not isinstance(x, np.ndarray) or x.shape != (n, 3) or x.dtype != np.float64:
        shape = getattr(x, "shape", None)
        dtype = getattr(x, "dtype", type(x).__name__)
        raise ForceFieldError(
            f"{name} must be a float64 numpy array of shape ({n}, 3) (got shape {shape}, dtype {dtype}): "
            "one row per node, node-major"
        )
    return x


def _finite_scalar(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and bool(np.isfinite(x))


def _element_mask(name: str, value, m: int) -> np.ndarray:
    if value is None:
        return np.ones(m, dtype=bool)
    arr = np.asarray(value)
    if arr.dtype == bool:
        if arr.shape != (m,):
            raise ForceFieldError(f"{name} as a boolean mask must have shape ({m},) (got {arr.shape})")
        return arr.copy()
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise ForceFieldError(f"{name} must be a boolean mask of shape ({m},) or integer element ids (got dtype {arr.dtype})")
    ids = arr.astype(np.int64).reshape(-1)
    if ids.size and (ids.min() < 0 or ids.max() >= m):
        raise ForceFieldError(f"{name} holds element ids outside [0, {m - 1}]: ids are 0-based rows of tets")
    mask = np.zeros(m, dtype=bool)
    mask[ids] = True
    return mask


class TensorMassForceField:
    """Elastic + viscous internal forces of a linear-tet mesh (see module docstring)."""

    def __init__(self, points, tets, young_modulus, poisson_ratio, *, law="linear", viscosity=0.0,
                 rv_alpha=0.174e6, rv_beta=1.881e6, nonlinear_strain_threshold=0.05,
                 nonlinear_elements=None, active_elements=None):
        from .mesh import validate_mesh  # agreed interface of the mesh module

        validate_mesh(points, tets)
        points = np.ascontiguousarray(points, dtype=np.float64)
        tets = np.ascontiguousarray(tets, dtype=np.int64)
        n, m = points.shape[0], tets.shape[0]
        if law not in LAWS:
            raise ForceFieldError(f"law must be one of {LAWS} (got {law!r})")
        if not _finite_scalar(rv_alpha) or rv_alpha <= 0.0:
            raise MaterialError(f"rv_alpha must be a finite number > 0 (got {rv_alpha!r}): the Raghavan-Vorp "
                                "alpha in Pa, e.g. 0.174e6")
        if not _finite_scalar(rv_beta) or rv_beta < 0.0:
            raise MaterialError(f"rv_beta must be a finite number >= 0 (got {rv_beta!r}): the Raghavan-Vorp "
                                "beta in Pa, e.g. 1.881e6 (0 gives a neo-Hookean-like law)")
        t = nonlinear_strain_threshold
        if not _finite_scalar(t) or t < 0.0:
            raise MaterialError(
                f"nonlinear_strain_threshold must be a finite number >= 0 (got {t!r}): a principal Green "
                "strain, e.g. 0.05 (0 corrects every element)"
            )
        e = element_array("young_modulus", young_modulus, m, "1.044e6 (Pa)")
        nu = element_array("poisson_ratio", poisson_ratio, m, "0.45")
        eta = element_array("viscosity", viscosity, m, "1.0e3 (Pa s), or 0")
        lam, mu = lame_parameters(e, nu)
        lam_v, mu_v = viscous_lame_parameters(eta, e, nu)
        active = _element_mask("active_elements", active_elements, m)
        if not active.any():
            raise ForceFieldError("active_elements selects no element: activate at least one tet")
        nonlinear = _element_mask("nonlinear_elements", nonlinear_elements, m)

        self.n_nodes = n
        self.law = law
        self.rv_alpha = float(rv_alpha)
        self.rv_beta = float(rv_beta)
        self.nonlinear_strain_threshold = float(t)
        self.nonlinear_fraction = 0.0
        self.active_elements = active
        act = np.flatnonzero(active)
        self._element_ids = act
        self._tets = np.ascontiguousarray(tets[act])
        self._grads, self._volumes = shape_gradients(points, self._tets)
        self._lam = np.ascontiguousarray(lam[act])
        self._mu = np.ascontiguousarray(mu[act])
        self._beta_over_alpha = self.rv_beta / self.rv_alpha
        self.stiffness: TensorMassTensors = tensor_mass_tensors(points, self._tets, self._lam, self._mu,
                                                                self._grads, self._volumes)
        # Damping: C = tau K when eta / E is uniform (one fused pass over K (u + tau v)),
        # separate viscous tensors otherwise.
        tau = eta[act] / e[act]
        self._tau = 0.0
        self._damping: TensorMassTensors | None = None
        self.has_damping = bool((tau > 0.0).any())
        if self.has_damping:
            if np.ptp(tau) <= 1e-12 * tau.max():
                self._tau = float(tau.mean())
            else:
                self._damping = tensor_mass_tensors(points, self._tets, lam_v[act], mu_v[act],
                                                    self._grads, self._volumes)
        m_a = act.size
        self._candidates = np.flatnonzero(nonlinear[act]).astype(np.int64)
        self._phi = np.zeros(m_a)
        self._nonlinear_ids = np.zeros(m_a, dtype=np.int64)
        self._nonlinear_count = 0
        self._u_last = np.zeros((n, 3))
        # ETMM screen: edges whose Green strain could mean an element over the threshold are
        # flagged during the linear pass; only the tets around them are examined exactly.
        # Measured (benchmarks/bench_tissue_kernels.py): the fused edge screen costs ~40 % of a linear
        # pass, checking a tet directly ~4 % of a linear pass per 1 % of tets, so the screen pays
        # only when most tets are candidates.
        self._screened = (law == "etmm" and self.nonlinear_strain_threshold > 0.0
                          and self._candidates.size > SCREEN_MIN_CANDIDATE_FRACTION * m_a)
        if self._screened:
            k = self.stiffness
            self._edge_screen = edge_screen_limits(points, self._tets, k.edges, k.element_edges,
                                                  self.nonlinear_strain_threshold)
            self._edge_elem_ptr, self._edge_elem_ids = edge_element_adjacency(k.element_edges, k.edges.shape[0])
            self._candidate_mask = np.zeros(m_a, dtype=np.uint8)
            self._candidate_mask[self._candidates] = 1
            self._stamp = np.zeros(m_a, dtype=np.int64)
            self._stamp_value = 0
            self._flagged = np.empty(k.edges.shape[0], dtype=np.int64)
            self._examined = np.empty(m_a, dtype=np.int64)
        self.screened_fraction = 0.0  # fraction of active tets examined exactly at the last add_forces
        self._work = np.empty((n, 3))
        # Hyperelastic per-element constants (small-strain moduli = the element's lam, mu).
        self._hyper_alpha = 0.5 * self._mu
        self._hyper_beta = self._hyper_alpha * self._beta_over_alpha
        self._hyper_kappa = self._lam + (2.0 / 3.0) * self._mu
        logger.info("tensor-mass force field: %d nodes, %d active tets, %d edges, law=%s",
                    n, m_a, self.stiffness.edges.shape[0], law)

    # ------------------------------------------------------------------------------------------
    # forces and tangents
    # ------------------------------------------------------------------------------------------
    def add_forces(self, u, v, out) -> None:
        """out += elastic(u) + viscous(v); u = x - x0, v velocity, all (n, 3) float64."""
        n = self.n_nodes
        _check_node_array("u", u, n)
        _check_node_array("out", out, n)
        if v is not None:
            _check_node_array("v", v, n)
        k = self.stiffness
        fused_damping = self._tau > 0.0 and v is not None
        if self.law == "hyperelastic":
            kernels.hyperelastic_forces(self._tets, self._grads, self._volumes, self._hyper_alpha,
                                        self._hyper_beta, self._hyper_kappa, u, out)
            np.copyto(self._u_last, u)
            if fused_damping:
                kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, v, -self._tau, out)
        elif self.law == "etmm":
            self._phi[self._nonlinear_ids[: self._nonlinear_count]] = 0.0  # forget the last state
            if self._screened:
                n_flagged = kernels.tensor_mass_force_screened(k.vertex, k.edges, k.edge_tensors,
                                                               self._edge_screen, u, out, self._flagged)
                self._stamp_value += 1
                n_examined = kernels.elements_of_flagged_edges(self._flagged, n_flagged, self._edge_elem_ptr,
                                                               self._edge_elem_ids, self._candidate_mask,
                                                               self._stamp, self._stamp_value, self._examined)
                examined = self._examined[:n_examined]
            else:
                kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, u, -1.0, out)
                examined = self._candidates
            self._nonlinear_count = kernels.etmm_correction(
                self._tets, self._grads, self._volumes, self._lam, self._mu, examined, u,
                self.nonlinear_strain_threshold, self._beta_over_alpha, self._phi, self._nonlinear_ids, out)
            m_a = self._tets.shape[0]
            self.nonlinear_fraction = self._nonlinear_count / m_a
            self.screened_fraction = examined.shape[0] / m_a
            np.copyto(self._u_last, u)
            if fused_damping:
                kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, v, -self._tau, out)
        else:
            if fused_damping:
                w = self._work
                np.multiply(v, self._tau, out=w)
                w += u
                kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, w, -1.0, out)
            else:
                kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, u, -1.0, out)
        if self._damping is not None and v is not None:
            c = self._damping
            kernels.tensor_mass_matvec(c.vertex, c.edges, c.edge_tensors, v, -1.0, out)

    def tangent_matvec(self, du, out) -> None:
        """out = K_t du at the last add_forces state (linear: K; etmm: secant; hyperelastic: exact)."""
        _check_node_array("du", du, self.n_nodes)
        _check_node_array("out", out, self.n_nodes)
        out.fill(0.0)
        if self.law == "hyperelastic":
            kernels.hyperelastic_tangent_matvec(self._tets, self._grads, self._volumes, self._hyper_alpha,
                                                self._hyper_beta, self._hyper_kappa, self._u_last, du, 1.0, out)
            return
        k = self.stiffness
        kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, du, 1.0, out)
        if self.law == "etmm" and self._nonlinear_count:
            kernels.scaled_elements_matvec(self._tets, self._grads, self._volumes, self._lam, self._mu,
                                           self._nonlinear_ids, self._nonlinear_count, self._phi, du, 1.0, out)

    def consistent_tangent_matvec(self, du, out) -> None:
        """out = d(-f)/du . du exactly at the last state (etmm: includes the change of dlam, dmu;
        not symmetric, so the CG solver uses :meth:`tangent_matvec`)."""
        if self.law != "etmm":
            self.tangent_matvec(du, out)
            return
        _check_node_array("du", du, self.n_nodes)
        _check_node_array("out", out, self.n_nodes)
        out.fill(0.0)
        k = self.stiffness
        kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, du, 1.0, out)
        kernels.etmm_consistent_tangent(self._tets, self._grads, self._volumes, self._lam, self._mu,
                                        self._candidates, self._u_last, du, self.nonlinear_strain_threshold,
                                        self._beta_over_alpha, out)

    def damping_matvec(self, dv, out) -> None:
        """out = C dv (zero if viscosity is 0)."""
        _check_node_array("dv", dv, self.n_nodes)
        _check_node_array("out", out, self.n_nodes)
        out.fill(0.0)
        if self._damping is not None:
            c = self._damping
            kernels.tensor_mass_matvec(c.vertex, c.edges, c.edge_tensors, dv, 1.0, out)
        elif self._tau > 0.0:
            k = self.stiffness
            kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, dv, self._tau, out)

    def damping_tensors(self) -> TensorMassTensors | None:
        if self._damping is not None:
            return self._damping
        return self.stiffness.scaled(self._tau) if self._tau > 0.0 else None

    def stiffness_diagonal(self) -> np.ndarray:
        """(n, 3) diagonal of K_t (hyperelastic: of the rest stiffness; fine for Jacobi)."""
        diag = np.ascontiguousarray(np.diagonal(self.stiffness.vertex, axis1=1, axis2=2))
        if self.law == "etmm" and self._nonlinear_count:
            kernels.scaled_elements_diagonal(self._tets, self._grads, self._volumes, self._lam, self._mu,
                                             self._nonlinear_ids, self._nonlinear_count, self._phi, diag)
        return diag

    def stiffness_matrix(self):
        """Rest (linear) stiffness as scipy CSR (3n x 3n)."""
        return tensors_to_csr(self.stiffness)

    # ------------------------------------------------------------------------------------------
    # diagnostics
    # ------------------------------------------------------------------------------------------
    def strain_energy(self, u) -> float:
        """Elastic energy: linear 1/2 u.Ku; etmm the secant energy 1/2 sum (1+phi_T) u_T.K_T u_T;
        hyperelastic sum V W(F)."""
        _check_node_array("u", u, self.n_nodes)
        if self.law == "hyperelastic":
            return float(kernels.hyperelastic_energy(self._tets, self._grads, self._volumes, self._hyper_alpha,
                                                     self._hyper_beta, self._hyper_kappa, u))
        k = self.stiffness
        ku = np.zeros_like(u)
        kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, u, 1.0, ku)
        energy = 0.5 * float(np.einsum("ij,ij->", u, ku))
        if self.law == "etmm":
            phi = np.zeros_like(self._phi)
            ids = np.zeros_like(self._nonlinear_ids)
            count = kernels.etmm_correction(self._tets, self._grads, self._volumes, self._lam, self._mu,
                                            self._candidates, u, self.nonlinear_strain_threshold,
                                            self._beta_over_alpha, phi, ids, ku)
            energy += float(kernels.scaled_elements_energy(self._tets, self._grads, self._volumes, self._lam,
                                                           self._mu, ids, count, phi, u))
        return energy

    def element_max_strain(self, u) -> np.ndarray:
        """(m_active,) largest principal Green strain magnitude per active element."""
        _check_node_array("u", u, self.n_nodes)
        out = np.empty(self._tets.shape[0])
        kernels.element_max_green_strain(self._tets, self._grads, u, out)
        return out

    def max_strain(self, u) -> float:
        """Max principal Green strain magnitude over the active elements."""
        return float(self.element_max_strain(u).max())

    def lumped_masses(self, density) -> np.ndarray:
        """(n,) lumped masses from the ACTIVE elements (nodes of inactive elements only: 0)."""
        m = self.active_elements.size
        rho = element_array("density", density, m, "1120.0 (kg/m^3)")
        if (rho <= 0.0).any():
            raise MaterialError(f"density must be > 0 (got {rho[rho <= 0.0][0]!r}): in kg/m^3, e.g. 1120.0")
        return lumped_masses(self._tets, self._volumes, rho[self._element_ids], self.n_nodes)

    def stiffening_margin(self, strain: float = STIFFENING_REFERENCE_STRAIN) -> float:
        """Upper bound of the tangent-stiffness growth factor for principal Green strains within
        +-strain (1 for the linear law): max over the uniaxial Raghavan-Vorp response of
        dP/dl / E = r + (l - 1) dr/dl, and the current secant factors 1 + phi."""
        if self.law == "linear":
            return 1.0
        green = np.linspace(-strain, strain, 401)
        stretch = np.sqrt(1.0 + 2.0 * green)
        r = rv_stiffening_ratio(green, self._beta_over_alpha)
        nominal = r * (stretch - 1.0)
        tangent = np.gradient(nominal, stretch)
        margin = max(float(tangent.max()), float(r.max()), 1.0)
        if self.law == "etmm" and self._nonlinear_count:
            margin = max(margin, 1.0 + float(self._phi.max()))
        return margin

    def critical_time_step(self, masses) -> float:
        """Largest stable step of explicit symplectic Euler, a SAFE (lower) estimate.

        omega_max^2 <= max_row sum_col |(M^-1 K)_rc| (Gershgorin, an upper bound on the largest
        eigenvalue of M^-1 K), times the stiffening margin for non-linear laws
        (:meth:`stiffening_margin`).  With damping the damped-oscillator limit of symplectic Euler,
        h^2 w^2 + 2 c h <= 4 with c bounded by Gershgorin on M^-1 C, gives
        dt = (sqrt(c^2 + 4 W^2) - c) / W^2 (= 2 / W without damping).  Over-estimating w and c
        only shortens dt, so the step is safe.
        """
        masses = np.asarray(masses, dtype=np.float64)
        if masses.shape != (self.n_nodes,) or not np.isfinite(masses).all() or (masses < 0).any():
            raise ForceFieldError(f"masses must be finite, >= 0, shape ({self.n_nodes},): use lumped_masses(density)")
        k = self.stiffness
        rows = np.empty((self.n_nodes, 3))
        kernels.gershgorin_row_sums(k.vertex, k.edges, k.edge_tensors, rows)
        moving = rows.max(axis=1) > 0.0
        if (masses[moving] <= 0.0).any():
            raise ForceFieldError("a node with stiffness has zero mass: give every active element a density > 0")
        omega2 = float((rows[moving].max(axis=1) / masses[moving]).max()) * self.stiffening_margin()
        c_bound = 0.0
        damping = self.damping_tensors()
        if damping is not None:
            kernels.gershgorin_row_sums(damping.vertex, damping.edges, damping.edge_tensors, rows)
            c_bound = float((rows[moving].max(axis=1) / masses[moving]).max())
        return float((np.sqrt(c_bound * c_bound + 4.0 * omega2) - c_bound) / omega2)

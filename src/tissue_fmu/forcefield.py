"""Tensor-mass force field (linear, Extended Tensor-Mass, hyperelastic reference).

Python layer: validates the inputs, precomputes the rest-state tensors (precompute.py) and calls
the numba kernels (kernels.py).  The material derivations are in materials.py.

Laws
- ``linear``: f = -K u with the vertex/edge tensors of docs/design.md section 6.
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
import scipy.sparse as sp

from . import kernels
from ._checks import is_finite_real
from .errors import ForceFieldError, MaterialError
from .laws import make_law
from .materials import (
    LAWS,
    element_array,
    lame_parameters,
    viscous_lame_parameters,
)
from .mesh import validate_mesh
from .precompute import (
    TensorMassTensors,
    lumped_masses,
    remove_element_tensors,
    shape_gradients,
    tensor_mass_tensors,
    tensors_to_csr,
)

logger = logging.getLogger(__name__)

# lame_parameters is re-exported here (agreed interface).
__all__ = ["ForceFieldError", "TensorMassForceField", "lame_parameters", "assemble_stiffness"]

# Explicit-step stiffening margin for non-linear laws: the time step stays a bound while every
# element's principal Green strains stay within +-STIFFENING_REFERENCE_STRAIN.
STIFFENING_REFERENCE_STRAIN = 0.1


def _check_node_array(name: str, x, n: int) -> np.ndarray:
    if not isinstance(x, np.ndarray) or x.shape != (n, 3) or x.dtype != np.float64:
        shape = getattr(x, "shape", None)
        dtype = getattr(x, "dtype", type(x).__name__)
        raise ForceFieldError(
            f"{name} must be a float64 numpy array of shape ({n}, 3) (got shape {shape}, dtype {dtype}): "
            "one row per node, node-major"
        )
    return x


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


def assemble_stiffness(points, tets, young_modulus, poisson_ratio) -> sp.csr_matrix:
    """Global stiffness K (3n x 3n CSR, node-major dofs, f = -K u) from the tensor-mass tensors.

    young_modulus, poisson_ratio: scalars or per-element (m,) arrays (validated).  The tets may
    list their vertices in any order (either orientation gives the same K); shapes, node ids,
    degenerate (flat) and non-manifold tets are refused with a MeshError naming them.
    """
    validate_mesh(points, tets, allow_inverted=True)
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    m = tets.shape[0]
    e = element_array("young_modulus", young_modulus, m, "1.044e6 (Pa)")
    nu = element_array("poisson_ratio", poisson_ratio, m, "0.45")
    lam, mu = lame_parameters(e, nu)
    return tensors_to_csr(tensor_mass_tensors(points, tets, lam, mu))


class TensorMassForceField:
    """Elastic + viscous internal forces of a linear-tet mesh (see module docstring)."""

    def __init__(self, points, tets, young_modulus, poisson_ratio, *, law="linear", viscosity=0.0,
                 rv_alpha=0.174e6, rv_beta=1.881e6, nonlinear_strain_threshold=0.05,
                 nonlinear_elements=None, active_elements=None):
        validate_mesh(points, tets)
        points = np.ascontiguousarray(points, dtype=np.float64)
        tets = np.ascontiguousarray(tets, dtype=np.int64)
        n, m = points.shape[0], tets.shape[0]
        if law not in LAWS:
            raise ForceFieldError(f"law must be one of {LAWS} (got {law!r})")
        if not is_finite_real(rv_alpha) or rv_alpha <= 0.0:
            raise MaterialError(f"rv_alpha must be a finite number > 0 (got {rv_alpha!r}): the Raghavan-Vorp "
                                "alpha in Pa, e.g. 0.174e6")
        if not is_finite_real(rv_beta) or rv_beta < 0.0:
            raise MaterialError(f"rv_beta must be a finite number >= 0 (got {rv_beta!r}): the Raghavan-Vorp "
                                "beta in Pa, e.g. 1.881e6 (0 gives a neo-Hookean-like law)")
        t = nonlinear_strain_threshold
        if not is_finite_real(t) or t < 0.0:
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
                self._lam_v, self._mu_v = lam_v[act], mu_v[act]
                self._damping = tensor_mass_tensors(points, self._tets, self._lam_v, self._mu_v,
                                                    self._grads, self._volumes)
        m_a = act.size
        self._points = np.ascontiguousarray(points)
        self._candidates = np.flatnonzero(nonlinear[act]).astype(np.int64)
        self._u_last = np.zeros((n, 3))
        self._work = np.empty((n, 3))
        self.screened_fraction = 0.0  # fraction of active tets examined exactly at the last add_forces
        #: (m_active,) True for the active elements taken out by :meth:`remove_elements`
        self.removed = np.zeros(m_a, dtype=bool)
        self._node_elements = np.bincount(self._tets.reshape(-1), minlength=n)  # elements per node
        self._law = make_law(law, self)
        logger.info("tensor-mass force field: %d nodes, %d active tets, %d edges, law=%s",
                    n, m_a, self.stiffness.edges.shape[0], law)

    # ------------------------------------------------------------------------------------------
    # forces and tangents
    # ------------------------------------------------------------------------------------------
    @property
    def material_law(self):
        """The law object (:mod:`tissue_fmu.laws`) behind this force field."""
        return self._law

    @property
    def nonlinear_fraction(self) -> float:
        """Fraction of active tets the non-linear correction acted on at the last add_forces."""
        return self._law.nonlinear_fraction

    @property
    def _screened(self) -> bool:
        return bool(getattr(self._law, "screened", False))

    def add_forces(self, u, v, out, rest_v_scale: float = 0.0) -> None:
        """out += elastic(u) + viscous(v); u = x - x0, v velocity, all (n, 3) float64.

        ``rest_v_scale`` (with v, laws that ``splits_rest_stiffness`` only): also out -=
        rest_v_scale K_0 v, fused into the rest-stiffness pass (the implicit step's -h K_t v is this
        plus :meth:`add_tangent_correction`)."""
        n = self.n_nodes
        _check_node_array("u", u, n)
        _check_node_array("out", out, n)
        if v is not None:
            _check_node_array("v", v, n)
        if rest_v_scale != 0.0:
            if v is None or not self._law.splits_rest_stiffness:
                raise ForceFieldError("rest_v_scale needs v and a law that splits off the rest stiffness")
            self._law.add_forces(u, v, out, rest_v_scale)
        else:
            self._law.add_forces(u, v, out)
        np.copyto(self._u_last, u)
        if self._damping is not None and v is not None:
            c = self._damping
            kernels.tensor_mass_matvec(c.vertex, c.edges, c.edge_tensors, v, -1.0, out)

    def tangent_matvec(self, du, out) -> None:
        """out = K_t du at the last add_forces state (linear: K; etmm: secant; hyperelastic: exact)."""
        _check_node_array("du", du, self.n_nodes)
        _check_node_array("out", out, self.n_nodes)
        out.fill(0.0)
        self._law.tangent_matvec(du, out)

    def consistent_tangent_matvec(self, du, out) -> None:
        """out = d(-f)/du . du exactly at the last state (etmm: includes the change of dlam, dmu;
        not symmetric, so the CG solver uses :meth:`tangent_matvec`).  ETMM touches only the
        elements above the strain threshold (the others have no correction and no derivative)."""
        _check_node_array("du", du, self.n_nodes)
        _check_node_array("out", out, self.n_nodes)
        out.fill(0.0)
        self._law.consistent_tangent_matvec(du, out)

    def system_matvec(self, du, k_scale: float, c_scale: float, out, consistent: bool = False) -> None:
        """out = k_scale K_t du + c_scale C du in one pass over the rest tensors where possible
        (uniform Kelvin-Voigt damping C = tau K_0 folds into the rest stiffness product)."""
        law = self._law
        if not law.splits_rest_stiffness:
            (self.consistent_tangent_matvec if consistent else self.tangent_matvec)(du, out)
            out *= k_scale
            if c_scale != 0.0 and self.has_damping:
                tmp = self._work
                self.damping_matvec(du, tmp)
                tmp *= c_scale
                out += tmp
            return
        out.fill(0.0)
        k = self.stiffness
        rest_scale = k_scale + (c_scale * self._tau if self._damping is None else 0.0)
        kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, du, rest_scale, out)
        law.add_tangent_correction(du, k_scale, out, consistent)
        if self._damping is not None and c_scale != 0.0:
            c = self._damping
            kernels.tensor_mass_matvec(c.vertex, c.edges, c.edge_tensors, du, c_scale, out)

    @property
    def splits_rest_stiffness(self) -> bool:
        """True when K_t = K_0 + a correction (linear, ETMM): add_forces(rest_v_scale=...) and
        add_tangent_correction are available."""
        return bool(self._law.splits_rest_stiffness)

    def add_tangent_correction(self, du, scale: float, out, consistent: bool = False) -> None:
        """out += scale (K_t - K_0) du at the last add_forces state (consistent or secant tangent)."""
        self._law.add_tangent_correction(du, scale, out, consistent)

    def tangent_blocks(self):
        """(active element ids (k,), blocks (k, 4, 4, 3, 3)): the consistent tangent minus the rest
        stiffness at the last add_forces state, per element and local vertex pair, or None when
        the law does not assemble it (hyperelastic).  ``blocks[c, j, k]`` couples local vertex j
        (row) to k (column) of active element ``ids[c]`` (rows of :attr:`active_tets`)."""
        return self._law.tangent_blocks()

    def nonlinear_element_ids(self):
        """Active element ids (rows of :attr:`active_tets`) whose tangent differs from the rest
        stiffness at the last add_forces state; None when every element does (hyperelastic)."""
        return self._law.nonlinear_element_ids()

    @property
    def active_tets(self) -> np.ndarray:
        """(m_active, 4) the active tets, in the order tangent_blocks numbers them."""
        return self._tets

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
        return self._law.stiffness_diagonal()

    def stiffness_matrix(self):
        """Rest (linear) stiffness as scipy CSR (3n x 3n)."""
        return tensors_to_csr(self.stiffness)

    # ------------------------------------------------------------------------------------------
    # topology change
    # ------------------------------------------------------------------------------------------
    def remove_elements(self, ids) -> np.ndarray:
        """Take active elements ``ids`` (rows of :attr:`active_tets`) out of the wall: their blocks
        leave the vertex and edge tensors (stiffness and damping) they were summed into, and their
        gradients and volumes become zero, so no kernel (forces, tangents, energies, strains,
        masses) sees them again. Only their own vertices and edges change. Returns the nodes left
        without any element (to be taken out of the dynamics by the model)."""
        m_a = self._tets.shape[0]
        try:
            ids = np.unique(np.asarray(ids, dtype=np.int64).reshape(-1))
        except (TypeError, ValueError):
            raise ForceFieldError(f"remove_elements: ids must be integers, rows of active_tets (got {ids!r})") from None
        if ids.size and (ids[0] < 0 or ids[-1] >= m_a):
            raise ForceFieldError(f"remove_elements: element ids must lie in [0, {m_a}) (got {ids[0]}..{ids[-1]}): "
                                  "they are rows of active_tets")
        ids = ids[~self.removed[ids]]
        if ids.size == 0:
            return np.zeros(0, dtype=np.int64)
        remove_element_tensors(self.stiffness, self._tets, self._grads, self._volumes, self._lam, self._mu, ids)
        if self._damping is not None:
            remove_element_tensors(self._damping, self._tets, self._grads, self._volumes, self._lam_v, self._mu_v,
                                   ids)
        self.removed[ids] = True
        self._grads[ids] = 0.0
        self._volumes[ids] = 0.0
        self._candidates = self._candidates[~self.removed[self._candidates]]
        self._law.remove_elements(ids)
        nodes = self._tets[ids].reshape(-1)
        np.subtract.at(self._node_elements, nodes, 1)
        return np.unique(nodes[self._node_elements[nodes] == 0])

    # ------------------------------------------------------------------------------------------
    # diagnostics
    # ------------------------------------------------------------------------------------------
    def strain_energy(self, u) -> float:
        """Elastic energy: linear 1/2 u.Ku; etmm the secant energy 1/2 sum (1+phi_T) u_T.K_T u_T;
        hyperelastic sum V W(F)."""
        _check_node_array("u", u, self.n_nodes)
        return self._law.strain_energy(u)

    def element_max_strain(self, u) -> np.ndarray:
        """(m_active,) largest principal Green strain magnitude per active element."""
        _check_node_array("u", u, self.n_nodes)
        out = np.empty(self._tets.shape[0])
        kernels.element_max_green_strain(self._tets, self._grads, u, out)
        return out

    def max_strain(self, u) -> float:
        """Max principal Green strain magnitude over the active elements."""
        _check_node_array("u", u, self.n_nodes)
        return float(kernels.max_green_strain(self._tets, self._grads, u))

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
        return self._law.stiffening_margin(strain)

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

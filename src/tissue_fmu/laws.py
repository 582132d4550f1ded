"""Material laws of the tensor-mass force field, one class each behind one protocol.

A law owns what differs between the laws: the elastic force, the tangents, the stiffness
diagonal, the energy, the stiffening margin of the explicit time step, and the element
matrices of its tangent beyond the rest stiffness (for an assembled, factorised tangent).
The shared element data (tets, shape gradients, volumes, Lame coefficients, rest tensors,
uniform Kelvin-Voigt ratio ``tau``) live on the :class:`~tissue_fmu.forcefield.TensorMassForceField`
the law is built for; the law never validates (the force field does).

``LAW_CLASSES`` maps each law name to its class; ``materials.LAWS`` is the one list of names
(TissueParameters and the force field check against it).
"""

from __future__ import annotations

import numpy as np

from . import kernels
from .materials import LAWS as LAW_NAMES
from .materials import rv_stiffening_ratio
from .precompute import edge_element_adjacency, edge_screen_limits

__all__ = ["MaterialLaw", "LinearLaw", "ETMMLaw", "HyperelasticLaw", "LAW_CLASSES", "make_law"]

# ETMM: above this fraction of candidate (non-linear-capable) tets, candidates are pre-screened
# by edge strains fused into the linear pass instead of checking every candidate tet.
SCREEN_MIN_CANDIDATE_FRACTION = 0.3


class MaterialLaw:
    """Protocol and shared behaviour of a law (the linear tensor-mass law by default).

    ``add_forces(u, v, out)``: out += elastic(u) (+ the uniform viscous force -tau K v when v is
    given); ``tangent_matvec(du, out)``: out += K_t du (symmetric: secant for ETMM);
    ``consistent_tangent_matvec(du, out)``: out += dK/du du exactly (may be non-symmetric);
    ``tangent_blocks()``: (element ids, (k, 4, 4, 3, 3) blocks) of consistent tangent minus rest
    stiffness at the last state, or None when the law cannot assemble it.
    """

    name = "linear"
    nonlinear = False

    def __init__(self, ff):
        self.ff = ff

    @property
    def nonlinear_fraction(self) -> float:
        return 0.0

    def add_forces(self, u, v, out, rest_v_scale: float = 0.0) -> None:
        """``rest_v_scale``: also out -= rest_v_scale K_0 v, in the same pass (the implicit step's
        right-hand side folds its -h K_0 v in here; laws with ``splits_rest_stiffness`` only)."""
        ff = self.ff
        k = ff.stiffness
        scale = self._v_scale(v, rest_v_scale)
        if scale != 0.0:
            w = ff._work
            np.multiply(v, scale, out=w)
            w += u
            kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, w, -1.0, out)
        else:
            kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, u, -1.0, out)

    def _v_scale(self, v, rest_v_scale: float) -> float:
        """Coefficient of -K_0 v in the force: the uniform viscosity tau plus ``rest_v_scale``."""
        if v is None:
            return 0.0
        return (self.ff._tau if self.ff._tau > 0.0 else 0.0) + rest_v_scale

    def tangent_matvec(self, du, out) -> None:
        k = self.ff.stiffness
        kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, du, 1.0, out)

    def consistent_tangent_matvec(self, du, out) -> None:
        self.tangent_matvec(du, out)

    #: True when the tangent is the rest stiffness plus add_tangent_correction (not hyperelastic).
    splits_rest_stiffness = True

    def add_tangent_correction(self, du, scale, out, consistent: bool) -> None:
        """out += scale * (K_t - K_0) du (consistent or secant tangent); nothing for the linear law."""

    def nonlinear_element_ids(self):
        """Active element ids whose tangent differs from the rest stiffness (None: all, unassembled)."""
        return np.zeros(0, dtype=np.int64)

    def tangent_blocks(self):
        """No correction: the rest stiffness is the tangent."""
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4, 3, 3))

    def stiffness_diagonal(self) -> np.ndarray:
        return np.ascontiguousarray(np.diagonal(self.ff.stiffness.vertex, axis1=1, axis2=2))

    def strain_energy(self, u) -> float:
        k = self.ff.stiffness
        ku = np.zeros_like(u)
        kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, u, 1.0, ku)
        return 0.5 * float(np.einsum("ij,ij->", u, ku))

    def stiffening_margin(self, strain: float) -> float:
        return 1.0

    def remove_elements(self, ids) -> None:
        """Elements ``ids`` left the wall (the force field zeroed their gradients and volumes and
        took them out of the rest tensors); a law with its own per-element state forgets them."""

    def _uniform_damping(self, v, out, rest_v_scale: float = 0.0) -> None:
        scale = self._v_scale(v, rest_v_scale)
        if scale != 0.0:
            k = self.ff.stiffness
            kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, v, -scale, out)


class LinearLaw(MaterialLaw):
    """f = -K u with the rest vertex/edge tensors."""


class _StiffeningLaw(MaterialLaw):
    """Shared by the non-linear laws: the uniaxial Raghavan-Vorp stiffening margin."""

    nonlinear = True

    def stiffening_margin(self, strain: float) -> float:
        green = np.linspace(-strain, strain, 401)
        stretch = np.sqrt(1.0 + 2.0 * green)
        r = rv_stiffening_ratio(green, self.ff._beta_over_alpha)
        nominal = r * (stretch - 1.0)
        tangent = np.gradient(nominal, stretch)
        return max(float(tangent.max()), float(r.max()), 1.0)


class ETMMLaw(_StiffeningLaw):
    """Linear + the per-element secant correction -(dlam A + dmu B) u_T above the strain threshold.

    Only the candidate tets are examined (edge-strain pre-screen when most tets are candidates);
    the tangents touch only the super-threshold elements (their data is taken once per state,
    at the first tangent product after add_forces).
    """

    name = "etmm"

    def __init__(self, ff):
        super().__init__(ff)
        m_a = ff._tets.shape[0]
        self._phi = np.zeros(m_a)
        self._nonlinear_ids = np.zeros(m_a, dtype=np.int64)
        self._nonlinear_count = 0
        self._candidate_mask = np.zeros(m_a, dtype=np.uint8)  # 1 for the tets that may turn non-linear
        self._candidate_mask[ff._candidates] = 1
        # Consistent-tangent data of the super-threshold elements (etmm_tangent_data), grown on demand.
        self._tangent_stale = True
        self._tangent_p = np.zeros(0)
        self._tangent_wg = np.zeros((0, 4, 3))
        self._tangent_ku = np.zeros((0, 4, 3))
        # Edge screen: edges whose Green strain could mean an element over the threshold are
        # flagged during the linear pass; only the tets around them are examined exactly.
        # Measured (benchmarks/bench_tissue_kernels.py): the fused edge screen costs ~40 % of a linear
        # pass, checking a tet directly ~4 % of a linear pass per 1 % of tets, so the screen pays
        # only when most tets are candidates.
        self.screened = (ff.nonlinear_strain_threshold > 0.0
                         and ff._candidates.size > SCREEN_MIN_CANDIDATE_FRACTION * m_a)
        if self.screened:
            k = ff.stiffness
            self._edge_screen = edge_screen_limits(ff._points, ff._tets, k.edges, k.element_edges,
                                                   ff.nonlinear_strain_threshold)
            self._edge_elem_ptr, self._edge_elem_ids = edge_element_adjacency(k.element_edges, k.edges.shape[0])
            self._stamp = np.zeros(m_a, dtype=np.int64)
            self._stamp_value = 0
            self._flagged = np.empty(k.edges.shape[0], dtype=np.int64)
            self._examined = np.empty(m_a, dtype=np.int64)

    @property
    def nonlinear_fraction(self) -> float:
        return self._nonlinear_count / self._phi.shape[0]

    def remove_elements(self, ids) -> None:
        self._candidate_mask[ids] = 0  # never examined again (the edge screen reads this mask)

    def add_forces(self, u, v, out, rest_v_scale: float = 0.0) -> None:
        ff = self.ff
        k = ff.stiffness
        self._phi[self._nonlinear_ids[: self._nonlinear_count]] = 0.0  # forget the last state
        if self.screened:
            n_flagged = kernels.tensor_mass_force_screened(k.vertex, k.edges, k.edge_tensors,
                                                           self._edge_screen, u, out, self._flagged)
            self._stamp_value += 1
            n_examined = kernels.elements_of_flagged_edges(self._flagged, n_flagged, self._edge_elem_ptr,
                                                           self._edge_elem_ids, self._candidate_mask,
                                                           self._stamp, self._stamp_value, self._examined)
            examined = self._examined[:n_examined]
        else:
            kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, u, -1.0, out)
            examined = ff._candidates
        self._nonlinear_count = kernels.etmm_correction(
            ff._tets, ff._grads, ff._volumes, ff._lam, ff._mu, examined, u,
            ff.nonlinear_strain_threshold, ff._beta_over_alpha, self._phi, self._nonlinear_ids, out)
        ff.screened_fraction = examined.shape[0] / self._phi.shape[0]
        self._tangent_stale = True
        self._uniform_damping(v, out, rest_v_scale)

    def tangent_matvec(self, du, out) -> None:
        super().tangent_matvec(du, out)
        if self._nonlinear_count:
            ff = self.ff
            kernels.scaled_elements_matvec(ff._tets, ff._grads, ff._volumes, ff._lam, ff._mu,
                                           self._nonlinear_ids, self._nonlinear_count, self._phi, du, 1.0, out)

    def add_tangent_correction(self, du, scale, out, consistent: bool) -> None:
        if not self._nonlinear_count:
            return
        ff = self.ff
        if consistent:
            ids, count, p, wg, ku = self._tangent_data()
            kernels.etmm_nonlinear_tangent_matvec(ff._tets, ff._grads, ff._volumes, ff._lam, ff._mu, ids, count,
                                                  p, wg, ku, du, scale, out)
        else:
            kernels.scaled_elements_matvec(ff._tets, ff._grads, ff._volumes, ff._lam, ff._mu,
                                           self._nonlinear_ids, self._nonlinear_count, self._phi, du, scale, out)

    def _tangent_data(self):
        """(ids, count, p, wg, ku) of the super-threshold elements at the last add_forces state."""
        count = self._nonlinear_count
        if self._tangent_stale:
            if self._tangent_p.shape[0] < count:
                size = max(count, 2 * self._tangent_p.shape[0])
                self._tangent_p = np.zeros(size)
                self._tangent_wg = np.zeros((size, 4, 3))
                self._tangent_ku = np.zeros((size, 4, 3))
            ff = self.ff
            kernels.etmm_tangent_data(ff._tets, ff._grads, ff._volumes, ff._lam, ff._mu, self._nonlinear_ids,
                                      count, ff._u_last, ff.nonlinear_strain_threshold, ff._beta_over_alpha,
                                      self._tangent_p, self._tangent_wg, self._tangent_ku)
            self._tangent_stale = False
        return self._nonlinear_ids, count, self._tangent_p, self._tangent_wg, self._tangent_ku

    def consistent_tangent_matvec(self, du, out) -> None:
        MaterialLaw.tangent_matvec(self, du, out)
        if self._nonlinear_count:
            ff = self.ff
            ids, count, p, wg, ku = self._tangent_data()
            kernels.etmm_nonlinear_tangent_matvec(ff._tets, ff._grads, ff._volumes, ff._lam, ff._mu, ids, count,
                                                  p, wg, ku, du, 1.0, out)

    def nonlinear_element_ids(self):
        return self._nonlinear_ids[: self._nonlinear_count]

    def tangent_blocks(self):
        count = self._nonlinear_count
        blocks = np.empty((count, 4, 4, 3, 3))
        if count:
            ff = self.ff
            ids, count, p, wg, ku = self._tangent_data()
            kernels.etmm_nonlinear_tangent_blocks(ff._grads, ff._volumes, ff._lam, ff._mu, ids, count, p, wg, ku,
                                                  blocks)
        return self._nonlinear_ids[:count].copy(), blocks

    def stiffness_diagonal(self) -> np.ndarray:
        diag = super().stiffness_diagonal()
        if self._nonlinear_count:
            ff = self.ff
            kernels.scaled_elements_diagonal(ff._tets, ff._grads, ff._volumes, ff._lam, ff._mu,
                                             self._nonlinear_ids, self._nonlinear_count, self._phi, diag)
        return diag

    def strain_energy(self, u) -> float:
        """Secant energy 1/2 sum (1 + phi_T) u_T.K_T u_T."""
        ff = self.ff
        return float(kernels.etmm_secant_energy(ff._tets, ff._grads, ff._volumes, ff._lam, ff._mu,
                                                self._candidate_mask, u, ff.nonlinear_strain_threshold,
                                                ff._beta_over_alpha))

    def stiffening_margin(self, strain: float) -> float:
        margin = super().stiffening_margin(strain)
        if self._nonlinear_count:
            margin = max(margin, 1.0 + float(self._phi.max()))
        return margin


class HyperelasticLaw(_StiffeningLaw):
    """Finite-strain compressible Raghavan-Vorp (slow accuracy reference): exact symmetric tangent."""

    name = "hyperelastic"

    def __init__(self, ff):
        super().__init__(ff)
        # Per-element constants (small-strain moduli = the element's lam, mu).
        self._alpha = 0.5 * ff._mu
        self._beta = self._alpha * ff._beta_over_alpha
        self._kappa = ff._lam + (2.0 / 3.0) * ff._mu

    def add_forces(self, u, v, out) -> None:
        ff = self.ff
        kernels.hyperelastic_forces(ff._tets, ff._grads, ff._volumes, self._alpha, self._beta, self._kappa, u, out)
        self._uniform_damping(v, out)

    def tangent_matvec(self, du, out) -> None:
        ff = self.ff
        kernels.hyperelastic_tangent_matvec(ff._tets, ff._grads, ff._volumes, self._alpha, self._beta, self._kappa,
                                            ff._u_last, du, 1.0, out)

    splits_rest_stiffness = False

    def nonlinear_element_ids(self):
        return None

    def tangent_blocks(self):
        return None  # every element: solved with the rest factorisation as preconditioner

    def strain_energy(self, u) -> float:
        ff = self.ff
        return float(kernels.hyperelastic_energy(ff._tets, ff._grads, ff._volumes, self._alpha, self._beta,
                                                 self._kappa, u))


LAW_CLASSES = {"linear": LinearLaw, "etmm": ETMMLaw, "hyperelastic": HyperelasticLaw}
assert tuple(LAW_CLASSES) == LAW_NAMES


def make_law(name: str, ff) -> MaterialLaw:
    return LAW_CLASSES[name](ff)

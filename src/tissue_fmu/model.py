"""The tissue model: mesh + material + boundary + integrator, advanced by ``step(t, dt)``.

Plain Python state, no FMI imports: the FMU wrapper declares variables and delegates here.
All validation happens in this layer (and :meth:`TissueParameters.validate`); the force field
kernels never see bad input.  Units SI, node-major (n, 3) arrays.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from . import kernels
from ._checks import is_finite_real, is_integer
from .forcefield import TensorMassForceField
from .errors import StabilityError, TissueError
from .integrators import BackwardEuler, JacobiPreconditioner, StepStatistics, SymplecticEuler
from .factorization import RestFactorization, TangentFactorization
from .materials import LAWS
from .mesh import TetMesh, aaa_mesh, load_mesh
from .failure import failed_elements, failure_stretch
from .precompute import signed_volumes

logger = logging.getLogger(__name__)

__all__ = ["TissueError", "StabilityError", "TissueParameters", "TissueModel"]

INTEGRATORS = ("explicit", "implicit")
PRECONDITIONERS = ("factorized", "jacobi")
#: "exact": each implicit step solved to cg_tolerance, its preconditioner kept equal to the step matrix
#: inside the frame; "budgeted": at most budget_iterations Krylov iterations per frame, preconditioned
#: by the rest factor (tissue_fmu.factorization.RestFactorization), the residual reported.
IMPLICIT_STEPS = ("exact", "budgeted")
# A step that moves a node farther than this many mesh diameters has diverged.
DIVERGENCE_FACTOR = 10.0
#: Green strain above which a warning says the laws are used outside their range (E = 1 is a
#: 73 % stretch; the Raghavan-Vorp data behind the ETMM go to about 30 %).
STRAIN_WARNING = 1.0
#: Green strain above which (or any inverted tetrahedron) a step is reported as diverged: no
#: tissue survives a 4.6x stretch, so the state no longer describes a wall.
STRAIN_DIVERGENCE = 10.0


def _check_number(name: str, value, *, minimum=None, minimum_inclusive=True, maximum=None,
                  maximum_inclusive=True, hint: str) -> None:
    """Raise TissueError naming ``name`` unless ``value`` is a finite real number in range."""
    if not is_finite_real(value):
        raise TissueError(f"{name} must be a finite number (got {value!r}): {hint}")
    if minimum is not None and (value < minimum if minimum_inclusive else value <= minimum):
        op = ">=" if minimum_inclusive else ">"
        raise TissueError(f"{name} must be {op} {minimum} (got {value!r}): {hint}")
    if maximum is not None and (value > maximum if maximum_inclusive else value >= maximum):
        op = "<=" if maximum_inclusive else "<"
        raise TissueError(f"{name} must be {op} {maximum} (got {value!r}): {hint}")


def _check_sphere(name: str, value) -> None:
    if value is None:
        return
    hint = "give (cx, cy, cz, radius) in m, e.g. (0.0, 0.0, 0.065, 0.03), or None for the whole mesh"
    try:
        entries = [float(x) for x in value]
    except (TypeError, ValueError):
        raise TissueError(f"{name} must be a sequence of 4 numbers (got {value!r}): {hint}") from None
    if len(entries) != 4 or not all(math.isfinite(x) for x in entries):
        raise TissueError(f"{name} must be 4 finite numbers (got {value!r}): {hint}")
    if entries[3] <= 0.0:
        raise TissueError(f"{name} radius must be > 0 (got {entries[3]!r}): {hint}")


@dataclass
class TissueParameters:
    """Material, integrator and boundary parameters of a tissue model.

    Defaults: AAA wall with the Raghavan-Vorp law (alpha = 0.174 MPa, beta = 1.881 MPa, so
    small-strain E = 6 alpha = 1.044 MPa), nearly incompressible, implicit integration at the
    30 Hz frame rate, clamped at the aortic inlet and outlet.
    """

    young_modulus: float = 1.044e6  # Pa
    poisson_ratio: float = 0.45
    density: float = 1120.0  # kg/m^3
    viscosity: float = 0.0  # Pa s, Kelvin-Voigt viscosity of the viscous tensor
    law: str = "etmm"  # "linear", "etmm" (linear + non-linear correction) or "hyperelastic"
    integrator: str = "implicit"  # "implicit" (backward Euler + CG) or "explicit" (symplectic Euler)
    substeps: int | str = "auto"  # explicit only: substeps per step, or "auto"
    cg_tolerance: float = 1e-6  # relative residual of the implicit solve
    cg_max_iterations: int = 1000
    preconditioner: str = "factorized"  # implicit: "factorized" (the step matrix, kept exact) or "jacobi"
    implicit_step: str = "exact"  # implicit: "exact" or "budgeted" (IMPLICIT_STEPS)
    budget_iterations: int = 4  # budgeted: Krylov iterations per frame (each one factor solve)
    clamp: tuple[str, ...] = ("inlet", "outlet")  # node sets held at rest
    active_region: tuple[float, float, float, float] | None = None  # (cx, cy, cz, radius) m
    nonlinear_region: tuple[float, float, float, float] | None = None  # where ETMM may correct
    nonlinear_strain_threshold: float = 0.05
    rv_alpha: float = 0.174e6  # Pa, Raghavan-Vorp alpha
    rv_beta: float = 1.881e6  # Pa, Raghavan-Vorp beta
    # Pa: elements whose equivalent uniaxial Cauchy stress reaches it fail and leave the wall
    # (tissue_fmu.failure); 0: the wall never fails. tissue_fmu.failure.DEFAULT_FAILURE_STRESS is the
    # measured value; the FMUs do not expose it until Contact follows a changing surface (issue 32).
    failure_stress: float = 0.0

    def validate(self) -> None:
        """Raise TissueError (a ValueError) naming the first bad parameter and the fix."""
        _check_number("young_modulus", self.young_modulus, minimum=0.0, minimum_inclusive=False,
                      hint="give Young's modulus in Pa, e.g. 1.044e6 for the AAA wall")
        _check_number("poisson_ratio", self.poisson_ratio, minimum=-1.0, minimum_inclusive=False,
                      maximum=0.5, maximum_inclusive=False,
                      hint="Poisson's ratio must lie in (-1, 0.5), e.g. 0.45 for the AAA wall")
        _check_number("density", self.density, minimum=0.0, minimum_inclusive=False,
                      hint="give the density in kg/m^3, e.g. 1120")
        _check_number("viscosity", self.viscosity, minimum=0.0,
                      hint="give the viscosity in Pa s (0 for none)")
        if self.law not in LAWS:
            raise TissueError(f"law must be one of {LAWS} (got {self.law!r})")
        if self.integrator not in INTEGRATORS:
            raise TissueError(f"integrator must be one of {INTEGRATORS} (got {self.integrator!r})")
        if self.substeps != "auto":
            if not is_integer(self.substeps):
                raise TissueError(f"substeps must be an integer >= 1 or 'auto' (got {self.substeps!r})")
            if self.substeps < 1:
                raise TissueError(f"substeps must be >= 1 (got {self.substeps!r}): or use 'auto'")
        _check_number("cg_tolerance", self.cg_tolerance, minimum=0.0, minimum_inclusive=False,
                      maximum=1.0, maximum_inclusive=False,
                      hint="give the relative CG residual, e.g. 1e-6")
        if not is_integer(self.cg_max_iterations) or self.cg_max_iterations < 1:
            raise TissueError(f"cg_max_iterations must be an integer >= 1 (got {self.cg_max_iterations!r}), e.g. 1000")
        if self.preconditioner not in PRECONDITIONERS:
            raise TissueError(f"preconditioner must be one of {PRECONDITIONERS} (got {self.preconditioner!r})")
        if self.implicit_step not in IMPLICIT_STEPS:
            raise TissueError(f"implicit_step must be one of {IMPLICIT_STEPS} (got {self.implicit_step!r})")
        if not is_integer(self.budget_iterations) or self.budget_iterations < 1:
            raise TissueError(f"budget_iterations must be an integer >= 1 (got {self.budget_iterations!r}), e.g. 4: "
                              "the Krylov iterations a budgeted step may spend per frame")
        if isinstance(self.clamp, str) or not all(isinstance(name, str) for name in self.clamp):
            raise TissueError(
                f"clamp must be a sequence of node set names (got {self.clamp!r}), e.g. ('inlet', 'outlet')"
            )
        _check_sphere("active_region", self.active_region)
        _check_sphere("nonlinear_region", self.nonlinear_region)
        _check_number("nonlinear_strain_threshold", self.nonlinear_strain_threshold, minimum=0.0,
                      hint="give the Green strain above which ETMM corrects an element, e.g. 0.05")
        _check_number("rv_alpha", self.rv_alpha, minimum=0.0, minimum_inclusive=False,
                      hint="Raghavan-Vorp alpha in Pa, e.g. 0.174e6")
        _check_number("rv_beta", self.rv_beta, minimum=0.0,
                      hint="Raghavan-Vorp beta in Pa, e.g. 1.881e6")
        _check_number("failure_stress", self.failure_stress, minimum=0.0,
                      hint="the wall's failure stress in Pa, e.g. 1.0e6, or 0 for a wall that never fails")


def _elements_in_sphere(mesh: TetMesh, sphere) -> np.ndarray:
    """(m,) bool: elements whose centroid lies within the sphere (cx, cy, cz, radius)."""
    centre = np.asarray(sphere[:3], dtype=np.float64)
    centroids = mesh.points[mesh.tets].mean(axis=1)
    return np.einsum("ij,ij->i", centroids - centre, centroids - centre) <= float(sphere[3]) ** 2


def _element_selection(mesh: TetMesh, selection, index: int) -> np.ndarray:
    """A material override's element selection -> (m,) bool mask."""
    where = f"materials[{index}]"
    m = mesh.n_tets
    if isinstance(selection, str):
        if selection not in mesh.element_sets:
            raise TissueError(
                f"{where}: unknown element set {selection!r}; the mesh has {sorted(mesh.element_sets)}"
            )
        mask = np.zeros(m, dtype=bool)
        mask[mesh.element_sets[selection]] = True
        return mask
    array = np.asarray(selection)
    if array.dtype == bool:
        if array.shape != (m,):
            raise TissueError(f"{where}: element mask must have shape ({m},) (got {array.shape})")
        return array.copy()
    if array.ndim == 1 and np.issubdtype(array.dtype, np.integer):
        if array.size and (array.min() < 0 or array.max() >= m):
            raise TissueError(f"{where}: element ids must lie in [0, {m}) (got {array.min()}..{array.max()})")
        mask = np.zeros(m, dtype=bool)
        mask[array] = True
        return mask
    raise TissueError(
        f"{where}: the element selection must be a bool mask ({m},), integer element ids or an element set name"
    )


class TissueModel:
    """Tensor-mass soft tissue advanced in time by ``step(t, dt)``.

    Parameters
    ----------
    mesh : TetMesh
    params : TissueParameters (validated here)
    materials : optional list of ``(elements, young_modulus, poisson_ratio)`` overrides applied in
        order; ``elements`` is a bool mask (m,), integer element ids or an element set name
        (e.g. a stiffer calcified patch: ``[(calcified_mask, 10e6, 0.45)]``).

    Clamped nodes (``params.clamp`` node sets) and frozen nodes stay at rest.  With an active
    region (elements whose centroid lies in the sphere ``params.active_region``) only active
    elements are simulated; every node of an inactive element is frozen, i.e. the nodes no
    active element touches and the interface, where the inactive tissue holds the active part
    like a clamp.  Contact forces act on surface nodes and are held until changed (forces on
    fixed nodes are taken by the support and move nothing).
    """

    def __init__(self, mesh: TetMesh, params: TissueParameters | None = None, materials=None):
        if not isinstance(mesh, TetMesh):
            raise TissueError(f"mesh must be a TetMesh (got {type(mesh).__name__}): build one with aaa_mesh() or load_mesh(path)")
        params = TissueParameters() if params is None else params
        params.validate()
        self.mesh = mesh
        self.params = params
        n, m = mesh.n_nodes, mesh.n_tets

        for name in params.clamp:
            if name not in mesh.node_sets:
                raise TissueError(
                    f"clamp: unknown node set {name!r}; this mesh has node sets {sorted(mesh.node_sets)}"
                )

        self.young_modulus, self.poisson_ratio = self._element_materials(materials)

        self.active_elements = (
            np.ones(m, dtype=bool) if params.active_region is None else _elements_in_sphere(mesh, params.active_region)
        )
        if not self.active_elements.any():
            raise TissueError(
                f"active_region {params.active_region!r} contains no element centroid: enlarge the radius or move the centre"
            )
        nonlinear = None if params.nonlinear_region is None else _elements_in_sphere(mesh, params.nonlinear_region)

        uniform = (np.all(self.young_modulus == self.young_modulus[0])
                   and np.all(self.poisson_ratio == self.poisson_ratio[0]))
        self.force_field = TensorMassForceField(
            mesh.points, mesh.tets,
            float(self.young_modulus[0]) if uniform else self.young_modulus,
            float(self.poisson_ratio[0]) if uniform else self.poisson_ratio,
            law=params.law,
            viscosity=float(params.viscosity),
            rv_alpha=float(params.rv_alpha),
            rv_beta=float(params.rv_beta),
            nonlinear_strain_threshold=float(params.nonlinear_strain_threshold),
            nonlinear_elements=nonlinear,
            active_elements=None if params.active_region is None else self.active_elements,
        )
        self.masses = np.asarray(self.force_field.lumped_masses(float(params.density)), dtype=np.float64)

        clamped = np.zeros(n, dtype=bool)
        for name in params.clamp:
            clamped[mesh.node_sets[name]] = True
        # Frozen: nodes no active element touches (they have no mass or stiffness), and the
        # nodes on the interface with the inactive (rigid, at rest) tissue.  Freeing the
        # interface would leave the active region floating unless a clamp set lies inside it
        # (a cantilever's tip region drifts 0.7 m in 10 steps).
        frozen = np.ones(n, dtype=bool)
        frozen[mesh.tets[self.active_elements].ravel()] = False
        frozen[mesh.tets[~self.active_elements].ravel()] = True
        self.clamped = clamped
        self.frozen = frozen
        self.fixed = clamped | frozen
        if self.fixed.all():
            raise TissueError("every node is clamped or outside the active region: nothing can move; "
                              "enlarge active_region or clamp fewer node sets")

        self._mesh_size = float(np.linalg.norm(mesh.points.max(axis=0) - mesh.points.min(axis=0)))
        self.surface_nodes, self.surface_triangles = mesh.surface()
        self.n_surface = int(self.surface_nodes.shape[0])

        self.time = 0.0
        self.displacement = np.zeros((n, 3))
        self.velocity = np.zeros((n, 3))
        self._external_force = np.zeros((n, 3))
        self._statistics = StepStatistics()
        self._critical_time_step: float | None = None
        self._max_strain = 0.0          # of the current displacement, computed once per step
        self._strain_warned = False     # the extreme-strain warning is given once
        self.last_dt: float | None = None  # size of the last step (default of compliance())
        self._compliance_factors: dict = {}  # dt -> TangentFactorization, when the integrator's cannot serve
        # Failure (tissue_fmu.failure): the stretch limit, the elements that failed (mesh rows), the
        # strain energy they held when they failed, and one record per failure
        self._failure_stretch = (None if params.failure_stress == 0.0 else
                                 failure_stretch(float(params.failure_stress), float(params.rv_alpha),
                                                 float(params.rv_beta)))
        self.failed = np.zeros(m, dtype=bool)
        self.released_energy = 0.0
        self.failures: list[dict] = []
        self.integrator = self._make_integrator()
        logger.info(
            "tissue model: %d nodes (%d fixed), %d/%d active tets, %d surface nodes, law=%s, integrator=%s",
            n, int(self.fixed.sum()), int(self.active_elements.sum()), m, self.n_surface, params.law,
            params.integrator if params.integrator == "explicit" else f"implicit/{params.preconditioner}",
        )

    # ----------------------------------------------------------------------------------
    # Construction helpers
    # ----------------------------------------------------------------------------------

    @classmethod
    def from_parameters(cls, params: TissueParameters | None = None, *, mesh_file=None, materials=None,
                        **aaa_mesh_kwargs) -> "TissueModel":
        """Build the model on the built-in AAA mesh (``aaa_mesh(**aaa_mesh_kwargs)``) or a mesh file."""
        if mesh_file is not None:
            if aaa_mesh_kwargs:
                raise TissueError(f"give either mesh_file or AAA mesh sizes, not both (got {sorted(aaa_mesh_kwargs)})")
            mesh = load_mesh(mesh_file)
        else:
            mesh = aaa_mesh(**aaa_mesh_kwargs)
        return cls(mesh, params, materials)

    @classmethod
    def default_aaa(cls) -> "TissueModel":
        """The default AAA wall: ``aaa_mesh()`` defaults and ``TissueParameters()`` defaults."""
        return cls.from_parameters()

    def _element_materials(self, materials) -> tuple[np.ndarray, np.ndarray]:
        m = self.mesh.n_tets
        young = np.full(m, float(self.params.young_modulus))
        poisson = np.full(m, float(self.params.poisson_ratio))
        if materials is None:
            return young, poisson
        if isinstance(materials, (str, bytes)) or not hasattr(materials, "__iter__"):
            raise TissueError("materials must be a list of (elements, young_modulus, poisson_ratio) tuples")
        for index, entry in enumerate(materials):
            try:
                selection, e_value, nu_value = entry
            except (TypeError, ValueError):
                raise TissueError(
                    f"materials[{index}] must be a tuple (elements, young_modulus, poisson_ratio) (got {entry!r})"
                ) from None
            mask = _element_selection(self.mesh, selection, index)
            _check_number(f"materials[{index}] young_modulus", e_value, minimum=0.0, minimum_inclusive=False,
                          hint="give Young's modulus in Pa, e.g. 10e6 for a calcified patch")
            _check_number(f"materials[{index}] poisson_ratio", nu_value, minimum=-1.0, minimum_inclusive=False,
                          maximum=0.5, maximum_inclusive=False, hint="Poisson's ratio must lie in (-1, 0.5)")
            young[mask] = float(e_value)
            poisson[mask] = float(nu_value)
        return young, poisson

    def _make_integrator(self):
        p = self.params
        if p.integrator == "explicit":
            return SymplecticEuler(
                self.force_field, self.masses, self.fixed, p.substeps,
                critical_time_step=self._critical_step(),
            )
        budgeted = p.implicit_step == "budgeted"
        if p.preconditioner == "jacobi":
            preconditioner = JacobiPreconditioner(self.force_field, self.masses, self.fixed)
        elif budgeted:
            preconditioner = RestFactorization(self.force_field, self.masses, self.fixed)
        else:
            preconditioner = TangentFactorization(self.force_field, self.masses, self.fixed)
        return BackwardEuler(
            self.force_field, self.masses, self.fixed, p.cg_tolerance,
            int(p.budget_iterations) if budgeted else p.cg_max_iterations,
            viscous=p.viscosity > 0.0, preconditioner=preconditioner, budgeted=budgeted,
        )

    def _critical_step(self) -> float:
        if self._critical_time_step is None:
            # Nodes outside the active region have no mass; they carry no stiffness either.
            masses = np.where(self.masses > 0.0, self.masses, 1.0)
            self._critical_time_step = float(self.force_field.critical_time_step(masses))
        return self._critical_time_step

    # ----------------------------------------------------------------------------------
    # Inputs and stepping
    # ----------------------------------------------------------------------------------

    def prepare(self, dt: float) -> None:
        """Do before the first step what it would otherwise pay for: the kernels' compilation (or
        cache load) and the implicit step's rest factorisation for steps of ``dt``. Changes no result."""
        if not is_finite_real(dt) or dt <= 0.0:
            raise TissueError(f"dt must be a finite number > 0 (got {dt!r}), e.g. 1/30")
        self.force_field.add_forces(self.displacement, self.velocity, np.zeros_like(self.displacement))
        preconditioner = getattr(self.integrator, "preconditioner", None)
        if isinstance(preconditioner, TangentFactorization):
            preconditioner.prepare(float(dt))

    def set_contact_force(self, forces) -> None:
        """Nodal forces (N) on the surface nodes: (n_surface, 3) or flat (n_surface*3,), held until changed."""
        try:
            array = np.asarray(forces, dtype=np.float64)
        except (TypeError, ValueError):
            raise TissueError(f"contact force must be numeric, shape ({self.n_surface}, 3) or ({3 * self.n_surface},)") from None
        if array.size != 3 * self.n_surface or array.ndim not in (1, 2) or (array.ndim == 2 and array.shape[1] != 3):
            raise TissueError(
                f"contact force has shape {array.shape}: expected ({self.n_surface}, 3) or flat "
                f"({3 * self.n_surface},) for the {self.n_surface} surface nodes"
            )
        array = array.reshape(self.n_surface, 3)
        if not np.isfinite(array).all():
            bad = np.flatnonzero(~np.isfinite(array).all(axis=1))
            raise TissueError(
                f"contact force contains NaN/Inf at surface node(s) {bad[:10].tolist()}: fix the contact model output"
            )
        self._external_force[self.surface_nodes] = array

    def step(self, t: float, dt: float) -> None:
        """Advance from time ``t`` to ``t + dt``.  Explicit refuses an unstable dt (StabilityError)."""
        if not is_finite_real(dt) or dt <= 0.0:
            raise TissueError(f"dt must be a finite number > 0 (got {dt!r}), e.g. 1/30")
        if not is_finite_real(t):
            raise TissueError(f"t must be a finite number (got {t!r})")
        stats = self.integrator.step(self.displacement, self.velocity, self._external_force, float(dt))
        # A non-linear law can stiffen past the rest-state stability bound; never hand NaN on.
        if not (np.isfinite(self.displacement).all() and np.isfinite(self.velocity).all()):
            raise TissueError(
                f"tissue state became NaN/Inf in the step from t = {t:.6g} s (dt = {dt:.4g} s, "
                f"{self.params.integrator} integrator): reduce dt, use more substeps or the implicit integrator"
            )
        # A linearised step can also diverge without NaN (a huge load on the hyperelastic law):
        # no tissue moves farther than several times its own size.
        reach = float(np.abs(self.displacement).max())
        if reach > DIVERGENCE_FACTOR * self._mesh_size:
            raise TissueError(
                f"tissue step diverged at t = {t:.6g} s: a node moved {reach:.3g} m, more than "
                f"{DIVERGENCE_FACTOR:g} x the mesh size {self._mesh_size:.3g} m; reduce the load or dt, "
                f"or use law='etmm'"
            )
        if self._failure_stretch is not None:  # before the deformation check: a torn element may be inverted
            ids = failed_elements(self.force_field, self.displacement, self._failure_stretch)
            if ids.size:
                self._fail(ids, float(t) + float(dt), float(dt))
        self._check_deformation(t, dt)
        self._statistics = stats
        self.time = float(t) + float(dt)
        self.last_dt = float(dt)

    def _check_deformation(self, t: float, dt: float) -> None:
        """Extreme strain gets a warning; inverted elements or an absurd strain end the run.

        Why: without it a 1 kPa wall or a 90 N indentation (the extremes study) runs on silently to
        Green strains of 1e3 (nodes across the lumen) while every node stays inside the
        divergence test above.
        """
        strain = self._max_strain = float(self.force_field.max_strain(self.displacement))
        if strain <= STRAIN_WARNING:
            return
        tets = self.mesh.tets[self.active_elements & ~self.failed]
        deformed = signed_volumes(self.mesh.points + self.displacement, tets)
        inverted = int(np.count_nonzero(deformed * signed_volumes(self.mesh.points, tets) <= 0.0))
        if inverted or strain > STRAIN_DIVERGENCE:
            what = f"{inverted} tetrahedra inverted" if inverted else f"Green strain {strain:.3g} > {STRAIN_DIVERGENCE:g}"
            raise TissueError(
                f"tissue step diverged at t = {t:.6g} s (dt = {dt:.4g} s): {what} (max Green strain {strain:.3g}); "
                f"the load is beyond what the {self.params.law} law and this mesh represent: reduce the load "
                f"(contact stiffness, indentation), raise young_modulus ({self.params.young_modulus:.4g} Pa) or refine "
                f"the mesh"
            )
        if not self._strain_warned:
            self._strain_warned = True
            logger.warning(
                "max Green strain %.3g at t = %.6g s exceeds %g (a %.0f %% stretch): the %s law is used outside "
                "the range it is calibrated for; reduce the load or raise young_modulus",
                strain, t + dt, STRAIN_WARNING, 100 * (math.sqrt(1 + 2 * STRAIN_WARNING) - 1), self.params.law)

    def _fail(self, active_ids: np.ndarray, t: float, dt: float) -> None:
        """Elements ``active_ids`` (rows of the force field's active tets) reached the failure stress:
        take them out of the wall (tissue_fmu.forcefield.TensorMassForceField.remove_elements),
        freeze the nodes left without an element, recompute the masses and refactorise the implicit
        step once; their strain energy is counted as released."""
        ff, u = self.force_field, self.displacement
        before = ff.strain_energy(u)
        nodes = np.unique(ff.active_tets[active_ids])
        contact_force = float(np.linalg.norm(self._external_force[nodes].sum(axis=0)))
        where = (self.mesh.points + u)[nodes].mean(axis=0)
        orphans = ff.remove_elements(active_ids)
        released = before - ff.strain_energy(u)
        self.failed[ff._element_ids[active_ids]] = True
        self.released_energy += released
        self.frozen[orphans] = True
        self.fixed[orphans] = True
        self.velocity[orphans] = 0.0
        self._external_force[orphans] = 0.0
        self.masses = np.asarray(ff.lumped_masses(float(self.params.density)), dtype=np.float64)
        self._critical_time_step = None
        self._compliance_factors = {}
        old = self.integrator
        self.integrator = self._make_integrator()
        if isinstance(old, BackwardEuler):
            np.copyto(self.integrator.dv, old.dv)
            np.copyto(self.integrator._dv_prev, old._dv_prev)
            self.integrator.dv[orphans] = 0.0
            self.integrator._dv_prev[orphans] = 0.0
        self.prepare(dt)
        record = {"time": t, "elements": int(active_ids.size), "failed_total": int(self.failed.sum()),
                  "position": where.tolist(), "contact_force": contact_force, "released_energy": released,
                  "orphaned_nodes": int(orphans.size)}
        self.failures.append(record)
        logger.warning(
            "tissue: %d element(s) failed at t = %.4f s at (%.4f, %.4f, %.4f) m: the wall's failure stress "
            "%.3g MPa was reached (contact force on them %.3g N); %d failed in all, %.3g J released",
            active_ids.size, t, *where, self.params.failure_stress / 1e6, contact_force, record["failed_total"],
            released)

    @property
    def perforated(self) -> bool:
        """Whether any element has failed."""
        return bool(self.failed.any())

    def reset(self) -> None:
        """Back to rest: zero displacement, velocity and contact force (failed elements stay failed)."""
        self.displacement.fill(0.0)
        self.velocity.fill(0.0)
        self._external_force.fill(0.0)
        self._statistics = StepStatistics()
        self._max_strain = 0.0
        self.time = 0.0
        if isinstance(self.integrator, BackwardEuler):
            self.integrator.dv.fill(0.0)
            self.integrator._dv_prev.fill(0.0)

    def get_state(self) -> dict:
        """A copy of the physical state a step depends on (for FMU get/set state and rollback).

        Restoring it reproduces the run to solver tolerance; the implicit preconditioner's own
        state (which tangent it last factorised, its Woodbury cache) is not included, so the Krylov
        iterates may differ in the last digits.  For a bit-identical continuation copy the whole
        model: ``copy.deepcopy(model)`` or ``pickle.loads(pickle.dumps(model))``. Failed elements are
        not part of this state (a failure changes the model itself): a copy of the model is what
        restores a run from before a failure.
        """
        state = {
            "time": self.time,
            "displacement": self.displacement.copy(),
            "velocity": self.velocity.copy(),
            "external_force": self._external_force.copy(),
        }
        if isinstance(self.integrator, BackwardEuler):
            state["warm_start"] = self.integrator.dv.copy()
            state["warm_start_previous"] = self.integrator._dv_prev.copy()
        return state

    def set_state(self, state: dict) -> None:
        """Restore a state returned by :meth:`get_state`."""
        self.time = float(state["time"])
        np.copyto(self.displacement, state["displacement"])
        np.copyto(self.velocity, state["velocity"])
        np.copyto(self._external_force, state["external_force"])
        self._max_strain = float(self.force_field.max_strain(self.displacement))
        if isinstance(self.integrator, BackwardEuler) and "warm_start" in state:
            np.copyto(self.integrator.dv, state["warm_start"])
            if "warm_start_previous" in state:
                np.copyto(self.integrator._dv_prev, state["warm_start_previous"])

    # ----------------------------------------------------------------------------------
    # Outputs
    # ----------------------------------------------------------------------------------

    def positions(self) -> np.ndarray:
        """(n, 3) current node positions."""
        return self.mesh.points + self.displacement

    def surface_positions(self, out: np.ndarray | None = None) -> np.ndarray:
        """(n_surface, 3) current positions of the surface nodes (into ``out`` when given, e.g. an
        FMU's output buffer: the same numbers without a copy)."""
        nodes = self.surface_nodes
        return np.add(self.mesh.points[nodes], self.displacement[nodes], out=out)

    def compliance(self, surface_node_ids, dt: float | None = None, tolerance: float | None = None) -> np.ndarray:
        """(3p, 3p) compliance W of the given surface nodes over the next step of size ``dt``.

        ``surface_node_ids``: p distinct local surface-node ids (rows of :meth:`surface_positions`).
        ``W[3 a + i, 3 b + j]`` is the displacement (m) of node a, component i, at the end of the
        next step per newton of extra contact force on node b, component j, held over the step:
        for the backward-Euler step ``(M + h C + h^2 K_t) dv = h (f + f_ext - h K_t v)``,
        ``u += h (v + dv)``, it is ``h^2 (M + h C + h^2 K_t)^-1`` restricted to those dofs, with the
        tangent ``K_t`` the step uses at the current state (ETMM: consistent, so W is slightly
        non-symmetric once elements are above the threshold; linear: symmetric positive definite).
        Clamped or frozen dofs give zero rows and columns.  ``dt`` defaults to the last step's
        size.  Each column is a pair of triangular solves with the integrator's factorisation
        (made exact by iterative refinement when it lags the tangent); with the explicit or the
        Jacobi integrator a factorisation of the same implicit matrix is built once per dt.
        ``tolerance``: relative residual of those solves (default: the model's cg_tolerance; a
        local model between frames can take a looser one). Does not change the model's results.
        With the budgeted step (``implicit_step = "budgeted"``) W is the wall's at rest stiffness,
        from cached columns of the rest factor: exact below the ETMM threshold, softer than the
        stiffened wall above it, and never a solve to tolerance inside a frame.
        """
        if dt is None:
            dt = self.last_dt
            if dt is None:
                raise TissueError("compliance: no step has been taken yet, so give dt (s), e.g. compliance(ids, 1/30)")
        if not is_finite_real(dt) or dt <= 0.0:
            raise TissueError(f"compliance: dt must be a finite number > 0 (got {dt!r}), e.g. 1/30")
        try:
            ids = np.asarray(surface_node_ids)
        except (TypeError, ValueError):
            ids = np.asarray([], dtype=object)
        if ids.ndim != 1 or ids.size == 0 or not np.issubdtype(ids.dtype, np.integer):
            raise TissueError(f"compliance: surface_node_ids must be a non-empty 1-D sequence of integers "
                              f"(local surface-node ids in [0, {self.n_surface})), got {surface_node_ids!r}")
        if ids.min() < 0 or ids.max() >= self.n_surface:
            raise TissueError(f"compliance: surface node ids must lie in [0, {self.n_surface}) "
                              f"(got {ids.min()}..{ids.max()}): they index surface_positions()")
        if np.unique(ids).size != ids.size:
            raise TissueError(f"compliance: surface node ids repeat ({ids.tolist()}): give each node once")
        h = float(dt)
        nodes = self.surface_nodes[ids.astype(np.int64)]
        dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
        integrator = self.integrator
        ff = self.force_field
        pc = None
        if (isinstance(integrator, BackwardEuler) and isinstance(integrator.preconditioner, TangentFactorization)
                and (integrator.preconditioner._h is None or integrator.preconditioner._h == h)):
            pc = integrator.preconditioner
        if pc is None:
            pc = self._compliance_factors.get(h)
            if pc is None:
                pc = self._compliance_factors[h] = TangentFactorization(ff, self.masses, self.fixed)
        free_index = pc._free_index
        free_cols = np.flatnonzero(free_index[dofs] >= 0)
        if isinstance(pc, RestFactorization):
            # the budgeted step: the wall's compliance at rest stiffness from cached columns (exact
            # below the ETMM threshold, softer than the stiffened wall above it), never a solve to
            # tolerance inside the frame, nor the tangent at the current state
            pc.prepare(h)
            x = pc.rest_inverse_block(nodes)
        else:
            # The tangent at the current state, as the next step will take it (same inputs, same result).
            ff.add_forces(self.displacement, self.velocity, np.zeros_like(self.displacement))
            consistent = getattr(ff, "nonlinear_fraction", 0.0) > 0.0
            if isinstance(integrator, BackwardEuler):
                consistent = consistent and integrator.consistent_tangent
            pc.update(h)
            x = pc.inverse_block(nodes)  # exact modes: cached columns of A_0^-1 (+ Woodbury), O(k p)
            if x is None:  # a lagging tangent factor or hyperelastic: solve, refine against the true matrix
                rhs = np.zeros((pc.free_dofs.size, free_cols.size))
                rhs[free_index[dofs[free_cols]], np.arange(free_cols.size)] = 1.0
                x = self._refine_compliance(pc, rhs, pc.solve_matrix(rhs), h, consistent,
                                            tolerance=float(self.params.cg_tolerance if tolerance is None
                                                            else tolerance))
                x = x[free_index[dofs[free_cols]], :]
        w = np.zeros((dofs.size, dofs.size))
        w[np.ix_(free_cols, free_cols)] = (h * h) * x
        return w

    def _refine_compliance(self, pc, rhs, x, h, consistent, tolerance=1e-11):
        """Columns of A^-1 (A the current step matrix) for the unit right-hand sides ``rhs`` (free
        numbering) by preconditioned GMRES per column, started from ``x`` = P^-1 rhs (P the
        lagging tangent factor, or the rest factor for the hyperelastic law), to ``tolerance``
        (the model's cg_tolerance: the accuracy the step itself is solved to)."""
        from .solvers import GMRESWorkspace, preconditioned_gmres

        n = self.mesh.n_nodes
        free_dofs = pc.free_dofs
        mass = np.repeat(np.where(self.masses > 0.0, self.masses, 1.0)[:, None], 3, axis=1)
        free = np.repeat((~self.fixed)[:, None], 3, axis=1).astype(np.float64)
        ff = self.force_field
        c_scale = h if self.params.viscosity > 0.0 else 0.0
        scratch = np.zeros((n, 3))

        def apply(p, out):
            ff.system_matvec(p, h * h, c_scale, out, consistent)
            np.multiply(mass, p, out=scratch)
            out += scratch

        work = GMRESWorkspace(n)
        b = np.zeros((n, 3))
        column = np.zeros((n, 3))
        result = np.empty_like(x)
        for c in range(rhs.shape[1]):
            b.fill(0.0)
            b.reshape(-1)[free_dofs] = rhs[:, c]
            column.fill(0.0)
            column.reshape(-1)[free_dofs] = x[:, c]
            iterations, residual, converged = preconditioned_gmres(
                apply, b, column, pc, free, tolerance, self.params.cg_max_iterations, work)
            if not converged:
                logger.warning("compliance: column %d reached a relative residual of %.3g in %d GMRES iterations",
                               c, residual, iterations)
            result[:, c] = column.reshape(-1)[free_dofs]
        return result

    def surface_velocities(self, out: np.ndarray | None = None) -> np.ndarray:
        """(n_surface, 3) current velocities of the surface nodes (into ``out`` when given)."""
        if out is None:
            return self.velocity[self.surface_nodes]
        return np.take(self.velocity, self.surface_nodes, axis=0, out=out)

    @property
    def strain_energy(self) -> float:
        return float(self.force_field.strain_energy(self.displacement))

    @property
    def kinetic_energy(self) -> float:
        return float(kernels.kinetic_energy(self.masses, self.velocity))

    @property
    def max_strain(self) -> float:
        return self._max_strain

    @property
    def nonlinear_fraction(self) -> float:
        return float(self.force_field.nonlinear_fraction)

    @property
    def solver_iterations(self) -> int:
        """CG iterations of the last implicit step; substeps of the last explicit step."""
        if isinstance(self.integrator, SymplecticEuler):
            return self._statistics.substeps
        return self._statistics.iterations

    @property
    def solver_residual(self) -> float:
        return self._statistics.relative_residual

    @property
    def solver_converged(self) -> bool:
        return self._statistics.converged

    @property
    def substeps(self) -> int:
        """Substeps used by the last step (1 for the implicit integrator, 0 before any step)."""
        return self._statistics.substeps

    @property
    def critical_time_step(self) -> float:
        """Explicit stability limit of this mesh and material (s), damping and stiffening included."""
        return self._critical_step()

"""The Tissue FMU: a thin FMI 3.0 Co-Simulation slave over :class:`tissue_fmu.model.TissueModel`.

Every variable is declared once, here; the model does the work. Ports follow DESIGN.md
section 4. Arrays are ``[n, 3]`` node-major, i.e. flat ``x0, y0, z0, x1, ...`` on the wire.

Array sizes depend on the mesh, so they are structural parameters (``n_surface_nodes``,
``n_surface_triangles``) whose start values are those of the default AAA mesh. A user who
changes the mesh sizes or gives a mesh file sets them to the counts of that mesh; the FMU checks
them when it leaves initialization mode and names the right values when they do not match
(``len(aaa_mesh(...).surface()[0])`` and ``len(aaa_mesh(...).surface()[1])`` give them without an FMU).
"""
from __future__ import annotations

import numpy as np
from pythonfmu3 import (
    Fmi3Causality,
    Fmi3Slave,
    Fmi3Variability,
    Float64,
    Int32,
    String,
)

from ._fmi_support import GuardedSlaveMixin
from .mesh import aaa_mesh, load_mesh
from .model import TissueModel, TissueParameters

C, V = Fmi3Causality, Fmi3Variability

#: Mesh sizes of the built-in AAA generator exposed as parameters, with their defaults.
AAA_SIZES = dict(aorta_radius=0.010, aneurysm_radius=0.025, aneurysm_length=0.060,
                 segment_length=0.130, wall_thickness=0.0015)
AAA_RESOLUTION = dict(n_circumferential=32, n_axial=40, n_radial=2)


def _default_surface_counts() -> tuple[int, int]:
    nodes, triangles = aaa_mesh(**AAA_SIZES, **AAA_RESOLUTION).surface()
    return int(nodes.shape[0]), int(triangles.shape[0])


class TissueSlave(GuardedSlaveMixin, Fmi3Slave):
    """Extended Tensor-Mass Model of the aneurysm wall (Tissue FMU)."""

    forwarded_loggers = (__name__.rsplit(".", 1)[0],)  # this package, under whatever name it was imported

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self._declare_basics("Extended Tensor-Mass Model of an abdominal aortic aneurysm wall "
                             "(linear tensor-mass + non-linear and viscous tensors)", 1.0 / 30.0)
        self.model: TissueModel | None = None

        defaults = TissueParameters()
        self.young_modulus = defaults.young_modulus
        self.poisson_ratio = defaults.poisson_ratio
        self.density = defaults.density
        self.viscosity = defaults.viscosity
        self.law = defaults.law
        self.integrator = defaults.integrator
        self.substeps = 0  # 0 = automatic (smallest stable count)
        self.cg_tolerance = defaults.cg_tolerance
        self.cg_max_iterations = defaults.cg_max_iterations
        self.nonlinear_strain_threshold = defaults.nonlinear_strain_threshold
        self.clamp = ",".join(defaults.clamp)
        self.active_radius = 0.0  # <= 0: the whole mesh is active
        self.active_center = np.zeros(3)
        self.mesh_file = ""
        for name, value in {**AAA_SIZES, **AAA_RESOLUTION}.items():
            setattr(self, name, value)

        fixed = dict(causality=C.parameter, variability=V.fixed)
        params = [
            ("young_modulus", "Pa", "Young's modulus (small-strain); AAA wall 1.044 MPa"),
            ("poisson_ratio", None, "Poisson ratio in (-1, 0.5)"),
            ("density", "kg/m3", "mass density"),
            ("viscosity", "Pa.s", "Kelvin-Voigt viscosity of the viscous tensor (0: off)"),
            ("cg_tolerance", None, "relative residual of the implicit conjugate-gradient solve"),
            ("nonlinear_strain_threshold", None, "Green strain above which ETMM corrects an element"),
            ("active_radius", "m", "radius of the active region around active_center (<= 0: whole mesh)"),
        ]
        self._register_scalars(params, C.parameter, V.fixed)
        self._register_array("active_center", (3,), C.parameter, "centre of the active region", "m",
                             variability=V.fixed)
        self.register_variable(String("law", **fixed, description="material law: linear, etmm or hyperelastic"))
        self.register_variable(String("integrator", **fixed, description="implicit (backward Euler + CG) or explicit (symplectic Euler)"))
        self.register_variable(String("clamp", **fixed, description="comma-separated node sets held at rest"))
        self.register_variable(String("mesh_file", **fixed, description="tetrahedral mesh file (meshio format); empty: built-in AAA generator"))
        self.register_variable(Int32("substeps", **fixed, description="explicit substeps per communication step (0: automatic)"))
        self.register_variable(Int32("cg_max_iterations", **fixed, description="maximum conjugate-gradient iterations"))
        for name in AAA_SIZES:
            self.register_variable(Float64(name, **fixed, unit="m", description=f"AAA generator: {name.replace('_', ' ')}"))
        for name in AAA_RESOLUTION:
            self.register_variable(Int32(name, **fixed, description=f"AAA generator: {name.replace('_', ' ')} element count"))
        n_nodes, n_triangles = _default_surface_counts()
        self._register_structural("n_surface_nodes", n_nodes, "surface nodes of the mesh (array size)")
        self._register_structural("n_surface_triangles", n_triangles, "surface triangles of the mesh (array size)")
        per_node = ("n_surface_nodes", 3)
        self._register_array("contact_force", per_node, C.input, "nodal contact forces on the surface nodes", "N")
        self._register_array("surface_positions", per_node, C.output, "positions of the surface nodes", "m")
        self._register_array("surface_velocities", per_node, C.output, "velocities of the surface nodes", "m/s")
        self._register_array("surface_triangles", ("n_surface_triangles", 3), C.calculatedParameter,
                             "surface triangles (indices into the surface nodes, outward)",
                             variability=V.fixed, dtype=np.int32)

        self.strain_energy = 0.0
        self.kinetic_energy = 0.0
        self.max_strain = 0.0
        self.nonlinear_fraction = 0.0
        self.solver_residual = 0.0
        self.critical_time_step = 0.0
        self.solver_iterations = 0
        self._register_scalars([
            ("strain_energy", "J", "elastic strain energy"),
            ("kinetic_energy", "J", "kinetic energy"),
            ("max_strain", None, "largest principal Green strain magnitude"),
            ("nonlinear_fraction", None, "fraction of active elements that paid for the non-linear correction"),
            ("solver_residual", None, "relative residual of the last implicit solve"),
            ("critical_time_step", "s", "explicit stability limit of the current mesh and material"),
        ], C.output, V.continuous)
        self.register_variable(Int32("solver_iterations", causality=C.output, variability=V.discrete,
                                     description="iterations of the last implicit solve (substeps when explicit)"))

    # -- model delegation -----------------------------------------------------------------------
    def _parameters(self) -> TissueParameters:
        active = None
        if self.active_radius > 0:
            active = (*map(float, self.active_center), float(self.active_radius))
        clamp = tuple(name.strip() for name in str(self.clamp).split(",") if name.strip())
        return TissueParameters(
            young_modulus=float(self.young_modulus), poisson_ratio=float(self.poisson_ratio),
            density=float(self.density), viscosity=float(self.viscosity), law=str(self.law),
            integrator=str(self.integrator), substeps="auto" if int(self.substeps) == 0 else int(self.substeps),
            cg_tolerance=float(self.cg_tolerance), cg_max_iterations=int(self.cg_max_iterations),
            clamp=clamp, active_region=active,
            nonlinear_strain_threshold=float(self.nonlinear_strain_threshold),
        )

    def _initialize_model(self) -> None:
        params = self._parameters()
        params.validate()  # parameter errors before the (slower) mesh work
        if self.mesh_file:
            mesh = load_mesh(self.mesh_file)
        else:
            mesh = aaa_mesh(**{k: float(getattr(self, k)) for k in AAA_SIZES},
                            **{k: int(getattr(self, k)) for k in AAA_RESOLUTION})
        model = TissueModel(mesh, params)
        if (model.n_surface, len(model.surface_triangles)) != (self.n_surface_nodes, self.n_surface_triangles):
            raise ValueError(
                f"the mesh has {model.n_surface} surface nodes and {len(model.surface_triangles)} surface "
                f"triangles, but n_surface_nodes = {self.n_surface_nodes} and n_surface_triangles = "
                f"{self.n_surface_triangles}: set these structural parameters to {model.n_surface} and "
                f"{len(model.surface_triangles)}"
            )
        self.model = model
        self.surface_triangles[...] = model.surface_triangles

    def _step_model(self, t: float, dt: float) -> None:
        self.model.set_contact_force(self.contact_force)
        self.model.step(t, dt)

    def _publish_outputs(self) -> None:
        model = self.model
        self.surface_positions[...] = model.surface_positions()
        self.surface_velocities[...] = model.surface_velocities()
        self.strain_energy = model.strain_energy
        self.kinetic_energy = model.kinetic_energy
        self.max_strain = model.max_strain
        self.nonlinear_fraction = model.nonlinear_fraction
        self.solver_residual = float(model.solver_residual)
        self.critical_time_step = model.critical_time_step
        self.solver_iterations = int(model.solver_iterations)

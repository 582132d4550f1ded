"""The Tissue FMU: its interface, declared once, and the glue to :class:`tissue_fmu.model.TissueModel`.

Ports follow DESIGN.md section 4. Arrays are ``[n, 3]`` node-major, i.e. flat ``x0, y0, z0, x1, ...``
on the wire.

Array sizes depend on the mesh, so they are structural parameters (``n_surface_nodes``,
``n_surface_triangles``) whose start values are those of the default AAA mesh. A user who
changes the mesh sizes or gives a mesh file sets them (in Configuration Mode) to the counts of
that mesh; the FMU checks them when it builds the model and names the right values when they do
not match (``len(aaa_mesh(...).surface()[0])`` and ``len(aaa_mesh(...).surface()[1])`` give them
without an FMU).
"""
from __future__ import annotations

import numpy as np

from ._fmi import FmuDeclaration, calculated, input_port, output, parameter, structural
from .mesh import aaa_mesh, load_mesh
from .model import TissueModel, TissueParameters

#: Mesh sizes of the built-in AAA generator exposed as parameters, with their defaults.
AAA_SIZES = dict(aorta_radius=0.010, aneurysm_radius=0.025, aneurysm_length=0.060,
                 segment_length=0.130, wall_thickness=0.0015)
AAA_RESOLUTION = dict(n_circumferential=32, n_axial=40, n_radial=2)


def _default_surface_counts() -> tuple[int, int]:
    nodes, triangles = aaa_mesh(**AAA_SIZES, **AAA_RESOLUTION).surface()
    return int(nodes.shape[0]), int(triangles.shape[0])


_defaults = TissueParameters()
_n_nodes, _n_triangles = _default_surface_counts()
PER_NODE = ("n_surface_nodes", 3)

VARIABLES = (
    parameter("young_modulus", float(_defaults.young_modulus), "Young's modulus (small-strain); AAA wall 1.044 MPa",
              "Pa"),
    parameter("poisson_ratio", float(_defaults.poisson_ratio), "Poisson ratio in (-1, 0.5)"),
    parameter("density", float(_defaults.density), "mass density", "kg/m3"),
    parameter("viscosity", float(_defaults.viscosity), "Kelvin-Voigt viscosity of the viscous tensor (0: off)",
              "Pa.s"),
    parameter("cg_tolerance", float(_defaults.cg_tolerance), "relative residual of the implicit Krylov solve"),
    parameter("nonlinear_strain_threshold", float(_defaults.nonlinear_strain_threshold),
              "Green strain above which ETMM corrects an element"),
    parameter("active_radius", 0.0, "radius of the active region around active_center (<= 0: whole mesh)", "m"),
    parameter("active_center", np.zeros(3), "centre of the active region", "m", shape=(3,)),
    parameter("law", str(_defaults.law), "material law: linear, etmm or hyperelastic"),
    parameter("integrator", str(_defaults.integrator), "implicit (backward Euler + CG) or explicit (symplectic Euler)"),
    parameter("clamp", ",".join(_defaults.clamp), "comma-separated node sets held at rest"),
    parameter("mesh_file", "", "tetrahedral mesh file (meshio format); empty: built-in AAA generator"),
    parameter("substeps", 0, "explicit substeps per internal step (0: automatic)"),
    parameter("cg_max_iterations", int(_defaults.cg_max_iterations), "maximum Krylov iterations"),
    parameter("compliance_tolerance", 1e-2, "relative residual of the compliance solves when the factorisation "
              "lags the tangent (W is Contact's model of the wall between frames)"),
    *(parameter(name, value, f"AAA generator: {name.replace('_', ' ')}", "m") for name, value in AAA_SIZES.items()),
    *(parameter(name, value, f"AAA generator: {name.replace('_', ' ')} element count")
      for name, value in AAA_RESOLUTION.items()),
    structural("n_surface_nodes", _n_nodes, "surface nodes of the mesh (array size)"),
    structural("n_surface_triangles", _n_triangles, "surface triangles of the mesh (array size)"),
    structural("n_patch_nodes", 16, "most surface nodes whose compliance Contact may ask for (array size)"),
    input_port("contact_force", "nodal contact forces on the surface nodes", "N", shape=PER_NODE),
    input_port("patch_nodes", "surface nodes whose compliance is wanted (from Contact), -1 padded", type="Int32",
               shape=("n_patch_nodes",), start=-1),
    output("surface_positions", "positions of the surface nodes", "m", shape=PER_NODE),
    output("surface_velocities", "velocities of the surface nodes", "m/s", shape=PER_NODE),
    calculated("surface_triangles", "surface triangles (indices into the surface nodes, outward)",
               shape=("n_surface_triangles", 3), type="Int32"),
    output("compliance", "compliance W of the wall at compliance_nodes over the next step: the displacement "
           "per newton held over the step, node-major (x, y, z) rows and columns; zero for -1 slots", "m/N",
           shape=("n_patch_nodes", 3, "n_patch_nodes", 3)),
    output("compliance_nodes", "the surface nodes W was computed for (patch_nodes when the step ended)",
           type="Int32", shape=("n_patch_nodes",)),
    output("frame", "tissue frames computed (internal steps): changes exactly when the outputs are new",
           type="Int32"),
    output("strain_energy", "elastic strain energy", "J"),
    output("kinetic_energy", "kinetic energy", "J"),
    output("max_strain", "largest principal Green strain magnitude"),
    output("nonlinear_fraction", "fraction of active elements that paid for the non-linear correction"),
    output("solver_residual", "relative residual of the last implicit solve"),
    output("critical_time_step", "explicit stability limit of the current mesh and material", "s"),
    output("solver_iterations", "iterations of the last implicit solve (substeps when explicit)", type="Int32"),
)


def _parameters(v) -> TissueParameters:
    active = None
    if v.active_radius > 0:
        active = (*map(float, v.active_center), float(v.active_radius))
    clamp = tuple(name.strip() for name in v.clamp.split(",") if name.strip())
    return TissueParameters(
        young_modulus=v.young_modulus, poisson_ratio=v.poisson_ratio, density=v.density, viscosity=v.viscosity,
        law=v.law, integrator=v.integrator, substeps="auto" if v.substeps == 0 else v.substeps,
        cg_tolerance=v.cg_tolerance, cg_max_iterations=v.cg_max_iterations, clamp=clamp, active_region=active,
        nonlinear_strain_threshold=v.nonlinear_strain_threshold,
    )


class TissueFmu:
    """Builds the tissue model from the parameters and steps it under the contact forces."""

    def __init__(self, values):
        self.values = v = values
        params = _parameters(v)
        params.validate()  # parameter errors before the (slower) mesh work
        if v.mesh_file:
            mesh = load_mesh(v.mesh_file)
        else:
            mesh = aaa_mesh(**{k: float(getattr(v, k)) for k in AAA_SIZES},
                            **{k: int(getattr(v, k)) for k in AAA_RESOLUTION})
        model = TissueModel(mesh, params)
        if (model.n_surface, len(model.surface_triangles)) != (v.n_surface_nodes, v.n_surface_triangles):
            raise ValueError(
                f"the mesh has {model.n_surface} surface nodes and {len(model.surface_triangles)} surface "
                f"triangles, but n_surface_nodes = {v.n_surface_nodes} and n_surface_triangles = "
                f"{v.n_surface_triangles}: set these structural parameters (in Configuration Mode) to "
                f"{model.n_surface} and {len(model.surface_triangles)}"
            )
        self.model = model
        v.surface_triangles = model.surface_triangles
        v.frame = 0
        v.compliance_nodes = -1
        self._publish()

    def step(self, t: float, dt: float) -> None:
        v = self.values
        self.model.set_contact_force(v.contact_force)
        self.model.step(t, dt)
        v.frame = v.frame + 1
        self._publish()
        self._publish_compliance(dt)

    def _publish_compliance(self, dt: float) -> None:
        """W for the patch Contact named, over the next step. ETMM's consistent tangent makes W
        slightly non-symmetric above the strain threshold; its symmetric part (positive definite)
        is what a penalty contact with a conservative wall uses."""
        v = self.values
        nodes = np.array(v.patch_nodes)
        valid = np.flatnonzero(nodes >= 0)
        block = None
        if valid.size:
            ids = nodes[valid]
            if ids.max() >= self.model.n_surface or np.unique(ids).size != ids.size:
                raise ValueError(f"patch_nodes must be distinct surface node ids in [0, {self.model.n_surface}) "
                                 f"or -1 (got {ids.tolist()})")
            block = self.model.compliance(ids, dt, tolerance=v.compliance_tolerance)
            block = 0.5 * (block + block.T)
        w = v.compliance.reshape(nodes.size * 3, nodes.size * 3)  # the FMU's buffer
        w[...] = 0.0
        if block is not None:
            dofs = (3 * valid[:, None] + np.arange(3)).ravel()
            w[np.ix_(dofs, dofs)] = block
        v.compliance_nodes = nodes

    def _publish(self) -> None:
        model, v = self.model, self.values
        model.surface_positions(out=v.surface_positions)  # straight into the FMU's buffers
        model.surface_velocities(out=v.surface_velocities)
        v.strain_energy = model.strain_energy
        v.kinetic_energy = model.kinetic_energy
        v.max_strain = model.max_strain
        v.nonlinear_fraction = model.nonlinear_fraction
        v.solver_residual = float(model.solver_residual)
        v.critical_time_step = model.critical_time_step
        v.solver_iterations = int(model.solver_iterations)


DECLARATION = FmuDeclaration(
    model_name="Tissue",
    description="Extended Tensor-Mass Model of an abdominal aortic aneurysm wall (linear tensor-mass + non-linear "
                "and viscous tensors)",
    internal_step=1.0 / 30.0,
    variables=VARIABLES,
    adapter=TissueFmu,
)

"""The Tissue FMU: its interface, declared once, and the glue to :class:`tissue_fmu.model.TissueModel`.

Ports follow docs/design.md section 4. Arrays are ``[n, 3]`` node-major, i.e. flat ``x0, y0, z0, x1, ...``
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

from ._coupling import PATCH_NODES, size_rules
from ._fmi import FmuDeclaration, Limit, calculated, input_port, output, parameter, structural
from .errors import MeshError
from .mesh import aaa_mesh, load_mesh
from .model import TissueModel, TissueParameters

#: Mesh sizes of the built-in AAA generator exposed as parameters, with their defaults.
AAA_SIZES = dict(aorta_radius=0.010, aneurysm_radius=0.025, aneurysm_length=0.060,
                 segment_length=0.130, wall_thickness=0.0015)
AAA_RESOLUTION = dict(n_circumferential=32, n_axial=40, n_radial=2)


def _default_surface_counts() -> tuple[int, int]:
    nodes, triangles = aaa_mesh(**AAA_SIZES, **AAA_RESOLUTION).surface()
    return int(nodes.shape[0]), int(triangles.shape[0])


#: The plausible range of every number an importer gives this FMU, and why (docs/design.md section 7 for
#: the reference values). Values outside are refused (fmi3Error naming the variable, the value and
#: this range) instead of being simulated into an absurd or endless result.
LIMITS = {
    "young_modulus": Limit(100.0, 1e10, "soft tissues are 1 kPa to 10 MPa and calcified plaque about 1 GPa; below "
                                        "100 Pa or above 10 GPa is a unit mistake (kPa, MPa?)"),
    "poisson_ratio": Limit(-0.99, 0.4999, "lambda = E nu / ((1 + nu)(1 - 2 nu)) grows without bound at 0.5 (0.4999 "
                                          "is already 1667 E) and at -1; tissue is 0.45 to 0.49"),
    "density": Limit(1.0, 1e5, "tissue is about 1000-1200 kg/m3; outside [1, 1e5] kg/m3 no material is meant"),
    "viscosity": Limit(0.0, 1e7, "the Kelvin-Voigt wall viscosity is 0 to about 1e4 Pa s; 1e7 Pa s freezes the wall"),
    "cg_tolerance": Limit(1e-15, 0.5, "a relative residual below 1e-15 is under round-off (never reached); above "
                                      "0.5 the solve does not reduce the residual"),
    "nonlinear_strain_threshold": Limit(0.0, 10.0, "a Green strain of 10 (a 4.6x stretch) is far past rupture of "
                                                   "any wall"),
    "active_radius": Limit(0.0, 10.0, "0 simulates the whole mesh; a region is at most the body (10 m)"),
    "active_center": Limit(-10.0, 10.0, "coordinates of the region's centre lie within the body (10 m)"),
    "substeps": Limit(0, 1_000_000, "explicit substeps per internal step (0: automatic); the work they cost is "
                                    "limited again by MAX_EXPLICIT_WORK"),
    "cg_max_iterations": Limit(1, 1_000_000, "Krylov iterations per implicit solve; 1e6 is beyond any converging "
                                             "solve of these meshes (the iterations cost about 0.1 ms each)"),
    "budget_iterations": Limit(1, 1000, "Krylov iterations per budgeted frame; each is a factor solve of a few "
                                        "milliseconds, so beyond 1000 the budget is not a frame's"),
    "compliance_tolerance": Limit(1e-15, 0.5, "a relative residual below 1e-15 is under round-off; above 0.5 the "
                                              "compliance is not solved for"),
    **{name: Limit(1e-4, 1.0, "AAA generator lengths are millimetres to centimetres (docs/design.md section 7); "
                              "beyond [0.1 mm, 1 m] the unit is wrong")
       for name in ("aorta_radius", "aneurysm_radius", "aneurysm_length", "segment_length", "wall_thickness")},
    "n_circumferential": Limit(8, 1024, "elements around the vessel: 8 at least for a round wall, 1024 (0.15 mm "
                                        "around the 25 mm sac) finer than any use; the element count is limited "
                                        "again by MAX_ELEMENTS"),
    "n_axial": Limit(1, 4096, "elements along the vessel; the element count is limited again by MAX_ELEMENTS"),
    "n_radial": Limit(1, 64, "elements across the 1.5 mm wall; 64 layers are 23 um thick"),
    "n_surface_nodes": Limit(3, 2_000_000, "surface nodes of a mesh within MAX_ELEMENTS"),
    "n_surface_triangles": Limit(1, 4_000_000, "surface triangles of a mesh within MAX_ELEMENTS"),
    "n_patch_nodes": Limit(1, 256, "the compliance block is (3 n)^2 values, solved column by column each frame: "
                                   "256 nodes are 590k values and 768 solves"),
    "contact_force": Limit(-1e4, 1e4, "a nodal force beyond 10 kN is 1000 times what a catheter or a haptic device "
                                      "applies (12 N): a broken connection or unit"),
}

#: Most tetrahedra a Tissue instance builds (generated or read): the 64x80x2 wall (61k tets) steps in
#: about 36 ms on a 2-core machine; 1M tets need gigabytes for the tensors and the factorisation.
MAX_ELEMENTS = 1_000_000
#: Most explicit work per internal step, in substeps x (active tetrahedra + SUBSTEP_OVERHEAD_ELEMENTS):
#: 3e8 is about 5 s of computation per step on a 2-core machine (18 ns per tetrahedron and substep: the
#: default wall, 15k tets with automatic substeps, is 9.5k substeps, 1.6e8, 2.7 s). A stiffer material or a
#: finer mesh needs the implicit integrator, not hours of substeps.
MAX_EXPLICIT_WORK = 3e8
#: A substep's fixed cost (about 13 us of Python and numpy calls, measured on a 192-tet mesh) in tetrahedra.
SUBSTEP_OVERHEAD_ELEMENTS = 1000

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
    parameter("active_radius", 0.0, "radius of the active region around active_center (0: whole mesh)", "m"),
    parameter("active_center", np.zeros(3), "centre of the active region", "m", shape=(3,)),
    parameter("law", str(_defaults.law), "material law: linear, etmm or hyperelastic"),
    parameter("integrator", str(_defaults.integrator), "implicit (backward Euler + CG) or explicit (symplectic Euler)"),
    parameter("clamp", ",".join(_defaults.clamp), "comma-separated node sets held at rest"),
    parameter("mesh_file", "", "tetrahedral mesh file (meshio format); empty: built-in AAA generator"),
    parameter("substeps", 0, "explicit substeps per internal step (0: automatic)"),
    parameter("cg_max_iterations", int(_defaults.cg_max_iterations), "maximum Krylov iterations"),
    parameter("implicit_step", str(_defaults.implicit_step), "exact (solved to cg_tolerance, whatever the frame "
              "costs) or budgeted (at most budget_iterations per frame, preconditioned by the rest factor; the "
              "residual left is the solver_residual output)"),
    parameter("budget_iterations", int(_defaults.budget_iterations), "budgeted step: Krylov iterations per frame "
              "(each one factor solve)"),
    parameter("compliance_tolerance", 1e-2, "relative residual of the compliance solves when the factorisation "
              "lags the tangent (W is Contact's model of the wall between frames)"),
    *(parameter(name, value, f"AAA generator: {name.replace('_', ' ')}", "m") for name, value in AAA_SIZES.items()),
    *(parameter(name, value, f"AAA generator: {name.replace('_', ' ')} element count")
      for name, value in AAA_RESOLUTION.items()),
    structural("n_surface_nodes", _n_nodes, "surface nodes of the mesh (array size)"),
    structural("n_surface_triangles", _n_triangles, "surface triangles of the mesh (array size)"),
    structural("n_patch_nodes", PATCH_NODES, "most surface nodes whose compliance Contact may ask for (array size)"),
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
        implicit_step=v.implicit_step, budget_iterations=v.budget_iterations,
        nonlinear_strain_threshold=v.nonlinear_strain_threshold,
    )


def _check_element_count(count: int, what: str) -> None:
    if count > MAX_ELEMENTS:
        raise ValueError(f"{what} is {count} tetrahedra, more than MAX_ELEMENTS = {MAX_ELEMENTS} (gigabytes of "
                         f"tensors and factorisation, minutes per step): use a coarser mesh")


def _check_explicit_work(model: TissueModel, step: float) -> None:
    """Refuse an explicit integration whose substeps would take far longer than a step should."""
    integrator = model.integrator
    # a given count below the stable one is refused by the first step (StabilityError), with its numbers
    substeps = integrator.substeps_for(step) if integrator.substeps == "auto" else int(integrator.substeps)
    elements = int(model.active_elements.sum())
    work = substeps * (elements + SUBSTEP_OVERHEAD_ELEMENTS)
    if work > MAX_EXPLICIT_WORK:
        automatic = "automatic " if model.params.substeps == "auto" else ""
        raise ValueError(
            f"substeps: the explicit integrator {'needs' if automatic else 'is given'} {substeps} {automatic}substeps per "
            f"internal step of {step:.6g} s "
            f"(critical time step {model.critical_time_step:.3g} s) on {elements} tetrahedra: {work:.3g} "
            f"substep-elements (SUBSTEP_OVERHEAD_ELEMENTS = {SUBSTEP_OVERHEAD_ELEMENTS} each for the substep itself), "
            f"more than MAX_EXPLICIT_WORK = {MAX_EXPLICIT_WORK:.3g} (about 5 s per step): use fewer substeps, the "
            f"implicit integrator, a softer or denser material, or a coarser mesh")


class TissueFmu:
    """Builds the tissue model from the parameters and steps it under the contact forces."""

    def __init__(self, values):
        self.values = v = values
        params = _parameters(v)
        params.validate()  # parameter errors before the (slower) mesh work
        if v.mesh_file:
            try:
                mesh = load_mesh(v.mesh_file)
            except MeshError as exc:  # named as the user knows it: the parameter they set
                raise MeshError(f"mesh_file = {v.mesh_file!r}: {exc}") from None
            _check_element_count(mesh.n_tets, f"the mesh file {v.mesh_file!r}")
        else:
            resolution = {k: int(getattr(v, k)) for k in AAA_RESOLUTION}
            _check_element_count(6 * resolution["n_circumferential"] * resolution["n_axial"] * resolution["n_radial"],
                                 "6 x n_circumferential x n_axial x n_radial = 6 x {n_circumferential} x {n_axial} x "
                                 "{n_radial}".format(**resolution))
            mesh = aaa_mesh(**{k: float(getattr(v, k)) for k in AAA_SIZES}, **resolution)
        model = TissueModel(mesh, params)
        if params.integrator == "explicit":
            _check_explicit_work(model, v.internal_step)
        else:  # the rest factorisation and the kernels' loading here, not in the first frame
            model.prepare(v.internal_step)
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
            if valid[-1] == valid.size - 1:  # the first slots, as Contact names them: a block in the corner
                w[:block.shape[0], :block.shape[0]] = block
            else:
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
    limits=LIMITS,
    size_rules=size_rules("Tissue"),
    # a frame costs milliseconds and up to a few hundred under strong load: 60 s of simulated time
    # in one call is minutes of work at worst, and no master needs more in one call
    max_steps_per_call=1800,
)

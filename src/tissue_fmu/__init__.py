"""Tensor-mass soft tissue for real-time simulation (the physics behind Tissue.fmu).

Units SI (m, kg, s, N, Pa); node arrays are (n, 3) float64, flat vectors node-major
(x0, y0, z0, x1, ...).  Layers: ``mesh`` (TetMesh, generators, I/O), ``forcefield`` with
``laws``/``precompute``/``materials``/``kernels`` (tensor-mass forces, numba), ``integrators``
(ODE solvers), ``solvers`` (Krylov), ``factorization`` (the implicit step's factorised
preconditioner), ``errors``, ``model`` (state and ``step(t, dt)``, validation), and the FMU
declaration ``fmu`` (not imported here: only the FMU build and runtime need it).

Python API
----------
Meshes
    ``aaa_mesh(aorta_radius=0.010, aneurysm_radius=0.025, aneurysm_length=0.060,
    segment_length=0.130, wall_thickness=0.0015, n_circumferential=32, n_axial=40, n_radial=2)``,
    ``box_mesh(size, divisions, origin)``, ``load_mesh(path)`` -> :class:`TetMesh` with
    ``points``, ``tets``, ``node_sets`` (AAA: inlet, outlet, inner, outer; box: xmin ... zmax),
    ``element_sets`` (AAA: sac), ``surface()``, ``volumes()``, ``quality()``.
Model
    ``TissueParameters(young_modulus=1.044e6, poisson_ratio=0.45, density=1120.0, viscosity=0.0,
    law="etmm", integrator="implicit", substeps="auto", cg_tolerance=1e-6,
    cg_max_iterations=1000, preconditioner="factorized", clamp=("inlet", "outlet"),
    active_region=None, nonlinear_region=None, nonlinear_strain_threshold=0.05,
    rv_alpha=0.174e6, rv_beta=1.881e6)`` with ``validate()``.

    ``TissueModel(mesh, params=None, materials=None)``; ``TissueModel.from_parameters(params,
    mesh_file=None, materials=None, **aaa_mesh_sizes)``; ``TissueModel.default_aaa()``.
    ``materials=[(elements, young_modulus, poisson_ratio), ...]`` overrides element materials
    (``elements``: bool mask, element ids or an element set name).

    Inputs: ``set_contact_force(forces)`` ((n_surface, 3) or flat, held until changed).
    Stepping: ``step(t, dt)``; ``reset()``; ``get_state()`` / ``set_state(state)``.
    Outputs: ``surface_positions()``, ``surface_velocities()``, ``positions()``,
    ``surface_nodes``, ``surface_triangles``, ``n_surface``, ``displacement``, ``velocity``,
    ``strain_energy``, ``kinetic_energy``, ``max_strain``, ``nonlinear_fraction``,
    ``solver_iterations``, ``solver_residual``, ``solver_converged``, ``substeps``,
    ``critical_time_step``, ``time``.
Errors
    :class:`TissueError` (a ValueError), the one base class of the package's errors, for bad input
    or a failed step; its subclasses :class:`StabilityError` (an explicit step exceeds the critical
    time step), :class:`MeshError` (bad meshes), :class:`MaterialError`, :class:`ForceFieldError`.
Building blocks
    :class:`TensorMassForceField` with one class per material law (``laws``: :class:`LinearLaw`,
    :class:`ETMMLaw`, :class:`HyperelasticLaw`), ``assemble_stiffness`` (any vertex order);
    integrators :class:`SymplecticEuler` (explicit, substeps) and :class:`BackwardEuler` (implicit;
    Krylov solvers in ``solvers``) with :class:`TangentFactorization` (the default: the step
    matrix factorised and kept exact, ``factorization``), :class:`FactorizedPreconditioner` (rest
    matrix only) or :class:`JacobiPreconditioner`.

Example
-------
>>> import numpy as np
>>> from tissue_fmu import TissueModel, TissueParameters
>>> model = TissueModel.from_parameters(TissueParameters(law="etmm"))   # default AAA wall
>>> force = np.zeros((model.n_surface, 3))
>>> force[:4, 0] = -0.25                       # 1 N on four surface nodes
>>> model.set_contact_force(force)
>>> for k in range(30):                        # one second at 30 Hz
...     model.step(k / 30, 1 / 30)
>>> positions = model.surface_positions()      # (n_surface, 3), to the contact model
>>> model.solver_converged, model.max_strain < 0.05
(True, True)
"""

from .errors import ForceFieldError, MaterialError, MeshError, StabilityError, TissueError
from .factorization import TangentFactorization
from .forcefield import TensorMassForceField, assemble_stiffness, lame_parameters
from .integrators import (
    BackwardEuler,
    FactorizedPreconditioner,
    JacobiPreconditioner,
    StepStatistics,
    SymplecticEuler,
)
from .laws import ETMMLaw, HyperelasticLaw, LinearLaw, MaterialLaw
from .mesh import TetMesh, aaa_mesh, box_mesh, load_mesh, save_mesh, validate_mesh
from .solvers import preconditioned_bicgstab, preconditioned_cg, preconditioned_gmres
from .model import TissueModel, TissueParameters

__all__ = [
    "TissueModel",
    "TissueParameters",
    "TissueError",
    "StabilityError",
    "TetMesh",
    "MeshError",
    "aaa_mesh",
    "box_mesh",
    "load_mesh",
    "save_mesh",
    "validate_mesh",
    "TensorMassForceField",
    "ForceFieldError",
    "MaterialError",
    "MaterialLaw",
    "LinearLaw",
    "ETMMLaw",
    "HyperelasticLaw",
    "TangentFactorization",
    "preconditioned_gmres",
    "assemble_stiffness",
    "lame_parameters",
    "SymplecticEuler",
    "BackwardEuler",
    "StepStatistics",
    "JacobiPreconditioner",
    "FactorizedPreconditioner",
    "preconditioned_cg",
    "preconditioned_bicgstab",
]

"""Static equilibrium of a small tensor-mass mesh for the verification tests: roller boundary
conditions and Newton's method on the free dofs with the consistent tangent assembled densely
(column by column from the force field: slow, exact, independent of the implicit integrator)."""
from __future__ import annotations

import numpy as np


def roller_dofs(mesh) -> np.ndarray:
    """Symmetry BCs: u_x = 0 on xmin, u_y = 0 on ymin, u_z = 0 on zmin (flat dof ids)."""
    return np.unique(np.concatenate([3 * mesh.node_sets[f"{a}min"] + i for i, a in enumerate("xyz")]))


def solve_statics(ff, u: np.ndarray, free: np.ndarray, tolerance: float, max_iterations: int = 30):
    """Newton on ``free`` (flat dof ids) from the flat displacement ``u`` (updated in place) until the
    largest residual force is below ``tolerance``; returns (internal forces (n, 3), iterations).
    Raises AssertionError when it does not converge."""
    n = u.size // 3
    for iteration in range(max_iterations):
        f = np.zeros((n, 3))
        ff.add_forces(u.reshape(-1, 3), None, f)
        residual = f.reshape(-1)[free]
        if np.abs(residual).max() < tolerance:
            return f, iteration
        columns = []
        for dof in free:
            e = np.zeros(3 * n)
            e[dof] = 1.0
            out = np.zeros((n, 3))
            ff.consistent_tangent_matvec(e.reshape(-1, 3), out)
            columns.append(out.reshape(-1)[free])
        u[free] += np.linalg.solve(np.array(columns).T, residual)
    raise AssertionError(f"Newton did not converge in {max_iterations} iterations")

"""Tissue step cost on the default AAA mesh against the 30 Hz frame budget (33.3 ms).

Measured side by side in one run:
  * implicit backward Euler, factorised preconditioner, linear and ETMM laws, under a 1 N load
    (ETMM stays linear) and a 5 N load (ETMM corrects ~half the elements: GMRES or BiCGSTAB on
    the consistent tangent): step time, Krylov iterations, real-time factor = 33.3 ms / step;
  * the same with the Jacobi preconditioner (the matrix-free textbook choice) for comparison;
  * explicit symplectic Euler at its automatic substep count: one whole 1/30 s frame, and its
    cost relative to the implicit step.

Run: .venv/bin/python benchmarks/bench_tissue_step.py [--steps 30]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from tissue_fmu import TissueModel, TissueParameters, aaa_mesh

FRAME = 1.0 / 30.0
BUDGET_MS = 1000.0 * FRAME


def sac_patch_force(model: TissueModel, total: float) -> np.ndarray:
    """(n_surface, 3): ``total`` N pushing inward on the outer sac wall, +x side, mid-sac."""
    points = model.mesh.points
    outer = np.intersect1d(model.mesh.node_sets["outer"], model.surface_nodes)
    p = points[outer]
    near = (np.abs(p[:, 2] - 0.5 * points[:, 2].max()) < 0.008) & (p[:, 0] > 0.9 * np.hypot(p[:, 0], p[:, 1]))
    patch = outer[near]
    force = np.zeros((model.n_surface, 3))
    force[np.searchsorted(model.surface_nodes, patch), 0] = -total / patch.size
    return force


def time_implicit(mesh, law: str, load: float, steps: int, nonsymmetric_solver="gmres", **params) -> dict:
    t0 = time.perf_counter()
    model = TissueModel(mesh, TissueParameters(law=law, **params))
    build = time.perf_counter() - t0
    model.integrator.nonsymmetric_solver = nonsymmetric_solver
    model.set_contact_force(sac_patch_force(model, load))
    t0 = time.perf_counter()
    model.step(0.0, FRAME)  # factorisation (once per dt) and first numba calls
    first = time.perf_counter() - t0
    times, iterations, converged = [], [], True
    for k in range(1, steps + 1):
        t0 = time.perf_counter()
        model.step(k * FRAME, FRAME)
        times.append(time.perf_counter() - t0)
        iterations.append(model.solver_iterations)
        converged &= model.solver_converged
    step_ms = 1000.0 * statistics.median(times)
    return dict(build=build, first=first, step_ms=step_ms, iterations=statistics.mean(iterations),
                converged=converged, residual=model.solver_residual, reach=np.abs(model.displacement).max(),
                nonlinear=model.nonlinear_fraction, solver=model.integrator.last_solver)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=30, help="timed implicit steps per case")
    args = parser.parse_args()

    mesh = aaa_mesh()
    print(f"default AAA mesh: {mesh.n_nodes} nodes, {mesh.n_tets} tets, frame budget {BUDGET_MS:.1f} ms")
    print(f"{'case':44s} {'step ms':>8s} {'iters':>6s} {'RT factor':>9s} {'conv':>5s} "
          f"{'|u|max mm':>9s} {'nl frac':>7s} {'first ms':>8s}")
    results = {}
    cases = [
        ("linear, 1 N, factorized", "linear", 1.0, {}),
        ("etmm, 1 N, factorized", "etmm", 1.0, {}),
        ("linear, 5 N, factorized", "linear", 5.0, {}),
        ("etmm, 5 N, factorized (GMRES)", "etmm", 5.0, {}),
        ("etmm, 5 N, factorized (BiCGSTAB)", "etmm", 5.0, dict(nonsymmetric_solver="bicgstab")),
        ("etmm, 5 N, factorized (GMRES), tol 1e-4", "etmm", 5.0, dict(cg_tolerance=1e-4)),
        ("linear, 1 N, jacobi (max 1000 it)", "linear", 1.0, dict(preconditioner="jacobi")),
    ]
    for label, law, load, params in cases:
        slow = params.get("preconditioner") == "jacobi" or params.get("nonsymmetric_solver") == "bicgstab"
        steps = min(args.steps, 5) if slow else args.steps
        r = time_implicit(mesh, law, load, steps, **params)
        results[label] = r
        print(f"{label:44s} {r['step_ms']:8.1f} {r['iterations']:6.1f} {BUDGET_MS / r['step_ms']:9.2f} "
              f"{str(r['converged']):>5s} {1000 * r['reach']:9.3f} {r['nonlinear']:7.3f} {1000 * r['first']:8.0f}")

    # Explicit: one whole frame at the automatic substep count.
    model = TissueModel(mesh, TissueParameters(law="linear", integrator="explicit", substeps="auto"))
    model.set_contact_force(sac_patch_force(model, 1.0))
    model.step(0.0, 10 * model.critical_time_step)  # numba warm-up
    model.reset()
    model.set_contact_force(sac_patch_force(model, 1.0))
    t0 = time.perf_counter()
    model.step(0.0, FRAME)
    explicit_ms = 1000.0 * (time.perf_counter() - t0)
    implicit_ms = results["linear, 1 N, factorized"]["step_ms"]
    print(f"\nexplicit symplectic Euler, linear: critical step {1e6 * model.critical_time_step:.2f} us, "
          f"{model.substeps} substeps per frame, frame {explicit_ms:.0f} ms "
          f"({1000 * explicit_ms / model.substeps:.0f} us/substep), RT factor {BUDGET_MS / explicit_ms:.3f}")
    print(f"explicit frame / implicit step (linear, factorized): {explicit_ms / implicit_ms:.0f}x")
    jacobi = results["linear, 1 N, jacobi (max 1000 it)"]
    print(f"jacobi / factorized step time (linear): {jacobi['step_ms'] / implicit_ms:.1f}x, "
          f"jacobi final relative residual {jacobi['residual']:.2e} (factorized "
          f"{results['linear, 1 N, factorized']['residual']:.1e})")


if __name__ == "__main__":
    main()

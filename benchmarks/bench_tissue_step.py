"""Implicit tissue step against the 30 Hz frame budget (33.3 ms), at growing wall sizes.

Setting: ETMM or linear law, implicit backward Euler at 30 Hz, viscosity 50 Pa s,
force in -x spread over the 4 surface nodes nearest the sac contact point (0.022, 0, 0.065), full
wall active; step time = median of the timed steps after 3 warm-up steps (mean and max are
printed too: a refactorisation shows up there).  Everything is measured side by side in one run;
this 2-core machine is shared, so compare the ratios, not the absolute times, between runs.

Printed:
  0. the worst frames: the load ramped to 0.5, 2 or 5 N over 10 frames from rest, 30 frames (the
     64x80x2 wall at 0.5 N): median, p99 and max of the step and the frames over the 33 ms budget,
     for the exact step and the budgeted step at several budgets side by side, with the budgeted
     step's displacement error against the exact step and against the fine reference (FRAME / 4);
  1. the frame-budget cases, the step against a baseline without the maintained factorisation
     (rest-state factorisation as GMRES preconditioner, consistent ETMM tangent over every
     candidate tet, no extrapolated warm start), and the ETMM / linear cost at the same load;
  2. how the step cost grows with the node count (>= 3 wall sizes) and where it goes: force
     (add_forces), tangent products, factorisation (rest factor, Woodbury columns and
     corrections, tangent refactorisations), solves (factor applications), other;
  3. the tangent strategies and solver backends measured choice by choice (default wall, 5 N);
  4. the compliance block for p = 4..16 contact nodes, relative to one step;
  5. the tangent-mode factorisation alternatives at the default wall's 5 N state (factor and solve
     times, GMRES iterations on the exact non-symmetric system), and the single-vector rest solve
     at every size (what bounds the 0.5 N steps);
  6. a step in which elements fail (issue 32) against the same step without, from the same state:
     the removal, the masses and the implicit step's refactorisation.

Run: python benchmarks/bench_tissue_step.py [--steps 10] [--quick]
"""

from __future__ import annotations

import argparse
import copy
import os
import statistics
import tempfile
import time
from collections import defaultdict

import numpy as np

from tissue_fmu import TissueModel, TissueParameters, aaa_mesh, kernels, load_mesh, save_mesh
from tissue_fmu.factorization import BACKENDS, TangentFactorization, backend_available, default_backend, sparse_lu
from tissue_fmu.integrators import BackwardEuler, FactorizedPreconditioner
from tissue_fmu.precompute import tensors_to_csr

FRAME = 1.0 / 30.0
BUDGET_MS = 1000.0 * FRAME
CONTACT_POINT = (0.022, 0.0, 0.065)
VISCOSITY = 50.0


def patch_force(model: TissueModel, total: float, k: int = 4) -> np.ndarray:
    d = np.linalg.norm(model.surface_positions() - np.asarray(CONTACT_POINT), axis=1)
    force = np.zeros((model.n_surface, 3))
    force[np.argsort(d)[:k], 0] = -total / k
    return force


# --------------------------------------------------------------------------------------
# the baseline: the step without the maintained factorisation, for the comparison columns
# --------------------------------------------------------------------------------------


class _BaselineBackwardEuler(BackwardEuler):
    """The baseline step: separate tangent and damping products, the all-candidate consistent
    ETMM kernel, the warm start without extrapolation."""

    def _apply_system(self, p, out):
        h = self._h
        tmp = self._apply_tmp
        self._tangent(p, out)
        out *= h * h
        if self.viscous:
            self.force_field.damping_matvec(p, tmp)
            tmp *= h
            out += tmp
        np.multiply(self.mass, p, out=tmp)
        out += tmp


def baseline_model(mesh, law: str) -> TissueModel:
    model = TissueModel(mesh, TissueParameters(law=law, viscosity=VISCOSITY))
    ff = model.force_field
    damping = ff.damping_tensors()
    pc = FactorizedPreconditioner(ff.stiffness_matrix(), model.masses, model.fixed,
                                  damping=None if damping is None else tensors_to_csr(damping))
    integrator = _BaselineBackwardEuler(ff, model.masses, model.fixed, model.params.cg_tolerance,
                                      model.params.cg_max_iterations, viscous=True, preconditioner=pc)
    integrator.extrapolate = False
    if law == "etmm":
        def consistent(du, out, ff=ff):
            out.fill(0.0)
            k = ff.stiffness
            kernels.tensor_mass_matvec(k.vertex, k.edges, k.edge_tensors, du, 1.0, out)
            kernels.etmm_consistent_tangent(ff._tets, ff._grads, ff._volumes, ff._lam, ff._mu, ff._candidates,
                                            ff._u_last, du, ff.nonlinear_strain_threshold, ff._beta_over_alpha, out)
        ff.consistent_tangent_matvec = consistent
    model.integrator = integrator
    return model


# --------------------------------------------------------------------------------------
# timing with a split
# --------------------------------------------------------------------------------------


class _Timed:
    """Wraps callables on an object, adding their wall time to a bucket."""

    def __init__(self):
        self.times = defaultdict(float)

    def wrap(self, obj, name, bucket):
        function = getattr(obj, name)

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                self.times[bucket] += time.perf_counter() - t0

        setattr(obj, name, timed)


class _TimedPreconditioner:
    def __init__(self, inner, timer):
        self.inner, self.timer = inner, timer

    def update(self, h):
        t0 = time.perf_counter()
        self.inner.update(h)
        self.timer.times["factorisation"] += time.perf_counter() - t0

    def record_iterations(self, n):
        if hasattr(self.inner, "record_iterations"):
            self.inner.record_iterations(n)

    def __call__(self, r, out):
        t0 = time.perf_counter()
        self.inner(r, out)
        self.timer.times["solves"] += time.perf_counter() - t0


def run(model: TissueModel, load: float, steps: int, warmup: int = 3, split: bool = False) -> dict:
    model.set_contact_force(patch_force(model, load))
    timer = _Timed()
    pc = model.integrator.preconditioner
    if split:
        ff = model.force_field
        timer.wrap(ff, "add_forces", "force")
        for name in ("tangent_matvec", "consistent_tangent_matvec", "system_matvec", "damping_matvec",
                     "add_tangent_correction"):
            if hasattr(ff, name):
                timer.wrap(ff, name, "tangent")
        model.integrator.preconditioner = _TimedPreconditioner(pc, timer)
    times, iterations = [], []
    factorizations0 = getattr(pc, "factorizations", 0)
    for k in range(warmup + steps):
        if k == warmup:
            timer.times.clear()
            factorizations0 = getattr(pc, "factorizations", 0)
        t0 = time.perf_counter()
        model.step(k * FRAME, FRAME)
        elapsed = time.perf_counter() - t0
        if k >= warmup:
            times.append(elapsed)
            iterations.append(model.solver_iterations)
    if split:
        model.integrator.preconditioner = pc
    total = sum(times)
    parts = {key: 1000.0 * value / steps for key, value in timer.times.items()}
    parts["other"] = 1000.0 * total / steps - sum(parts.values())
    return dict(median=1000.0 * statistics.median(times), mean=1000.0 * total / steps, max=1000.0 * max(times),
                iterations=statistics.mean(iterations), nonlinear=model.nonlinear_fraction,
                factorizations=getattr(pc, "factorizations", 0) - factorizations0, parts=parts,
                mode=getattr(pc, "mode", "rest"), displacement=model.displacement.copy())


def line(label: str, r: dict) -> str:
    return (f"{label:46s} {r['median']:8.1f} {r['mean']:8.1f} {r['max']:8.1f} {r['iterations']:6.2f} "
            f"{r['factorizations']:5d} {r['nonlinear']:7.3f}  {r['mode']}")


HEADER = f"{'case':46s} {'median':>8s} {'mean':>8s} {'max':>8s} {'iters':>6s} {'facts':>5s} {'nl frac':>7s}  mode"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=10, help="timed steps per case (after 3 warm-up steps)")
    parser.add_argument("--quick", action="store_true", help="skip the largest wall and the 64x80x2 baseline run")
    parser.add_argument("--only", type=int, default=None,
                        help="run only this section (0: the worst frames; 5: the tangent alternatives; 6: a "
                             "step with a failure)")
    args = parser.parse_args()
    steps = args.steps
    if args.only == 0:
        worst_frames(aaa_mesh(), aaa_mesh(n_circumferential=64, n_axial=80, n_radial=2))
        return
    if args.only == 6:
        failure_step(aaa_mesh(), aaa_mesh(n_circumferential=64, n_axial=80, n_radial=2))
        return
    if args.only == 5:
        sizes = [(32, 40, 2), (48, 60, 2), (64, 80, 2)] + ([] if args.quick else [(80, 100, 2)])
        tangent_alternatives(aaa_mesh(), None, sizes)
        return
    installed = [name for name in BACKENDS if backend_available(name)]
    print(f"frame budget {BUDGET_MS:.1f} ms; rest factor backend: {default_backend()} (installed: "
          f"{', '.join(installed)}; see tissue_fmu.factorization.BACKENDS)")

    # 1. the frame-budget cases, the step and the baseline
    default = aaa_mesh()
    big = aaa_mesh(n_circumferential=64, n_axial=80, n_radial=2)
    with tempfile.TemporaryDirectory() as folder:  # the same wall through a mesh file
        path = os.path.join(folder, "wall_64x80x2.vtu")
        save_mesh(big, path)
        from_file = load_mesh(path)
    worst_frames(default, big)
    frame_budget_cases(default, big, from_file, steps, args.quick)
    # 2. growth with the node count and where the time goes
    sizes = [(32, 40, 2), (48, 60, 2), (64, 80, 2)] + ([] if args.quick else [(80, 100, 2)])
    growth(sizes, steps)
    # 3. choices, one at a time (default wall, ETMM, 5 N; and 64x80x2, 0.5 N for the backend)
    choices(default, big, installed, steps)
    # 4. compliance cost
    compliance_cost(default, steps)
    # 5. tangent-mode alternatives and the rest solve
    tangent_alternatives(default, big, sizes)
    # 6. a step with a failure
    failure_step(default, big)


def frame_costs(model: TissueModel, peak: float, frames: int, ramp: int,
                substeps: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(frames,) s per frame and (frames, n, 3) displacements at the frames' ends, with the load ramped
    linearly to ``peak`` over ``ramp`` frames, then held; ``substeps``: steps of FRAME / substeps per
    frame (the fine reference)."""
    costs = np.empty(frames)
    displacements = np.empty((frames,) + model.displacement.shape)
    h = FRAME / substeps
    for k in range(frames):
        model.set_contact_force(patch_force(model, peak * min(k + 1, ramp) / ramp))
        t0 = time.perf_counter()
        for j in range(substeps):
            model.step(k * FRAME + j * h, h)
        costs[k] = time.perf_counter() - t0
        displacements[k] = model.displacement
    return costs, displacements


#: the budgets (Krylov iterations per frame) section 0 compares, per wall
BUDGETS = {"default": [2, 4, 6, 8], "64x80x2": [1, 2]}


def worst_frames(default, big, frames: int = 30, ramp: int = 10) -> None:
    """Section 0: every frame counts. The load ramped to its peak over ``ramp`` frames, then held, for
    ``frames`` frames from rest (the rest factorisation and the kernels' loading done before, as the
    FMU does at initialisation; the first frames, where the wall starts to stiffen, are the ones a user
    meets): median, p99 and max of the frame, the frames over the 33 ms budget, and the budgeted
    step's displacement error against the exact step and against the fine reference (the exact step
    at FRAME / 4), the largest over the frames of the largest nodal difference, as a percentage of the
    largest displacement."""
    print(f"\n0. worst frames: the load ramped over {ramp} frames, {frames} frames from rest (ms per frame)")
    print(f"{'case':30s} {'step':26s} {'median':>7s} {'p99':>7s} {'max':>7s} {'over':>5s} {'vs exact':>9s} "
          f"{'vs fine':>8s} {'max res':>8s}")
    for label, wall, mesh, peak in [("default wall, etmm, 0.5 N", "default", default, 0.5),
                                    ("default wall, etmm, 2 N", "default", default, 2.0),
                                    ("default wall, etmm, 5 N", "default", default, 5.0),
                                    ("64x80x2 wall, etmm, 0.5 N", "64x80x2", big, 0.5)]:
        def model(**budgeted):
            m = TissueModel(mesh, TissueParameters(law="etmm", viscosity=VISCOSITY, **budgeted))
            m.prepare(FRAME)
            return m

        _, fine = frame_costs(model(), peak, frames, ramp, substeps=4)
        costs, exact = frame_costs(model(), peak, frames, ramp)
        scale = np.abs(fine).max()

        def error(u):
            return 100.0 * np.abs(u - exact).max() / scale, 100.0 * np.abs(u - fine).max() / scale

        rows = [("exact", 1000.0 * costs, error(exact), 0.0)]
        for iterations in BUDGETS[wall]:
            m = model(implicit_step="budgeted", budget_iterations=iterations)
            residuals = []
            m.integrator.step = _recording(m.integrator.step, residuals)
            costs, u = frame_costs(m, peak, frames, ramp)
            rows.append((f"budgeted, {iterations} iterations", 1000.0 * costs, error(u), max(residuals)))
        for step, c, (e_exact, e_fine), residual in rows:
            print(f"{label:30s} {step:26s} {np.median(c):7.1f} {np.percentile(c, 99):7.1f} {c.max():7.1f} "
                  f"{int((c > BUDGET_MS).sum()):2d}/{frames} {e_exact:8.3f}% {e_fine:7.3f}% {residual:8.1e}")


def _recording(step, residuals):
    def recorded(*args):
        statistics = step(*args)
        residuals.append(statistics.relative_residual)
        return statistics
    return recorded


def frame_budget_cases(default, big, from_file, steps: int, quick: bool) -> None:
    """Section 1: the frame-budget cases, the step against the baseline, ETMM against linear."""
    print(f"\n1. frame-budget cases (ms per step; median/mean/max of {steps} after 3)")
    print(HEADER)
    results = {}
    for label, mesh, law, load, baseline in [
        ("default wall, linear, 5 N", default, "linear", 5.0, False),
        ("default wall, etmm, 5 N", default, "etmm", 5.0, False),
        ("default wall, etmm, 5 N, baseline", default, "etmm", 5.0, True),
        ("default wall, linear, 5 N, baseline", default, "linear", 5.0, True),
        ("64x80x2 wall, linear, 0.5 N", big, "linear", 0.5, False),
        ("64x80x2 wall, etmm, 0.5 N", big, "etmm", 0.5, False),
        ("64x80x2 wall, etmm, 0.5 N, baseline", big, "etmm", 0.5, True),
        ("64x80x2 wall from a .vtu file, etmm, 0.5 N", from_file, "etmm", 0.5, False),
    ]:
        if baseline and mesh is big and quick:
            continue
        model = baseline_model(mesh, law) if baseline else TissueModel(mesh, TissueParameters(law=law, viscosity=VISCOSITY))
        results[label] = r = run(model, load, steps)
        print(line(label, r))
    a, b = results["default wall, etmm, 5 N"], results["default wall, linear, 5 N"]
    print(f"ETMM / linear at 5 N (default wall): median {a['median'] / b['median']:.2f}, mean {a['mean'] / b['mean']:.2f}"
          f"  (target <= 1.5; the paper reports 4)")
    f = results["default wall, etmm, 5 N, baseline"]
    print(f"speed-up over the baseline step, default wall ETMM 5 N: median {f['median'] / a['median']:.1f}x, "
          f"mean {f['mean'] / a['mean']:.1f}x; max |u - u_baseline| / max |u| = "
          f"{np.abs(a['displacement'] - f['displacement']).max() / np.abs(f['displacement']).max():.1e}")
    if "64x80x2 wall, etmm, 0.5 N, baseline" in results:
        f, a = results["64x80x2 wall, etmm, 0.5 N, baseline"], results["64x80x2 wall, etmm, 0.5 N"]
        print(f"speed-up over the baseline step, 64x80x2 ETMM 0.5 N: median {f['median'] / a['median']:.1f}x")
    print(f"64x80x2 ETMM 0.5 N / linear 0.5 N: {results['64x80x2 wall, etmm, 0.5 N']['median'] / results['64x80x2 wall, linear, 0.5 N']['median']:.2f}")


def growth(sizes, steps: int) -> None:
    """Section 2: the step's cost by wall size and load, and where it goes."""
    print("\n2. growth with the node count (etmm, 0.5 N and 5 N; ms per step, mean of the timed steps)")
    print(f"{'wall':10s} {'nodes':>6s} {'load':>5s} {'median':>8s} {'mean':>8s} {'force':>7s} {'tangent':>8s} "
          f"{'factor':>7s} {'solves':>7s} {'other':>7s} {'iters':>6s} {'mode':>8s}")
    for nc, na, nr in sizes:
        mesh = aaa_mesh(n_circumferential=nc, n_axial=na, n_radial=nr)
        for load in (0.5, 5.0):
            model = TissueModel(mesh, TissueParameters(law="etmm", viscosity=VISCOSITY))
            r = run(model, load, steps, split=True)
            p = r["parts"]
            print(f"{nc}x{na}x{nr:<5d} {mesh.n_nodes:6d} {load:5.1f} {r['median']:8.1f} {r['mean']:8.1f} "
                  f"{p.get('force', 0):7.2f} {p.get('tangent', 0):8.2f} {p.get('factorisation', 0):7.2f} "
                  f"{p.get('solves', 0):7.2f} {p['other']:7.2f} {r['iterations']:6.2f} {r['mode']:>8s}")


def choices(default, big, installed, steps: int) -> None:
    """Section 3: each tangent strategy and solver backend against the chosen one."""
    print("\n3. choices measured one at a time (ms per step)")
    print(HEADER)
    cases = [
        ("default, 5 N: chosen (budget 24, >6 its)", default, 5.0, {}),
        ("default, 5 N: refactor every step", default, 5.0, dict(refactor_iterations=0)),
        ("default, 5 N: refactor when > 2 its", default, 5.0, dict(refactor_iterations=2, refactor_budget=10**9)),
        ("default, 5 N: never refactor", default, 5.0, dict(refactor_iterations=10**9, refactor_budget=10**9)),
        ("default, 5 N: no extrapolated warm start", default, 5.0, dict(extrapolate=False)),
        ("default, 5 N: rest factor only (GMRES)", default, 5.0, dict(rest_only=True)),
        ("64x80x2, 0.5 N: Woodbury (chosen)", big, 0.5, {}),
        ("64x80x2, 0.5 N: assembled tangent instead", big, 0.5, dict(max_lowrank_dofs=-1)),
    ]
    for backend in installed:  # the rest factor's backends side by side (the same steps otherwise)
        cases += [(f"64x80x2, 0.5 N: rest factor by {backend}", big, 0.5, dict(backend=backend)),
                  (f"64x80x2, 0.5 N linear: {backend}", big, 0.5, dict(law="linear", backend=backend)),
                  (f"default, 0.5 N linear: {backend}", default, 0.5, dict(law="linear", backend=backend))]
    for label, mesh, load, options in cases:
        options = dict(options)
        model = TissueModel(mesh, TissueParameters(law=options.pop("law", "etmm"), viscosity=VISCOSITY))
        if options.pop("rest_only", False):
            model.integrator.preconditioner.max_lowrank_dofs = 10**9
            model.integrator.preconditioner.update = lambda h, pc=model.integrator.preconditioner: (
                pc._set_step(h) if h != pc._h else None, setattr(pc, "mode", "rest"))
        if "extrapolate" in options:
            model.integrator.extrapolate = options.pop("extrapolate")
        if "backend" in options:
            model.integrator.preconditioner = TangentFactorization(model.force_field, model.masses, model.fixed,
                                                                   backend=options.pop("backend"))
        for key, value in options.items():
            setattr(model.integrator.preconditioner, key, value)
        print(line(label, run(model, load, steps)))


def compliance_cost(default, steps: int) -> None:
    """Section 4: the compliance block for p = 4..16 contact nodes, relative to one step."""
    print("\n4. compliance block (default wall, etmm) relative to one step: first call for a patch (its"
          "\n   columns solved), and again for the same patch (cached columns; what a per-step caller pays)")
    for load in (0.5, 5.0):
        model = TissueModel(default, TissueParameters(law="etmm", viscosity=VISCOSITY))
        r = run(model, load, steps)
        d = np.linalg.norm(model.surface_positions() - np.asarray(CONTACT_POINT), axis=1)
        order = np.argsort(d)
        for p in (4, 8, 12, 16):
            fresh = copy.deepcopy(model)
            t0 = time.perf_counter()
            fresh.compliance(order[:p])
            first = 1000.0 * (time.perf_counter() - t0)
            t0 = time.perf_counter()
            for _ in range(3):
                fresh.compliance(order[:p])
            again = 1000.0 * (time.perf_counter() - t0) / 3
            print(f"  {load:3.1f} N, p = {p:2d} ({3 * p:2d} columns, mode {fresh.integrator.preconditioner.mode:7s}): "
                  f"first {first:7.1f} ms = {first / r['median']:5.2f} x the step, again {again:6.2f} ms = "
                  f"{again / r['median']:5.3f} x the step ({r['median']:.1f} ms)")


def _best_ms(function, repeat: int = 3):
    best, result = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = function()
        best = min(best, time.perf_counter() - t0)
    return 1000.0 * best, result


def _gmres_iterations(a, b, solve, tolerance: float) -> int:
    """Right-preconditioned GMRES iterations (scipy, restart 50) for A x = b to ``tolerance``."""
    from scipy.sparse.linalg import LinearOperator, gmres

    n = a.shape[0]
    count = [0]

    def callback(_):
        count[0] += 1

    preconditioner = LinearOperator((n, n), matvec=solve)
    x, info = gmres(a, b, M=preconditioner, rtol=tolerance, restart=50, maxiter=20, callback=callback,
                    callback_type="pr_norm")
    return count[0] if info == 0 else -1


def tangent_alternatives(default, big, sizes) -> None:
    """Section 5: what a tangent refactorisation costs with each backend, and what it buys."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    print("\n5. tangent-mode alternatives, default wall, ETMM, 5 N, state after 6 steps (tangent mode):"
          "\n   factor = best of 2 (CHOLMOD: analysis + numeric);"
          "\n   GMRES = iterations on the exact non-symmetric step matrix to 1e-6 with that preconditioner")
    model = TissueModel(default, TissueParameters(law="etmm", viscosity=VISCOSITY))
    model.set_contact_force(patch_force(model, 5.0))
    pc = model.integrator.preconditioner
    stale = None
    for k in range(6):
        model.step(k * FRAME, FRAME)
        if k == 2:
            stale = pc._tangent_data.copy() if pc._tangent_data is not None else None
    h, ff = FRAME, pc.force_field
    ids, blocks = ff.tangent_blocks()
    data = pc._rest_data.copy()
    kernels.scatter_element_blocks(ff.active_tets, ids, ids.shape[0], blocks, h * h, pc._indptr, pc._offsets, data)
    free_data = data[pc._keep]
    nf = pc._free_dofs.size
    a = sp.csr_matrix((free_data, pc._f_indices, pc._f_indptr), shape=(nf, nf))
    sym = ((a + a.T) * 0.5).tocsr()
    sym.sort_indices()
    b = np.random.default_rng(0).standard_normal(nf)
    asym = abs(a - a.T).max() / abs(a).max()
    print(f"   {nf} free dofs, {ids.shape[0]} super-threshold tets; max |A - A^T| / max |A| = {asym:.3f}")
    print(f"   {'preconditioner':66s} {'factor':>8s} {'solve':>7s} {'GMRES':>6s}")

    def row(label, factor_ms, solve, note=""):
        solve_ms, _ = _best_ms(lambda: solve(b), 5)
        its = _gmres_iterations(a, b, solve, model.params.cg_tolerance)
        factor = f"{factor_ms:8.1f}" if factor_ms is not None else f"{'-':>8s}"
        print(f"   {label:66s} {factor} {solve_ms:7.2f} {its:6d}  {note}")

    ms, lu = _best_ms(lambda: sparse_lu(pc._free_matrix(free_data)), 2)
    row("SuperLU of the exact tangent, MMD(A+A^T) (chosen)", ms, lambda r: lu.solve(r, trans="T"),
        f"nnz(L+U) {lu.L.nnz + lu.U.nnz}")
    inverse = np.argsort(lu.perm_c)
    permuted = pc._free_matrix(free_data)[inverse][:, inverse].tocsc()
    ms, lu_p = _best_ms(lambda: splu(permuted, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                                     options={"SymmetricMode": True}), 2)

    def solve_permuted(r, lu_p=lu_p, inverse=inverse):
        x = np.empty_like(r)
        x[inverse] = lu_p.solve(r[inverse], trans="T")
        return x

    row("same, ordering of an earlier factorisation reused", ms, solve_permuted)
    if stale is not None:
        lu_s = sparse_lu(pc._free_matrix(stale))
        row("SuperLU of the tangent 3 steps earlier (what reuse gives)", None, lambda r: lu_s.solve(r, trans="T"))
    cholmods = [name for name in BACKENDS if BACKENDS[name].factor is not None and backend_available(name)]
    rest = sp.csr_matrix((pc._rest_data[pc._keep], pc._f_indices, pc._f_indptr), shape=(nf, nf))
    for name in cholmods:
        factor_class = BACKENDS[name].factor
        ms, ch = _best_ms(lambda: factor_class(sym.indptr, sym.indices, sym.data), 2)
        row(f"CHOLMOD ({name}) of the symmetric part (A + A^T) / 2", ms, ch.solve)
        ms, cr = _best_ms(lambda: factor_class(rest.indptr, rest.indices, rest.data), 2)
        row(f"CHOLMOD ({name}) of the rest matrix (no refactorisation)", ms, cr.solve)

    print(f"\n   single-vector rest solve (the whole 0.5 N step is one), ms, by {' / '.join(cholmods + ['SuperLU'])}:")
    for nc, na, nr in sizes:
        mesh = aaa_mesh(n_circumferential=nc, n_axial=na, n_radial=nr)
        model = TissueModel(mesh, TissueParameters(law="linear", viscosity=VISCOSITY))
        model.step(0.0, FRAME)
        pc = model.integrator.preconditioner
        rhs = np.random.default_rng(0).standard_normal(pc._free_dofs.size)
        rest = pc._rest_data[pc._keep]
        times = []
        for name in cholmods:
            factor = BACKENDS[name].factor(pc._f_indptr, pc._f_indices, rest)
            times.append(_best_ms(lambda: factor.solve(rhs), 5)[0])
        lu = sparse_lu(pc._free_matrix(rest))
        superlu_ms = _best_ms(lambda: lu.solve(rhs, trans="T"), 5)[0]
        print(f"   {nc}x{na}x{nr}: {pc._free_dofs.size} free dofs, {' / '.join(f'{t:6.2f}' for t in times + [superlu_ms])} "
              f"(nnz(L) of SuperLU {lu.L.nnz}: {16e-6 * lu.L.nnz / superlu_ms:.1f} GB/s reading it twice)")


def failure_step(default, big, repeat: int = 3) -> None:
    """Section 6: the cost of a frame in which elements fail, against the same frame without, from
    the same state (the wall loaded with 2 N for 12 frames; the failure stretch set just below the
    largest stretch the next frame reaches, so that its most strained elements fail)."""
    import logging

    from tissue_fmu.failure import failed_elements

    logging.getLogger("tissue_fmu.model").setLevel(logging.ERROR)  # the failure's log line, 2 x repeat times
    print("\n6. a frame with a failure against the same frame without (ms, best of "
          f"{repeat}; ETMM, 2 N, whole wall)")
    print(f"{'case':46s} {'normal':>8s} {'failure':>8s} {'ratio':>6s} {'failed':>6s}")
    for label, mesh in [("default wall", default), ("64x80x2 wall", big)]:
        for step in ("exact", "budgeted"):
            model = TissueModel(mesh, TissueParameters(law="etmm", viscosity=VISCOSITY, implicit_step=step,
                                                       budget_iterations=4 if mesh is default else 1))
            model.prepare(FRAME)
            model.set_contact_force(patch_force(model, 2.0))
            for k in range(12):
                model.step(k * FRAME, FRAME)
            probe = copy.deepcopy(model)
            probe.step(12 * FRAME, FRAME)
            ff, u = probe.force_field, probe.displacement
            tension = np.sqrt(1.0 + 2.0 * ff.element_max_strain(u))
            limit = float(np.sort(tension)[-5])  # the five most stretched elements fail
            normal, failing = [], []
            for _ in range(repeat):
                for times, stretch in ((normal, None), (failing, limit)):
                    m = copy.deepcopy(model)
                    m._failure_stretch = stretch
                    t0 = time.perf_counter()
                    m.step(12 * FRAME, FRAME)
                    times.append(1000.0 * (time.perf_counter() - t0))
            failed = failed_elements(probe.force_field, probe.displacement, limit).size
            print(f"{label + ', ' + step:46s} {min(normal):8.1f} {min(failing):8.1f} "
                  f"{min(failing) / min(normal):6.1f} {failed:6d}")


if __name__ == "__main__":
    main()

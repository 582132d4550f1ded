"""Tensor-mass kernels: precompute time, linear force vs scipy CSR SpMV, ETMM and hyperelastic cost.

Run: ``python benchmarks/bench_tissue_kernels.py`` (single thread; all ratios measured in this run).
Targets: precompute of 100k tets < 2 s; linear kernel >= 1.5x faster than CSR SpMV with the
identical stiffness; ETMM force <= 1.5x the linear force when a minority of tets is non-linear.
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import time  # noqa: E402

import numpy as np  # noqa: E402

from tissue_fmu import kernels  # noqa: E402
from tissue_fmu.forcefield import TensorMassForceField  # noqa: E402
from tissue_fmu.materials import lame_parameters  # noqa: E402
from tissue_fmu.mesh import aaa_mesh, box_mesh  # noqa: E402
from tissue_fmu.precompute import tensor_mass_tensors, tensors_to_csr  # noqa: E402

E, NU = 1.044e6, 0.45


def best_of(fn, repeat=30):
    fn()  # warm-up (and numba compile)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times), float(np.median(times))


def indentation(points, centre, radius, depth, axis=2):
    """Smooth localized indentation: a Gaussian dent of the given depth (m) around centre."""
    r2 = ((points - centre) ** 2).sum(axis=1)
    u = np.zeros_like(points)
    u[:, axis] = -depth * np.exp(-r2 / (2 * radius**2))
    return u


def bench_mesh(name, mesh, centre, radius, depth):
    pts, tets = mesh.points, mesh.tets
    print(f"\n== {name}: {mesh.n_tets} tets, {mesh.n_nodes} nodes")
    lam, mu = lame_parameters(E, NU)

    t_pre, _ = best_of(lambda: tensor_mass_tensors(pts, tets, lam, mu), repeat=3)
    tensors = tensor_mass_tensors(pts, tets, lam, mu)
    t0 = time.perf_counter()
    TensorMassForceField(pts, tets, E, NU, law="etmm")
    t_ff = time.perf_counter() - t0
    print(f"precompute (gradients, vertex/edge tensors): {t_pre:.3f} s; full etmm force-field setup "
          f"incl. mesh validation and edge screen: {t_ff:.3f} s")

    # ---- linear kernel vs CSR SpMV, identical operator
    k = tensors_to_csr(tensors)
    u = 1e-4 * np.random.default_rng(0).standard_normal(pts.shape)
    out = np.zeros_like(u)
    flat = u.reshape(-1)

    def tensor_mass():
        out.fill(0.0)
        kernels.tensor_mass_matvec(tensors.vertex, tensors.edges, tensors.edge_tensors, u, 1.0, out)

    y = np.empty(3 * mesh.n_nodes)

    def csr():
        # the CSR product into a preallocated vector (scipy's internal kernel, no allocation)
        y.fill(0.0)
        from scipy.sparse._sparsetools import csr_matvec

        csr_matvec(k.shape[0], k.shape[1], k.indptr, k.indices, k.data, flat, y)

    t_tm, t_tm_med = best_of(tensor_mass, 50)
    t_csr, t_csr_med = best_of(csr, 50)
    t_csr_op, _ = best_of(lambda: k @ flat, 50)
    tensor_mass()
    diff = np.abs(out.reshape(-1) - k @ flat).max()
    print(f"linear force: tensor-mass {t_tm * 1e3:.3f} ms (median {t_tm_med * 1e3:.3f}), CSR SpMV "
          f"{t_csr * 1e3:.3f} ms (median {t_csr_med * 1e3:.3f}; K @ u incl. allocation {t_csr_op * 1e3:.3f}); "
          f"speed-up {t_csr / t_tm:.2f}x (median {t_csr_med / t_tm_med:.2f}x, vs K @ u {t_csr_op / t_tm:.2f}x); "
          f"max |diff| {diff:.2e} (|Ku|max {np.abs(out).max():.2e})")
    nnz_bytes = k.data.nbytes + k.indices.nbytes + k.indptr.nbytes
    tm_bytes = tensors.vertex.nbytes + tensors.edge_tensors.nbytes + tensors.edges.nbytes
    print(f"operator storage: tensor-mass {tm_bytes / 1e6:.1f} MB, CSR {nnz_bytes / 1e6:.1f} MB")

    # ---- ETMM / hyperelastic force cost relative to the linear force
    u = indentation(pts, centre, radius, depth)
    f = np.zeros_like(u)
    linear = TensorMassForceField(pts, tets, E, NU, law="linear")
    centroids = pts[tets].mean(axis=1)
    region = ((centroids - centre) ** 2).sum(axis=1) < (2.5 * radius) ** 2
    wide = ((centroids - centre) ** 2).sum(axis=1) < (5.0 * radius) ** 2

    def force_of(ff):
        def run():
            f.fill(0.0)
            ff.add_forces(u, None, f)
        return run

    t_lin, _ = best_of(force_of(linear))
    cases = [
        (f"etmm, non-linear region around the contact ({region.mean():.1%} of tets)",
         dict(law="etmm", nonlinear_elements=region)),
        (f"etmm, wider non-linear region ({wide.mean():.1%} of tets)", dict(law="etmm", nonlinear_elements=wide)),
        ("etmm, every tet a candidate (edge pre-screen)", dict(law="etmm")),
        ("etmm, every tet corrected (threshold 0)", dict(law="etmm", nonlinear_strain_threshold=0.0)),
        ("hyperelastic reference", dict(law="hyperelastic")),
    ]
    print(f"state: Gaussian indentation depth {depth * 1e3:.1f} mm, radius {radius * 1e3:.1f} mm, "
          f"max principal Green strain {linear.max_strain(u):.3f}; "
          f"linear force {t_lin * 1e3:.3f} ms")
    for label, kwargs in cases:
        ff = TensorMassForceField(pts, tets, E, NU, **kwargs)
        t, _ = best_of(force_of(ff), 20)
        extra = ""
        if ff.law == "etmm":
            extra = f", non-linear fraction {ff.nonlinear_fraction:.2%}"
            if ff._screened:
                extra += f", examined after screen {ff.screened_fraction:.1%}"
        print(f"  {label}: {t * 1e3:.3f} ms = {t / t_lin:.2f}x linear{extra}")


def main():
    print("single thread: NUMBA_NUM_THREADS=%s" % os.environ["NUMBA_NUM_THREADS"])
    box = box_mesh(size=(0.1, 0.1, 0.1), divisions=(26, 26, 25))
    bench_mesh("box 0.1 m", box, centre=np.array([0.05, 0.05, 0.1]), radius=0.008, depth=0.003)
    aaa = aaa_mesh(n_circumferential=96, n_axial=104, n_radial=2)
    top = aaa.points[np.argmax(aaa.points[:, 0])].copy()  # outer wall at the sac's widest point, +x
    top[2] = 0.065
    bench_mesh("AAA", aaa, centre=top, radius=0.004, depth=0.0015)


if __name__ == "__main__":
    main()

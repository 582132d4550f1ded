"""Catheter 1 kHz step: the plain-numpy step (reference) vs the numba kernels.

Run: ``python benchmarks/bench_catheter_step.py``. The reference implementations are the ones
the tests compare against (tests/test_catheter_kernels.py); both sides run interleaved in this
run, on the default 30-segment catheter on a bent 3-vertex centerline in mode "regulate".
Target: kernel step <= 30 us, i.e. a ratio >= 4 over the plain-numpy step.
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from test_catheter_kernels import (  # noqa: E402
    ReferenceStepper,
    ref_active_chain,
    ref_chain_back,
    ref_frame,
)

from catheter_fmu import CatheterModel, CatheterParameters  # noqa: E402

N_STEPS = 2000
ROUNDS = 7


def per_call_us(fn, n: int) -> float:
    t0 = time.perf_counter()
    fn(n)
    return (time.perf_counter() - t0) / n * 1e6


def main() -> None:
    centerline = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.04], [0.022, 0.0, 0.065]])
    params = CatheterParameters(n_segments=30, centerline=centerline, controller_mode="regulate")
    new, old = CatheterModel(params, 1e-3), CatheterModel(params, 1e-3)
    ref = ReferenceStepper(old)
    new.reset(0.07)
    ref.reset(0.07)
    force = np.array([0.1, 0.0, -0.2])

    def run_new(n):
        for k in range(n):
            new.step(k * 1e-3, 1e-3, 0.07 + k * 1e-6, 0.0, force)

    last_ref = {}

    def run_old(n):
        for k in range(n):
            last_ref["out"] = ref.step(k * 1e-3, 1e-3, 0.07 + k * 1e-6, 0.0, force)

    curve = new.curve
    kin = new.kinematics
    n_prox = kin.n_segments - kin.n_active
    s_b = 0.07 - kin.active_length
    base, t, e1, e2 = kin.base_frame(0.07)

    pairs = {
        "step (whole)": (run_old, run_new),
        "chain_back (26 joints)": (
            lambda n: [ref_chain_back(curve, s_b, n_prox, 0.005) for _ in range(n)],
            lambda n: [curve.chain_back(s_b, n_prox, 0.005) for _ in range(n)],
        ),
        "frame": (
            lambda n: [ref_frame(curve, s_b) for _ in range(n)],
            lambda n: [curve.frame(s_b) for _ in range(n)],
        ),
        "active_chain (4 links)": (
            lambda n: [ref_active_chain(kin.n_active, 0.005, base, t, e1, e2, (0.3, 0.1)) for _ in range(n)],
            lambda n: [kin.active_chain(base, t, e1, e2, (0.3, 0.1)) for _ in range(n)],
        ),
    }
    for old_fn, new_fn in pairs.values():  # warm-up (numba cache load)
        old_fn(50)
        new_fn(50)

    print(f"catheter step, {params.n_segments} segments, best of {ROUNDS} x {N_STEPS} calls, interleaved")
    print(f"{'':24s} {'reference us':>13s} {'kernels us':>11s} {'ratio':>7s}")
    for name, (old_fn, new_fn) in pairs.items():
        old_t, new_t = [], []
        for _ in range(ROUNDS):
            old_t.append(per_call_us(old_fn, N_STEPS))
            new_t.append(per_call_us(new_fn, N_STEPS))
        o, w = min(old_t), min(new_t)
        print(f"{name:24s} {o:13.2f} {w:11.2f} {o / w:7.1f}")
    # Both models took the same steps with the same inputs: their outputs must agree.
    err = float(np.max(np.abs(new.outputs.centerline_positions - last_ref["out"]["centerline_positions"])))
    print(f"max |positions new - reference| after all steps: {err:.2e} m ({err / 0.005:.1e} segment lengths)")

if __name__ == "__main__":
    main()

"""The summary's statistics (peaks, energies, operator warnings) folded a block of steps at a time
(a compiled stretch's replay, in numpy) give the same numbers, bit for bit, as folded a step at a
time (the Python path): random blocks of random lengths against the step-at-a-time fold."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from orchestration.observers.statistics import BLOCK_FOLD_ROWS, Statistics

BASE = 3000  # ticks per second
STEP = 3     # the component's step in ticks


def _statistics() -> Statistics:
    scene = SimpleNamespace(summary={"peaks": ["c.force", "c.depth"], "energy": ["c.energy", "c.vector_energy"],
                                     "warnings": ["c.warning"]})
    statistics = Statistics(scene)
    statistics.initializing(SimpleNamespace(seconds=lambda tick: tick / BASE))
    return statistics


def _signals(rng, n: int) -> dict[str, np.ndarray]:
    """Values with what a fold must get right: ties of the largest magnitude, signed zeros, runs of a
    warning switching on and off, a first sample at tick 0."""
    force = rng.choice([-1.0, 0.0, 0.5, 1.0, 2.0], size=(n, 3)) * rng.choice([1.0, 1.0 + 1e-15], size=(n, 3))
    force[rng.random(n) < 0.1] = [2.0, -2.0, 2.0]  # the same magnitude, many times
    depth = rng.choice([0.0, -0.0, 1e-4, 2e-4, 3e-4], size=(n, 1))
    energy = rng.normal(size=(n, 1))
    energy[rng.random(n) < 0.1] = -0.0
    warning = (rng.random((n, 1)) < 0.3).astype(float)
    return {"force": force, "depth": depth, "energy": energy, "vector_energy": rng.normal(size=(n, 2)),
            "warning": warning}


@pytest.mark.parametrize("seed", range(40))
def test_a_block_at_a_time_folds_as_a_step_at_a_time(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 400))
    signals = _signals(rng, n)
    ticks = [STEP * k for k in range(n)] if rng.random() < 0.5 else [STEP * (k + 1) for k in range(n)]
    comp = SimpleNamespace(name="c", step=STEP)
    by_step, by_block = _statistics(), _statistics()
    for k, tick in enumerate(ticks):
        by_step.stepped(comp, tick, {name: values[k] for name, values in signals.items()})
    start, blocks = 0, 0
    while start < n:  # blocks of random lengths, long ones (in numpy) and short ones (a row at a time)
        stop = min(n, start + int(rng.choice([1, 2, BLOCK_FOLD_ROWS - 1, BLOCK_FOLD_ROWS, 33, 200])))
        by_block.stepped_block(comp, ticks[start:stop], {name: values[start:stop] for name, values in signals.items()},
                               start)
        start, blocks = stop, blocks + 1
    step_report, block_report = by_step.report(), by_block.report()
    assert repr(block_report) == repr(step_report)  # bit for bit, signed zeros and types included
    assert block_report["peaks"]["c.force"]["value"] > 0.0 and block_report["operator_warnings"]["c.warning"]


def test_a_block_with_a_nan_is_folded_a_step_at_a_time():
    """A NaN (which an FMU never reports, but a block of the scene might) is skipped by the peak as
    the step-at-a-time fold skips it, not taken as the largest value."""
    comp = SimpleNamespace(name="c", step=STEP)
    statistics = _statistics()
    depth = np.array([[1.0], [np.nan], [3.0]] + [[0.5]] * BLOCK_FOLD_ROWS)
    n = len(depth)
    signals = {"force": np.zeros((n, 3)), "depth": depth, "energy": np.zeros((n, 1)),
               "vector_energy": np.zeros((n, 2)), "warning": np.zeros((n, 1))}
    statistics.stepped_block(comp, [STEP * (k + 1) for k in range(n)], signals, 0)
    assert statistics.report()["peaks"]["c.depth"] == {"value": 3.0, "time_s": 3 * STEP / BASE}

"""The cost of every step of a component: median, p99 and max, and the steps over their budget.

A median hides the frames that matter (a tissue frame late under the hardest push leaves the haptic
loop rendering a wall that does not move), so each component keeps the distribution of its step
costs in constant memory, whatever the run's length: a histogram of nanoseconds with unit bins
below 128 ns and 64 bins per octave above (1.6 % wide, as HdrHistogram does), and the exact
maximum and count over budget. A step's budget is its own period in real time (33.3 ms for a
30 Hz tissue).

What a cost is: the wall time of the step as its host measured it: the worker process's for an
FMU hosted out of process (the master's waiting is not counted), the compiled loop's from setting
the inputs to reading the outputs (``compiled_loop.c`` bins them with the same :func:`cost_bin`),
else the host's call.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["StepCosts", "cost_bin"]

#: unit bins (ns) below 2^LINEAR_BITS, then 2^SUB_BITS bins per octave (compiled_loop.c's COST_LINEAR_BITS
#: and COST_SUB_BITS; tests/test_c_constants.py holds them equal)
LINEAR_BITS = 7
SUB_BITS = 6
_LINEAR, _PER_OCTAVE = 1 << LINEAR_BITS, 1 << SUB_BITS
#: bins up to 2^63 ns
BINS = _LINEAR + (63 - LINEAR_BITS) * _PER_OCTAVE


def cost_bin(ns: int) -> int:
    """The bin of a cost of ``ns`` nanoseconds (compiled_loop.c's ``cost_bin``, the same integers)."""
    if ns < _LINEAR:
        return max(ns, 0)
    k = ns.bit_length() - 1
    return _LINEAR + (k - LINEAR_BITS) * _PER_OCTAVE + ((ns >> (k - SUB_BITS)) & (_PER_OCTAVE - 1))


def _bin_middle(index: int) -> float:
    """The middle of bin ``index``, in ns."""
    if index < _LINEAR:
        return float(index)
    k, sub = divmod(index - _LINEAR, _PER_OCTAVE)
    k += LINEAR_BITS
    width = 1 << (k - SUB_BITS)
    return ((_PER_OCTAVE + sub) << (k - SUB_BITS)) + 0.5 * width


class StepCosts:
    """Step costs of one component; ``budget``: a step's period in real time (s)."""

    def __init__(self, budget: float):
        self.budget_ns = int(round(float(budget) * 1e9))
        self.count = 0
        self.over_budget = 0
        self.max_ns = 0
        self.bins = np.zeros(BINS, dtype=np.int64)  # also counted in place by the compiled loop

    def add(self, seconds: float) -> None:
        ns = int(round(seconds * 1e9))
        self.bins[cost_bin(ns)] += 1
        self.counted(1, ns, int(ns > self.budget_ns))

    def counted(self, count: int, max_ns: int, over_budget: int) -> None:
        """Steps whose bins were already counted (by the compiled loop): their number, the longest and
        how many went over budget."""
        self.count += int(count)
        self.max_ns = max(self.max_ns, int(max_ns))
        self.over_budget += int(over_budget)

    def quantile(self, q: float) -> float:
        """The ``q`` quantile (0 < q <= 1) in seconds, to within a bin (1.6 %): its bin's middle, at
        most the maximum."""
        if self.count == 0:
            return 0.0
        rank = max(1, math.ceil(q * self.count))
        index = int(np.searchsorted(np.cumsum(self.bins), rank))
        return min(_bin_middle(index), float(self.max_ns)) * 1e-9

    def report(self) -> dict:
        """For the summary: seconds, and how many steps were timed and went over their budget."""
        return {"median_s": self.quantile(0.5), "p99_s": self.quantile(0.99), "max_s": self.max_ns * 1e-9,
                "budget_s": self.budget_ns * 1e-9, "over_budget": self.over_budget, "timed_steps": self.count}

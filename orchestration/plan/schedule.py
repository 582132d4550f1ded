"""The schedule: which call comes next, as a function of where the components stand.

Which call comes next is a function of the components' tick counts relative to the slowest one,
of the phase within the hyperperiod and of which steps are in flight; the decision is computed
once per such state and then looked up (a 1 kHz loop beside a 30 Hz tissue has 300 ticks of
hyperperiod and a few hundred states), so the per-tick work is a table lookup. The stepping
algorithm (``orchestration.run.algorithm``) asks for :meth:`Schedule.next`; the compiled loop
plans a stretch of steps ahead with :meth:`Schedule.decide_at`, the same rule.

A decision is ``(True, rank)``: start that component's step, ``(False, rank)``: collect its step
in flight, or None: every component reached its end.
"""
from __future__ import annotations

import math
from typing import Callable

from orchestration.errors import OrchestrationError

#: Most schedule states remembered; a pathological rate mix beyond that is decided afresh each time.
MEMO_LIMIT = 200_000

Decision = tuple[bool, int]


class Schedule:
    """The schedule of ``components`` (each with ``time``, ``step``, ``end``, ``running``, ``rank``,
    ``asynchronous``, ``routes``, ``name``) for a run that ends at tick ``end``; ``seconds(tick)``
    names times in errors."""

    def __init__(self, components: list, end: int, seconds: Callable[[int], float]):
        self.components = components
        self.seconds = seconds
        #: the hyperperiod of the components' steps, in ticks
        self.period = 1
        for comp in components:
            self.period = math.lcm(self.period, comp.step)
        #: how far ahead of the slowest a component may step, in ticks
        self.lookahead = 2 * max((c.step for c in components), default=1)
        #: decisions from states before this tick are remembered (beyond it the end changes them)
        self.memo_until = end - 3 * self.lookahead
        self._memo: dict = {}

    def forget(self) -> None:
        """The run's end moved (a component ended the simulation): remember no more decisions."""
        self.memo_until = -1

    def next(self) -> Decision | None:
        """The next call, for the components as they stand."""
        comps = self.components
        t_min = min(c.time for c in comps) if comps else self.memo_until
        if t_min < self.memo_until and comps:
            key = (t_min % self.period, *[c.time - t_min for c in comps], *[c.running for c in comps])
            decision = self._memo.get(key)
            if decision is None:
                decision = self.decide_at([c.time for c in comps], [c.running for c in comps])
                if len(self._memo) < MEMO_LIMIT:
                    self._memo[key] = decision
            return decision
        return self.decide_at([c.time for c in comps], [c.running for c in comps])

    def decide_at(self, times: list[int], running: list[bool]) -> Decision | None:
        """The decision for the components at ``times`` (ticks reached) with the steps ``running``
        in flight: a function of these alone."""
        comps = self.components
        lookahead = self.lookahead
        pending = [i for i, c in enumerate(comps) if times[i] < c.end or running[i]]
        if not pending:
            return None
        t_min = min(times[i] for i in pending)
        best = None
        for i in pending:
            c = comps[i]
            if running[i] or times[i] >= c.end or times[i] - t_min > lookahead or not _ready_at(c, times):
                continue
            # Earliest first; at the same tick the steps done here go before a worker's start,
            # which has a whole step to run and would hold up this tick (at a 30 Hz frame: its
            # averaged inputs, the copy into shared memory) for a few tenths of a millisecond.
            if best is None or (times[i], c.asynchronous, c.rank) < (times[best], comps[best].asynchronous,
                                                                     comps[best].rank):
                best = i
        if best is not None:
            return True, comps[best].rank
        in_flight = [i for i in pending if running[i]]
        if in_flight:
            return False, comps[min(in_flight, key=lambda i: (times[i], comps[i].rank))].rank
        stuck = ", ".join(f"{comps[i].name} at t = {self.seconds(times[i]):.6g} s" for i in pending)
        raise OrchestrationError(f"no component can step ({stuck}); this is a bug in the scene checks")


def _ready_at(comp, times: list[int]) -> bool:
    """Whether each producer ``comp`` reads has reached the last of its grid points at or before
    the tick ``comp``'s next step evaluates its inputs at."""
    for route in comp.routes:
        producer = route.producer
        if producer is None or route.history is None:
            continue
        tau = times[comp.rank] + route.need_offset
        need = min((tau // producer.step) * producer.step, producer.end)
        if times[producer.rank] < need:
            return False
    return True

"""Real-time pacing: each paced step waits for its time on the wall clock, and how late it ends is
measured."""
from __future__ import annotations

import logging
import os
import time

import numpy as np

from orchestration.observers.base import Observer

logger = logging.getLogger(__name__)


#: Without a CPU of its own, how long before a paced step is due the pacing stops sleeping and
#: spins: waking from a sleep takes 0.1-1 ms on a virtual machine (measured below).
SPIN_S = 0.3e-3


class RealtimePacing(Observer):
    """Paces the fastest components to the wall clock and measures how late each of their steps ends.

    A step of ``[t, t + h]`` may not start before wall time ``t`` (from the loop's first step) and
    should end by ``t + h``: its lateness is the wall time at its end minus ``t + h``. A haptic
    loop that misses its 1 ms deadline is what an operator feels as a stall.

    A paced run owns the machine, as a haptic loop does. With two or more CPUs allowed, this
    process keeps the first one while the worker processes and helper processes (the surface
    writer) share the others (``cpus`` in the report) until the run ends, and it spins between
    steps instead of sleeping; otherwise it sleeps until ``SPIN_S`` before a step and spins the
    rest. A worker woken for its step is otherwise often placed on this process's CPU and takes it
    for milliseconds; a sleeping CPU wakes late and with cold caches. Each of these choices missed
    fewer deadlines than the alternative in runs side by side (docs/performance.md).

    Inside a compiled stretch (``compiled_loop.c``) the program paces and measures the steps the
    same way (``paced``, ``origin``, ``sleeps``; it sets ``origin`` at the run's first paced step
    when that step is its own) and hands their lateness over afterwards (``paced_block``).
    """

    times_steps = True
    paces = True
    names_its_ports = False

    def __init__(self, pace: bool = True):
        self.pace = pace
        self.lateness: list[float] = []
        self._fastest = None
        #: time.perf_counter() at simulated time 0: set when the run's first paced step starts
        self.origin: float | None = None
        self.cpus: dict[str, int] = {}
        self._own_cpus = None

    def subscribes(self, comp) -> bool:
        return True  # the fastest are known once every component is (initializing)

    def initializing(self, algorithm) -> None:
        self.seconds = algorithm.seconds
        self._fastest = min((c.step for c in algorithm.ordered), default=None)

    def initialized(self, algorithm) -> None:
        others = {c.name: c.host.pid for c in algorithm.ordered if getattr(c.host, "pid", None) is not None}
        for observer in algorithm.observers:  # helper processes (the writers)
            others.update(getattr(observer, "processes", {}))
        try:
            allowed = sorted(os.sched_getaffinity(0))
        except (AttributeError, OSError):  # not Linux
            return
        if not others or len(allowed) < 2:
            return
        try:
            os.sched_setaffinity(0, {allowed[0]})
            self._own_cpus = set(allowed)
            self.cpus["master"] = allowed[0]
            for k, (name, pid) in enumerate(others.items()):
                cpu = allowed[1 + k % (len(allowed) - 1)]
                os.sched_setaffinity(pid, {cpu})
                self.cpus[name] = cpu
        except OSError as exc:  # a worker that just ended, a restricted container: pacing goes on
            logger.debug("realtime: placing processes on CPUs failed: %s", exc)

    def started(self, algorithm) -> None:
        self.origin = None

    def finished(self, algorithm) -> None:
        if self._own_cpus is not None:
            try:
                os.sched_setaffinity(0, self._own_cpus)
            except OSError as exc:
                logger.warning("realtime: restoring this process's CPUs failed: %s", exc)
            self._own_cpus = None

    def paced(self, comp) -> bool:
        """Whether ``comp``'s steps are paced (and measured): the fastest components'."""
        return comp.step == self._fastest

    @property
    def sleeps(self) -> bool:
        """Whether the wait for a step sleeps until ``SPIN_S`` before it (else it spins all the way)."""
        return self._own_cpus is None

    def clock_origin(self, tick: int) -> float:
        """``time.perf_counter()`` at simulated time 0, set by the first paced step (from ``tick``)."""
        if self.origin is None:
            # The loop's clock starts at its first step: what the observers do when the run
            # starts (the progress bar's import of tqdm: 6-7 ms) is not the loop being late.
            self.origin = time.perf_counter() - self.seconds(tick)
        return self.origin

    def before_step(self, comp, tick: int) -> None:
        if comp.step != self._fastest:
            return
        due = self.clock_origin(tick) + self.seconds(tick)
        if self.pace:
            ahead = due - time.perf_counter()
            if ahead > SPIN_S and self.sleeps:
                time.sleep(ahead - SPIN_S)
            while time.perf_counter() < due:  # spin: waking from a sleep is late
                pass

    def stepped(self, comp, tick: int, outputs) -> None:
        if tick and comp.step == self._fastest:
            self.lateness.append((time.perf_counter() - self.origin) - self.seconds(tick))

    def paced_block(self, comp, lateness: np.ndarray) -> None:
        """How late each of ``comp``'s paced steps ended, a compiled stretch's in time order (the
        compiled loop paces them as ``before_step`` does and measures them as ``stepped`` does)."""
        self.lateness.extend(lateness.tolist())

    def report(self) -> dict:
        late = np.asarray(self.lateness)
        missed = late[late > 0]
        out = {"haptic_steps": int(late.size), "missed": int(missed.size),
               "worst_lateness_s": float(missed.max()) if missed.size else 0.0, "cpus": dict(self.cpus)}
        if late.size:
            positive = np.maximum(late, 0.0)
            out.update(lateness_p50_s=float(np.percentile(positive, 50)),
                       lateness_p99_s=float(np.percentile(positive, 99)),
                       lateness_max_s=float(positive.max()))
        return out

"""Rate transitions: the value a consumer sees from a producer that steps at another rate.

A producer's outputs exist only at its communication points (integer ticks). A consumer that
reads it at evaluation tick ``tau`` sees the samples with tick ``<= tau`` (which ones exist
depends on the connection's ordering; see ``master``) through one of

* ``hold``: the latest sample;
* ``interpolate``: linear interpolation at ``tau - H`` (``H`` the producer's step) between the
  two samples around it: exact for signals linear in time, one producer step of delay, never
  ahead of the data;
* ``extrapolate``: first order from the latest two samples, ``y_k + (tau - t_k) (y_k - y_k-1) / H``;
* ``average``: the mean of the producer's samples in ``(tau - h, tau]`` (``h`` the consumer's
  step), e.g. the 1 kHz contact forces over one 30 Hz tissue step. With 1 ms and 1/30 s the
  windows hold 33 or 34 samples, counted exactly. The sums are kept as the samples arrive
  (:class:`WindowSums`): the consumer's step finds its mean ready instead of summing 33 cold
  64 KB samples at a 30 Hz frame, inside the 1 kHz loop.

Each transition keeps the samples it needs in a history of its own kind (``history``): the
master hands each sample to it, copied first if the history ``keeps_values``.

Before a producer has two samples, interpolate and extrapolate hold the first one.
"""
from __future__ import annotations

from bisect import bisect_right
from collections import deque
from enum import Enum

import numpy as np


def _check_order(ticks, tick: int) -> None:
    if ticks and tick <= ticks[-1]:
        raise ValueError(f"samples must arrive in time order (tick {tick} after {ticks[-1]})")


class SampleHistory:
    """The samples ``(tick, value)`` of one producer port, oldest first, pruned as consumers advance."""

    __slots__ = ("step", "ticks", "values", "count")
    #: ``append`` keeps the array it is given (the master hands it a copy)
    keeps_values = True

    def __init__(self, step: int):
        self.step = int(step)
        self.ticks: deque[int] = deque()
        self.values: deque[np.ndarray] = deque()
        self.count = 0  # samples appended so far (a consumer can tell that nothing new arrived)

    def append(self, tick: int, value: np.ndarray) -> None:
        _check_order(self.ticks, tick)
        self.ticks.append(int(tick))
        self.values.append(value)
        self.count += 1

    def extend(self, ticks: list[int], values, keep_from: int | None = None, copy: bool = False) -> None:
        """``append`` each of ``ticks`` (increasing) with its value, at once; then ``prune(keep_from)``
        when given, without keeping the samples that it would drop. ``copy``: ``values`` is an array
        that changes later (the compiled loop's tape): copy the rows kept, only those."""
        if not ticks:
            return
        _check_order(self.ticks, ticks[0])
        self.count += len(ticks)
        new = 0  # the first of the new samples kept
        if keep_from is not None:
            held = len(self.ticks)
            drop = self._dropped(held + len(ticks),
                                 bisect_right(self.ticks, keep_from) + bisect_right(ticks, keep_from))
            if drop >= held:
                self.ticks.clear()
                self.values.clear()
                new = drop - held
            else:
                self._drop(drop)
        self.ticks.extend(ticks[new:])
        self.values.extend(values[new:].copy() if copy else values[new:])

    def prune(self, keep_from: int) -> None:
        """Drop samples older than ``keep_from``, always keeping the latest two."""
        ticks = self.ticks
        if len(ticks) > 2 and ticks[1] <= keep_from:
            self._drop(self._dropped(len(ticks), bisect_right(ticks, keep_from)))

    @staticmethod
    def _dropped(count: int, at_or_before: int) -> int:
        """How many of ``count`` samples a prune drops when ``at_or_before`` of them have a tick at or
        before ``keep_from``: those before the latest such sample (ticks increase), the latest two kept."""
        return max(0, min(count - 2, at_or_before - 1))

    def _drop(self, count: int) -> None:
        pop_tick, pop_value = self.ticks.popleft, self.values.popleft
        for _ in range(count):
            pop_tick()
            pop_value()

    def latest_index(self, tau: int) -> int:
        """Index of the latest sample with tick <= tau (-1 if none)."""
        ticks = self.ticks
        i = len(ticks) - 1
        while i >= 0 and ticks[i] > tau:
            i -= 1
        return i


class WindowSums:
    """The running sums of a producer port's samples over the windows ``(k W - W, k W]`` of a
    consumer whose step is ``W`` ticks (where its evaluation ticks fall): what ``average`` needs,
    without keeping the samples. A window's sum starts as a copy of its first sample and adds the
    others in time order, then is divided by their number (tested bitwise against summing the
    kept samples).
    """

    __slots__ = ("step", "window", "ticks", "count", "_sums")
    keeps_values = False  # append reads the array at once and keeps none of it

    def __init__(self, step: int, window: int):
        self.step = int(step)
        self.window = int(window)
        self.ticks: deque[int] = deque(maxlen=2)  # the latest ticks (the master asks for the last)
        self.count = 0
        self._sums: dict[int, list] = {}  # window end tick -> [sum array, number of samples]

    def append(self, tick: int, value: np.ndarray) -> None:
        end = self._window_end(tick)
        entry = self._sums.get(end)
        if entry is None:
            self._sums[end] = [np.array(value, dtype=np.float64, copy=True), 1]
        else:
            np.add(entry[0], value, out=entry[0])
            entry[1] += 1
        self._counted(tick)

    def window_sum(self, end: int) -> np.ndarray | None:
        """The running sum of the window ending at tick ``end`` (None before its first sample)."""
        entry = self._sums.get(end)
        return None if entry is None else entry[0]

    def window_count(self, end: int) -> int:
        """The samples in the window ending at tick ``end`` so far."""
        entry = self._sums.get(end)
        return 0 if entry is None else entry[1]

    def extend_summed(self, ticks: list[int], opened: dict[int, np.ndarray]) -> None:
        """Count the samples at ``ticks`` (increasing) that were already added into their windows'
        sums (by the compiled loop); ``opened`` maps the end of each window that one of them opened
        (its first sample) to the window's new sum."""
        if not ticks:
            return
        _check_order(self.ticks, ticks[0])
        window, sums = self.window, self._sums
        i, n = 0, len(ticks)
        while i < n:  # a window at a time: its samples are those up to its end
            end = -(-ticks[i] // window) * window
            j = bisect_right(ticks, end, i)
            new = opened.get(end)
            if new is not None:
                sums[end] = [new, j - i]
            else:
                sums[end][1] += j - i
            i = j
        self.ticks.extend(ticks[-2:])
        self.count += n

    def _window_end(self, tick: int) -> int:
        """The end of the window a sample at ``tick`` belongs to (samples arrive in time order)."""
        _check_order(self.ticks, tick)
        return -(-tick // self.window) * self.window

    def _counted(self, tick: int) -> None:
        self.ticks.append(int(tick))
        self.count += 1

    def prune(self, keep_from: int) -> None:
        """Drop the windows that end before ``keep_from`` (the dict holds them oldest first)."""
        sums = self._sums
        while sums:
            oldest = next(iter(sums))
            if oldest >= keep_from:
                break
            del sums[oldest]

    def mean(self, tau: int) -> np.ndarray:
        """Mean of the samples with tick in ``(tau - window, tau]`` (a new array)."""
        if tau % self.window:
            raise ValueError(f"tick {tau} is not the end of a window of {self.window} ticks")
        entry = self._sums.get(tau)
        if entry is None:  # the scene checks make the producer at least as fast as the window
            raise LookupError(f"no sample in the window ({tau - self.window}, {tau}]")
        return np.divide(entry[0], entry[1])


def hold(history: SampleHistory, tau: int) -> tuple[np.ndarray, int]:
    """Latest sample at or before ``tau``; also returns its tick (to set an input only when it changes)."""
    i = history.latest_index(tau)
    if i < 0:
        raise LookupError(f"no sample at or before tick {tau}")
    return history.values[i], history.ticks[i]


def interpolate(history: SampleHistory, tau: int) -> np.ndarray:
    """Linear interpolation at ``tau - H`` between the samples around it (one producer step of delay)."""
    target = tau - history.step
    i = history.latest_index(target)
    if i < 0:
        return history.values[0]
    t0 = history.ticks[i]
    if t0 == target or i + 1 >= len(history.ticks):
        return history.values[i]
    t1 = history.ticks[i + 1]
    w = (target - t0) / (t1 - t0)
    y0, y1 = history.values[i], history.values[i + 1]
    return y0 + w * (y1 - y0)


def extrapolate(history: SampleHistory, tau: int) -> np.ndarray:
    """First-order extrapolation from the latest two samples at or before ``tau``."""
    i = history.latest_index(tau)
    if i < 0:
        raise LookupError(f"no sample at or before tick {tau}")
    if i == 0:
        return history.values[0]
    t1, t0 = history.ticks[i], history.ticks[i - 1]
    y1, y0 = history.values[i], history.values[i - 1]
    if tau == t1:
        return y1
    return y1 + ((tau - t1) / (t1 - t0)) * (y1 - y0)


# -- the registry: one class per transition, used by the scene checks and by the master -----------
class Compiled(Enum):
    """How the compiled loop (``orchestration.run.compiled_loop``) makes a transition's value
    between two components it steps: what a transition declares, never inferred from its class."""

    #: the latest sample by tau, as it is (``hold``)
    LATEST = "latest"
    #: the mean of the window the program sums as the samples arrive (``average``)
    WINDOW_MEAN = "window mean"


class Transition:
    """A rate transition on one connection: the value its consumer reads at tick ``tau``.

    A subclass gives ``name`` (the scene's ``transition = "..."``), ``value`` and, where the
    transition only makes sense for some rates, ``scene_problem``. ``keyed`` transitions return
    the tick of the sample they pass on, so the master sets the input only when that changes.
    ``compiled`` says how the compiled loop makes the same value in C; a class that does not
    declare it in its own body (a subclass of ``Hold`` too) has None, and its connections between
    in-process components are then stepped in Python.
    """

    name: str = ""
    summary: str = ""
    keyed: bool = False
    compiled: Compiled | None = None

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if "compiled" not in cls.__dict__:
            cls.compiled = None

    def __init__(self, producer_step: int, consumer_step: int):
        self.consumer_step = int(consumer_step)
        self.history = self.new_history(int(producer_step), self.consumer_step)

    @staticmethod
    def new_history(producer_step: int, consumer_step: int):
        """The history this transition reads (what the master appends the producer's samples to)."""
        return SampleHistory(producer_step)

    def value(self, tau: int) -> tuple[np.ndarray, int | None]:
        raise NotImplementedError

    @classmethod
    def scene_problem(cls, producer_step, consumer_step) -> str | None:
        """Why this transition cannot join these rates (steps in seconds), or None."""
        return None


class Hold(Transition):
    name, summary, keyed = "hold", "the latest sample", True
    compiled = Compiled.LATEST

    def value(self, tau):
        return hold(self.history, tau)


class Interpolate(Transition):
    name, summary = "interpolate", "linear between the samples around tau - H (one producer step late)"

    def value(self, tau):
        return interpolate(self.history, tau), None


class Extrapolate(Transition):
    name, summary = "extrapolate", "first order from the latest two samples"

    def value(self, tau):
        return extrapolate(self.history, tau), None


class Average(Transition):
    name, summary = "average", "the mean of the samples within the consumer's step"
    compiled = Compiled.WINDOW_MEAN

    @staticmethod
    def new_history(producer_step, consumer_step):
        return WindowSums(producer_step, consumer_step)

    def value(self, tau):
        return self.history.mean(tau), None

    @classmethod
    def scene_problem(cls, producer_step, consumer_step):
        if producer_step is not None and consumer_step is not None and producer_step > consumer_step:
            return ("\"average\" means over the fast producer's samples in the consumer's step, but the producer "
                    "is the slower one; use hold, interpolate or extrapolate")
        return None


#: name -> class, every transition a scene may name (filled by :func:`register`)
REGISTRY: dict[str, type[Transition]] = {}


def register(cls: type[Transition]) -> type[Transition]:
    """Make a transition class one a scene can name (``transition = cls.name``); a class decorator."""
    if not cls.name or cls.name in REGISTRY:
        raise ValueError(f"a transition needs a name of its own, not {cls.name!r} (taken: {', '.join(REGISTRY)})")
    REGISTRY[cls.name] = cls
    return cls


for _builtin in (Hold, Interpolate, Extrapolate, Average):
    register(_builtin)
#: what a connection between equal rates uses when the scene names none
DEFAULT = "hold"

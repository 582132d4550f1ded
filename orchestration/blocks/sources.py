"""Continuous sources: ``evaluate(t)`` gives their exact outputs at any time, a pure function of t."""
from __future__ import annotations

import bisect
import math

import numpy as np

from orchestration.blocks.options import BlockConfigError, check_choice, check_units
from orchestration.checks import is_real
from orchestration.hosts.description import PortInfo


INTERPOLATIONS = ("linear", "hold")


def checked_time(t) -> float:
    if not (is_real(t) and math.isfinite(t)):
        raise ValueError(f"t must be a finite time in s (got {t!r})")
    return float(t)


# ---------------------------------------------------------------------------------- sources
class Source:
    """A continuous source: outputs only, ``evaluate(t)`` exact at any t."""

    name: str
    ports: dict[str, PortInfo]
    continuous = True
    #: the outputs never change: the master sets them once, at initialization
    constant = False

    def evaluate(self, t: float) -> dict[str, np.ndarray]:  # pragma: no cover - interface
        raise NotImplementedError

    def evaluate_many(self, times: np.ndarray) -> dict[str, np.ndarray]:
        """The outputs at each of ``times`` (s): ``{name: array of one flat row per time}``, each row
        bit for bit ``evaluate(t)[name]`` (the compiled loop fills a stretch's inputs with it)."""
        rows = [self.evaluate(float(t)) for t in times]
        return {name: np.array([np.asarray(row[name], dtype=np.float64).reshape(-1) for row in rows])
                for name in self.ports}


def check_times(problems, times, key="times"):
    """Knot times: a non-empty list of finite, strictly increasing numbers; the array or None."""
    if isinstance(times, (str, bytes)) or not hasattr(times, "__len__"):
        problems.append(f"{key} must be a list of knot times in s (got {times!r}), e.g. [0.0, 1.0, 3.0]")
        return None
    t = [float(v) if is_real(v) else math.nan for v in times]
    bad = [i for i, v in enumerate(t) if not math.isfinite(v)]
    if len(t) == 0:
        problems.append(f"{key} must hold at least one time (got an empty list)")
        return None
    if bad:
        problems.append(f"{key}[{bad[0]}] must be a finite number (got {list(times)[bad[0]]!r}): give knot times in s")
        return None
    dec = [i for i in range(1, len(t)) if not t[i] > t[i - 1]]
    if dec:
        i = dec[0]
        problems.append(f"{key} must be strictly increasing ({key}[{i}] = {t[i]!r} after {key}[{i - 1}] = "
                        f"{t[i - 1]!r}): give each knot time once, in order")
        return None
    return np.asarray(t, dtype=np.float64)


def check_outputs(problems, outputs, n_times, key="outputs"):
    """Per-output knot values: {name: ((n_times, width) array, is_scalar)}; n_times None skips the count."""
    clean = {}
    if not isinstance(outputs, dict) or not outputs:
        problems.append(f"{key} must be a non-empty table output name -> list of values, one per time "
                        f"(got {outputs!r}), e.g. {{ insertion = [0.0, 0.05] }}")
        return clean
    for name, values in outputs.items():
        where = f"{key}.{name}"
        if not isinstance(name, str) or not name:
            problems.append(f"{key} has an invalid output name {name!r}: use a non-empty string")
            continue
        if isinstance(values, (str, bytes)) or not hasattr(values, "__len__") or len(values) == 0:
            problems.append(f"{where} must be a non-empty list of values, one per time (got {values!r})")
            continue
        rows, kinds, ok = [], set(), True
        for i, v in enumerate(values):
            scalar = is_real(v)
            row = [v] if scalar else (list(v) if hasattr(v, "__len__") and not isinstance(v, (str, bytes)) else None)
            if row is None or not row or not all(is_real(x) and math.isfinite(x) for x in row):
                problems.append(f"{where}[{i}] must be a finite number or a list of finite numbers (got {v!r})")
                ok = False
                break
            rows.append(row)
            kinds.add((len(row), scalar))
        if not ok:
            continue
        if len(kinds) > 1:
            problems.append(f"{where} mixes values of different lengths: give every knot the same number of "
                            f"components (all numbers, or all lists of one length)")
            continue
        if n_times is not None and len(rows) != n_times:
            problems.append(f"{where} has {len(rows)} values but times has {n_times}: give one value per knot time")
            continue
        width, scalar = next(iter(kinds))
        clean[name] = (np.asarray(rows, dtype=np.float64).reshape(len(rows), width), scalar)
    return clean


class PiecewiseLinearSource(Source):
    """Outputs interpolated between knots (``"linear"``) or held from the last knot (``"hold"``).

    Before the first knot the first value is held, after the last knot the last value. The value at
    a knot time is the knot value exactly.
    """

    def __init__(self, name: str, times, outputs: dict, interpolation: str = "linear",
                 units: dict[str, str] | None = None):
        problems: list[str] = []
        clean_times = check_times(problems, times)
        clean = check_outputs(problems, outputs, None if clean_times is None else len(clean_times))
        check_choice(problems, "interpolation", interpolation, INTERPOLATIONS)
        units = check_units(problems, "units", units, list(outputs) if isinstance(outputs, dict) else [])
        if problems:
            raise BlockConfigError(problems, name)
        self._build(name, clean_times, clean, interpolation, units)

    def _build(self, name, times, clean, interpolation, units):
        self.name = name
        self.interpolation = interpolation
        self.times = times
        self._t = times.tolist()  # bisect on a list is the fastest scalar lookup
        self._names = list(clean)
        self._slices = {}
        columns, start = [], 0
        self.ports = {}
        for out, (values, scalar) in clean.items():
            width = values.shape[1]
            self._slices[out] = slice(start, start + width)
            start += width
            columns.append(values)
            self.ports[out] = PortInfo(name=out, causality="output", type="Float64",
                                       variability="continuous" if interpolation == "linear" else "discrete",
                                       unit=units.get(out), shape=() if scalar else (width,),
                                       start=values[0, 0] if scalar else values[0].tolist())
        self._values = np.ascontiguousarray(np.concatenate(columns, axis=1))  # (n_times, total width)
        # evaluate() works on plain floats (a few values per tick: numpy's per-call cost would dominate);
        # the same IEEE operations, so the same values as the array formula in _row
        self._rows = self._values.tolist()
        self._hold = interpolation == "hold"
        self._slice_list = list(self._slices.items())

    def _row(self, t: float) -> np.ndarray:
        i = bisect.bisect_right(self._t, t)  # times[i-1] <= t < times[i]
        if i == 0:
            return self._values[0].copy()
        if i == len(self._t) or self.interpolation == "hold":
            return self._values[i - 1].copy()
        t0, t1 = self._t[i - 1], self._t[i]
        w = (t - t0) / (t1 - t0)
        # (1-w) v0 + w v1 is v0 exactly at w = 0 (knots are hit through w = 0 only)
        return (1.0 - w) * self._values[i - 1] + w * self._values[i]

    def evaluate_many(self, times: np.ndarray) -> dict[str, np.ndarray]:
        times = np.asarray(times, dtype=np.float64)
        if not np.isfinite(times).all():
            return super().evaluate_many(times)  # evaluate says what is wrong
        knots, values = self.times, self._values
        i = np.searchsorted(knots, times, side="right")  # as bisect_right: knots[i-1] <= t < knots[i]
        out = values[np.maximum(i - 1, 0)]  # held: the first row before the first knot, the last after
        if not self._hold:
            inner = (i > 0) & (i < len(knots))
            if inner.any():
                k = i[inner]
                w = (times[inner] - knots[k - 1]) / (knots[k] - knots[k - 1])
                # the IEEE operations of evaluate, elementwise: (1 - w) v0 + w v1
                out[inner] = (1.0 - w)[:, None] * values[k - 1] + w[:, None] * values[k]
        return {out_name: out[:, s] for out_name, s in self._slice_list}

    def evaluate(self, t: float) -> dict[str, np.ndarray]:
        if not (type(t) is float and math.isfinite(t)):
            t = checked_time(t)
        rows = self._rows
        i = bisect.bisect_right(self._t, t)  # times[i-1] <= t < times[i]
        if i == 0:
            row = rows[0]
        elif i == len(rows) or self._hold:
            row = rows[i - 1]
        else:
            t0, t1 = self._t[i - 1], self._t[i]
            w = (t - t0) / (t1 - t0)
            v = 1.0 - w
            row = [v * a + w * b for a, b in zip(rows[i - 1], rows[i])]
        return {out: np.array(row[s]) for out, s in self._slice_list}


class ExternalSource(Source):
    """Values given from outside, step by step, in place of a scene's source with the same ports:
    what the scene exported as one FMU reads from its importer's inputs. ``values[name]`` (a flat
    float64 array of the port's size) is what every evaluation returns until it is set again; the
    embedding master sets it before it advances the run over the time it holds for."""

    def __init__(self, name: str, ports: dict[str, PortInfo]):
        self.name = name
        self.ports = dict(ports)
        self.values = {port: np.array(info.start if info.start is not None else 0.0, dtype=np.float64).reshape(-1)
                       for port, info in self.ports.items()}

    def evaluate(self, t: float) -> dict[str, np.ndarray]:
        return {name: (value.copy() if value.size > 1 else value[0].copy()) for name, value in self.values.items()}

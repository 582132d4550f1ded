"""The statistics observer: peaks, energies, warnings, deadlines and implausible outputs for the
summary."""
from __future__ import annotations

import logging
import math

import numpy as np

from orchestration.observers.plausibility import PLAUSIBILITY_STEP_VALUES, plausible_range
from orchestration.scene.model import Scene
from orchestration.observers.base import Observer

logger = logging.getLogger(__name__)


#: Blocks of steps at least this long (a compiled stretch's) are folded into the statistics in numpy;
#: shorter ones (a paced tick's) a row at a time, which costs less for a few rows
BLOCK_FOLD_ROWS = 8


class Statistics(Observer):
    """Peaks, energies and operator warnings named in the scene's ``[summary]``, and the physical
    plausibility of every stepped component's outputs (:data:`PLAUSIBLE_MAGNITUDE`): an output
    beyond its range is counted in ``implausible_outputs`` and makes a line of the summary's
    ``warnings`` (and of the log), so that such a run never reads as a clean "completed"."""

    def __init__(self, scene: Scene):
        summary = scene.summary
        self.peaks = {ref: (0.0, 0.0) for ref in summary.get("peaks", [])}
        self.energy: dict[str, dict] = {}
        self.warnings: dict[str, dict] = {}
        self.by_component: dict[str, list[tuple[str, str, str]]] = {}
        for kind in ("peaks", "energy", "warnings"):
            for ref in summary.get(kind, []):
                comp, port = ref.split(".")
                self.by_component.setdefault(comp, []).append((kind, port, ref))
        #: per component, its outputs checked at every step / at the end: (port, ref, low, high)
        self.checks: dict[str, list[tuple[str, str, float, float]]] = {}
        self.final_checks: dict[str, list[tuple[str, str, float, float]]] = {}
        #: ref -> (low, high, why, unit) of every checked output
        self.ranges: dict[str, tuple[float, float, str, str | None]] = {}
        #: ref -> what left its range: steps, first_s, worst value (and its excess, internal)
        self.implausible: dict[str, dict] = {}
        components = getattr(scene, "components", {})
        consumers: dict[tuple[str, str], list] = {}
        for c in getattr(scene, "connections", ()):
            target = components.get(c.target)
            port = target.ports.get(c.target_port) if target is not None else None
            if port is not None:
                consumers.setdefault((c.source, c.source_port), []).append((f"{c.target}.{c.target_port}", port))
        for spec in components.values():
            if spec.is_continuous:  # a source's values are the scene's own, checked when it is loaded
                continue
            for port in spec.ports.values():
                bounds = plausible_range(port, consumers.get((spec.name, port.name), ()))
                if bounds is None:
                    continue
                ref = f"{spec.name}.{port.name}"
                self.ranges[ref] = (*bounds, port.unit)
                every_step = port.size <= PLAUSIBILITY_STEP_VALUES
                (self.checks if every_step else self.final_checks).setdefault(spec.name, []).append(
                    (port.name, ref, bounds[0], bounds[1]))

    def ports(self, component: str) -> list[str]:
        names = [port for _, port, _ in self.by_component.get(component, [])]
        names += [port for port, *_ in self.checks.get(component, [])]
        return list(dict.fromkeys(names))

    def initializing(self, algorithm) -> None:
        self.seconds = algorithm.seconds

    def stepped(self, comp, tick: int, outputs) -> None:
        for kind, port, ref in self.by_component.get(comp.name, ()):
            # plain floats: cheaper than numpy for a few values
            self._take(kind, ref, comp.step, (tick,), (outputs[port].tolist(),))
        for port, ref, low, high in self.checks.get(comp.name, ()):
            values = outputs[port]
            if values.size <= 16:  # plain floats again; a NaN makes the sum NaN (min and max may miss it)
                row = values.tolist()
                total = sum(row)
                if total == total and low <= min(row) and max(row) <= high:
                    continue
            elif low <= values.min() and values.max() <= high:  # numpy's min and max are NaN for a NaN
                continue
            self._fold_implausible(ref, low, high, (tick,), np.asarray(values, dtype=np.float64).reshape(1, -1))

    def stepped_block(self, comp, ticks: list[int], outputs: dict[str, np.ndarray], first_step: int) -> None:
        """``stepped`` for steps ending at ``ticks``; ``outputs[port]`` has a row per step."""
        for port, ref, low, high in self.checks.get(comp.name, ()):
            rows = outputs[port]
            if not (low <= rows.min() and rows.max() <= high):
                self._fold_implausible(ref, low, high, ticks, np.asarray(rows, dtype=np.float64))
        for kind, port, ref in self.by_component.get(comp.name, ()):
            rows = outputs[port]
            if len(ticks) < BLOCK_FOLD_ROWS or not np.isfinite(rows).all():
                self._take(kind, ref, comp.step, ticks, rows.tolist())
            else:
                self._take_block(kind, ref, comp.step, ticks, rows)

    def _take(self, kind: str, ref: str, step: int, ticks, rows) -> None:
        """Fold the values ``rows`` of ``ref`` at ``ticks`` (in time order) into its statistic."""
        seconds = self.seconds
        if kind == "peaks":
            peak, at = self.peaks[ref]
            for tick, values in zip(ticks, rows):
                magnitude = math.hypot(*values) if len(values) > 1 else abs(values[0])
                if magnitude > peak:
                    peak, at = magnitude, seconds(tick)
            self.peaks[ref] = (peak, at)
        elif kind == "energy":
            for values in rows:
                v = values[0] if len(values) == 1 else math.hypot(*values)
                e = self.energy.get(ref)
                if e is None:
                    e = self.energy[ref] = {"initial": v, "final": v, "min": v, "max": v}
                e["final"] = v
                if v < e["min"]:
                    e["min"] = v
                if v > e["max"]:
                    e["max"] = v
        else:
            w = self._warning(ref, step)
            for tick, values in zip(ticks, rows):
                on = values[0] != 0
                if on and not w["_on"]:
                    w["count"] += 1
                    if w["first_s"] is None:
                        w["first_s"] = seconds(tick)
                if on and tick:  # the step that ended at tick (none ends at 0) was spent warning
                    w["_on_steps"] += 1
                w["_on"] = on

    def _take_block(self, kind: str, ref: str, step: int, ticks: list[int], rows: np.ndarray) -> None:
        """``_take`` of finite ``rows`` (an array, a row per tick), the same numbers in numpy: the
        extremes and edges are picked, not computed, and a vector's magnitude is still
        ``math.hypot``, only for the rows that may raise the peak."""
        seconds = self.seconds
        size = rows.shape[1]
        if kind == "peaks":
            peak, at = self.peaks[ref]
            if size == 1:
                magnitudes = np.abs(rows[:, 0])
                i = int(np.argmax(magnitudes))  # the first of the largest, as the strict > keeps it
                if magnitudes[i] > peak:
                    peak, at = float(magnitudes[i]), seconds(ticks[i])
            else:
                # |v| <= sqrt(n) max |v_k|: a row below the peak by this bound cannot raise it
                bound = np.abs(rows).max(axis=1) * (math.sqrt(size) * (1.0 + 1e-12))
                for i in np.flatnonzero(bound > peak).tolist():
                    magnitude = math.hypot(*rows[i].tolist())
                    if magnitude > peak:
                        peak, at = magnitude, seconds(ticks[i])
            self.peaks[ref] = (peak, at)
        elif kind == "energy":
            if size > 1:
                self._take(kind, ref, step, ticks, rows.tolist())
                return
            values = rows[:, 0]
            e = self.energy.get(ref)
            if e is None:
                first = float(values[0])
                e = self.energy[ref] = {"initial": first, "final": first, "min": first, "max": first}
            e["final"] = float(values[-1])
            e["min"] = min(e["min"], float(values.min()))
            e["max"] = max(e["max"], float(values.max()))
        else:
            w = self._warning(ref, step)
            on = rows[:, 0] != 0
            before = np.empty_like(on)
            before[0] = w["_on"]
            before[1:] = on[:-1]
            rising = np.flatnonzero(on & ~before)
            if rising.size:
                w["count"] += int(rising.size)
                if w["first_s"] is None:
                    w["first_s"] = seconds(ticks[int(rising[0])])
            w["_on_steps"] += int(np.count_nonzero(on & (np.asarray(ticks) != 0)))
            w["_on"] = bool(on[-1])

    def _fold_implausible(self, ref: str, low: float, high: float, ticks, rows: np.ndarray) -> None:
        """Count the rows (one per tick) of ``ref`` with a value outside [low, high]; keep the first
        time and the value furthest out (a NaN before all: nothing is further), the first of equals."""
        with np.errstate(invalid="ignore"):
            excess = np.maximum(low - rows, rows - high)
        excess[np.isnan(excess)] = math.inf
        bad = (excess > 0).any(axis=1)
        count = int(np.count_nonzero(bad))
        if not count:
            return
        worst = int(np.argmax(excess))  # row-major: the earliest step, then the first value
        entry = self.implausible.get(ref)
        if entry is None:
            entry = self.implausible[ref] = {"steps": 0, "first_s": self.seconds(ticks[int(np.argmax(bad))]),
                                             "worst": None, "_excess": -math.inf}
        entry["steps"] += count
        if excess.flat[worst] > entry["_excess"]:
            entry["_excess"], entry["worst"] = float(excess.flat[worst]), float(rows.flat[worst])

    def finished(self, algorithm) -> None:
        """The outputs too large to check at every step, as the run ends (those the run read); then
        each implausible output is logged. Never raises: the run's summary comes next."""
        if not hasattr(self, "seconds"):  # the run ended before it initialized
            return
        try:
            for comp in algorithm.ordered:
                for port, ref, low, high in self.final_checks.get(comp.name, ()):
                    values = comp.outputs.get(port)
                    if values is None:
                        continue
                    row = np.asarray(values, dtype=np.float64).reshape(1, -1)
                    if not (low <= row.min() and row.max() <= high):
                        self._fold_implausible(ref, low, high, (comp.time,), row)
        except Exception as exc:  # a host that went away with its buffers: the check is a courtesy
            logger.warning("checking the final outputs' plausibility failed: %s", exc)
        for text in self.plausibility_warnings():
            logger.warning("%s", text)

    def plausibility_warnings(self) -> list[str]:
        """A line for each output that left its plausible range, the earliest first."""
        lines = []
        for ref, entry in sorted(self.implausible.items(), key=lambda item: (item[1]["first_s"], item[0])):
            low, high, why, unit = self.ranges[ref]
            unit = f" {unit}" if unit else ""
            worst = entry["worst"]
            worst = "NaN" if worst != worst else f"{worst:.6g}{unit}"
            lines.append(f"{ref} left its plausible range [{low:g}, {high:g}]{unit} at t = {entry['first_s']:.6g} s "
                         f"({entry['steps']} step(s), {worst} at worst; {why}): its results from then on are not "
                         "physical; check the scene's forces, parameters and units")
        return lines

    def _warning(self, ref: str, step: int) -> dict:
        w = self.warnings.get(ref)
        if w is None:
            w = self.warnings[ref] = {"count": 0, "first_s": None, "_on": False, "_on_steps": 0,
                                      "_step_s": self.seconds(step)}
        return w

    def report(self) -> dict:
        out: dict = {}
        if self.peaks:
            out["peaks"] = {ref: {"value": v, "time_s": t} for ref, (v, t) in self.peaks.items()}
        if self.energy:
            out["energy"] = {ref: {**e, "drift": e["final"] - e["initial"]} for ref, e in self.energy.items()}
        if self.warnings:
            out["operator_warnings"] = {ref: {"count": w["count"], "time_on_s": w["_on_steps"] * w["_step_s"],
                                              "first_s": w["first_s"]}
                                        for ref, w in self.warnings.items()}
        if self.ranges:
            def number(x: float):  # JSON has no NaN or infinity
                return x if math.isfinite(x) else (None if x != x else str(x))

            out["implausible_outputs"] = {
                "count": len(self.implausible), "checked": len(self.ranges),
                "outputs": {ref: {"steps": e["steps"], "first_s": e["first_s"], "worst": number(e["worst"]),
                                  "range": [number(self.ranges[ref][0]), number(self.ranges[ref][1])],
                                  "unit": self.ranges[ref][3]}
                            for ref, e in sorted(self.implausible.items(), key=lambda item: (item[1]["first_s"],
                                                                                               item[0]))}}
            warnings = self.plausibility_warnings()
            if warnings:
                out["warnings"] = warnings
        return out

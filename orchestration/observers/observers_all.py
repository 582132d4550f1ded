"""Observers of a run: recording, statistics, real-time pacing and progress.

Each is notified by :class:`~orchestration.run.algorithm.MultirateAlgorithm` (see its ``Observer``
protocol) and never changes what the components compute. A new observer is one class here.
"""
from __future__ import annotations

import logging
import math
import os
import time
from pathlib import Path

import numpy as np

from orchestration.blocks import PLANT_MAX_POSITION, PLANT_MAX_SPEED
from orchestration.scene.model import Scene

logger = logging.getLogger(__name__)


class Recording:
    """CSV rows of the scene's ``[record]`` ports and the surface time series (VTU + PVD)."""

    def __init__(self, scene: Scene, out_dir: Path, *, surfaces: bool = True):
        self.scene = scene
        self.out_dir = Path(out_dir)
        self.surfaces = list(scene.surfaces) if surfaces else []
        self.recorder = None
        self._recorded = {name: list(ports) for name, ports in scene.record.items()}
        # Surface frames and the CSV rows' text are written by processes of their own, started
        # now: their start-up (half a second for the surface writer's imports) runs beside the
        # FMUs' set-up, not into the first steps.
        self._surface_writer = self._row_writer = None
        if self.surfaces:
            from orchestration.observers.surface_writer import SurfaceWriter

            self._surface_writer = SurfaceWriter(self.out_dir)
        if self._recorded:
            from orchestration.observers.row_writer import RowWriter

            self._row_writer = RowWriter()

    def ports(self, component: str) -> list[str]:
        ports = list(self._recorded.get(component, []))
        for surface in self.surfaces:
            if surface.component == component:
                ports += [surface.positions, *surface.point_data]
        return ports

    def initializing(self, algorithm) -> None:
        from orchestration.observers.recorder import Recorder

        self.seconds = algorithm.seconds
        self.base = algorithm.base
        self.recorder = Recorder(self.out_dir, surface_writer=self._surface_writer, row_writer=self._row_writer)
        for name, ports in self._recorded.items():
            spec = self.scene.components[name]
            self.recorder.add_stream(name, [(p, spec.ports[p].size, spec.ports[p].unit) for p in ports])

    def initialized(self, algorithm) -> None:
        for surface in self.surfaces:
            values = algorithm.get_values(surface.component, [surface.triangles, surface.positions,
                                                                *surface.point_data])
            triangles = np.asarray(values[surface.triangles]).reshape(-1, 3).astype(np.int64)
            self.recorder.add_surface_series(surface.name, triangles)
            self._write_surface(surface, 0, values)

    def stepped(self, comp, tick: int, outputs) -> None:
        if comp.name in self._recorded:
            self.recorder.write(comp.name, self.seconds(tick), outputs)
        if tick:
            for surface in self.surfaces:
                if surface.component == comp.name and comp.steps % surface.every == 0:
                    self._write_surface(surface, tick, outputs)

    def stepped_block(self, comp, ticks: list[int], outputs: dict[str, np.ndarray], first_step: int) -> None:
        """``stepped`` for steps ``first_step + 1, ...`` ending at ``ticks``; ``outputs[port]`` has a row per step."""
        if comp.name in self._recorded:
            # int64 / int: correctly rounded below 2**53, the same floats as self.seconds
            self.recorder.write_rows(comp.name, np.array(ticks, dtype=np.int64) / self.base, outputs)
        for surface in self.surfaces:
            if surface.component == comp.name:
                for i, tick in enumerate(ticks):
                    if tick and (first_step + i + 1) % surface.every == 0:
                        self._write_surface(surface, tick, {name: values[i] for name, values in outputs.items()})

    def _write_surface(self, surface, tick: int, outputs) -> None:
        positions = np.asarray(outputs[surface.positions]).reshape(-1, 3)
        point_data = {name: np.asarray(outputs[name]).reshape(positions.shape[0], -1).squeeze()
                      for name in surface.point_data}
        self.recorder.write_surface(surface.name, self.seconds(tick), positions, point_data)

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()  # closes the writer processes too, once everything is on disk
        else:  # the run ended before recording began
            for writer in (self._surface_writer, self._row_writer):
                if writer is not None:
                    writer.close()

    @property
    def surface_errors(self) -> list[str]:
        """What the surface writer could not write (known once closed)."""
        return self.recorder.surface_errors if self.recorder is not None else []

    @property
    def row_errors(self) -> list[str]:
        """What the row writer could not write (known once closed)."""
        return self.recorder.row_errors if self.recorder is not None else []

    @property
    def writers(self) -> list:
        """The run's writer processes that were started (surface writer, row writer)."""
        return [writer for writer in (self._surface_writer, self._row_writer) if writer is not None]

    @property
    def processes(self) -> dict[str, int]:
        """Helper processes of the run by name (the writers), for the real-time pacing."""
        return {writer.label: writer.pid for writer in self.writers}

    @property
    def files(self) -> dict:
        return self.recorder.files if self.recorder is not None else {}


# -- physical plausibility of the outputs ------------------------------------------------------------
#: The plausible magnitude of a run's outputs, by unit: every value of a Float output of a stepped
#: component (an FMU or a block such as the device plant) lies within +-bound, or the run's summary
#: warns ("warnings", "implausible_outputs"): a value beyond it is a model that diverged, a unit slip
#: or a force far beyond the scene's, not a result. An output whose FMU declares min/max in its
#: modelDescription.xml (from its limit table, FmuDeclaration.limits) is held to that range instead;
#: one without it is also held to the range of each input it feeds (the consumer's limit table is the
#: contract, e.g. Tissue's compliance to Contact's). Outputs in other units that feed no such input
#: are not checked. The one table of these bounds.
PLAUSIBLE_MAGNITUDE: dict[str, tuple[float, str]] = {
    "m": (PLANT_MAX_POSITION, "positions and lengths: the body, the vessel and a device's workspace (about 0.2 m) "
                              "lie within metres of the origin; a device plant starting beyond it is refused too"),
    "m/s": (PLANT_MAX_SPEED, "speeds: a hand, a device or a wall moves at centimetres to metres per second"),
    "N": (1e4, "forces: 10 kN is 1000 times what a catheter or a haptic device applies; the FMUs refuse a force "
               "input beyond it"),
    "J": (1e5, "energies: the work of 10 kN over 10 m"),
    "N/m": (1e9, "stiffnesses: the Catheter refuses a tip stiffness beyond it"),
    "rad": (1e6, "angles: the Catheter refuses a rotation beyond 1e6 rad (160k turns)"),
}
#: Outputs of up to this many values are checked at every step; larger ones (a tissue's surface, its
#: nodal forces: thousands of values each step) at the end of the run, where the run reads them.
PLAUSIBILITY_STEP_VALUES = 1024


def _declared(port) -> tuple[float, float] | None:
    if port.minimum is None and port.maximum is None:
        return None
    return (-math.inf if port.minimum is None else float(port.minimum),
            math.inf if port.maximum is None else float(port.maximum))


def plausible_range(port, consumers=()) -> tuple[float, float, str] | None:
    """``(low, high, why)`` bounding every value of the output ``port`` (a PortInfo), or None when
    nothing bounds it: its declared min/max, else the declared ranges of the inputs it feeds
    (``consumers``: ``(name, PortInfo)``) and PLAUSIBLE_MAGNITUDE of its unit, all of them."""
    if port.causality != "output" or port.type not in ("Float64", "Float32"):
        return None
    declared = _declared(port)
    if declared is not None:
        return (*declared, "the range its FMU declares for it (min/max in its modelDescription.xml)")
    # each bound that applies, as (low, high, why): the output must keep within all of them
    bounds = [(*_declared(target), f"the range {name} accepts (min/max in its FMU's modelDescription.xml)")
              for name, target in consumers if _declared(target) is not None]
    magnitude = PLAUSIBLE_MAGNITUDE.get(port.unit)
    if magnitude is not None:
        bounds.append((-magnitude[0], magnitude[0], magnitude[1]))
    if not bounds:
        return None
    narrowest = min(bounds, key=lambda b: b[1] - b[0])
    return max(b[0] for b in bounds), min(b[1] for b in bounds), narrowest[2]


def _excess(value: float, low: float, high: float) -> float:
    """How far ``value`` lies outside [low, high] (inf for NaN: nothing is further)."""
    if value != value:
        return math.inf
    return max(low - value, value - high)


#: Blocks of steps at least this long (a compiled stretch's) are folded into the statistics in numpy;
#: shorter ones (a paced tick's) a row at a time, which costs less for a few rows
BLOCK_FOLD_ROWS = 8


class Statistics:
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


#: Without a CPU of its own, how long before a paced step is due the pacing stops sleeping and
#: spins: waking from a sleep takes 0.1-1 ms on a virtual machine (measured below).
SPIN_S = 0.3e-3


class RealtimePacing:
    """Paces the fastest components to the wall clock and measures how late each of their steps ends.

    A step of ``[t, t + h]`` may not start before wall time ``t`` (from the loop's first step) and
    should end by ``t + h``: its lateness is the wall time at its end minus ``t + h``. A haptic
    loop that misses its 1 ms deadline is what an operator feels as a stall.

    A paced run owns the machine, as a haptic loop does. With two or more CPUs allowed, this
    process keeps the first one while the worker processes and helper processes (the surface
    writer) share the others (``cpus`` in the report) until the run ends, and it spins between
    steps instead of sleeping; otherwise it sleeps until ``SPIN_S`` before a step and spins the
    rest. A worker woken for its step was often placed on this process's CPU and took it for
    milliseconds; a sleeping CPU wakes late and with cold caches. Measured on this 2-core VM
    (default scene without surfaces, 4 s, 8000 paced steps): sleeping to the deadline missed
    950-1470 deadlines, spinning its last 0.3 ms 670-690 (two or three runs each); with CPUs
    apart, spinning throughout against sleeping to 0.3 ms before, five runs each alternating,
    medians 536 against 904 (p99 lateness 1.7 against 2.7 ms), in another five 416 against 635.
    What remains is mostly the contact's step that takes in each new tissue frame (1.5-2.5 ms
    then; 0.4-0.8 ms for the intake since it runs in numba kernels, 0.35-0.45 ms since the tool's
    query is one too): it now ends about on time (at the median, 0.12 ms early to 0.04 ms late).

    Inside a compiled stretch (``compiled_loop.c``) the program paces and measures the steps the
    same way (``paced``, ``origin``, ``sleeps``; it sets ``origin`` at the run's first paced step
    when that step is its own) and hands their lateness over afterwards (``paced_block``).
    """

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


class Progress:
    """A tqdm bar in simulated seconds (shown after one second of wall time)."""

    def __init__(self, scene: Scene, duration: float, enabled: bool = True):
        self.scene, self.duration, self.enabled = scene, float(duration), enabled
        self.bar = None
        self._shown = 0

    def started(self, algorithm) -> None:
        from tqdm import tqdm

        self.seconds = algorithm.seconds
        self._every = max(1, algorithm.base // 100)
        self._end = algorithm.end
        self.bar = tqdm(total=self.duration, desc=self.scene.name, unit="s", delay=1.0, disable=not self.enabled,
                        bar_format="{l_bar}{bar}| {n:.3f}/{total:.3f} s sim [{elapsed}<{remaining}]")

    def advance(self, tick: int) -> None:
        if self.bar is not None and (tick - self._shown >= self._every or tick >= self._end):
            self.bar.update(self.seconds(tick) - self.bar.n)
            self._shown = tick

    def finished(self, algorithm) -> None:
        if self.bar is not None:
            self.bar.close()

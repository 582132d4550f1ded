"""The multirate master: steps every component at its own rate, moves values, records results.

Time is exact. Every step and the duration are rationals; the master counts integer *ticks* of
``1 / L`` seconds, ``L`` the least common multiple of their denominators (1/30 s and 1 ms give
ticks of 1/3000 s: the tissue steps 100 ticks, the haptic loop 3). An FMU is called with
``t = float(Fraction(tick, L))``, never with a sum of floats.

Which value a consumer sees. A consumer stepping ``[t, t + h]`` evaluates each input connection at
tick ``tau``: ``tau = t`` for a ``jacobi`` connection (the producer's samples up to the start of the
step) and ``tau = t + h`` for ``gauss-seidel`` (up to the end: the producer steps first). The rate
transition (``transitions``) turns the producer's samples at ticks ``<= tau`` into the value. So a
step can start as soon as each producer has reached the last of its grid points ``<= tau``; that
is the only scheduling rule, and the values a component receives depend on nothing else. Hence
the result is the same whether components step one after another in this process or concurrently
in worker processes: a ``jacobi`` connection from the 30 Hz tissue lets its 33 ms step run while
the 1 kHz loop goes on, as the seed's separate simulator and haptic processes did.

Initialization propagates outputs to inputs before the first step: components leave
initialization mode in the order of their connections (producers first), each receiving the
initial outputs of those already initialized, including parameters such as the surface triangles.

A failure of any component (an error status, a crashed worker, Ctrl-C, SIGTERM) ends the run with
everything recorded so far on disk and a summary that says which component, which call and at
what simulated time.
"""
from __future__ import annotations

import logging
import math
import signal
import threading
import time
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np

from . import transitions as tr
from .errors import FmuCallError, OrchestrationError
from .scene import ComponentSpec, ConnectionSpec, Scene

logger = logging.getLogger(__name__)


class RunInterrupted(OrchestrationError):
    """The run was stopped by Ctrl-C or SIGTERM."""


@dataclass
class _Input:
    """One incoming connection of a component, resolved for the run."""

    spec: ConnectionSpec
    port: str
    transition: str
    jacobi: bool
    producer: "_Component | None" = None    # stepped producer
    source: object = None                   # continuous source (evaluate(t))
    history: tr.SampleHistory | None = None
    last_key: object = None
    last_value: np.ndarray | None = None
    need_offset: int = 0                    # tau - t (0 for jacobi, h for gauss-seidel)
    parameter: bool = False                 # a parameter: set once, at initialization


@dataclass
class _Component:
    spec: ComponentSpec
    host: object
    step: int                               # ticks
    rank: int
    end: int                                # last tick it reaches
    time: int = 0                           # ticks reached (completed)
    running: bool = False
    started_at: float = 0.0
    busy: float = 0.0
    steps: int = 0
    inputs: list[_Input] = field(default_factory=list)
    observed: list[str] = field(default_factory=list)
    recorded: list[str] = field(default_factory=list)
    histories: dict[str, list[tr.SampleHistory]] = field(default_factory=dict)
    consumers: list[tuple["_Component", _Input]] = field(default_factory=list)
    surfaces: list = field(default_factory=list)          # VTU series written from this component

    @property
    def name(self) -> str:
        return self.spec.name


def tick_base(scene: Scene) -> int:
    """Ticks per second: the lcm of the denominators of every step and of the duration."""
    base = scene.duration.denominator
    for comp in scene.components.values():
        if comp.step is not None:
            base = math.lcm(base, comp.step.denominator)
    return base


class _Statistics:
    """Peaks, energies and warnings named in the scene's [summary], updated as outputs arrive."""

    def __init__(self, scene: Scene):
        self.peaks = {ref: (0.0, 0.0) for ref in scene.summary.get("peaks", [])}
        self.energy: dict[str, dict] = {}
        self.energy_refs = list(scene.summary.get("energy", []))
        self.warning_refs = list(scene.summary.get("warnings", []))
        self.warnings: dict[str, dict] = {}
        self.by_component: dict[str, list[tuple[str, str, str]]] = {}
        for kind, refs in (("peak", self.peaks), ("energy", self.energy_refs), ("warning", self.warning_refs)):
            for ref in refs:
                comp, port = ref.split(".")
                self.by_component.setdefault(comp, []).append((kind, port, ref))

    def ports(self, component: str) -> list[str]:
        return [port for _, port, _ in self.by_component.get(component, [])]

    def update(self, component: str, t: float, h: float, outputs: dict[str, np.ndarray]) -> None:
        for kind, port, ref in self.by_component.get(component, ()):
            value = outputs[port]
            if kind == "peak":
                magnitude = math.sqrt(float(value @ value)) if value.size > 1 else abs(float(value[0]))
                if magnitude > self.peaks[ref][0]:
                    self.peaks[ref] = (magnitude, t)
            elif kind == "energy":
                v = float(value[0]) if value.size == 1 else math.sqrt(float(value @ value))
                e = self.energy.setdefault(ref, {"initial": v, "final": v, "min": v, "max": v})
                e["final"] = v
                e["min"] = min(e["min"], v)
                e["max"] = max(e["max"], v)
            else:
                on = bool(value[0] != 0)
                w = self.warnings.setdefault(ref, {"count": 0, "time_on_s": 0.0, "first_s": None, "_on": False})
                if on and not w["_on"]:
                    w["count"] += 1
                    if w["first_s"] is None:
                        w["first_s"] = t
                if on:
                    w["time_on_s"] += h
                w["_on"] = on

    def report(self) -> dict:
        out: dict = {}
        if self.peaks:
            out["peaks"] = {ref: {"value": v, "time_s": t} for ref, (v, t) in self.peaks.items()}
        if self.energy:
            out["energy"] = {ref: {**e, "drift": e["final"] - e["initial"]} for ref, e in self.energy.items()}
        if self.warnings:
            out["operator_warnings"] = {ref: {k: v for k, v in w.items() if not k.startswith("_")}
                                        for ref, w in self.warnings.items()}
        return out


class Simulation:
    """One run of a scene. ``run()`` returns the summary dict (also written as JSON)."""

    def __init__(self, scene: Scene, out_dir: Path | str, *, hosting: str | None = None,
                 realtime: bool | None = None, progress: bool = True, duration: Fraction | float | None = None,
                 plots: bool = True, vtu: bool = True, observe: dict[str, list[str]] | None = None):
        self.scene = scene
        self.out_dir = Path(out_dir)
        #: forced for every FMU (the command line's --hosting), else each FMU's own or the scene's
        self.forced_hosting = hosting
        self.realtime = scene.realtime if realtime is None else realtime
        self.progress = progress
        self.duration = Fraction(repr(float(duration))) if isinstance(duration, float) else (
            Fraction(duration) if duration is not None else scene.duration)
        self.make_plots = plots
        self.write_vtu = vtu
        #: extra ports to read after every step (studies): {component: [port, ...]}
        self.extra_observed = dict(observe or {})
        #: the latest outputs of every component, {component: {port: array}}, kept after the run
        self.final_outputs: dict[str, dict[str, np.ndarray]] = {}
        self.base = math.lcm(tick_base(scene), self.duration.denominator)
        self.end = int(self.duration * self.base)
        self.components: dict[str, _Component] = {}
        self.sources: dict[str, object] = {}
        self.recorder = None
        self.stats = _Statistics(scene)
        self.deadline_misses = 0
        self.worst_lateness = 0.0
        self.deadline_steps = 0
        self._stop_reason: str | None = None
        self._source_cache: dict[str, tuple[int, dict]] = {}

    # -- time ------------------------------------------------------------------------------------
    def seconds(self, tick: int) -> float:
        # int / int is correctly rounded in Python: the same float as float(Fraction(tick, base))
        return tick / self.base

    # -- setup ---------------------------------------------------------------------------------
    def hosting_of(self, spec: ComponentSpec) -> str:
        if not spec.is_fmu:
            return "in-process"
        return self.forced_hosting or spec.hosting or self.scene.hosting

    @property
    def hosting(self) -> str:
        """"in-process", "out-of-process", or "mixed (out-of-process: a, b)"."""
        fmus = [c for c in self.scene.components.values() if c.is_fmu]
        kinds = {self.hosting_of(c) for c in fmus}
        if len(kinds) <= 1:
            return kinds.pop() if kinds else "in-process"
        workers = [c.name for c in fmus if self.hosting_of(c) == "out-of-process"]
        return f"mixed (out-of-process: {', '.join(workers)})"

    def _make_host(self, spec: ComponentSpec):
        if not spec.is_fmu:
            return spec.block
        if self.hosting_of(spec) == "in-process":
            from .hosting import InProcessFmu

            return InProcessFmu(spec.name, spec.description)
        from .worker import WorkerFmu

        return WorkerFmu(spec.name, spec.description)

    def _setup(self) -> None:
        scene = self.scene
        stepped = [s for s in scene.components.values() if not s.is_continuous]
        order = _initialization_order(scene, [s.name for s in stepped])
        for rank, name in enumerate(order):
            spec = scene.components[name]
            step = int(spec.step * self.base)
            end = -(-self.end // step) * step
            self.components[name] = _Component(spec=spec, host=None, step=step, rank=rank, end=end)
        for spec in scene.components.values():
            if spec.is_continuous:
                self.sources[spec.name] = spec.block

        # Observed ports: those with consumers, recorded, summarised or drawn.
        for conn in scene.connections:
            target = self.components[conn.target]
            in_port = target.spec.ports[conn.target_port]
            is_parameter = in_port.causality != "input"
            inp = _Input(spec=conn, port=conn.target_port, transition=conn.transition or "hold",
                         jacobi=conn.ordering == "jacobi", parameter=is_parameter)
            if conn.source in self.sources:
                inp.source = self.sources[conn.source]
            else:
                producer = self.components[conn.source]
                inp.producer = producer
                if not is_parameter:
                    inp.history = tr.SampleHistory(producer.step)
                    producer.histories.setdefault(conn.source_port, []).append(inp.history)
                    producer.consumers.append((target, inp))
                    _add(producer.observed, conn.source_port)
            inp.need_offset = 0 if inp.jacobi else target.step
            target.inputs.append(inp)
        for name, ports in scene.record.items():
            comp = self.components[name]
            comp.recorded = list(ports)
            for port in ports:
                _add(comp.observed, port)
        for name, comp in self.components.items():
            for port in self.stats.ports(name):
                _add(comp.observed, port)
        for surface in scene.surfaces if self.write_vtu else ():
            comp = self.components[surface.component]
            comp.surfaces.append(surface)
            for port in (surface.positions, *surface.point_data):
                _add(comp.observed, port)
        for name, ports in self.extra_observed.items():
            if name not in self.components:
                raise OrchestrationError(f"observe: no stepped component {name!r} in the scene")
            for port in ports:
                if port not in self.components[name].spec.ports:
                    raise OrchestrationError(f"observe: {name} has no port {port!r}")
                _add(self.components[name].observed, port)

        # Hosts, instantiated one after the other (a worker process loads its FMU while the master waits).
        for comp in self.components.values():
            comp.host = self._make_host(comp.spec)
        for comp in self.components.values():
            _call(comp, "instantiate", 0.0, comp.host.instantiate)
        for comp in self.components.values():
            params = comp.spec.parameters
            if params:
                structural = {k: v for k, v in params.items() if comp.spec.ports[k].causality == "structuralParameter"}
                rest = {k: v for k, v in params.items() if k not in structural}
                for group in (structural, rest):
                    if group:
                        _call(comp, "set parameters", 0.0, lambda g=group: comp.host.set_values(g))
            _call(comp, "fmi3EnterInitializationMode", 0.0, lambda: comp.host.enter_initialization(0.0))

    def _initialize(self) -> None:
        """Leave initialization mode producer-first, propagating initial outputs (and parameters)."""
        from .recording import Recorder

        self.recorder = Recorder(self.out_dir)
        for name, ports in self.scene.record.items():
            comp = self.components[name]
            self.recorder.add_stream(name, [(p, comp.spec.ports[p].size, comp.spec.ports[p].unit) for p in ports])
        done: set[str] = set()
        for comp in sorted(self.components.values(), key=lambda c: c.rank):
            parameters = {}
            for inp in comp.inputs:
                if not inp.parameter:
                    continue
                producer = inp.producer
                if producer is None:
                    value = self._evaluate(inp.source, 0)[inp.spec.source_port]
                elif producer.name in done:
                    value = _call(producer, "get values", 0.0,
                                  lambda p=producer, i=inp: p.host.get_values([i.spec.source_port]))[inp.spec.source_port]
                else:
                    raise OrchestrationError(f"{inp.spec.label}: the parameter's producer {producer.name} is initialized "
                                             f"after {comp.name}; parameters cannot flow around a loop")
                parameters[inp.port] = _typed(value, comp.spec.ports[inp.port])
            if parameters:
                _call(comp, "set parameters", 0.0, lambda: comp.host.set_values(parameters))
            input_ports = [i.port for i in comp.inputs if comp.spec.ports[i.port].causality == "input"]
            _call(comp, "configure", 0.0, lambda: comp.host.configure(input_ports, list(comp.observed)))
            values = self._input_values(comp, initial=True, done=done)
            if values:
                _call(comp, "set inputs", 0.0, lambda: comp.host.set_inputs(values))
            _call(comp, "fmi3ExitInitializationMode", 0.0, comp.host.exit_initialization)
            outputs = _call(comp, "get outputs", 0.0, comp.host.get_outputs)
            self._store(comp, 0, outputs)
            done.add(comp.name)
        if self.write_vtu:
            for surface in self.scene.surfaces:
                comp = self.components[surface.component]
                triangles = _call(comp, "get values", 0.0,
                                  lambda: comp.host.get_values([surface.triangles]))[surface.triangles]
                self.recorder.add_surface_series(surface.name, np.asarray(triangles).reshape(-1, 3).astype(np.int64))
                self._write_surface(surface, comp, 0, None)

    # -- values ----------------------------------------------------------------------------------
    def _input_values(self, comp: _Component, initial: bool = False, done: set | None = None) -> dict:
        values: dict[str, np.ndarray] = {}
        t = comp.time
        for inp in comp.inputs:
            if inp.parameter:
                continue  # set once, at initialization
            tau = t + (0 if initial else inp.need_offset)
            key = None
            if inp.source is not None:
                if inp.last_value is not None and inp.source.constant:
                    continue
                value = self._evaluate(inp.source, tau)[inp.spec.source_port]
            else:
                if initial and inp.producer.name not in (done or ()):
                    continue  # producer not initialized yet (a loop): the start value stands
                h = inp.history
                if not h.ticks:
                    continue
                kind = inp.transition
                if kind == "hold":
                    value, key = tr.hold(h, tau)
                elif kind == "interpolate":
                    value = tr.interpolate(h, tau)
                elif kind == "extrapolate":
                    value = tr.extrapolate(h, tau)
                else:
                    value = tr.average(h, tau, comp.step)
            if key is not None:
                if key == inp.last_key:
                    continue
                inp.last_key = key
            else:
                last = inp.last_value
                if last is not None and (value is last or (value.shape == last.shape and (value == last).all())):
                    continue
                inp.last_value = value
            values[inp.port] = value
        return values

    def _evaluate(self, source, tau: int) -> dict[str, np.ndarray]:
        """A source's outputs at tick ``tau``, evaluated once per tick for all its connections."""
        cached = self._source_cache.get(source.name)
        if cached is not None and cached[0] == tau:
            return cached[1]
        outputs = source.evaluate(self.seconds(tau))
        self._source_cache[source.name] = (tau, outputs)
        return outputs

    def _store(self, comp: _Component, tick: int, outputs: dict[str, np.ndarray]) -> None:
        self.final_outputs[comp.name] = outputs
        for port, histories in comp.histories.items():
            value = outputs[port]
            for history in histories:
                history.append(tick, value)
        t = self.seconds(tick)
        if comp.recorded:
            self.recorder.write(comp.name, t, outputs)
        self.stats.update(comp.name, t, self.seconds(comp.step) if tick else 0.0, outputs)
        # Drop samples no consumer can still ask for.
        for consumer, inp in comp.consumers:
            keep_from = consumer.time - 2 * comp.step - consumer.step
            inp.history.prune(keep_from)

    def _write_surface(self, surface, comp: _Component, tick: int, outputs: dict | None) -> None:
        if outputs is None:
            outputs = _call(comp, "get values", 0.0,
                            lambda: comp.host.get_values([surface.positions, *surface.point_data]))
        positions = np.asarray(outputs[surface.positions]).reshape(-1, 3)
        point_data = {name: np.asarray(outputs[name]).reshape(positions.shape[0], -1).squeeze()
                      for name in surface.point_data}
        self.recorder.write_surface(surface.name, self.seconds(tick), positions, point_data)

    # -- scheduling ------------------------------------------------------------------------------
    def _ready(self, comp: _Component) -> bool:
        for inp in comp.inputs:
            producer = inp.producer
            if producer is None or inp.history is None:
                continue
            tau = comp.time + inp.need_offset
            need = min((tau // producer.step) * producer.step, producer.end)
            if producer.time < need:
                return False
        return True

    def _start(self, comp: _Component) -> None:
        t = comp.time
        if self.realtime and comp.step == self._fastest:
            lag = self.seconds(t) - (time.perf_counter() - self._wall_start)
            if lag > 0:
                time.sleep(lag)
        values = self._input_values(comp)
        comp.running = True
        comp.started_at = time.perf_counter()
        _call(comp, "fmi3DoStep", self.seconds(t),
              lambda: comp.host.start_step(self.seconds(t), self.seconds(comp.step), values))

    def _finish(self, comp: _Component) -> None:
        t = comp.time
        outputs = _call(comp, "fmi3DoStep", self.seconds(t), comp.host.finish_step)
        now = time.perf_counter()
        comp.busy += now - comp.started_at
        comp.running = False
        comp.time = t + comp.step
        comp.steps += 1
        if self.realtime and comp.step == self._fastest:
            self.deadline_steps += 1
            late = (now - self._wall_start) - self.seconds(comp.time)
            if late > 0:
                self.deadline_misses += 1
                self.worst_lateness = max(self.worst_lateness, late)
        self._store(comp, comp.time, outputs)
        for surface in comp.surfaces:
            if comp.steps % surface.every == 0:
                self._write_surface(surface, comp, comp.time, outputs)

    def _loop(self, bar) -> None:
        from multiprocessing.connection import wait

        comps = sorted(self.components.values(), key=lambda c: c.rank)
        lookahead = 2 * max(c.step for c in comps)
        concurrent = any(c.host.wait_handle() is not None for c in comps)
        shown = 0
        while True:
            if self._stop_reason:
                raise RunInterrupted(self._stop_reason)
            pending = [c for c in comps if c.time < self.end or c.running]
            if not pending:
                break
            t_min = min(c.time for c in pending)
            candidates = [c for c in pending if not c.running and c.time < self.end
                          and c.time - t_min <= lookahead and self._ready(c)]
            if len(candidates) > 1:
                candidates.sort(key=lambda c: (c.time, c.rank))
            if not concurrent and candidates:
                candidates = candidates[:1]
            for comp in candidates:
                self._start(comp)
                if comp.host.wait_handle() is None:
                    self._finish(comp)
            running = [c for c in comps if c.running]
            if running and not candidates:
                handles = {c.host.wait_handle(): c for c in running}
                for handle in wait(list(handles), timeout=1.0):
                    self._finish(handles[handle])
            elif not running and not candidates:
                stuck = ", ".join(f"{c.name} at t = {self.seconds(c.time):.6g} s" for c in pending)
                raise OrchestrationError(f"no component can step ({stuck}); this is a bug in the scene checks")
            if bar is not None:
                reached = min(c.time for c in comps)
                if reached - shown >= self.base // 100 or reached >= self.end:
                    bar.update(self.seconds(reached) - bar.n)
                    shown = reached

    # -- the run -------------------------------------------------------------------------------
    def run(self) -> dict:
        from tqdm import tqdm

        from .recording import write_summary

        self.out_dir.mkdir(parents=True, exist_ok=True)
        status, error = "completed", None
        t_setup = time.perf_counter()
        wall = 0.0
        previous_handlers = self._install_signal_handlers()
        try:
            self._setup()
            self._initialize()
            self._fastest = min(c.step for c in self.components.values())
            self._wall_start = time.perf_counter()
            setup_time = self._wall_start - t_setup
            with tqdm(total=float(self.duration), desc=self.scene.name, unit="s", delay=1.0,
                      disable=not self.progress, bar_format="{l_bar}{bar}| {n:.3f}/{total:.3f} s sim "
                      "[{elapsed}<{remaining}]") as bar:
                self._loop(bar)
            wall = time.perf_counter() - self._wall_start
        except RunInterrupted as exc:
            status, error = "interrupted", str(exc)
        except KeyboardInterrupt:
            status, error = "interrupted", "interrupted by Ctrl-C"
        except OrchestrationError as exc:
            status, error = "failed", str(exc)
        finally:
            if wall == 0.0 and hasattr(self, "_wall_start"):
                wall = time.perf_counter() - self._wall_start
            setup_time = (self._wall_start - t_setup) if hasattr(self, "_wall_start") else time.perf_counter() - t_setup
            self._restore_signal_handlers(previous_handlers)
            messages = self._teardown()
        summary = self._summary(status, error, wall, setup_time, messages)
        if self.make_plots and self.scene.plots and self.recorder is not None:
            try:
                from .plots import plot_signals

                summary["results"]["plots"] = [str(p) for p in plot_signals(self.out_dir, self.scene.plots)]
            except Exception as exc:  # plots are a convenience: never lose the summary over them
                logger.warning("plots failed: %s", exc)
        write_summary(self.out_dir, summary)
        self.summary_text = self.format(summary)
        return summary

    def _unit(self, ref: str) -> str:
        comp, port = ref.split(".")
        unit = self.scene.components[comp].ports[port].unit
        return f" {unit}" if unit else ""

    def format(self, summary: dict) -> str:
        """The readable summary printed after a run (summary.json has everything)."""
        lines = []
        rtf = summary["real_time_factor"]
        head = (f"{summary['scene']}: {summary['status']}, {summary['simulated_time_s']:.4g} s simulated in "
                f"{summary['wall_time_s']:.3g} s")
        if rtf:
            head += f" (real-time factor {rtf:.2f}, {summary['hosting']}; setup {summary['setup_time_s']:.1f} s)"
        lines.append(head)
        if summary["error"]:
            lines.append(f"  error: {summary['error']}")
        for name, comp in summary["components"].items():
            lines.append(f"  {name:10s} {comp['rate_hz']:8.6g} Hz  {comp['steps']:7d} steps  busy {comp['busy_wall_s']:6.2f} s")
        for ref, peak in summary.get("peaks", {}).items():
            lines.append(f"  peak {ref:32s} {peak['value']:.4g}{self._unit(ref)} at {peak['time_s']:.3f} s")
        for ref, e in summary.get("energy", {}).items():
            unit = self._unit(ref)
            lines.append(f"  energy {ref:30s} final {e['final']:.4g}{unit}, range [{e['min']:.4g}, {e['max']:.4g}]{unit}, "
                         f"drift {e['drift']:.4g}{unit}")
        for ref, w in summary.get("operator_warnings", {}).items():
            first = f", first at {w['first_s']:.3f} s" if w["first_s"] is not None else ""
            lines.append(f"  warning {ref:29s} raised {w['count']} time(s), on for {w['time_on_s']:.3f} s{first}")
        if "deadlines" in summary:
            d = summary["deadlines"]
            lines.append(f"  haptic deadlines missed: {d['missed']} of {d['haptic_steps']} "
                         f"(worst {1e3 * d['worst_lateness_s']:.2f} ms late)")
        messages = summary.get("fmu_messages", [])
        errors = [m for m in messages if m["status"] in ("error", "fatal")]
        lines.append(f"  FMU messages: {len(messages)} ({len(errors)} errors)" if messages else "  FMU messages: none")
        for m in messages[:5]:
            lines.append(f"    {m['component']} [{m['status']}] {m['message'][:200]}")
        lines.append(f"  results in {summary['results']['folder']}/: summary.json, a CSV per component, "
                     "PNG plots, surfaces as .pvd (ParaView)")
        return "\n".join(lines)

    def _teardown(self) -> list[dict]:
        messages = []
        if self.recorder is not None:
            self.recorder.close()
        for comp in self.components.values():
            host = comp.host
            if host is None:
                continue
            try:
                host.terminate()
            except Exception as exc:  # terminate never raises by contract; belt and braces
                logger.warning("%s: terminate failed: %s", comp.name, exc)
            for status, text in getattr(host, "messages", []):
                if status >= 1:
                    messages.append({"component": comp.name, "status": _STATUS.get(status, str(status)), "message": text})
        return messages

    def _summary(self, status: str, error: str | None, wall: float, setup_time: float, messages: list) -> dict:
        reached = min((c.time for c in self.components.values()), default=0)
        simulated = self.seconds(reached)
        summary = {
            "scene": self.scene.name,
            "description": self.scene.description,
            "status": status,
            "error": error,
            "hosting": self.hosting,
            "simulated_time_s": simulated,
            "requested_time_s": float(self.duration),
            "wall_time_s": wall,
            "setup_time_s": setup_time,
            "real_time_factor": simulated / wall if wall > 0 else None,
            "components": {
                c.name: {"step_s": self.seconds(c.step), "rate_hz": self.base / c.step, "steps": c.steps,
                         "busy_wall_s": c.busy, "hosting": self.hosting_of(c.spec)}
                for c in sorted(self.components.values(), key=lambda c: c.rank)
            },
            **self.stats.report(),
            "fmu_messages": messages,
        }
        if self.realtime:
            summary["deadlines"] = {"haptic_steps": self.deadline_steps, "missed": self.deadline_misses,
                                    "worst_lateness_s": self.worst_lateness}
        files = self.recorder.files if self.recorder is not None else {}
        # every file but the individual surface frames (the .pvd lists those)
        summary["results"] = {"folder": str(self.out_dir),
                              **{k: str(v) for k, v in files.items() if not k.endswith("]")}}
        return summary

    def _install_signal_handlers(self):
        if threading.current_thread() is not threading.main_thread():
            return None

        def on_term(signum, frame):
            self._stop_reason = "stopped by SIGTERM"

        return signal.signal(signal.SIGTERM, on_term)

    @staticmethod
    def _restore_signal_handlers(previous) -> None:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


_STATUS = {0: "ok", 1: "warning", 2: "discard", 3: "error", 4: "fatal"}


def _add(items: list, item) -> None:
    if item not in items:
        items.append(item)


def _typed(value, port):
    array = np.asarray(value)
    if port.type.startswith("Float"):
        return array.astype(np.float64)
    if port.type == "Boolean":
        return array.astype(bool)
    return np.rint(array).astype(np.int64)


def _call(comp: _Component, call: str, t: float, action):
    """Run a host call; turn anything but FmuCallError into one naming the component and call."""
    try:
        return action()
    except FmuCallError:
        raise
    except (KeyboardInterrupt, RunInterrupted):
        raise
    except Exception as exc:
        raise FmuCallError(comp.name, call, t, f"{type(exc).__name__}: {exc}") from exc


def _initialization_order(scene: Scene, names: list[str]) -> list[str]:
    """Producers before consumers; a loop is entered where only jacobi connections lead in."""
    remaining = list(names)
    edges = [(c.source, c.target, c.ordering) for c in scene.connections if c.source in names and c.target in names]
    order: list[str] = []
    while remaining:
        def blocked(n, kinds):
            return any(t == n and s in remaining and k in kinds for s, t, k in edges)
        free = [n for n in remaining if not blocked(n, ("gauss-seidel", "jacobi"))]
        if not free:
            free = [n for n in remaining if not blocked(n, ("gauss-seidel",))] or remaining
        order.append(free[0])
        remaining.remove(free[0])
    return order


def run_scene(scene: Scene, out_dir, **kwargs) -> tuple[dict, str]:
    """Run ``scene`` into ``out_dir``; return (summary dict, readable summary text)."""
    simulation = Simulation(scene, out_dir, **kwargs)
    summary = simulation.run()
    return summary, simulation.summary_text

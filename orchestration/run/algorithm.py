"""The multirate co-simulation algorithm: integer scheduling, stepping and value routing.

Time is exact. Every step and the duration are rationals; the algorithm counts integer *ticks* of
``1 / L`` seconds, ``L`` the least common multiple of their denominators (1/30 s and 1 ms give
ticks of 1/3000 s: the tissue steps 100 ticks, the haptic loop 3). An FMU is called with
``t = tick / L`` (correctly rounded), never with a sum of floats.

Which value a consumer sees. A consumer stepping ``[t, t + h]`` evaluates each input connection at
tick ``tau``: ``tau = t`` for a ``jacobi`` connection (the producer's samples up to the start of the
step) and ``tau = t + h`` for ``gauss-seidel`` (up to the end: the producer steps first). The rate
transition (:mod:`orchestration.plan.transitions`) turns the producer's samples at ticks ``<= tau`` into the value.
So a step can start as soon as each producer has reached the last of its grid points ``<= tau``;
that is the only scheduling rule, and the values a component receives depend on nothing else.
Hence the result is the same whether components step one after another in this process or
concurrently in worker processes: a ``jacobi`` connection from the 30 Hz tissue lets its 33 ms
step run while the 1 kHz loop goes on.

The schedule (:mod:`orchestration.plan.schedule`) says which call comes next. A step of a host
that is ``asynchronous`` (a worker process) is started as soon as it may, after the in-process
steps of the same tick, and collected as soon as it is done (looked at every few calls) or when a
consumer needs it, whichever comes first: values depend on ticks only, so when is a matter of
wall time, and early is off the tick that needs the result. The input routes and the output
fan-out are precomputed per component.

Initialization propagates outputs to inputs before the first step: components leave
initialization mode in the order of their connections (producers first), each receiving the
initial outputs of those already initialized, including parameters such as the surface triangles.

Observers (:class:`~orchestration.observers.base.Observer`) see every step's outputs; the
algorithm knows nothing of files, statistics or wall-clock pacing.

The compiled loop (:mod:`.compiled_loop`) makes the stretches of in-process steps between two
events that need this module (a worker's step starting or collected) in C: planned with
:meth:`~orchestration.plan.schedule.Schedule.decide_at` and these routing rules, replayed into the
histories and observers afterwards; the same calls with the same values as stepping here (tested bitwise).
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Callable

import numpy as np

from orchestration.plan import transitions as tr
from orchestration.errors import FmuCallError, OrchestrationError
from orchestration.observers.base import Observer
from orchestration.plan.schedule import Schedule
from orchestration.run.compiled_loop import CompiledLoop, load_program_runner
from orchestration.run.step_costs import StepCosts
from orchestration.scene.model import ComponentSpec, ConnectionSpec, ORDERINGS, Ordering, Scene

logger = logging.getLogger(__name__)

#: Asynchronous steps are looked at (a poll without waiting, about 1 us) every this many events + 1.
_POLL_EVERY_MASK = 3


class RunInterrupted(OrchestrationError):
    """The run was stopped by Ctrl-C or SIGTERM."""


class RunTerminated(OrchestrationError):
    """A component asked to end the simulation (``terminateSimulation`` out of ``fmi3DoStep``)."""

    def __init__(self, component: str, time: float):
        self.component = component
        self.time = time
        super().__init__(f"{component} requested terminateSimulation at t = {time:.6g} s")


@dataclass(eq=False)
class Route:
    """One incoming connection of a component, resolved for the run."""

    spec: ConnectionSpec
    port: str
    parameter: bool = False                 # set once, at initialization
    producer: "Component | None" = None     # stepped producer
    source: object = None                   # continuous source (evaluate(t))
    history: tr.SampleHistory | tr.WindowSums | None = None
    transition: tr.Transition | None = None
    need_offset: int = 0                    # tau - t: 0 for jacobi, the consumer's step for gauss-seidel
    last_key: object = None
    last_value: np.ndarray | None = None
    last_bytes: bytes | None = None         # last_value.tobytes(), kept so each step converts one array
    seen: int = -1                          # history.count when a keyed transition last took its newest sample


@dataclass(eq=False)
class Component:
    """A stepped component during a run: its host, its grid in ticks, its routes and listeners."""

    spec: ComponentSpec
    rank: int                               # its place in the initialization order and in ``ordered``
    step: int                               # ticks
    end: int                                # last tick it reaches
    host: object = None
    time: int = 0                           # ticks reached (completed)
    running: bool = False
    asynchronous: bool = False              # its host steps in another process
    steps: int = 0
    busy: float = 0.0                       # wall seconds inside its calls (or in flight)
    started_at: float = 0.0
    costs: StepCosts | None = None          # each step's cost, as its host or the compiled loop measured it
    routes: list[Route] = field(default_factory=list)
    observed: list[str] = field(default_factory=list)
    histories: dict[str, list] = field(default_factory=dict)  # per port: its consumers' histories
    consumers: list[tuple["Component", Route]] = field(default_factory=list)
    listeners: list[Callable] = field(default_factory=list)     # observers' stepped(comp, tick, outputs)
    pre_step: list[Callable] = field(default_factory=list)      # observers' before_step(comp, tick)
    outputs: dict[str, np.ndarray] = field(default_factory=dict)  # the latest, valid until its next step

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


def call(comp: Component, what: str, t: float | None, action):
    """Run a host call; anything but an FmuCallError becomes one naming the component, call and time."""
    try:
        return action()
    except FmuCallError:
        raise
    except (KeyboardInterrupt, RunInterrupted):
        raise
    except Exception as exc:
        raise FmuCallError(comp.name, what, t, f"{type(exc).__name__}: {exc}") from exc


class MultirateAlgorithm:
    """Steps the stepped components of ``scene`` from 0 to ``duration`` (exact) over their hosts.

    ``make_host(spec)`` gives each stepped component its host (the ``ComponentHost`` protocol of
    :mod:`.hosting`); continuous sources are created per run from their spec, unless ``sources``
    gives one by name (an embedding master's, e.g. :class:`~orchestration.blocks.sources.ExternalSource`). ``observers`` are
    notified of every step's outputs; ``extra_observed`` names more ports to read after each step.
    """

    def __init__(self, scene: Scene, duration: Fraction, make_host: Callable[[ComponentSpec], object],
                 observers: list = (), extra_observed: dict[str, list[str]] | None = None,
                 compiled_loop: bool = True, sources: dict[str, object] | None = None):
        self.scene = scene
        self.duration = Fraction(duration)
        self.base = math.lcm(tick_base(scene), self.duration.denominator)
        self.end = int(self.duration * self.base)
        self.make_host = make_host
        self.observers = list(observers)
        for observer in self.observers:
            if not isinstance(observer, Observer):
                raise TypeError(f"{observer!r} is no observer: subclass orchestration.observers.base.Observer")
        self.extra_observed = dict(extra_observed or {})
        #: sources given by an embedding master in place of the scene's (by name, the same ports)
        self.given_sources = dict(sources or {})
        self.components: dict[str, Component] = {}
        self.ordered: list[Component] = []
        self.sources: dict[str, object] = {}
        #: set by the master's SIGINT/SIGTERM handler; checked between ticks and between setup calls
        self.stop_reason: str | None = None
        #: 1 after a stop request, 2 after a second one (forced); handed to hosts that wait (workers)
        self.stop_level = 0
        #: set when a component asked to end the run; the others finish the steps that end by then
        self.terminated: RunTerminated | None = None
        self._source_cache: dict[str, tuple[int, dict]] = {}
        #: which call comes next (set by run(): the components' steps are known by then)
        self.schedule: Schedule | None = None
        #: run stretches of in-process steps in C (:mod:`.compiled_loop`) where the components allow it
        self.use_compiled_loop = compiled_loop
        #: the compiled loop of the run (None: every step in Python); its ``steps`` count what it made
        self.compiled_loop = None

    # -- time ------------------------------------------------------------------------------------
    def seconds(self, tick: int) -> float:
        # int / int is correctly rounded in Python: the same float as float(Fraction(tick, base))
        return tick / self.base

    @property
    def reached(self) -> int:
        """The tick every component has reached."""
        return min((c.time for c in self.ordered), default=0)

    def request_stop(self, reason: str, level: int) -> None:
        """A stop request (from a signal handler: flags only). ``level`` 1 stops at the next check;
        2 (a second request) also tells the hosts that wait for a worker to abandon the call."""
        self.stop_reason = reason
        self.stop_level = level
        for comp in self.ordered:
            self._pass_stop_level(comp)

    def _pass_stop_level(self, comp: Component) -> None:
        if comp.host is not None and hasattr(comp.host, "stop_level"):  # hosts that wait (workers)
            comp.host.stop_level = self.stop_level

    def check_stop(self) -> None:
        """Raise RunInterrupted if a stop was requested (between calls, never inside one)."""
        if self.stop_reason:
            raise RunInterrupted(self.stop_reason)

    # -- setup -----------------------------------------------------------------------------------
    def setup(self) -> None:
        """Resolve routes, create and instantiate the hosts, set parameters, enter initialization."""
        if self.use_compiled_loop:  # built or loaded now, as the FMUs are, not in the run's time
            load_program_runner()
        scene = self.scene
        stepped = [s for s in scene.components.values() if not s.is_continuous]
        for rank, name in enumerate(initialization_order(scene, [s.name for s in stepped])):
            spec = scene.components[name]
            step = int(spec.step * self.base)
            self.components[name] = Component(spec=spec, rank=rank, step=step,
                                              end=-(-self.end // step) * step,
                                              costs=StepCosts(float(Fraction(step, self.base))))
        self.ordered = list(self.components.values())
        for spec in scene.components.values():
            if spec.is_continuous:
                given = self.given_sources.get(spec.name)
                self.sources[spec.name] = given if given is not None else spec.new_block()

        for conn in scene.connections:
            target = self.components[conn.target]
            is_parameter = target.spec.ports[conn.target_port].causality != "input"
            route = Route(spec=conn, port=conn.target_port, parameter=is_parameter)
            if conn.source in self.sources:
                route.source = self.sources[conn.source]
            else:
                producer = self.components[conn.source]
                route.producer = producer
                if not is_parameter:
                    route.transition = tr.REGISTRY[conn.transition or tr.DEFAULT](producer.step, target.step)
                    route.history = route.transition.history
                    producer.histories.setdefault(conn.source_port, []).append(route.history)
                    producer.consumers.append((target, route))
                    _add(producer.observed, conn.source_port)
            route.need_offset = 0 if conn.ordering == Ordering.JACOBI else target.step
            target.routes.append(route)
        for observer in self.observers:
            for comp in self.ordered:
                for port in observer.ports(comp.name):
                    _add(comp.observed, port)
                if observer.subscribes(comp):
                    comp.listeners.append(observer.stepped)
                    if observer.times_steps:
                        comp.pre_step.append(observer.before_step)
        for name, ports in self.extra_observed.items():
            if name not in self.components:
                raise OrchestrationError(f"observe: no stepped component {name!r} in the scene")
            for port in ports:
                if port not in self.components[name].spec.ports:
                    raise OrchestrationError(f"observe: {name} has no port {port!r}")
                _add(self.components[name].observed, port)

        # Hosts, instantiated one after the other (a worker process loads its FMU while the master waits).
        self.check_stop()
        for comp in self.ordered:
            comp.host = self.make_host(comp.spec)
            comp.asynchronous = comp.host.asynchronous
            self._pass_stop_level(comp)
        for comp in self.ordered:
            self.check_stop()
            call(comp, "instantiate", 0.0, comp.host.instantiate)
        for comp in self.ordered:
            self.check_stop()
            if comp.spec.parameters:  # structural ones are set in Configuration Mode by the host
                call(comp, "set parameters", 0.0, lambda c=comp: c.host.set_values(c.spec.parameters))
            call(comp, "fmi3EnterInitializationMode", 0.0, lambda c=comp: c.host.enter_initialization(0.0))

    def finished(self) -> None:
        """Tell every observer that the run ended (however it ended)."""
        for observer in self.observers:
            observer.finished(self)

    def initialize(self) -> None:
        """Leave initialization mode producer-first, propagating initial outputs (and parameters)."""
        for observer in self.observers:
            observer.initializing(self)
        done: set[str] = set()
        for comp in self.ordered:
            self.check_stop()
            parameters = {}
            for route in comp.routes:
                if not route.parameter:
                    continue
                producer = route.producer
                port = route.spec.source_port
                if producer is None:
                    value = self._evaluate(route.source, 0)[port]
                elif producer.name in done:
                    value = call(producer, "get values", 0.0, lambda p=producer, n=port: p.host.get_values([n]))[port]
                else:
                    raise OrchestrationError(f"{route.spec.label}: the parameter's producer {producer.name} is "
                                             f"initialized after {comp.name}; parameters cannot flow around a loop")
                parameters[route.port] = _typed(value, comp.spec.ports[route.port])
            if parameters:
                call(comp, "set parameters", 0.0, lambda: comp.host.set_values(parameters))
            input_ports = [r.port for r in comp.routes if not r.parameter]
            call(comp, "configure", 0.0, lambda: comp.host.configure(input_ports, list(comp.observed)))
            values = self._input_values(comp, initial=True, done=done)
            if values:
                call(comp, "set inputs", 0.0, lambda: comp.host.set_inputs(values))
            call(comp, "fmi3ExitInitializationMode", 0.0, comp.host.exit_initialization)
            outputs = call(comp, "get outputs", 0.0, comp.host.get_outputs)
            self._store(comp, 0, outputs)
            done.add(comp.name)
        for observer in self.observers:
            observer.initialized(self)

    def get_values(self, component: str, names: list[str]) -> dict[str, np.ndarray]:
        """Values of any readable variables of a component (between steps; not the hot path)."""
        comp = self.components[component]
        return call(comp, "get values", self.seconds(comp.time), lambda: comp.host.get_values(list(names)))

    # -- values ----------------------------------------------------------------------------------
    def _input_values(self, comp: Component, initial: bool = False, done: set | None = None) -> dict:
        values: dict[str, np.ndarray] = {}
        t = comp.time
        for route in comp.routes:
            if route.parameter:
                continue
            tau = t if initial else t + route.need_offset
            key = None
            if route.source is not None:
                if route.last_value is not None and route.source.constant:
                    continue
                value = self._evaluate(route.source, tau)[route.spec.source_port]
            else:
                if initial and route.producer.name not in done:
                    continue  # producer not initialized yet (a loop): the start value stands
                history = route.history
                if history.count == route.seen:
                    continue  # hold gave the newest sample and nothing arrived since: the same value
                if not history.ticks:
                    continue
                value, key = route.transition.value(tau)
                if key is not None and key == history.ticks[-1]:
                    route.seen = history.count
            if key is not None:
                if key == route.last_key:
                    continue
                route.last_key = key
            # A new sample with the same bits as the last one set (a force that stays zero, a patch
            # that stays the same) is not set again. Bitwise: much cheaper than an elementwise compare.
            last = route.last_value
            if last is not None and value is last:
                continue
            data = value.tobytes()
            if data == route.last_bytes:
                continue
            route.last_value, route.last_bytes = value, data
            values[route.port] = value
        return values

    def _evaluate(self, source, tau: int) -> dict[str, np.ndarray]:
        """A source's outputs at tick ``tau``, evaluated once per tick for all its connections."""
        cached = self._source_cache.get(source.name)
        if cached is not None and cached[0] == tau:
            return cached[1]
        outputs = source.evaluate(self.seconds(tau))
        self._source_cache[source.name] = (tau, outputs)
        return outputs

    def _store(self, comp: Component, tick: int, outputs: dict[str, np.ndarray]) -> None:
        """Keep what consumers will read (copies: a host's outputs are valid until its next step)."""
        comp.outputs = outputs
        for port, histories in comp.histories.items():
            value = outputs[port]
            sample = None  # one copy shared by the histories that keep it: nobody writes to it
            for history in histories:
                if history.keeps_values:
                    if sample is None:
                        sample = value.copy()
                    history.append(tick, sample)
                else:
                    history.append(tick, value)
        for listener in comp.listeners:
            listener(comp, tick, outputs)
        # Drop samples no consumer can still ask for.
        for consumer, route in comp.consumers:
            route.history.prune(consumer.time - 2 * comp.step - consumer.step)

    # -- stepping --------------------------------------------------------------------------------
    def start_step(self, comp: Component, clock) -> None:
        t = comp.time
        for hook in comp.pre_step:
            hook(comp, t)
        values = self._input_values(comp)
        comp.running = True
        comp.started_at = clock()
        ts = t / self.base
        try:  # call() without building a closure per step
            comp.host.start_step(ts, comp.step / self.base, values)
        except (FmuCallError, KeyboardInterrupt, RunInterrupted):
            raise
        except Exception as exc:
            raise FmuCallError(comp.name, "fmi3DoStep", ts, f"{type(exc).__name__}: {exc}") from exc

    def finish_step(self, comp: Component, clock) -> None:
        t = comp.time
        try:
            outputs = comp.host.finish_step()
        except (FmuCallError, KeyboardInterrupt, RunInterrupted):
            raise
        except Exception as exc:
            raise FmuCallError(comp.name, "fmi3DoStep", t / self.base, f"{type(exc).__name__}: {exc}") from exc
        elapsed = clock() - comp.started_at
        comp.busy += elapsed
        # the FMU's own time where its host measured it (a worker: without the master's waiting)
        measured = getattr(comp.host, "last_step_seconds", None)
        comp.costs.add(elapsed if measured is None else measured)
        comp.running = False
        comp.time = t + comp.step
        comp.steps += 1
        self._store(comp, comp.time, outputs)
        if getattr(comp.host, "terminate_requested", False) and self.terminated is None:
            self._end_at(comp.time)
            self.terminated = RunTerminated(comp.name, self.seconds(comp.time))

    def _end_at(self, tick: int) -> None:
        """End the run at ``tick``: each component makes the steps that end by then, none beyond."""
        self.end = tick
        if self.schedule is not None:
            self.schedule.forget()  # decisions near the end are not remembered
        for c in self.ordered:
            c.end = max(c.time, (tick // c.step) * c.step)

    def run(self, clock, progress: Callable[[int], None] | None = None) -> None:
        """Step until every component has reached the end; ``progress(tick)`` now and then."""
        comps = self.ordered
        schedule = self.schedule = Schedule(comps, self.end, self.seconds)
        events = 0
        asynchronous = [c for c in comps if c.asynchronous]
        loop = None
        if self.use_compiled_loop:
            loop = self.compiled_loop = CompiledLoop.for_algorithm(self)
        members = loop.members if loop is not None else {}
        stretched = False
        for observer in self.observers:
            observer.started(self)
        while True:
            if self.stop_reason:
                raise RunInterrupted(self.stop_reason)
            if asynchronous and (stretched or not events & _POLL_EVERY_MASK):
                stretched = False
                # A worker's step is collected once it is done, not at the tick that needs it: a
                # 30 Hz result then reaches the histories (copies, recording) between haptic
                # ticks instead of inside the one that also takes in the new frame.
                for comp in asynchronous:
                    if comp.running and comp.host.step_done():
                        self.finish_step(comp, clock)
            decision = schedule.next()
            if decision is None:
                break
            start, index = decision
            comp = comps[index]
            if start and index in members:
                made = loop.run_stretch(clock)
                if made:
                    events += made
                    stretched = True
                    if progress is not None:
                        progress(self.reached)
                    continue
            self._carry_out(comp, start, clock)
            events += 1
            if progress is not None and not events & 63:
                progress(self.reached)
        if progress is not None:
            progress(self.reached)
        if self.terminated is not None:
            raise self.terminated

    def advance(self, tick: int, clock: Callable[[], float] = time.perf_counter) -> None:
        """Step each component to the last point of its grid at or before ``tick`` (at most the run's
        end): for a master that embeds this one and advances it call by call (the scene exported as
        one FMU). The same steps with the same values as :meth:`run`, whose values depend on ticks only;
        a step starts once its inputs exist, as there, and no step ends beyond ``tick``. In Python
        (the compiled loop plans stretches up to a fixed end)."""
        if self.schedule is None:
            self.schedule = Schedule(self.ordered, self.end, self.seconds)
            self.schedule.forget()  # the ends move with every call: no decision is remembered
            for observer in self.observers:
                observer.started(self)
        tick = min(int(tick), self.end)
        comps = self.ordered
        for comp in comps:
            comp.end = max(comp.time, (tick // comp.step) * comp.step)
        schedule = self.schedule
        while True:
            if self.stop_reason:
                raise RunInterrupted(self.stop_reason)
            decision = schedule.next()
            if decision is None:
                break
            start, index = decision
            self._carry_out(comps[index], start, clock)
        if self.terminated is not None:
            raise self.terminated

    def _carry_out(self, comp: Component, start: bool, clock) -> None:
        """A decision of the schedule: start ``comp``'s step (and finish it, unless it runs in a worker)
        or collect its step in flight."""
        if start:
            self.start_step(comp, clock)
            if not comp.asynchronous:
                self.finish_step(comp, clock)
        else:
            self.finish_step(comp, clock)

    # -- the end ---------------------------------------------------------------------------------
    def keep_outputs(self) -> dict[str, dict[str, np.ndarray]]:
        """Copies of every component's latest outputs (hosts' buffers go away at teardown)."""
        return {c.name: {port: np.array(value, copy=True) for port, value in c.outputs.items()} for c in self.ordered}

    def teardown(self) -> list[tuple[str, int, str]]:
        """Terminate every host (never raises); return their log messages as (component, status, text)."""
        messages = []
        for comp in self.ordered:
            host = comp.host
            if host is None:
                continue
            try:
                host.terminate()
            except Exception as exc:  # terminate never raises by contract; belt and braces
                logger.warning("%s: terminate failed: %s", comp.name, exc)
            for status, text in getattr(host, "messages", []):
                messages.append((comp.name, status, text))
        return messages


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


def initialization_order(scene: Scene, names: list[str]) -> list[str]:
    """Producers before consumers; a loop is entered where only jacobi connections lead in."""
    remaining = list(names)
    edges = [(c.source, c.target, c.ordering) for c in scene.connections if c.source in names and c.target in names]
    order: list[str] = []
    while remaining:
        def blocked(n, kinds):
            return any(t == n and s in remaining and k in kinds for s, t, k in edges)
        free = [n for n in remaining if not blocked(n, ORDERINGS)]
        if not free:
            free = [n for n in remaining if not blocked(n, (Ordering.GAUSS_SEIDEL,))] or remaining
        order.append(free[0])
        remaining.remove(free[0])
    return order

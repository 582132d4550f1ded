"""The compiled loop: stretches of in-process steps planned here and run in C (``compiled_loop.c``).

Between two events that need the master itself (a worker's step starting or being collected, a
component it cannot compile), a run is a stretch of steps of in-process FMUs: in the default
scene, the catheter and the contact at 1 kHz for the 33 or 34 ticks between two frames of the
30 Hz tissue in its worker; with every FMU in process, all three for up to ``MAX_STEPS`` steps,
ending where they began in the hyperperiod (so that the next stretch runs the same program).
Python's cost per step (routing values, reading outputs, filling histories) is about twice the
models' own. Here each stretch is planned by the algorithm's own scheduler
(:meth:`~orchestration.plan.schedule.Schedule.decide_at`) and routing rules, and written as a flat program of FMI
calls and copies that C runs in one go:

* the steps, in the order the scheduler makes them, each ``fmi3Set*`` of an input connection
  that the Python path would make (the same transition, key and bitwise comparison with the last
  value set), ``fmi3DoStep``, the observed outputs' ``fmi3Get*``;
* the samples other components read (copied to a tape), window sums of ``average`` transitions
  added as the samples arrive (and divided by their number when a member reads the mean), the
  ports the observers read (copied to the tape).

Afterwards the master replays the stretch in Python (histories, observers, step counts) from the
tape, so that everything downstream (recording, statistics, the next step's inputs) sees exactly
what the Python path gives: the results are bit-identical (tested). The program stops at a call
that fails, logs an error, or whose fmi3DoStep raises a flag; the master replays the steps before
it and carries on from there in Python, reporting the failure as the Python path reports it.

A component takes part when it runs in this process through the FMI binding, nobody times its
steps but the real-time pacing (``run --realtime``: the program waits for each paced step's time
on the wall clock and measures how late it ends, as the pacing does in Python), its connected and
observed ports are numbers (every numeric type and Boolean; the casts to and from float64 are
checked as the binding checks them), and the connections between two such components use
``hold`` or ``average``. The rest of the scene steps in Python between the stretches. Without a C
compiler the whole run stays in Python (logged once).
"""
from __future__ import annotations

import array
import ctypes
import logging
import re
import time
from bisect import bisect_right
from ctypes import c_bool, c_double, c_int64, c_void_p
from pathlib import Path

import numpy as np

from fmu_build.compiler import shared_library
from fmu_build.errors import BuildError
from fmu_build.paths import BUILD_DIR
from orchestration.plan import transitions as tr
from orchestration.errors import FmuCallError
from orchestration.hosts.fmi3 import Fmi3Instance
from orchestration.observers.pacing import SPIN_S

logger = logging.getLogger(__name__)

#: Most steps in one stretch (the program's size; a stretch ends earlier at any event of its own).
#: Longer stretches replay less often but take longer to plan and to make a program of; 512 is
#: where the master's own Python per run is least for the default scene with every FMU in process
#: (docs/performance.md)
MAX_STEPS = 512
#: Stretches planned from the same schedule state are remembered (up to this many states) ...
PLAN_CACHE_LIMIT = 10_000
#: ... and their programs up to this many operations in all (32 bytes each): a rate mix with many
#: schedule states has its later programs made afresh for each stretch instead of kept
PROGRAM_CACHE_OPS = 1 << 20
#: Tape ranges closer than this many values are copied as one
_GAP = 16
#: Bytes of one component's tape (its outputs in a stretch, a row per step): a stretch holds at most
#: as many of its steps as fit (at least 16), so that a component with large outputs stays small
_TAPE_BYTES = 8 << 20
_FLOAT64 = np.dtype(np.float64)

#: an OP_SET of a value that is no producer's sample (a source's, an interpolation)
NO_KEY = -2 ** 63


class _Component(ctypes.Structure):
    _fields_ = [("instance", c_void_p), ("do_step", c_void_p), ("logged_errors", c_void_p),
                ("errors_seen", c_int64), ("step", c_int64), ("busy_ns", c_int64), ("started_ns", c_int64),
                ("flags", c_bool * 4), ("last_time", c_double), ("cost_bins", c_void_p), ("budget_ns", c_int64),
                ("cost_count", c_int64), ("cost_max_ns", c_int64), ("cost_over", c_int64)]


class _Port(ctypes.Structure):
    _fields_ = [("component", c_int64), ("function", c_void_p), ("vrs", c_void_p), ("n_vrs", c_int64),
                ("slot", c_void_p), ("native", c_void_p), ("size", c_int64), ("cast", c_int64),
                ("last", c_void_p), ("last_valid", c_int64), ("last_key", c_int64), ("has_key", c_int64),
                ("sets", c_int64)]


class _Window(ctypes.Structure):
    _fields_ = [("sum", c_void_p), ("opened", c_int64), ("count", c_int64), ("size", c_int64)]


class _Pacing(ctypes.Structure):
    _fields_ = [("origin", c_double), ("started", c_int64), ("pace", c_int64), ("sleep", c_int64), ("spin", c_double),
                ("lateness", c_void_p)]


class _Result(ctypes.Structure):
    _fields_ = [("ops_done", c_int64), ("reason", c_int64), ("status", c_int64)]


#: The C half, compiled by the system C compiler once per version of the source.
SOURCE = Path(__file__).resolve().with_name("compiled_loop.c")


def c_constants(source: str) -> dict[str, int]:
    """The integer constants of C source text: the members of its enums (counted as C counts them)
    and its ``#define NAME <integer>`` lines, by name."""
    constants = {}
    for match in re.finditer(r"^[ \t]*#[ \t]*define[ \t]+(\w+)[ \t]+(-?\d+)[ \t]*$", source, re.MULTILINE):
        constants[match[1]] = int(match[2])
    for body in re.findall(r"\benum\s*\w*\s*\{([^}]*)\}", source):
        value = -1
        for item in body.split(","):
            name, _, given = (part.strip() for part in item.partition("="))
            if name:
                value = int(given, 0) if given else value + 1
                constants[name] = value
    return constants


# The program's operations, the reasons a program stops and the casts, as compiled_loop.c numbers
# them (read from the source that is compiled, so the two cannot drift apart).
_C = c_constants(SOURCE.read_text())
OP_NOP, OP_BEGIN, OP_SET, OP_STEP, OP_GET, OP_END, OP_COPY, OP_WINDOW, OP_PACE, OP_LATE, OP_MEAN = (
    _C[name] for name in ("OP_NOP", "OP_BEGIN", "OP_SET", "OP_STEP", "OP_GET", "OP_END", "OP_COPY", "OP_WINDOW",
                          "OP_PACE", "OP_LATE", "OP_MEAN"))
DONE, CALL_FAILED, ERROR_LOGGED, STEP_FLAGS, BAD_OP, NOT_EXACT = (
    _C[name] for name in ("DONE", "CALL_FAILED", "ERROR_LOGGED", "STEP_FLAGS", "BAD_OP", "NOT_EXACT"))
#: numpy dtype of a port's native buffer -> compiled_loop.c's CAST_*
_CASTS = {np.dtype(dtype): _C[name] for dtype, name in (
    (np.float64, "CAST_NONE"), (np.bool_, "CAST_BOOL"), (np.int8, "CAST_INT8"), (np.uint8, "CAST_UINT8"),
    (np.int16, "CAST_INT16"), (np.uint16, "CAST_UINT16"), (np.int32, "CAST_INT32"), (np.uint32, "CAST_UINT32"),
    (np.float32, "CAST_FLOAT32"), (np.int64, "CAST_INT64"), (np.uint64, "CAST_UINT64"))}


def compiled_loop_library(build_dir: Path = BUILD_DIR) -> Path:
    """Compile (once per source version) the compiled loop's C half; return the library's path."""
    return shared_library("compiled_loop", "the master's compiled loop", [SOURCE], lambda output: [
        # -O3 vectorises the window sums (elementwise, so the same sums as at -O2)
        "-std=gnu11", "-O3", "-g", "-Wall", "-Wextra", "-fPIC", "-shared", str(SOURCE), "-o", str(output)], build_dir)


_library_state: dict = {}


def load_program_runner():
    """``run_program`` of the compiled library (built on first use), or None when it cannot be built;
    its ``clock`` (``pacing_clock``) as an attribute."""
    if "run" not in _library_state:
        try:
            library = ctypes.CDLL(str(compiled_loop_library()))
        except (BuildError, OSError) as exc:
            logger.warning("the master's compiled loop is not available, every step runs in Python: %s", exc)
            _library_state["run"] = None
        else:
            run = library.run_program
            run.restype = _Result
            run.argtypes = [c_void_p, c_int64, c_int64, c_int64, c_void_p, c_void_p, c_void_p, c_void_p]
            clock = library.pacing_clock
            clock.restype, clock.argtypes = c_double, []
            run.clock = clock
            _library_state["run"] = run
    return _library_state["run"]


def _address(thing) -> int:
    """The address of a ctypes function or of a numpy array's data."""
    if isinstance(thing, np.ndarray):
        return thing.__array_interface__["data"][0]
    return ctypes.cast(thing, c_void_p).value


class _Member:
    """What the loop knows of one component that takes part: its C records and its tape."""

    def __init__(self, comp, instance: Fmi3Instance):
        self.comp = comp
        self.instance = instance
        self.routes: list = []          # its input connections (not parameters), in the scene's order
        self.port_index: dict = {}      # route -> its input port's record index
        self.last_values: dict = {}     # route -> the float64 buffer of the last value set
        self.written: dict = {}         # route -> the last value the loop handed back (its buffer holds it)
        self.step_ops: tuple = ()       # the ops after its fmi3DoStep: read the outputs, stop the clock
        self.tape_offsets: dict[str, int] = {}
        self.listener_ports: list[tuple[str, int, int]] = []
        self.copies: list[tuple[int, int, int]] = []        # (offset in a tape row, output address, size)
        self.windows: list = []         # (output address, size, WindowSums) of its average transitions
        self.listeners: list = []       # its observers' stepped, the pacing's aside
        self.paced = False              # its steps are paced in real time
        self.consumer_of: dict = {}     # id of one of its histories -> the component that reads it
        self.tape = np.empty((0, 0))    # its outputs in a stretch, one row per step
        self.tape_address = 0
        self.capacity = 0               # the tape's rows: its most steps in one stretch


class _Template:
    """The program of one stretch from one schedule state, ticks counted from the stretch's start.

    Each stretch writes its values where the program reads them: the sources' values into staging
    rows, the samples read from histories that do not change in the stretch into ``ops`` in place
    (``patches``), the windows' sums into a table.
    """

    def __init__(self):
        self.ops = array.array("q")
        #: (rank, tick, row, index of its last op + 1, its window slots, its lateness slot or -1)
        self.steps: list[tuple] = []
        self.sources: list[tuple] = []    # (source, its ticks, [(port, staging rows)]): continuous sources' values
        #: values read from histories that stay, per route: (route, its ops' indices (an array and a
        #: list), their taus, the value's size)
        self.patches: list[tuple] = []
        self.windows: list[tuple] = []    # (WindowSums, end tick, size) per window slot
        self.means: list[np.ndarray] = []  # where the windows' means read in the stretch are made
        self.constants: list[tuple] = []  # (op index, route) of the one set of a constant source's value
        #: rank -> its steps' end ticks, its first and last tape rows, for each of its windows the slots
        #: its steps added to: what the replay of a whole stretch needs
        self.replay: dict[int, tuple] = {}
        self.codes = np.empty(0, dtype=np.int64)  # the ops' codes: a view of ``ops``
        self.first_paced: int | None = None  # tick of the first paced step
        self.lateness = np.empty(0)        # how late each paced step ended (slots in step order)


class _Building:
    """What the making of one template keeps track of, step by step."""

    def __init__(self, steps: list[tuple[int, int]]):
        self.rows: dict[int, int] = {}
        #: each member's samples in this stretch so far: their ticks (increasing) and tape row addresses
        self.produced: dict[int, tuple[list[int], list[int]]] = {rank: ([], []) for rank, _ in steps}
        self.counts: dict[int, int] = {}
        for rank, _ in steps:
            self.counts[rank] = self.counts.get(rank, 0) + 1
        self.staging: dict = {}   # route -> (its staging rows, [(row, tau)])
        self.patches: dict = {}   # route -> ([op index], [tau], size) of the values read from histories that stay
        self.windows: dict = {}   # (WindowSums, end tick, size) -> slot
        self.added: dict[int, int] = {}  # window slot -> the samples added to it so far in the program
        self.means: dict = {}     # route -> the array its window's mean is made in
        self.late_slots = 0


class CompiledLoop:
    """Runs the stretches of in-process steps of one :class:`MultirateAlgorithm` run in C."""

    def __init__(self, algorithm, run_program):
        self.algorithm = algorithm
        self._run_program = run_program
        comps = algorithm.ordered
        pacers = {id(hook.__self__): hook.__self__ for c in comps for hook in c.pre_step if hook.__self__.paces}
        #: the real-time pacing, which the program does for the steps it paces (one at most)
        self.pacer = next(iter(pacers.values())) if len(pacers) == 1 else None
        self._pacing = _Pacing(0.0, 0, 0, 0, SPIN_S, None)
        self._records = (_Component * len(comps))()
        self._ports: list[_Port] = []
        self._port_objects: list = []   # the binding's records, for error messages (call names)
        self.members: dict[int, _Member] = {}
        for comp in comps:
            if self._can_take_part(comp) and len(pacers) <= 1:
                self.members[comp.rank] = self._member(comp)
        # a connection between two members must be a hold (the value a consumer reads is a sample) or
        # an average (the mean of a window the program sums), between ports of one size (the scene
        # checks it; the program copies the consumer's size)
        changed = True
        while changed:
            changed = False
            for rank, member in list(self.members.items()):
                if any(r.producer is not None and r.producer.rank in self.members and (
                        r.transition.compiled is None or member.last_values[r].size !=
                        self.members[r.producer.rank].instance.output_views[r.spec.source_port].size)
                       for r in member.routes):
                    del self.members[rank]
                    changed = True
        self._port_array = (_Port * max(1, len(self._ports)))(*self._ports)
        self._plans: dict = {}
        self._templates: dict = {}  # (start in the hyperperiod, steps) -> their program, kept
        self._cached_ops = 0
        self.stretches = 0
        self.steps = 0

    @classmethod
    def for_algorithm(cls, algorithm) -> "CompiledLoop | None":
        """The loop for ``algorithm`` once it is initialized, or None when no component can take part."""
        if algorithm.end >= 2 ** 53 or not any(cls._can_take_part(c) for c in algorithm.ordered):
            return None  # (ticks beyond 2**53 would not convert to seconds as Python converts them)
        run = load_program_runner()
        if run is None:
            return None
        loop = cls(algorithm, run)
        return loop if loop.members else None

    # -- who takes part ------------------------------------------------------------------------------
    @staticmethod
    def _can_take_part(comp) -> bool:
        instance = getattr(comp.host, "instance", None)
        if comp.asynchronous or not isinstance(instance, Fmi3Instance) or instance.freed or instance.fatal:
            return False
        if "fmi3DoStep" not in instance.library.functions:
            return False  # the Python path reports it
        if not all(hook.__self__.paces for hook in comp.pre_step):
            return False  # someone times each step: only the real-time pacing is done in the program
        for listener in comp.listeners:
            observer = listener.__self__
            if not observer.paces and not observer.names_its_ports:
                return False  # an observer that may read ports it does not name
        for histories in comp.histories.values():
            if any(type(h) not in (tr.SampleHistory, tr.WindowSums) for h in histories):
                return False
        if any(g.native.dtype not in _CASTS for g in instance.output_groups):
            return False
        ports = instance.input_ports
        for route in comp.routes:
            if route.parameter:
                continue
            port = ports.get(route.port)
            if port is None or (port.cast and port.native.dtype not in _CASTS):
                return False
        return True

    def _member(self, comp) -> _Member:
        instance = comp.host.instance
        member = _Member(comp, instance)
        record = self._records[comp.rank]
        record.instance = instance.live_handle
        record.do_step = _address(instance.library.functions["fmi3DoStep"])
        record.logged_errors = _address(instance.logged_errors)
        record.step = comp.step
        record.cost_bins = comp.costs.bins.ctypes.data  # counted in place (the array lives as long as comp)
        record.budget_ns = comp.costs.budget_ns
        for route in comp.routes:
            if route.parameter:
                continue
            port = instance.input_ports[route.port]
            last = np.zeros(port.size)
            member.routes.append(route)
            member.port_index[route] = len(self._ports)
            member.last_values[route] = last
            self._ports.append(_Port(comp.rank, _address(port.setter), ctypes.addressof(port.vr), 1,
                                     _address(port.slot), _address(port.native), port.size,
                                     _CASTS[port.native.dtype], _address(last), 0, 0, 0, 0))
            self._port_objects.append(port)
        step_ops = []
        for group in instance.output_groups:
            step_ops += (OP_GET, len(self._ports), 0, 0)
            self._ports.append(_Port(comp.rank, _address(group.getter), ctypes.addressof(group.vrs), group.count,
                                     _address(group.slot), _address(group.native), group.size,
                                     _CASTS[group.native.dtype], None, 0, 0, 0, 0))
            self._port_objects.append(group)
        member.step_ops = tuple(step_ops) + (OP_END, comp.rank, 0, 0)
        # The tape: the observed output buffer's ranges that hold what histories keep and observers read.
        member.listeners = [listener for listener in comp.listeners if not listener.__self__.paces]
        member.paced = self.pacer is not None and self.pacer.paced(comp)
        wanted: list[str] = []
        for listener in member.listeners:
            for name in listener.__self__.ports(comp.name):
                if name not in wanted:
                    wanted.append(name)
        listened = set(wanted)
        for name, histories in comp.histories.items():
            if any(h.keeps_values for h in histories) and name not in wanted:
                wanted.append(name)
        views = instance.output_views
        buffer_start = min((_address(v) for v in views.values()), default=0)
        spans = sorted(((_address(views[n]) - buffer_start) // 8, views[n].size, n) for n in wanted)
        ranges: list[list[int]] = []  # [buffer offset, size] of each copied range
        for start, size, name in spans:
            if ranges and start <= ranges[-1][0] + ranges[-1][1] + _GAP:
                ranges[-1][1] = max(ranges[-1][1], start + size - ranges[-1][0])
            else:
                ranges.append([start, size])
        width = 0
        for start, size in ranges:
            member.copies.append((width, buffer_start + 8 * start, size))
            for name_start, name_size, name in spans:
                if start <= name_start < start + size:
                    member.tape_offsets[name] = width + name_start - start
            width += size
        member.listener_ports = [(name, member.tape_offsets[name], views[name].size) for name in wanted
                                 if name in listened]
        member.consumer_of = {id(route.history): consumer for consumer, route in comp.consumers}
        member.windows = [(_address(views[name]), views[name].size, history)
                          for name, histories in comp.histories.items() for history in histories
                          if not history.keeps_values]
        member.capacity = min(MAX_STEPS, max(16, _TAPE_BYTES // (8 * max(1, width))))
        member.tape = np.empty((member.capacity, width))
        member.tape_address = _address(member.tape)
        return member

    # -- planning ------------------------------------------------------------------------------------
    def _plan(self) -> list:
        """``[steps, span, template, remembered]``: the steps ``(rank, tick)`` the scheduler makes next
        while they are members' steps (in a paced run, up to the next paced tick), ticks counted from
        the slowest component's; how far they reach; their program once made and kept; whether the
        plan is remembered for its schedule state (not near the end of the run)."""
        algorithm = self.algorithm
        schedule = algorithm.schedule
        comps = algorithm.ordered
        times = [c.time for c in comps]
        running = [c.running for c in comps]
        t_min = min(times)
        key = None
        if t_min < schedule.memo_until:
            key = (t_min % schedule.period, *[t - t_min for t in times], *running)
            cached = self._plans.get(key)
            if cached is not None and t_min + cached[1] <= schedule.memo_until:
                return cached
        members = self.members
        steps: list[tuple[int, int]] = []
        counts = dict.fromkeys(members, 0)
        period = schedule.period
        paced_tick = None
        aligned = None  # (steps, times) where every component last stood at one multiple of the period
        while True:
            if times[0] % period == 0 and times.count(times[0]) == len(times) and not any(running) and steps:
                aligned = (len(steps), list(times))
            full = len(steps) == MAX_STEPS
            if not full:
                decision = schedule.decide_at(times, running)
                if decision is None or not decision[0] or decision[1] not in members:
                    break
                rank = decision[1]
                full = counts[rank] == members[rank].capacity
            if full:
                # a full stretch ends where it started in the hyperperiod, so that the next is its twin
                # (the same plan and program) rather than a new program for every stretch
                if aligned is not None:
                    del steps[aligned[0]:]
                    times = aligned[1]
                break
            if members[rank].paced:
                # A paced run waits for every tick: a stretch of one tick leaves the master's own work
                # (a worker's step collected, the replay) to the wait before the next, where stretches
                # of 33 ticks lumped it before their first (140 of 8000 deadlines missed, against 0)
                if paced_tick is None:
                    paced_tick = times[rank]
                elif times[rank] != paced_tick:
                    break
            counts[rank] += 1
            steps.append((rank, times[rank] - t_min))
            times[rank] += comps[rank].step
        remembered = key is not None and len(self._plans) < PLAN_CACHE_LIMIT
        plan = [steps, max(times) - t_min, None, remembered]
        if remembered:
            self._plans[key] = plan
        return plan

    def _template(self, steps: list[tuple[int, int]], t0: int) -> _Template:
        """The program of a stretch of ``steps`` (ticks from the stretch's start ``t0``): what is known
        before its values are (see :meth:`_fill`). It serves every stretch of the same steps that
        starts at the same place in the hyperperiod (which each window divides)."""
        comps = self.algorithm.ordered
        members = self.members
        template = _Template()
        ops = template.ops
        building = _Building(steps)
        for rank, tick in steps:
            member = members[rank]
            if member.paced:
                ops.extend((OP_PACE, tick, 0, 0))
                if template.first_paced is None:
                    template.first_paced = tick
            ops.extend((OP_BEGIN, rank, 0, 0))
            for route in member.routes:
                self._input_ops(template, building, member, route, rank, tick + route.need_offset)
            ops.extend((OP_STEP, rank, tick, 0))
            ops.extend(member.step_ops)
            self._output_ops(template, building, member, rank, tick, tick + comps[rank].step, t0)
        self._finish_template(template, building)
        return template

    def _input_ops(self, template: _Template, building: _Building, member: _Member, route, rank: int,
                   tau: int) -> None:
        """The operations that set one input of a member's step that reads at ``tau``."""
        ops = template.ops
        staging = building.staging
        index = member.port_index[route]
        size = member.last_values[route].size
        if route.source is not None and route.source.constant:
            # the Python path sets a constant source's value once in a run: here its first time
            if route not in staging:
                staging[route] = (np.empty((1, size)), [(0, tau)])
                template.constants.append((len(ops) // 4, route))
                ops.extend((OP_SET, index, _address(staging[route][0]), NO_KEY))
            return
        if route.source is not None:  # its value at tau, written into a row of its staging array
            if route not in staging:
                staging[route] = (np.empty((building.counts[rank], size)), [])
            values, items = staging[route]
            ops.extend((OP_SET, index, _address(values) + 8 * size * len(items), NO_KEY))
            items.append((len(items), tau))
            return
        producer = route.producer.rank
        averaged = route.transition.compiled is tr.Compiled.WINDOW_MEAN
        slot = building.windows.get((route.history, tau, size)) if averaged else None
        if slot is not None:  # an average over a window the stretch adds to: its mean, made when read
            if route not in building.means:
                building.means[route] = np.empty(size)
            mean = building.means[route]
            ops.extend((OP_MEAN, slot, _address(mean), building.added[slot]))
            ops.extend((OP_SET, index, _address(mean), NO_KEY))
            return
        if producer in building.produced and route.transition.compiled is tr.Compiled.LATEST:
            # a hold of a sample made in this stretch, if there is one by tau
            sample_ticks, addresses = building.produced[producer]
            latest = bisect_right(sample_ticks, tau) - 1
            if latest >= 0:
                offset = self.members[producer].tape_offsets[route.spec.source_port]
                ops.extend((OP_SET, index, addresses[latest] + 8 * offset, sample_ticks[latest]))
                return
        # a sample from before the stretch (its producer's history does not change in it)
        patch = building.patches.setdefault(route, ([], [], size))
        patch[0].append(len(ops) // 4)
        patch[1].append(tau)
        ops.extend((OP_NOP, index, 0, 0))

    @staticmethod
    def _output_ops(template: _Template, building: _Building, member: _Member, rank: int, tick: int,
                    sample_tick: int, t0: int) -> None:
        """The operations after a member's step from ``tick``: its outputs to the tape, its samples
        added to the windows they fall in, its lateness when paced."""
        ops = template.ops
        row = building.rows.get(rank, 0)
        building.rows[rank] = row + 1
        row_address = member.tape_address + 8 * member.tape.shape[1] * row
        for offset, address, size in member.copies:
            ops.extend((OP_COPY, row_address + 8 * offset, address, size))
        building.produced[rank][0].append(sample_tick)
        building.produced[rank][1].append(row_address)
        slots = []
        windows = building.windows
        for address, size, history in member.windows:
            end = -(-(t0 + sample_tick) // history.window) * history.window - t0  # from the stretch's start
            slot = windows.setdefault((history, end, size), len(windows))
            building.added[slot] = building.added.get(slot, 0) + 1
            ops.extend((OP_WINDOW, slot, address, size))
            slots.append(slot)
        late = -1
        if member.paced:
            late, building.late_slots = building.late_slots, building.late_slots + 1
            ops.extend((OP_LATE, late, sample_tick, 0))
        template.steps.append((rank, tick, row, len(ops) // 4, slots, late))

    def _finish_template(self, template: _Template, building: _Building) -> None:
        """What the fill and the replay of a template's stretches need, once its operations are known."""
        template.lateness = np.empty(building.late_slots)
        template.patches = [(route, np.array(indices, dtype=np.int64), indices, taus, size)
                            for route, (indices, taus, size) in building.patches.items()]
        template.codes = np.frombuffer(template.ops, dtype=np.int64)[::4]  # (ops keeps its size from here on)
        template.replay = self._replay_data(template.steps)
        groups: dict = {}  # the routes of one source read at the same ticks: evaluated once
        for route, (values, items) in building.staging.items():
            ticks = tuple(tau for _, tau in items)
            group = groups.setdefault((id(route.source), ticks), (route.source, np.array(ticks, dtype=np.int64), []))
            group[2].append((route.spec.source_port, values))
        template.sources = list(groups.values())
        template.windows = list(building.windows)
        template.means = list(building.means.values())

    # -- one stretch ---------------------------------------------------------------------------------
    def run_stretch(self, clock) -> int:
        """Make the steps of the stretch that starts at the scheduler's next decision; returns how
        many were made (0: the stretch is too short, the caller steps as before)."""
        plan = self._plan()
        steps, _, template, remembered = plan
        if len(steps) < 2:
            return 0
        t0 = min(c.time for c in self.algorithm.ordered)
        if template is None:
            # the same steps from the same place in the hyperperiod make the same program, whatever
            # the schedule state (near the end of a run, where states are not remembered, most are)
            key = (t0 % self.algorithm.schedule.period, tuple(steps))
            template = self._templates.get(key)
            if template is None:
                template = self._template(steps, t0)
                size = len(template.ops) // 4
                if self._cached_ops + size <= PROGRAM_CACHE_OPS:
                    self._templates[key] = template
                    self._cached_ops += size
            if remembered and key in self._templates:
                plan[2] = template
        fill = self._fill(template, t0)
        if fill is None:
            return 0
        return self._execute(template, t0, fill, clock)

    def _fill(self, template: _Template, t0: int):
        """Write this stretch's values into its template: the sources' values at their ticks, the
        samples read from histories that stay, the windows' sums. None: the Python path steps."""
        base = self.algorithm.base
        for source, ticks, targets in template.sources:
            # int64 / int: correctly rounded below 2**53, the times algorithm.seconds gives
            values = source.evaluate_many((ticks + t0) / base)
            for port, rows in targets:
                value = values[port]
                if value.dtype != _FLOAT64 or value.shape != (len(ticks), rows.shape[1]):
                    return None  # compared as its own type by the Python path
                rows[:len(ticks)] = value
        ops = template.ops
        for op, route in template.constants:  # set once in a run, then never again
            ops[4 * op] = OP_SET if route.last_value is None else OP_NOP
        keep = []
        codes = template.codes
        for route, indices, index_list, taus, size in template.patches:
            history = route.history
            if not history.ticks:
                codes[indices] = OP_NOP  # the Python path finds no sample and sets nothing
                continue
            if route.last_value is not None and route.last_value.dtype != _FLOAT64:
                return None  # compared as its own type by the Python path
            for i, tau in enumerate(taus):
                try:
                    value, key = route.transition.value(t0 + tau)
                except (LookupError, ValueError):
                    return None  # the Python path reports it
                if value.dtype != _FLOAT64 or not value.flags.c_contiguous or value.size != size:
                    return None  # the Python path converts it, or says what is wrong
                keep.append(value)
                k = 4 * index_list[i]
                ops[k], ops[k + 2], ops[k + 3] = OP_SET, _address(value), NO_KEY if key is None else key - t0
                if i == 0 and key is not None and not _sample_between(history, t0 + tau, t0 + taus[-1]):
                    # one sample all through the stretch: set once, at most (the Python path finds the same key)
                    codes[indices[1:]] = OP_NOP
                    break
        windows = (_Window * max(1, len(template.windows)))()
        opened = {}
        for slot, (history, end, size) in enumerate(template.windows):
            existing = history.window_sum(t0 + end)
            if existing is None:
                existing = opened[slot] = np.empty(size)
            windows[slot].opened = int(slot not in opened)
            windows[slot].sum = _address(existing)
            windows[slot].count = history.window_count(t0 + end)
            windows[slot].size = size
            keep.append(existing)
        return keep, windows, opened

    def _execute(self, template: _Template, t0: int, fill, clock) -> int:
        keep, windows, opened = fill
        algorithm = self.algorithm
        records = self._records
        members = self.members
        ports = self._port_array
        taking_part = [members[rank] for rank in template.replay]
        for member in taking_part:
            record = records[member.comp.rank]
            record.busy_ns = 0
            record.cost_count = record.cost_max_ns = record.cost_over = 0
            record.errors_seen = int(member.instance.logged_errors[0])
            for route, last in member.last_values.items():
                port = ports[member.port_index[route]]
                value = route.last_value
                port.last_valid = value is not None
                port.sets = 0
                if value is not None and value is not member.written.get(route):  # set from Python since
                    last[:] = value.reshape(-1)
                port.has_key = route.last_key is not None
                port.last_key = route.last_key if route.last_key is not None else 0
        marks = {member.comp.rank: len(member.instance.messages) for member in taking_part}
        pacing = self._pacing
        if template.first_paced is not None:
            pacer = self.pacer
            # the pacing's origin, from its clock (time.perf_counter) to the program's; before the run's
            # first paced step the program sets it there, as the pacing would (other steps may come first)
            to_program = self._run_program.clock() - time.perf_counter()
            pacing.started = pacer.origin is not None
            pacing.origin = pacer.origin + to_program if pacing.started else 0.0
            pacing.pace, pacing.sleep = pacer.pace, pacer.sleeps
            pacing.lateness = _address(template.lateness)
        ops = template.ops
        result = self._run_program(ops.buffer_info()[0], len(ops) // 4, t0, algorithm.base,
                                   ctypes.addressof(records), ctypes.addressof(ports), ctypes.addressof(windows),
                                   ctypes.addressof(pacing))
        if template.first_paced is not None and pacing.started and self.pacer.origin is None:
            self.pacer.origin = pacing.origin - to_program
        stopped_at = result.ops_done
        made = 0
        for step in template.steps:
            if step[3] > stopped_at:
                break
            made += 1
        self._replay(template, t0, made, opened)
        for member in taking_part:  # the binding's, the host's and the routes' view of where each is
            comp = member.comp
            record = records[comp.rank]
            comp.busy += record.busy_ns * 1e-9
            comp.costs.counted(record.cost_count, record.cost_max_ns, record.cost_over)
            for route, last in member.last_values.items():
                port = ports[member.port_index[route]]
                if port.sets:
                    route.last_value = member.written[route] = last.copy()
                    route.last_bytes = route.last_value.tobytes()
                if port.has_key:
                    route.last_key = port.last_key
                history = route.history
                # the Python path's shortcut: nothing arrived since the route took the newest sample
                route.seen = history.count if (history is not None and history.ticks and port.has_key
                                               and route.last_key == history.ticks[-1]) else -1
        self.stretches += 1
        self.steps += made
        if result.reason == DONE:
            return made
        rank, tick = template.steps[made][:2]
        k = 4 * stopped_at
        self._stopped(rank, t0 + tick, tuple(ops[k:k + 4]), result, marks[rank], clock)
        return made + 1

    def _replay_data(self, steps: list[tuple]) -> dict[int, tuple]:
        """Per rank of ``steps`` (a template's, or the first of them): its steps' end ticks from the
        stretch's start, its first and last tape rows, for each of its windows the slots it added to,
        its lateness slots."""
        comps = self.algorithm.ordered
        data = {}
        for rank in dict.fromkeys(step[0] for step in steps):
            own = [step for step in steps if step[0] == rank]
            comp_step = comps[rank].step
            slots = [sorted({step[4][w] for step in own}) for w in range(len(self.members[rank].windows))]
            late = [step[5] for step in own if step[5] >= 0]
            data[rank] = ([step[1] + comp_step for step in own], own[0][2], own[-1][2], slots, late)
        return data

    def _replay(self, template: _Template, t0: int, made: int, opened: dict) -> None:
        """What the Python path does after each of the first ``made`` steps (``_finish``, ``_store``),
        from the tapes: step counts, histories, observers."""
        base = self.algorithm.base
        data = template.replay if made == len(template.steps) else self._replay_data(template.steps[:made])
        blocks = []
        for rank, (ends, first_row, last_row, window_slots, late) in data.items():  # where each is now
            member = self.members[rank]
            comp = member.comp
            blocks.append((member, comp.steps, [t0 + end for end in ends], member.tape[first_row:last_row + 1],
                           window_slots, late))
            comp.time = t0 + ends[-1]
            comp.steps += len(ends)
            member.instance.time = comp.time / base
            comp.host.terminate_requested = comp.host.early_return = False
            comp.host.last_successful_time = member.instance.time
            comp.outputs = member.instance.output_views
        for member, first_step, ticks, rows, window_slots, late in blocks:  # what each made
            comp = member.comp
            if late:
                self.pacer.paced_block(comp, template.lateness[late])
            window_index = 0
            for name, histories in comp.histories.items():
                for history in histories:
                    if history.keeps_values:
                        offset = member.tape_offsets[name]
                        # pruned as it goes: the samples its consumer can no longer ask for are not
                        # kept, nor copied from the tape
                        consumer = member.consumer_of[id(history)]
                        history.extend(ticks, rows[:, offset:offset + comp.outputs[name].size],
                                       consumer.time - 2 * comp.step - consumer.step, copy=True)
                    else:
                        sums = {t0 + template.windows[slot][1]: opened[slot]
                                for slot in window_slots[window_index] if slot in opened}
                        history.extend_summed(ticks, sums)
                        consumer = member.consumer_of[id(history)]
                        history.prune(consumer.time - 2 * comp.step - consumer.step)
                        window_index += 1
            if member.listeners:
                columns = {name: rows[:, offset:offset + size] for name, offset, size in member.listener_ports}
                for listener in member.listeners:
                    listener.__self__.stepped_block(comp, ticks, columns, first_step)

    def _stopped(self, rank: int, tick: int, op, result, mark: int, clock) -> None:
        """The program stopped inside the step of ``rank`` at ``tick``: report or finish it as Python would."""
        algorithm = self.algorithm
        member = self.members[rank]
        comp = member.comp
        instance = member.instance
        t = tick / algorithm.base
        instance.time = t
        code = op[0]
        if result.reason == STEP_FLAGS:  # the step went through; what follows it is the Python path's
            record = self._records[rank]
            terminate, early = bool(record.flags[1]), bool(record.flags[2])
            last = record.last_time if terminate or early else (tick + comp.step) / algorithm.base
            instance.time = last
            host = comp.host
            host.terminate_requested, host.early_return, host.last_successful_time = terminate, early, last
            comp.running = True
            comp.started_at = clock()
            algorithm.finish_step(comp, clock)
            return
        if result.reason == BAD_OP:
            raise RuntimeError(f"the compiled loop met an unknown operation {code} (a bug)")
        if result.reason == NOT_EXACT and code == OP_GET:  # a 64-bit integer beyond 2**53: the binding names it
            instance.time = (tick + comp.step) / algorithm.base
            instance.refuse_wide(self._port_objects[op[1]])
        if result.reason == NOT_EXACT:  # the binding's own check says what and raises, as in the Python path
            try:
                instance.push_port(self._port_objects[op[1]])
            except ValueError as exc:
                raise FmuCallError(comp.name, "fmi3DoStep", t, f"{type(exc).__name__}: {exc}") from exc
            raise RuntimeError("the compiled loop and the binding disagree on an input's cast (a bug)")
        if code == OP_GET:
            instance.time = (tick + comp.step) / algorithm.base  # the step itself went through
        if code == OP_STEP:
            instance.step_problem(t, int(result.status), mark)
            raise FmuCallError(comp.name, "fmi3DoStep", t, instance.logged_reason(mark), int(result.status))
        call = self._port_objects[op[1]].call
        instance.check_status(call, int(result.status), mark)
        raise FmuCallError(comp.name, call, instance.time, instance.logged_reason(mark), int(result.status))


def _sample_between(history, after: int, until: int) -> bool:
    """Whether ``history`` holds a sample with tick in ``(after, until]``."""
    for tick in reversed(history.ticks):
        if tick <= after:
            return False
        if tick <= until:
            return True
    return False

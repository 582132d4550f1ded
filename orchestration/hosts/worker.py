"""Hosting an FMU in its own process, so that a crashing FMU cannot take the master down.

The worker (a "spawn" child) runs an :class:`~orchestration.hosts.in_process.InProcessFmu`. Commands and
replies are tiny tuples over a ``multiprocessing.Pipe`` (the protocol: :class:`Command` and
:class:`Reply`, below); every value array moves through one ``SharedMemory`` block allocated by
``configure``: ``[inputs | observed outputs]`` as float64 slots laid out by
:func:`~orchestration.hosts.buffers.slot_layout`. A step is: the master writes the inputs into their
slots and sends ``(STEP, t, h, which)``; the worker pushes those slots into the FMU, steps, reads
the observed outputs into their slots and replies with fmi3DoStep's flags. No array is pickled.

Each reply carries the FMU's log messages since the previous one; they land in ``messages`` and
the ``orchestration.fmu.<name>`` logger of the master. While waiting, the master watches the
worker's process sentinel as well as the pipe, so a worker that dies (segfault, abort, kill)
raises :class:`~orchestration.errors.WorkerCrash` instead of hanging or killing the master.

A worker that is alive but does not answer (stopped with SIGSTOP, deadlocked, swapping) is not
waited for forever: every reply has a deadline. During the run it is the scene's
``[scene] worker_timeout`` if set, else ``max(10 s, 100 x the slowest of the recent replies)``;
the first calls (start, instantiation, initialization: loading and compiling) get a separate,
generous allowance. A missed deadline kills the worker and raises a WorkerCrash naming the call,
the simulated time and the wait, so the run ends "failed".

The worker ignores SIGINT from its first instruction on (the terminal sends Ctrl-C to the whole
process group; the master decides how the run stops and shuts the worker down). SIGTERM keeps its
default: it is how multiprocessing ends a daemon worker left over at exit; sent to the whole
group (a service manager), it reaches the master first, which reports the run "interrupted".
"""
from __future__ import annotations

import dataclasses
import errno
import logging
import multiprocessing
import os
import select
import signal
import sys
import time
from multiprocessing.shared_memory import SharedMemory

import numpy as np

from orchestration.errors import LOG_LEVELS, FmuCallError, OrchestrationError, WorkerCrash, exit_description
from orchestration.hosts.buffers import slot_layout
from orchestration.hosts.in_process import InProcessFmu, PortConfigurationError, check_port_lists
from orchestration.hosts.native_threads import limit_native_threads
from orchestration.hosts.description import FmuDescription, PortInfo
from orchestration.stopping import STOP_SIGNALS, RecentSlowest, start_shielded

logger = logging.getLogger(__name__)

#: While waiting for a reply, how often the master checks that the worker is still alive (ms).
_LIVENESS_INTERVAL_MS = 500
#: How long terminate() waits for the worker to shut down cleanly before killing it (s).
_SHUTDOWN_TIMEOUT = 10.0
#: The allowance for the first calls (instantiation, initialization), which may load a model
#: and compile its kernels (about a minute here with an empty numba cache).
SETUP_TIMEOUT = 600.0
#: The call named in errors until the worker holds the FMU's description.
START_CALL = "start worker"


class Command:
    """Master -> worker messages: ``(kind, *arguments)``; each is answered by one reply.

    ========================  ==========================================  =================================
    kind                      arguments                                   reply payload
    ========================  ==========================================  =================================
    INSTANTIATE               -                                           None
    SET_VALUES                {name: value}                               None
    GET_VALUES                [name, ...]                                 {name: float64 array}
    GET_NATIVE                [name, ...]                                 {name: array, [str] or [bytes]}
    ENTER_INITIALIZATION      start time                                  None
    EXIT_INITIALIZATION       -                                           None
    CONFIGURE                 shared memory name, inputs, observed        None
    SET_INPUTS                input indices (None: all)                   None (values are in the slots)
    GET_OUTPUTS               -                                           None (values are in the slots)
    STEP                      t, h, input indices (None: all, (): none)   (terminate_requested, early_return,
                                                                           last_successful_time, seconds the
                                                                           step took in the worker)
    TERMINATE                 -                                           None, then the worker exits
    ========================  ==========================================  =================================
    """

    INSTANTIATE = "instantiate"
    SET_VALUES = "set_values"
    GET_VALUES = "get_values"
    GET_NATIVE = "get_native"
    ENTER_INITIALIZATION = "enter_initialization"
    EXIT_INITIALIZATION = "exit_initialization"
    CONFIGURE = "configure"
    SET_INPUTS = "set_inputs"
    GET_OUTPUTS = "get_outputs"
    STEP = "step"
    TERMINATE = "terminate"


class Reply:
    """Worker -> master messages: ``(kind, payload, messages)``, ``messages`` the FMU's log since the
    previous reply as ``((status, text), ...)``. The worker first sends ``(OK, None, ())`` once it
    runs; the master then sends the FMU's description (no command tuple: it comes once, first),
    answered by OK once the worker holds it."""

    OK = "ok"        # payload: the command's result
    RAISE = "raise"  # payload: the exception, raised in the master


class WorkerFmu:
    """The :class:`~orchestration.hosts.in_process.ComponentHost` protocol, with the FMU in a worker process.

    ``start_timeout`` bounds the worker's start (interpreter, imports); ``setup_timeout`` each
    call until the FMU is initialized; ``reply_timeout`` each later reply (None: automatic, see the
    module doc). ``stop_level`` is set by the master on Ctrl-C/SIGTERM: 1 abandons a setup call
    that is still running (a worker compiling for a minute is killed, not waited for), 2 (a
    second signal) abandons any call.
    """

    asynchronous = True

    def __init__(self, name: str, description: FmuDescription, start_timeout: float = 120.0,
                 reply_timeout: float | None = None, setup_timeout: float = SETUP_TIMEOUT):
        self.name = name
        self.description = description
        self.ports: dict[str, PortInfo] = dict(description.ports)
        self.messages: list[tuple[int, str]] = []
        self.start_timeout = float(start_timeout)
        self.reply_timeout = None if reply_timeout is None else float(reply_timeout)
        self.setup_timeout = max(float(setup_timeout), self.reply_timeout or 0.0)
        self.stop_level = 0
        self._in_setup = True        # until exit_initialization has answered
        self._sent_at = 0.0          # monotonic time of the last command sent
        self.replies = RecentSlowest()  # the automatic reply deadline during the run
        self.terminate_requested = False
        self.early_return = False
        self.last_successful_time = 0.0
        self.last_step_seconds = None  # the last step's time in the worker (the algorithm's step cost)
        self._logger = logging.getLogger(f"orchestration.fmu.{name}")
        self._process = None
        self._conn = None
        self._poller = None
        self._shm: SharedMemory | None = None
        self._time: float | None = None
        self._crash_reason: str | None = None
        self._pending: tuple[str, float] | None = None
        self._terminated = False
        self._inputs: list[str] = []
        self._input_slots: dict[str, np.ndarray] = {}
        self._input_index: dict[str, int] = {}
        self._output_views: dict[str, np.ndarray] = {}

    # -- lifecycle ---------------------------------------------------------------------------------
    def instantiate(self) -> None:
        if self._process is not None:
            raise RuntimeError(f"{self.name}: instantiate() was called twice")
        if self._terminated:
            raise RuntimeError(f"{self.name}: instantiate() after terminate()")
        context = multiprocessing.get_context("spawn")
        parent_end, child_end = context.Pipe(duplex=True)
        # Only small arguments go with the spawn: start() writes them into a pipe whose reading
        # end this process holds too, so a child that dies before reading them all (a script
        # that starts a run when imported) would block it forever. The description (its ports'
        # start values: 80 KB for Tissue) follows once the worker answers.
        self._process = context.Process(target=_worker_main, args=(child_end, self.name),
                                        name=f"fmu-worker-{self.name}", daemon=True)
        start_shielded(self._process)  # _worker_main ignores SIGINT, then unblocks
        child_end.close()  # so that the worker's death reads as end-of-file here
        self._conn = parent_end
        self._sent_at = time.monotonic()
        self._receive(START_CALL, timeout=self.start_timeout)
        # The FMPy model description object stays here: the worker needs only the ports.
        description = dataclasses.replace(self.description, model_description=None)
        self._call(START_CALL, description)
        self._call("fmi3InstantiateCoSimulation", (Command.INSTANTIATE,))

    def set_values(self, values: dict[str, object]) -> None:
        self._call("set_values", (Command.SET_VALUES, dict(values)))

    def get_values(self, names: list[str]) -> dict[str, np.ndarray]:
        return self._call("get_values", (Command.GET_VALUES, list(names)))

    def get_native(self, names: list[str]) -> dict[str, object]:
        """Values in the FMU's own types (see :meth:`InProcessFmu.get_native`)."""
        return self._call("get_native", (Command.GET_NATIVE, list(names)))

    def enter_initialization(self, start_time: float) -> None:
        self._time = float(start_time)
        self._call("fmi3EnterInitializationMode", (Command.ENTER_INITIALIZATION, self._time))
        self.last_successful_time = self._time

    def exit_initialization(self) -> None:
        self._call("fmi3ExitInitializationMode", (Command.EXIT_INITIALIZATION,))
        self._in_setup = False

    def configure(self, inputs: list[str], observed: list[str]) -> None:
        inputs, observed = list(inputs), list(observed)
        check_port_lists(self.name, self.ports, inputs, observed)
        self._require_worker("configure")
        in_layout, in_size = slot_layout(self.ports, inputs)
        out_layout, out_size = slot_layout(self.ports, observed)
        self._release_shared_memory()
        self._shm = _reserve_shared_memory(self.name, 8 * max(1, in_size + out_size), self._time)
        block = np.ndarray((in_size + out_size,), dtype=np.float64, buffer=self._shm.buf)
        block[:] = 0.0
        self._inputs = inputs
        self._input_index = {name: i for i, name in enumerate(inputs)}
        self._input_slots = {name: block[a:b] for name, (a, b) in in_layout.items()}
        self._output_views = {name: block[in_size + a:in_size + b] for name, (a, b) in out_layout.items()}
        del block
        self._call("configure", (Command.CONFIGURE, self._shm.name, inputs, observed))

    # -- hot path ----------------------------------------------------------------------------------
    def _write_inputs(self, values: dict[str, np.ndarray]):
        """Copy ``values`` into their slots; return what the worker must push (None: all inputs)."""
        slots = self._input_slots
        for name, value in values.items():
            slot = slots.get(name)
            if slot is None:
                raise PortConfigurationError(f"{self.name}.{name} is not among the configured inputs "
                                             f"({', '.join(self._inputs) or 'none'}): list it in configure()")
            value = np.asarray(value, dtype=np.float64)
            if value.size != slot.size:
                raise ValueError(f"{self.name}.{name} expects {slot.size} value(s), got {value.size}")
            np.copyto(slot, value.reshape(slot.size))
        if len(values) == len(self._inputs):
            return None
        index = self._input_index
        return tuple(index[name] for name in values)

    def set_inputs(self, values: dict[str, np.ndarray]) -> None:
        self._require_idle("set_inputs")
        which = self._write_inputs(values)
        self._call("set_inputs", (Command.SET_INPUTS, which))

    def get_outputs(self) -> dict[str, np.ndarray]:
        self._require_idle("get_outputs")
        self._call("get_outputs", (Command.GET_OUTPUTS,))
        return {name: view.copy() for name, view in self._output_views.items()}

    def start_step(self, t: float, h: float, inputs: dict[str, np.ndarray]) -> None:
        self._require_idle("start_step")
        which = self._write_inputs(inputs) if inputs else ()
        self._time = t
        self._send("fmi3DoStep", (Command.STEP, t, h, which))
        self._pending = ("fmi3DoStep", t + h)

    def finish_step(self) -> dict[str, np.ndarray]:
        if self._pending is None:
            raise RuntimeError(f"{self.name}: finish_step() without start_step()")
        call, t_end = self._pending
        self._pending = None
        (self.terminate_requested, self.early_return, self.last_successful_time,
         self.last_step_seconds) = self._receive(call)
        self._time = self.last_successful_time
        return self._output_views  # views of the shared block: valid until the next step

    def step_done(self) -> bool:
        """Whether the step in flight has ended (or the worker is gone): finish_step will not wait."""
        if self._pending is None:
            return True
        return bool(self._watch().poll(0))

    def _watch(self):
        """One poll object on the pipe and the process sentinel: a microsecond per look, where
        multiprocessing.connection.wait builds a selector each time (10-20 us)."""
        if self._poller is None:
            self._poller = select.poll()
            self._poller.register(self._conn.fileno(), select.POLLIN)
            self._poller.register(self._process.sentinel, select.POLLIN)
        return self._poller

    @property
    def pid(self) -> int | None:
        """The worker process's id (None before instantiate)."""
        return None if self._process is None else self._process.pid

    # -- shutdown ----------------------------------------------------------------------------------
    def terminate(self) -> None:
        """Shut the worker down (fmi3Terminate, free), kill it if it does not stop, free shared memory.

        Idempotent; never raises; ``messages`` keep what the worker sent.
        """
        if self._terminated:
            return
        self._terminated = True
        process, conn = self._process, self._conn
        try:
            if process is not None and conn is not None and self._crash_reason is None and process.is_alive():
                if self._pending is not None:  # the reply of a step in flight comes first
                    self._pending = None
                    try:
                        self._receive("fmi3DoStep", timeout=_SHUTDOWN_TIMEOUT)
                    except FmuCallError:
                        pass
                if self._crash_reason is None:  # not killed while we waited for that reply
                    conn.send((Command.TERMINATE,))
                    self._sent_at = time.monotonic()
                    self._receive("fmi3Terminate", timeout=_SHUTDOWN_TIMEOUT)
        except Exception as exc:  # terminate never raises: the worker is killed below if need be
            logger.warning("%s: clean worker shutdown failed: %s", self.name, exc)
        if process is not None:
            try:
                process.join(_SHUTDOWN_TIMEOUT)
                if process.is_alive():
                    logger.warning("%s: worker did not exit within %.0f s; killing it", self.name, _SHUTDOWN_TIMEOUT)
                    process.kill()
                    process.join(5.0)
                process.close()
            except Exception as exc:
                logger.warning("%s: stopping the worker process failed: %s", self.name, exc)
        if conn is not None:
            try:
                conn.close()
            except Exception:
                pass
        self._release_shared_memory()

    def _release_shared_memory(self) -> None:
        self._input_slots, self._output_views = {}, {}
        if self._shm is None:
            return
        shm, self._shm = self._shm, None
        try:
            shm.close()
        except Exception as exc:  # a view still exported: unlink anyway, the memory goes with the process
            logger.warning("%s: closing shared memory failed: %s", self.name, exc)
        try:
            shm.unlink()
        except FileNotFoundError:
            pass
        except Exception as exc:
            logger.warning("%s: unlinking shared memory %s failed: %s", self.name, shm.name, exc)

    # -- messaging ---------------------------------------------------------------------------------
    def _call(self, call: str, message):
        self._require_idle(call)
        self._send(call, message)
        return self._receive(call)

    def _send(self, call: str, message) -> None:
        self._require_worker(call)
        try:
            self._conn.send(message)
        except (BrokenPipeError, ConnectionError, EOFError, OSError):
            raise self._crashed(call) from None
        self._sent_at = time.monotonic()

    def reply_deadline(self) -> tuple[float, str]:
        """How long the next reply may take (s), and why that long (for the error message)."""
        if self._in_setup:
            return self.setup_timeout, "the allowance for its first calls (loading, instantiation, initialization)"
        if self.reply_timeout is not None:
            return self.reply_timeout, "the scene's [scene] worker_timeout"
        return self.replies.deadline("reply")

    def _receive(self, call: str, timeout: float | None = None):
        conn = self._conn
        poller = self._watch()
        conn_fd = conn.fileno()
        while True:
            events = poller.poll(_LIVENESS_INTERVAL_MS)
            if any(fd == conn_fd for fd, _ in events):
                break
            # Only after half a second without an answer: the hot path never gets here.
            if events or not self._process.is_alive():  # the sentinel: the worker is gone
                if conn.poll():  # it answered before it went away
                    break
                raise self._crashed(call)
            waited = time.monotonic() - self._sent_at
            if self.stop_level >= (1 if self._in_setup else 2):
                self._kill(f"the run was stopped while the worker was busy with it ({waited:.1f} s); "
                           "the worker was killed")
                raise WorkerCrash(self.name, call, self._time, self._crash_reason)
            if timeout is not None:
                limit, why = timeout, "the allowance for this call"
            else:
                limit, why = self.reply_deadline()
            if waited > limit:
                pid = self._process.pid
                self._kill(f"the worker (pid {pid}) did not answer within {limit:.3g} s ({why}); it was killed "
                           f"after {waited:.3g} s")
                raise WorkerCrash(self.name, call, self._time, self._crash_reason)
        try:
            kind, payload, messages = conn.recv()
        except (EOFError, ConnectionError, OSError):
            raise self._crashed(call) from None
        if not self._in_setup:
            self.replies.add(time.monotonic() - self._sent_at)
        for status, text in messages:
            self.messages.append((status, text))
            self._logger.log(LOG_LEVELS.get(status, logging.ERROR), "%s", text)
        if kind == Reply.RAISE:
            raise payload
        return payload

    def _kill(self, reason: str) -> None:
        """Kill the worker (works on a stopped process too) and record why it is gone."""
        self._crash_reason = reason
        try:
            self._process.kill()
            self._process.join(5.0)
        except Exception as exc:
            logger.warning("%s: killing the worker failed: %s", self.name, exc)

    def _crashed(self, call: str) -> WorkerCrash:
        """The WorkerCrash for ``call``; the first one records why the worker is gone."""
        if self._crash_reason is None:
            process = self._process
            exitcode = None
            if process is not None:
                process.join(2.0)
                exitcode = process.exitcode
            pid = process.pid if process is not None else "?"
            self._crash_reason = f"the worker process (pid {pid}) died: {exit_description(exitcode)}"
            if call == START_CALL:
                self._crash_reason += _start_up_hint()
        return WorkerCrash(self.name, call, self._time, self._crash_reason)

    def _require_worker(self, call: str) -> None:
        if self._crash_reason is not None:
            raise WorkerCrash(self.name, call, self._time, self._crash_reason)
        if self._terminated:
            raise RuntimeError(f"{self.name}: {call} after terminate()")
        if self._process is None:
            raise RuntimeError(f"{self.name}: call instantiate() before {call}")

    def _require_idle(self, call: str) -> None:
        if self._pending is not None:
            raise RuntimeError(f"{self.name}: {call} while a step is in flight: call finish_step() first")


def _reserve_shared_memory(name: str, size: int, t: float | None) -> SharedMemory:
    """A new shared memory block of ``size`` bytes whose pages are all reserved now.

    The block is a file in /dev/shm (a tmpfs): creating it only sets its size, and its pages are
    allocated when first written. On a nearly full /dev/shm that first write, in the middle of the
    run, kills the process with SIGBUS (and the dead run leaves the block behind). Reserving the
    pages at once (posix_fallocate) turns that into an error here, before the run starts, and the
    block is removed again. Raises FmuCallError naming the size, the cause and the fixes.
    """
    def failure(exc: OSError) -> FmuCallError:
        return FmuCallError(name, "configure", t, (
            f"cannot reserve {size} bytes of shared memory for the worker's values in /dev/shm "
            f"({exc.strerror or exc}): free space there (df -h /dev/shm; a container's is set by its "
            f"--shm-size) or host {name} in the run's own process (--hosting in-process)"))

    try:
        shm = SharedMemory(create=True, size=size)
    except OSError as exc:
        raise failure(exc) from None
    try:
        fd = getattr(shm, "_fd", -1)  # CPython's POSIX SharedMemory keeps its file open as _fd
        if fd >= 0:
            try:
                os.posix_fallocate(fd, 0, shm.size)
            except OSError as exc:
                if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
                    raise
                _check_free_space(shm.size)  # a file system that cannot reserve: at least look
    except OSError as exc:
        _discard_shared_memory(shm)
        raise failure(exc) from None
    return shm


def _check_free_space(size: int) -> None:
    """OSError(ENOSPC) when /dev/shm visibly lacks ``size`` bytes (where there is no /dev/shm: nothing)."""
    try:
        stat = os.statvfs("/dev/shm")
    except OSError:
        return
    if stat.f_bavail * stat.f_frsize < size:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def _discard_shared_memory(shm: SharedMemory) -> None:
    try:
        shm.close()
    except Exception:
        pass
    try:
        shm.unlink()
    except Exception as exc:
        logger.warning("unlinking shared memory %s failed: %s", shm.name, exc)


# -- the worker process ----------------------------------------------------------------------------
class _WorkerState:
    """What the worker holds: the FMU host and its views of the shared memory block."""

    def __init__(self, name: str, description: FmuDescription):
        self.host = InProcessFmu(name, description, log_to_logger=False)
        self.shm: SharedMemory | None = None

    def configure(self, shm_name: str, inputs: list[str], observed: list[str]) -> None:
        self.detach()
        ports = self.host.ports
        _, in_size = slot_layout(ports, inputs)
        _, out_size = slot_layout(ports, observed)
        self.shm = SharedMemory(name=shm_name)
        block = np.ndarray((in_size + out_size,), dtype=np.float64, buffer=self.shm.buf)
        self.host.bind(inputs, observed, block[:in_size], block[in_size:])

    def detach(self) -> None:
        if self.shm is not None:
            self.host.unbind()
            try:
                self.shm.close()
            except BufferError:  # a view is still alive; the mapping goes with the process
                pass
            self.shm = None


def _start_up_hint() -> str:
    """Why a worker dies before it answers, when the cause is the usual one (see its traceback)."""
    main = getattr(sys.modules.get("__main__"), "__file__", None)
    if main is None:
        return ""
    return (f" (its traceback is on stderr). A worker process starts by importing the main script, "
            f"{main}: if that script starts a run when it is imported, put that code under "
            f'if __name__ == "__main__":')


def _worker_main(conn, name: str) -> None:
    """Take the FMU's description, then serve commands until TERMINATE or until the master goes away."""
    # Ctrl-C in the terminal reaches the whole process group: the master handles it and shuts
    # the worker down, so the worker must not die of it first. Both signals were blocked since
    # before the spawn (see instantiate): ignore SIGINT, then unblock, which discards a pending
    # SIGINT (a pending SIGTERM ends the worker now, as it would have during start-up).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    limit_native_threads()  # before the FMU loads its libraries: this CPU is shared with the haptic loop's
    conn.send((Reply.OK, None, ()))
    try:
        description = conn.recv()
    except (EOFError, OSError):  # the master is gone
        return
    state = _WorkerState(name, description)
    host = state.host

    def push(which):
        host.instance.push(which)

    def pull():
        host.instance.pull()

    handlers = {
        Command.INSTANTIATE: lambda: host.instantiate(),
        Command.SET_VALUES: lambda values: host.set_values(values),
        Command.GET_VALUES: lambda names: host.get_values(names),
        Command.GET_NATIVE: lambda names: host.get_native(names),
        Command.ENTER_INITIALIZATION: lambda t: host.enter_initialization(t),
        Command.EXIT_INITIALIZATION: lambda: host.exit_initialization(),
        Command.CONFIGURE: lambda shm_name, inputs, observed: state.configure(shm_name, inputs, observed),
        Command.SET_INPUTS: push,
        Command.GET_OUTPUTS: pull,
    }
    _reply(conn, Reply.OK, None, host)
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):  # the master is gone
            break
        command = message[0]
        try:
            if command == Command.STEP:
                _, t, h, which = message
                instance = host.instance
                if which != ():
                    instance.push(which)
                started = time.perf_counter()
                result = host.step(t, h)
                instance.pull()
                payload = (result.terminate_requested, result.early_return, result.last_successful_time,
                           time.perf_counter() - started)
            elif command == Command.TERMINATE:
                break
            else:
                payload = handlers[command](*message[1:])
            kind = Reply.OK
        except Exception as exc:  # sent to the master, raised there
            kind, payload = Reply.RAISE, exc
        _reply(conn, kind, payload, host)
    state.detach()
    host.terminate()
    try:
        _reply(conn, Reply.OK, None, host)
    except (OSError, ValueError):
        pass
    conn.close()


def _reply(conn, kind: str, payload, host: InProcessFmu) -> None:
    messages = ()
    if host.messages:
        messages = tuple(host.messages)
        host.messages.clear()
    try:
        conn.send((kind, payload, messages))
    except (OSError, ValueError):
        raise
    except Exception as exc:  # an exception that cannot be pickled
        error = OrchestrationError(f"{host.name}: {type(payload).__name__}: {payload} (raised in the worker)")
        conn.send((Reply.RAISE, error, messages))
        logger.debug("unpicklable reply %r: %s", payload, exc)

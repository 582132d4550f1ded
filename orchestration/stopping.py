"""Stopping a run on Ctrl-C (SIGINT) or SIGTERM: a flag read between ticks, never an exception.

In-process FMUs run Python code (the models) called through ctypes from this very process. A
``KeyboardInterrupt`` raised while such a call is on the stack is turned into a fatal error
inside the FMU (and, once in a while, a crash of the interpreter), so while a run is in progress
SIGINT and SIGTERM must not raise: their handlers here only record the request and tell the
listeners (the master sets ``algorithm.stop_reason``, checked between ticks and between setup
calls, as cheap as before). The first request stops the run cleanly at the next tick (a worker
still loading is killed, plots are skipped); a second one forces a faster stop (workers are killed
instead of waited for); either way the recorded rows and the summary are written.

Exit codes of ``python -m orchestration run`` after a stop: 128 + the signal number, as a shell
reports a process ended by that signal: :data:`EXIT_SIGINT` (130) for Ctrl-C,
:data:`EXIT_SIGTERM` (143) for SIGTERM.

This module is imported first by ``python -m orchestration`` (see ``__main__``), so it must stay
light: no numpy, no orchestration modules.
"""
from __future__ import annotations

import contextlib
import logging
import signal
import threading
from typing import Callable, Iterator

logger = logging.getLogger(__name__)

EXIT_SIGINT = 128 + signal.SIGINT    # 130
EXIT_SIGTERM = 128 + signal.SIGTERM  # 143
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

_REASONS = {signal.SIGINT: "interrupted by Ctrl-C (SIGINT)", signal.SIGTERM: "stopped by SIGTERM"}


class StopRequest:
    """What the signal handlers record: the first signal's reason, how many arrived, who to tell."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.reason: str | None = None
        self.count = 0
        self._listeners: list[Callable[["StopRequest"], None]] = []
        self._previous: dict = {}  # the handlers install() replaced

    @property
    def requested(self) -> bool:
        return self.reason is not None

    @property
    def forced(self) -> bool:
        """A second signal: stop faster (kill workers rather than wait for them, skip plots)."""
        return self.count >= 2

    @property
    def exit_code(self) -> int:
        return 128 + int(self.signum) if self.signum is not None else 0

    def listen(self, callback: Callable[["StopRequest"], None]) -> None:
        """Call ``callback(self)`` on every signal from now on (and at once if one already arrived)."""
        self._listeners.append(callback)
        if self.requested:
            callback(self)

    def unlisten(self, callback) -> None:
        with contextlib.suppress(ValueError):
            self._listeners.remove(callback)

    def request(self, signum: int) -> None:
        """Record a stop request as if ``signum`` had arrived (the signal handler; tests)."""
        self.count += 1
        if self.signum is None:
            self.signum = signum
            self.reason = _REASONS.get(signum, f"stopped by signal {signum}")
        for callback in list(self._listeners):
            callback(self)

    def _handler(self, signum, frame) -> None:
        # Runs in the main thread between two bytecodes, possibly inside an FMU's Python code
        # called through ctypes: set flags only, never raise, never block.
        self.request(signum)


_active: StopRequest | None = None


def _take_over(request: StopRequest) -> dict:
    """Point SIGINT and SIGTERM at ``request``; return the handlers replaced.

    A signal this process ignores stays ignored: a sweep worker or a background job was told to
    leave Ctrl-C to someone else (the sweep process, the shell), who stops it another way.
    """
    previous = {}
    for sig in STOP_SIGNALS:
        if signal.getsignal(sig) is signal.SIG_IGN:
            continue
        previous[sig] = signal.signal(sig, request._handler)
    return previous


def active() -> StopRequest | None:
    """The request whose handlers are installed, if any."""
    return _active


def install() -> StopRequest:
    """Install flag-only handlers for SIGINT and SIGTERM for the rest of the process.

    ``python -m orchestration`` calls this before anything else (a Ctrl-C during the imports and
    the setup counts too); commands other than ``run`` give the signals back with :func:`uninstall`.
    """
    global _active
    if _active is None:
        request = StopRequest()
        request._previous = _take_over(request)
        _active = request
    return _active


def uninstall() -> None:
    """Restore the handlers :func:`install` replaced; a signal that arrived meanwhile is re-raised."""
    global _active
    request, _active = _active, None
    if request is None:
        return
    for sig, previous in request._previous.items():
        signal.signal(sig, previous)
    if request.signum is not None:
        signal.raise_signal(request.signum)


@contextlib.contextmanager
def stop_signals() -> Iterator[StopRequest]:
    """Flag-only SIGINT/SIGTERM handlers for the duration of a run, then the previous ones back.

    Reuses the handlers already installed (the command line installs them for the whole
    process). Off the main thread (where Python cannot install handlers) it yields a request no
    signal sets, so a run in a thread pool behaves as before. A signal that arrived is delivered
    again once the previous handlers are back: a program calling ``run_scene`` (a study's loop)
    still gets its ``KeyboardInterrupt``, but only after the run's results and summary are written.
    """
    if _active is not None:
        yield _active
        return
    if threading.current_thread() is not threading.main_thread():
        yield StopRequest()
        return
    request = install()
    try:
        yield request
    finally:
        if request.requested:
            logger.debug("run stopped: %s (%d signal(s)); delivering it to the caller", request.reason, request.count)
        uninstall()


def start_shielded(process) -> None:
    """Start a ``multiprocessing`` child that cannot die of a stop signal sent to the whole group
    (Ctrl-C in the terminal) during its interpreter start-up.

    The child inherits this thread's signal mask across fork and exec: with SIGINT and SIGTERM
    blocked they stay pending until the child's own code decides (workers ignore SIGINT, then
    unblock). A child dying during start-up would also hang ``start()`` forever: it writes the
    pickled process object into a pipe whose reading end it still holds itself. The resource
    tracker is started first: starting it unblocks both signals behind our back.
    """
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        process.start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


def set_process_name(name: str) -> None:
    """Name this process in ``top`` and ``ps`` (Linux: its ``comm``, at most 15 characters), so
    that a run's helper processes are told apart from its FMU workers; elsewhere nothing."""
    try:
        with open("/proc/self/comm", "w") as comm:
            comm.write(name[:15])
    except OSError:
        pass


#: The automatic deadline of a helper or worker process the run waits for: at least this many
#: seconds ...
DEADLINE_FLOOR = 10.0
#: ... or this many times the slowest recent wait (a step's cost varies: a tissue step that
#: refactorises takes 10x its median; a 100x margin only catches a process that is stuck).
DEADLINE_FACTOR = 100.0
#: Waits per window of the "recent" slowest one (the last one to two windows count).
_RECENT_WINDOW = 256


class RecentSlowest:
    """The slowest of a process's recent waits (the last one to two windows of them), and the
    automatic deadline it gives: the one rule for the FMU workers and the writer processes."""

    def __init__(self):
        self.current = 0.0  # slowest wait in the current window (s)
        self.before = 0.0   # ... and in the window before
        self._count = 0

    def add(self, seconds: float) -> None:
        if seconds > self.current:
            self.current = seconds
        self._count += 1
        if self._count >= _RECENT_WINDOW:
            self.before, self.current, self._count = self.current, 0.0, 0

    def deadline(self, what: str) -> tuple[float, str]:
        """(seconds, why) of the automatic deadline; ``what`` names the wait ("reply", "wait")."""
        slowest = max(self.current, self.before)
        return max(DEADLINE_FLOOR, DEADLINE_FACTOR * slowest), (
            f"max({DEADLINE_FLOOR:g} s, {DEADLINE_FACTOR:g} x its slowest recent {what} of {slowest:.3g} s); set "
            "[scene] worker_timeout to change it")

"""A helper process beside the run (the surface writer, the row writer): started so that a stop
signal sent to the whole process group cannot kill it, fed in order through a pipe, and closed by
a handshake that waits until it has done everything it was sent and returns the errors it met.

When the run's process dies, the helper reads what is still in the pipe, does it and ends (its
loop ends at end of file); Ctrl-C and SIGTERM sent to the group do not stop it before that.

The run never waits for a helper without a deadline, as it never waits for a worker without one
(:mod:`.worker`): a helper that makes no progress for longer than the deadline while the run waits
for it (the pipe is full, or the closing handshake is not answered) is killed and reported, so a
helper stopped with SIGSTOP, deadlocked or swapping cannot hold the run forever. Progress is any
byte it takes from the pipe or any CPU time it spends (a helper that runs only on idle CPUs, the
surface writer, still advances slowly while the run keeps both CPUs busy; a stopped one does not).
The deadline is the scene's ``[scene] worker_timeout`` when the run sets :attr:`HelperProcess.timeout`,
else the workers' automatic rule: ``max(10 s, 100 x the longest recent wait that ended in
progress)``. A second Ctrl-C or SIGTERM kills a helper the run is waiting for at once.

While the run goes on, a helper reports its first error of each kind at once (a *notice*: a file
it could not write and why, what it kept), so that the run can stop instead of producing results
that cannot be kept (a full or read-only volume); every error is returned by the closing handshake.
"""
from __future__ import annotations

import logging
import multiprocessing
import os
import select
import signal
import socket
import struct
import threading
import time
from multiprocessing.reduction import ForkingPickler
from typing import Callable

from orchestration import stopping
from orchestration.stopping import STOP_SIGNALS, RecentSlowest, set_process_name, start_shielded

log = logging.getLogger(__name__)

#: The longest close() waits for the work still queued, however much progress the helper makes (a
#: writer that ran only on idle CPUs may have most of a run's work left when the run ends).
CLOSE_TIMEOUT_S = 600.0
#: While waiting for a helper, how often the run looks at its progress, its liveness and a stop request (s).
_WATCH_INTERVAL_S = 0.2


class HelperProcess:
    """``target(conn, *args)`` in a process of its own, ``send`` per message, ``close`` at the end.

    The target calls :func:`begin_helper`, then :func:`serve`. ``label`` names the helper in
    messages ("row writer"). ``send`` may be called from one thread at a time per message (a lock
    keeps messages whole); ``poll`` from any thread.
    """

    def __init__(self, label: str, target, *args):
        self.label = label
        #: seconds without progress before a helper the run waits for is killed (None: automatic)
        self.timeout: float | None = None
        #: called with each notice (a dict, see :func:`serve`) as it arrives, in the thread that reads it
        self.on_notice: Callable[[dict], None] | None = None
        #: every notice received so far
        self.notices: list[dict] = []
        context = multiprocessing.get_context("spawn")
        self._conn, child_end = context.Pipe(duplex=True)
        self._process = context.Process(target=target, args=(child_end, *args), name=_process_name(label),
                                        daemon=True)
        start_shielded(self._process)  # the target ignores both: it ends when this process closes the pipe
        child_end.close()
        # Messages are written without blocking (send with MSG_DONTWAIT on the pipe's socket, in
        # the framing Connection.recv reads), so that a full pipe is a wait the run watches, not
        # a write() it cannot leave. Where the pipe is no socket (not Linux) send blocks as before.
        try:
            self._sock: socket.socket | None = socket.socket(fileno=os.dup(self._conn.fileno()))
        except OSError:
            self._sock = None
        self._send_lock = threading.Lock()
        self._recv_lock = threading.Lock()
        self._send_error: str | None = None
        #: why the run killed the helper (None: it was not killed by the run)
        self._killed: str | None = None
        self._closed = False
        self._waits = RecentSlowest()  # the automatic deadline: the workers' rule (stopping.RecentSlowest)

    @property
    def pid(self) -> int:
        return self._process.pid

    @property
    def gone(self) -> bool:
        """The helper can no longer take work (it died, was killed, or a send failed)."""
        return self._send_error is not None or self._killed is not None

    # -- sending -------------------------------------------------------------------------------
    def send(self, message) -> bool:
        """Queue one message (True), or False when the helper is gone (close() reports it). Waits
        while the pipe is full, at most until the helper has made no progress for the deadline
        (then it is killed)."""
        if self.gone or self._closed:
            return False
        payload = bytes(ForkingPickler.dumps(message))
        size = len(payload)
        # The framing of multiprocessing.connection.Connection._send_bytes, which recv() reads.
        header = struct.pack("!i", size) if size <= 0x7FFFFFFF else struct.pack("!i", -1) + struct.pack("!Q", size)
        with self._send_lock:
            if self.gone:
                return False
            if self._sock is None:
                try:
                    self._conn.send_bytes(payload)
                    return True
                except (OSError, ValueError) as exc:
                    self._send_error = f"{type(exc).__name__}: {exc}"
                    return False
            return self._write(header + payload)

    def _write(self, data: bytes) -> bool:
        view = memoryview(data)
        watch = None
        dead = False
        while view:
            try:
                view = view[self._sock.send(view, socket.MSG_DONTWAIT):]
                if watch is not None:
                    watch.progressed()
                continue
            except (BlockingIOError, InterruptedError):
                pass
            except (OSError, ValueError) as exc:
                self._send_error = f"{type(exc).__name__}: {exc}"
                return False
            # The pipe is full: wait for room, watching the helper.
            if watch is None:
                watch = _Watch(self)
            try:
                select.select([self._process.sentinel], [self._sock], [], _WATCH_INTERVAL_S)
            except (OSError, ValueError):  # the sentinel was closed (the process object closed)
                pass
            self.poll()
            if not self._process.is_alive():
                if dead:  # a second look and still no room: the helper is gone
                    self._send_error = f"the process ended ({self.exit_description()})"
                    return False
                dead = True
                continue  # the next send says how (a broken pipe, once its unread messages are freed)
            if not watch.check():
                return False
        if watch is not None:
            watch.done()
        return True

    # -- receiving -----------------------------------------------------------------------------
    def poll(self) -> None:
        """Take the notices the helper has sent so far (never waits; a thread that is reading
        them already is left to it)."""
        if not self._recv_lock.acquire(blocking=False):
            return
        try:
            while not self._conn.closed and self._conn.poll(0):
                message = self._conn.recv()
                if message[0] == "notice":
                    self._notice(message[1])
        except (EOFError, OSError):
            pass
        finally:
            self._recv_lock.release()

    def _notice(self, notice: dict) -> None:
        self.notices.append(notice)
        if self.on_notice is not None:
            try:
                self.on_notice(notice)
            except Exception:  # a notice must never cost the run: the error is in close()'s list too
                log.exception("%s: handling a notice failed", self.label)

    def _await_reply(self):
        """The answer to "close" (the helper's errors), or None when it died or was killed first."""
        watch = _Watch(self)
        start = time.monotonic()
        while True:
            with self._recv_lock:
                try:
                    if self._conn.poll(_WATCH_INTERVAL_S):
                        message = self._conn.recv()
                        if message[0] == "closed":
                            return message[1]
                        self._notice(message[1])
                        watch.progressed()
                        continue
                except (EOFError, OSError):
                    return None
            if not self._process.is_alive():
                return None
            if time.monotonic() - start > CLOSE_TIMEOUT_S:
                self._kill(f"it had not finished its work {CLOSE_TIMEOUT_S:g} s after the run ended; it was killed")
                return None
            if not watch.check():
                return None

    # -- the end -------------------------------------------------------------------------------
    def close(self, work: str) -> list[str]:
        """Wait until everything sent is done; the helper's errors, if any (``work`` names what it
        does, for the error when it died: "frame", "row"). Idempotent."""
        if self._closed:
            return []
        errors = None
        if self.send(("close",)):
            errors = self._await_reply()
        self._closed = True
        if errors is None:
            self._process.join(timeout=2)
            if self._killed is not None:
                errors = [f"the {self.label} process (pid {self.pid}) was killed: {self._killed}"]
            else:
                errors = [f"the {self.label} process ended before writing every {work} "
                          f"(exit code {self._process.exitcode})"]
                if self._send_error:
                    errors[0] += f": {self._send_error}"
        self._conn.close()
        if self._sock is not None:
            self._sock.close()
        self._process.join(timeout=5)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
        return errors

    def exit_description(self) -> str:
        """How the helper ended, for messages ("killed by signal SIGKILL"); "running" while it runs."""
        from orchestration.errors import exit_description

        if self._process.is_alive():
            return "running"
        if self._killed is not None:
            return f"killed by the run: {self._killed}"
        return exit_description(self._process.exitcode)

    def _kill(self, reason: str) -> None:
        """Kill the helper (works on a stopped process too) and record why."""
        self._killed = reason
        log.error("%s (pid %d): %s", self.label, self.pid, reason)
        try:
            self._process.kill()
            self._process.join(5)
        except Exception as exc:
            log.warning("%s: killing the process failed: %s", self.label, exc)

    def deadline(self) -> tuple[float, str]:
        """How long the helper may go without progress while the run waits for it, and why."""
        if self.timeout is not None:
            return self.timeout, "the scene's [scene] worker_timeout"
        return self._waits.deadline("wait")

    def _waited(self, seconds: float) -> None:
        self._waits.add(seconds)


class _Watch:
    """One wait for a helper: when did it last make progress, and is that too long ago?"""

    def __init__(self, helper: HelperProcess):
        self.helper = helper
        self.since = time.monotonic()
        self.cpu = _cpu_time(helper.pid)

    def progressed(self) -> None:
        now = time.monotonic()
        self.helper._waited(now - self.since)
        self.since = now

    def done(self) -> None:
        self.progressed()

    def check(self) -> bool:
        """False once the helper was killed (no progress within the deadline, or a forced stop)."""
        helper = self.helper
        cpu = _cpu_time(helper.pid)
        if cpu != self.cpu:
            self.cpu = cpu
            self.progressed()
        waited = time.monotonic() - self.since
        request = stopping.active()
        if request is not None and request.forced:
            helper._kill(f"the run was stopped ({request.reason}, a second time) while it waited {waited:.1f} s "
                         "for the helper")
            return False
        limit, why = helper.deadline()
        if waited > limit:
            helper._kill(f"it made no progress for {waited:.3g} s while the run waited for it (deadline "
                         f"{limit:.3g} s: {why})")
            return False
        return True


def _cpu_time(pid: int):
    """CPU time the process has spent so far, in any unit (None when the system does not say)."""
    try:
        with open(f"/proc/{pid}/schedstat", "rb") as handle:  # nanoseconds on a CPU
            return int(handle.read().split()[0])
    except (OSError, ValueError, IndexError):
        pass
    try:
        with open(f"/proc/{pid}/stat", "rb") as handle:  # clock ticks: utime + stime
            fields = handle.read().rsplit(b")", 1)[1].split()
            return int(fields[11]) + int(fields[12])
    except (OSError, ValueError, IndexError):
        return None


def _process_name(label: str) -> str:
    """The helper's process name in ``ps`` and ``top``: "row writer" runs as "row-writer"."""
    return label.replace(" ", "-")


def begin_helper(label: str) -> None:
    """First thing in a helper's target: ignore the stop signals (the run's process ends it by
    closing the pipe), unblock them as start_shielded had blocked them, and name the process.

    SIGXFSZ is ignored too (Python does so at start-up; said here so that it holds whatever
    started us): a write past a file-size limit (``ulimit -f``) then fails with EFBIG, which the
    helper reports and recovers from, instead of killing it mid-row."""
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)
    if hasattr(signal, "SIGXFSZ"):
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    set_process_name(_process_name(label))


def serve(conn, label: str, handle: Callable[[tuple], None]) -> None:
    """A helper's loop: ``handle`` each message in the order sent, until ``("close",)`` (answered with
    ``("closed", errors)``) or until the run's process is gone (end of file: everything it sent is
    done). A message that fails is an error, logged and kept, and the loop goes on (the next may
    succeed: a disk that was full).

    The first error for each name (a stream, a surface: ``message[1]``) is also sent at once as
    ``("notice", {"name", "error", ...})``, with whatever the exception adds in its ``notice``
    attribute (a dict: the file, what it keeps): the run learns of it while it goes on. One per
    name, so the notices never fill the pipe back to a run that reads them only now and then.
    """
    errors: list[str] = []
    noticed: set = set()
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        if message[0] == "close":
            conn.send(("closed", errors))
            return
        try:
            handle(message)
        except Exception as exc:
            name = message[1]
            errors.append(f"{name}: {type(exc).__name__}: {exc}")
            log.error("%s: %s", label, errors[-1])
            if name not in noticed:
                noticed.add(name)
                notice = {"name": name, "error": errors[-1], **(getattr(exc, "notice", None) or {})}
                try:
                    conn.send(("notice", notice))
                except (OSError, ValueError):  # the run's process is gone: nobody to tell
                    pass

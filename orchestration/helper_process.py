"""A helper process beside the run (the surface writer, the row writer): started so that a stop
signal sent to the whole process group cannot kill it, fed in order through a pipe, and closed by
a handshake that waits until it has done everything it was sent and returns the errors it met.

When the run's process dies, the helper reads what is still in the pipe, does it and ends (its
loop ends at end of file); Ctrl-C and SIGTERM sent to the group do not stop it before that.
"""
from __future__ import annotations

import logging
import multiprocessing
import signal
from typing import Callable

from .stopping import STOP_SIGNALS, set_process_name, start_shielded

log = logging.getLogger(__name__)

#: How long close() waits for the work still queued (a writer that ran only on idle CPUs may have
#: most of a run's work left when the run ends).
CLOSE_TIMEOUT_S = 600.0


class HelperProcess:
    """``target(conn, *args)`` in a process of its own, ``send`` per message, ``close`` at the end.

    The target calls :func:`begin_helper`, then :func:`serve`. ``label`` names the helper in
    messages ("row writer").
    """

    def __init__(self, label: str, target, *args):
        self.label = label
        context = multiprocessing.get_context("spawn")
        self._conn, child_end = context.Pipe(duplex=True)
        self._process = context.Process(target=target, args=(child_end, *args), name=_process_name(label),
                                        daemon=True)
        start_shielded(self._process)  # the target ignores both: it ends when this process closes the pipe
        child_end.close()
        self._send_error: str | None = None
        self._closed = False

    @property
    def pid(self) -> int:
        return self._process.pid

    def send(self, message) -> bool:
        """Queue one message (True), or False when the helper is gone (close() reports it); may
        block while the pipe is full."""
        if self._send_error is None:
            try:
                self._conn.send(message)
                return True
            except (OSError, ValueError) as exc:
                self._send_error = f"{type(exc).__name__}: {exc}"
        return False

    def close(self, work: str) -> list[str]:
        """Wait until everything sent is done; the helper's errors, if any (``work`` names what it
        does, for the error when it died: "frame", "row"). Idempotent."""
        if self._closed:
            return []
        self._closed = True
        errors = [f"the {self.label} process ended before writing every {work} (exit code {self._process.exitcode})"]
        try:
            self._conn.send(("close",))
            if self._conn.poll(CLOSE_TIMEOUT_S):
                errors = self._conn.recv()
        except (OSError, EOFError) as exc:
            errors[0] += f": {self._send_error or exc}"
        finally:
            self._conn.close()
            self._process.join(timeout=5)
            if self._process.is_alive():
                self._process.kill()
                self._process.join()
        return errors


def _process_name(label: str) -> str:
    """The helper's process name in ``ps`` and ``top``: "row writer" runs as "row-writer"."""
    return label.replace(" ", "-")


def begin_helper(label: str) -> None:
    """First thing in a helper's target: ignore the stop signals (the run's process ends it by
    closing the pipe), unblock them as start_shielded had blocked them, and name the process."""
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    set_process_name(_process_name(label))


def serve(conn, label: str, handle: Callable[[tuple], None]) -> None:
    """A helper's loop: ``handle`` each message in the order sent, until ``("close",)`` (answered with
    the errors met) or until the run's process is gone (end of file: everything it sent is done).
    A message that fails is an error, logged and kept, and the loop goes on (the next may succeed:
    a disk that was full)."""
    errors: list[str] = []
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        if message[0] == "close":
            conn.send(errors)
            return
        try:
            handle(message)
        except Exception as exc:
            errors.append(f"{message[1]}: {type(exc).__name__}: {exc}")
            log.error("%s: %s", label, errors[-1])

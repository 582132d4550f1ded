"""Errors of the orchestrator: what failed, in which component, at which simulated time, and why.

Also the one place for FMI status codes and their names (:data:`STATUS_NAMES`, :func:`status_name`,
:data:`LOG_LEVELS`) and for describing how a child process ended (:func:`exit_description`).
"""
from __future__ import annotations

import logging
import signal

#: fmi3Status values.
FMI_OK, FMI_WARNING, FMI_DISCARD, FMI_ERROR, FMI_FATAL = range(5)
STATUS_NAMES = ("fmi3OK", "fmi3Warning", "fmi3Discard", "fmi3Error", "fmi3Fatal")
#: Short names of the statuses, as the run summary lists logged messages.
SHORT_STATUS_NAMES = ("ok", "warning", "discard", "error", "fatal")
#: The logging level an FMU message of each status is logged at.
LOG_LEVELS = {FMI_OK: logging.INFO, FMI_WARNING: logging.WARNING, FMI_DISCARD: logging.WARNING,
              FMI_ERROR: logging.ERROR, FMI_FATAL: logging.CRITICAL}


def status_name(status: int | None) -> str | None:
    """"fmi3Error" for 3; None for None; "status 7" for a value outside the standard."""
    if status is None:
        return None
    return STATUS_NAMES[status] if 0 <= status < len(STATUS_NAMES) else f"status {status}"


def short_status_name(status: int) -> str:
    """"error" for 3; the number as text for a value outside the standard."""
    return SHORT_STATUS_NAMES[status] if 0 <= status < len(SHORT_STATUS_NAMES) else str(status)


def signal_name(signum: int) -> str:
    """"SIGABRT" for 6; the number as text for an unknown signal."""
    try:
        return signal.Signals(signum).name
    except ValueError:
        return str(signum)


def exit_description(returncode: int | None) -> str:
    """How a child process ended, from its exit code (negative: the signal that killed it)."""
    if returncode is None:
        return "exit status unknown"
    if returncode < 0:
        return f"killed by signal {signal_name(-returncode)}"
    return f"exited with code {returncode}"


class OrchestrationError(RuntimeError):
    """Base of every error the orchestrator raises on purpose."""


class FmuCallError(OrchestrationError):
    """A call into a component failed.

    ``str()`` reads like "Contact: fmi3DoStep at t = 0.123000 s failed (fmi3Error): <reason>",
    where the reason is the FMU's last logged error message.
    """

    def __init__(self, component: str, call: str, time: float | None, reason: str, status: int | None = None):
        self.component = component
        self.call = call
        self.time = time
        self.reason = reason
        self.status = status
        super().__init__(self._message())

    def _message(self) -> str:
        when = f" at t = {self.time:.6f} s" if self.time is not None else ""
        name = status_name(self.status)
        status = f" ({name})" if name else ""
        return f"{self.component}: {self.call}{when} failed{status}: {self.reason}"

    def __reduce__(self):  # keeps the fields when pickled (e.g. across processes)
        return (type(self), (self.component, self.call, self.time, self.reason, self.status))


class WorkerCrash(FmuCallError):
    """The process hosting the component died; the reason names its exit code or signal."""


class FmuBinaryError(OrchestrationError):
    """An FMU's binary cannot be loaded into a process (truncated, for another machine, missing FMI
    functions); found by reading it as data before ``dlopen``, which a truncated binary would kill
    with SIGBUS. The message names the file and the fix (``orchestration.hosts.fmi3.BINARY_FIX``)."""

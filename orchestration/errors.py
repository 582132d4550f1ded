"""Errors of the orchestrator: what failed, in which component, at which simulated time, and why."""
from __future__ import annotations

STATUS_NAMES = ("fmi3OK", "fmi3Warning", "fmi3Discard", "fmi3Error", "fmi3Fatal")


def status_name(status: int | None) -> str | None:
    if status is None:
        return None
    return STATUS_NAMES[status] if 0 <= status < len(STATUS_NAMES) else f"status {status}"


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

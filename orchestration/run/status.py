"""How a run ends: the one list of run statuses."""
from __future__ import annotations

from enum import StrEnum


class RunStatus(StrEnum):
    """A run's ``status`` in its summary (a string there, and equal to one here)."""

    #: the run reached its duration
    COMPLETED = "completed"
    #: an FMU asked to end the simulation (terminateSimulation); its results are complete up to then
    TERMINATED = "terminated"
    #: stopped by Ctrl-C or SIGTERM
    INTERRUPTED = "interrupted"
    #: a component failed, or results were lost (a write that failed, a writer that stopped answering)
    FAILED = "failed"

    @property
    def complete(self) -> bool:
        """Whether its results are complete (they replace the last complete run's)."""
        return self in COMPLETE


#: the statuses whose results are complete; a loss of results makes them FAILED
COMPLETE = (RunStatus.COMPLETED, RunStatus.TERMINATED)

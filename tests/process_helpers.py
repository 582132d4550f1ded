"""Which processes a run left behind: the members of its process group (a run started in a
session of its own has the group of its PID: the orchestrator, its workers, the resource tracker)."""
from __future__ import annotations

import time
from pathlib import Path


def _group(pgid: int):
    """(pid, name, command line) of each live process in the process group ``pgid``."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            name = (entry / "comm").read_text().strip()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[2]) == pgid and fields[0] != "Z":
            yield int(entry.name), name, cmdline


def group_members(pgid: int) -> list[str]:
    """Processes still in the run's process group (its workers, the writers, the resource tracker):
    ``"pid: [name] command line"``."""
    return [f"{pid}: [{name}] {cmdline[:120]}" for pid, name, cmdline in _group(pgid)]


def group_pids(pgid: int, name: str) -> list[int]:
    """The processes of group ``pgid`` named ``name`` (their comm: "row-writer", "surface-writer")."""
    return [pid for pid, comm, _ in _group(pgid) if comm == name]


def assert_no_process_left(pgid: int, grace: float = 5.0) -> None:
    deadline = time.monotonic() + grace
    while group_members(pgid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert group_members(pgid) == [], "processes of the run outlived it"

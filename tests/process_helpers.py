"""Which processes a run left behind: the members of its process group (a run started in a
session of its own has the group of its PID: the orchestrator, its workers, the resource tracker)."""
from __future__ import annotations

import time
from pathlib import Path


def group_members(pgid: int) -> list[str]:
    """Processes still in the run's process group (its workers, the writers, the resource tracker):
    ``"pid: [name] command line"``."""
    found = []
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
            found.append(f"{entry.name}: [{name}] {cmdline[:120]}")
    return found


def assert_no_process_left(pgid: int, grace: float = 5.0) -> None:
    deadline = time.monotonic() + grace
    while group_members(pgid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert group_members(pgid) == [], "processes of the run outlived it"

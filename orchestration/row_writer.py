"""CSV rows turned into text and written by a process of their own, beside the run.

The text of a row is the exact shortest ``repr`` of each float (so the values read back bit for
bit), and making it is most of what recording a row costs: about 0.7 us per value, 8-10 us per
row of the default scene's catheter and contact, two rows per millisecond of the 1 kHz loop
(about 7 % of its wall time). The recorder keeps the rows as float64 blocks instead and hands
each block, as bytes, to this process, which makes the text and appends it to the CSV file.

Nothing is lost: blocks are written in the order they were sent, always as whole lines;
:meth:`RowWriter.close` waits until every block is on disk, and a run's process that dies leaves
the writer to write what it was sent (:mod:`.helper_process`); a writer that dies (killed) leaves
the recorder to write the rows itself from then on, so only the rows the writer had taken and not
yet written are missing, and the run's summary says so. Unlike the surface writer it runs
at normal priority: the rows of a run that is still going reach the disk within the recorder's
flush interval (about 2 % of one CPU for the default scene).
"""
from __future__ import annotations

import os
from pathlib import Path

from .helper_process import HelperProcess, begin_helper, serve

#: The helper's name in messages; its process runs as "row-writer".
LABEL = "row writer"

_float_repr = float.__repr__  # exact shortest round-trip text


def format_rows(values: list[float], n_values: int) -> str:
    """The CSV text of rows of ``n_values`` floats given one after another: each row one line of
    the values' exact ``repr`` joined by commas, every line ending in a newline."""
    text = map(_float_repr, values)
    lines = [",".join(row) for row in zip(*[text] * n_values)]
    lines.append("")
    return "\n".join(lines)


def write_all(fd: int, data: bytes) -> None:
    """Write every byte: os.write may write less than asked (a full disk, signals)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


class RowWriter:
    """The writer process: ``add_stream`` once per CSV file (its header already written), ``write``
    per block of rows, ``close`` at the end.

    Validation stays with the caller (the recorder); errors of the writer itself (a full disk) are
    logged by it as they happen and returned by ``close``. ``write`` may block while the pipe is full:
    call it off the thread that must not wait (the recorder's flusher thread does).
    """

    label = LABEL

    def __init__(self):
        self._helper = HelperProcess(LABEL, _serve)

    @property
    def pid(self) -> int:
        return self._helper.pid

    def add_stream(self, name: str, path: Path, n_values: int) -> None:
        """Rows named ``name`` have ``n_values`` floats and are appended to ``path``."""
        self._helper.send(("stream", name, str(path), int(n_values)))

    def write(self, name: str, rows: bytes) -> bool:
        """Append whole rows (float64, native byte order, row after row) to stream ``name``; False
        when the writer is gone (the rows were not taken: write them some other way)."""
        return self._helper.send(("rows", name, rows))

    def close(self) -> list[str]:
        """Wait until every block sent is written; the writer's errors, if any. Idempotent."""
        return self._helper.close("row")


def _serve(conn) -> None:
    """The writer's loop: blocks in the order sent, until "close" or until the run's process is gone."""
    begin_helper(LABEL)
    streams: dict[str, tuple[int, int]] = {}  # name -> (fd, n_values)

    def handle(message: tuple) -> None:
        if message[0] == "stream":
            _, name, path, n_values = message
            streams[name] = (os.open(path, os.O_WRONLY | os.O_APPEND), n_values)
        else:
            _, name, rows = message
            fd, n_values = streams[name]
            write_all(fd, format_rows(memoryview(rows).cast("d").tolist(), n_values).encode("ascii"))

    try:
        serve(conn, LABEL, handle)
    finally:
        for fd, _ in streams.values():
            os.close(fd)

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

A block that cannot be written (a full volume, a read-only one, a file-size limit) leaves no part
of a row behind: the file is cut back to where the block began (:func:`append_lines`), the writer
tells the run at once which file, why and how many rows it keeps (a notice, see
:func:`~.helper_process.serve`), and writes nothing more to that file, so it stays a complete
prefix of the run's rows.
"""
from __future__ import annotations

import logging
import os
from pathlib import Path

from orchestration.observers.helper_process import HelperProcess, begin_helper, serve

#: The helper's name in messages; its process runs as "row-writer".
LABEL = "row writer"

_float_repr = float.__repr__  # exact shortest round-trip text

log = logging.getLogger(__name__)


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


def append_lines(fd: int, data: bytes) -> None:
    """Append ``data`` (whole lines) to the file open at ``fd``: all of it, or, when a write fails
    (OSError), none of it: the file is cut back to where it was, so that a full volume or a
    file-size limit (EFBIG) never leaves part of a row. A file that cannot be cut back (a
    read-only volume) keeps the part; readers skip a truncated last line."""
    start = os.lseek(fd, 0, os.SEEK_END)  # appended writes go to the end: this is where they begin
    try:
        write_all(fd, data)
    except OSError:
        try:
            os.ftruncate(fd, start)
        except OSError as exc:
            log.warning("could not cut a partly written block of rows back (%s): the file ends in a part of a row",
                        exc.strerror or exc)
        raise


class RowsNotWritten(Exception):
    """A block of rows was not written: an earlier block to the same file had failed."""


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

    @property
    def helper(self) -> HelperProcess:
        """The process: its deadline (``timeout``), its notices (``on_notice``, ``poll``)."""
        return self._helper


class _Stream:
    """One file the writer appends to, and what it has written there."""

    __slots__ = ("path", "fd", "n_values", "rows", "last_time", "failed")

    def __init__(self, path: str, fd: int, n_values: int):
        self.path = path
        self.fd = fd
        self.n_values = n_values
        self.rows = 0                    # rows this writer has appended
        self.last_time: float | None = None
        self.failed: str | None = None   # why nothing more is written to the file


def _serve(conn) -> None:
    """The writer's loop: blocks in the order sent, until "close" or until the run's process is gone."""
    begin_helper(LABEL)
    streams: dict[str, _Stream] = {}

    def handle(message: tuple) -> None:
        if message[0] == "stream":
            _, name, path, n_values = message
            try:
                fd = os.open(path, os.O_WRONLY | os.O_APPEND)
            except OSError as exc:
                streams[name] = stream = _Stream(path, -1, n_values)
                stream.failed = f"it could not be opened ({exc.strerror or exc})"
                exc.notice = _notice(stream, exc)
                raise
            streams[name] = _Stream(path, fd, n_values)
            return
        _, name, rows = message
        stream = streams[name]
        values = memoryview(rows).cast("d")
        count = len(values) // stream.n_values
        if stream.failed is not None:
            raise RowsNotWritten(f"{count} rows not written to {stream.path}: {stream.failed}")
        try:
            append_lines(stream.fd, format_rows(values.tolist(), stream.n_values).encode("ascii"))
        except OSError as exc:
            stream.failed = f"a write failed earlier ({exc.strerror or exc})"
            exc.notice = _notice(stream, exc)
            raise
        if count:
            stream.rows += count
            stream.last_time = values[(count - 1) * stream.n_values]

    try:
        serve(conn, LABEL, handle)
    finally:
        for stream in streams.values():
            if stream.fd >= 0:
                os.close(stream.fd)


def _notice(stream: _Stream, exc: OSError) -> dict:
    """What the run is told when a file cannot be written: which, why, and what it keeps."""
    return {"kind": "rows", "path": stream.path, "errno": exc.errno, "reason": exc.strerror or str(exc),
            "rows_kept": stream.rows, "last_time": stream.last_time}

"""Result recording: streamed CSV per component, VTU surface time series, run summary.

Rows go to disk as they are produced, each component at its own rate, so a run that fails or is
killed keeps everything up to that point:

* every stream is a CSV file ``<component>.csv`` with a quoted header row (``"time"`` first, array
  ports expanded to ``"name[0]"``, ``"name[1]"``, ...) and one unquoted row of floats per sample,
  written with ``repr`` so the values read back bit for bit;
* rows are collected in memory as float64 blocks and handed on at least every ``flush_interval``
  wall seconds (by a small background thread, so rows are not held back while the caller is busy
  elsewhere; without a row writer by the writing call too), always as whole lines, and at
  :meth:`Recorder.close`, which is also registered with :mod:`atexit`. With a ``row_writer``
  (:mod:`.row_writer`) a process of its own makes the text and writes it, so the 1 kHz loop only
  copies a row's floats (less than half the cost of making the text); without one, the flush writes the text itself;
* units are kept apart in ``units.json`` so the CSV header stays plain;
* a tissue surface is a series of ``.vtu`` files plus a ParaView collection ``<name>.pvd`` that is
  rewritten atomically after every frame, so a killed run still opens in ParaView; during a run a
  process of its own writes them (:mod:`.surface_writer`), so the 1 kHz loop does not wait 8 ms
  for each.

Results that cannot be kept are never passed over in silence. A write that fails (a full or
read-only volume, a file-size limit: EFBIG, with SIGXFSZ ignored) leaves whole rows only, and is
told to ``on_loss`` as soon as it is known (the master then ends the run: what it would compute
could not be kept); so is a results folder deleted under the run (looked at with every flush). At
:meth:`Recorder.close` the recorder checks what is on disk against what it was given, file by file
(rows counted where something went wrong, frames looked for), and lists in :attr:`Recorder.losses`
what is missing, where and why; each surface's ``.pvd`` then lists exactly the frames on disk, and
:attr:`Recorder.files` only files that exist.
"""
from __future__ import annotations

import atexit
import contextlib
import csv
import errno
import io
import json
import logging
import math
import os
import threading
import time as _time
from numbers import Real
from pathlib import Path

import numpy as np

from orchestration.errors import OrchestrationError
from orchestration.observers.row_writer import append_lines, format_rows, write_all
from orchestration.observers.surface_writer import write_frame, write_pvd

log = logging.getLogger(__name__)

#: Rows a stream's block holds at first (a fifth of a second at 1 kHz, the default flush interval).
_BLOCK_ROWS = 256


class RecordingError(ValueError):
    """A stream or surface series was declared or written inconsistently."""


class ResultsWriteError(OrchestrationError):
    """A result file could not be created or written (a full or read-only volume, no permission)."""


def io_problem(exc: OSError) -> str:
    """Why a write failed, and what to do about it, for messages: "No space left on device: free
    space on that volume or choose another --out"."""
    reason = exc.strerror or str(exc)
    hint = _IO_HINTS.get(exc.errno)
    return f"{reason}: {hint}" if hint else reason


_IO_HINTS = {
    errno.ENOSPC: "the volume is full; free space on it or choose another --out",
    errno.EDQUOT: "the disk quota is used up; free space or choose another --out",
    errno.EROFS: "the volume is read-only; choose an --out on a writable one",
    errno.EACCES: "no permission to write there; choose an --out you can write to",
    errno.EPERM: "no permission to write there; choose an --out you can write to",
    errno.EFBIG: "the file reached the file-size limit (ulimit -f); raise the limit or record less",
    errno.ENOENT: "the folder is gone (deleted during the run?)",
}


def _atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` so readers see either the old or the new file, never half of one."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8", newline="\n") as handle:
            handle.write(text)  # no fsync: this guards against the process dying, not the machine
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):  # a full volume: leave no half-written temporary file
            os.unlink(tmp)
        raise


def _column_names(name: str, size: int) -> list[str]:
    return [name] if size == 1 else [f"{name}[{i}]" for i in range(size)]


class _Stream:
    """One component's CSV file: fixed port list, the rows not yet handed on (a float64 block)."""

    __slots__ = ("component", "path", "ports", "columns", "n_values", "fd", "rows", "filled", "handed", "failed",
                 "cause")

    def __init__(self, component: str, path: Path, ports: list[tuple[str, int]], fd: int):
        self.component = component
        self.path = path
        self.ports = ports
        self.n_values = 1 + sum(size for _, size in ports)  # time + values
        #: (port name, its columns in a row, their number)
        self.columns: list[tuple[str, slice, int]] = []
        start = 1
        for name, size in ports:
            self.columns.append((name, slice(start, start + size), size))
            start += size
        self.fd = fd
        self.rows = np.empty((_BLOCK_ROWS, self.n_values))
        self.filled = 0
        #: rows handed on (to the writer process or the file): the rows the file should hold
        self.handed = 0
        #: a write of this process failed: nothing more is written to the file (it stays a prefix)
        self.failed = False
        #: why rows of this file may be missing (checked at close), None while nothing went wrong
        self.cause: str | None = None

    def advance(self) -> None:
        """The row at ``filled`` is complete; the block doubles when full (the rows come faster
        than the flushes)."""
        self.filled += 1
        if self.filled == len(self.rows):
            self._double()

    def reserve(self, rows: int) -> np.ndarray:
        """The next ``rows`` rows of the block (to be filled, then counted with ``filled += rows``);
        the block doubles until a row stays free after them."""
        while self.filled + rows >= len(self.rows):
            self._double()
        return self.rows[self.filled:self.filled + rows]

    def _double(self) -> None:
        self.rows = np.concatenate([self.rows, np.empty_like(self.rows)])

    def take(self) -> np.ndarray | None:
        """The filled rows (a copy), the block emptied; None when there are none."""
        if not self.filled:
            return None
        rows = self.rows[:self.filled].copy()
        self.filled = 0
        return rows


class Recorder:
    """Streams component results, surface frames and units to ``out_dir`` as they are produced.

    The master owns one recorder per run: ``add_stream`` once per recorded component (before the
    first ``write``), then ``write`` every time that component produces outputs; ``close`` at the
    end (idempotent; also runs at interpreter exit so an exception in the caller still leaves
    complete rows on disk). Not meant to be shared between processes.
    """

    def __init__(self, out_dir: Path | str, flush_interval: float = 0.2, surface_writer=None, row_writer=None):
        if not (isinstance(flush_interval, Real) and math.isfinite(flush_interval) and flush_interval > 0):
            raise RecordingError(f"flush_interval must be a finite number of seconds > 0 (got {flush_interval!r}): "
                                 "e.g. 0.2 hands rows to the OS five times per second")
        self.out_dir = Path(out_dir)
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            folder = os.stat(self.out_dir)
        except OSError as exc:
            raise ResultsWriteError(f"cannot create the results folder {self.out_dir} ({io_problem(exc)})") from None
        #: the folder's identity: a folder deleted (or replaced) under the run is noticed by it
        self._folder_id = (folder.st_dev, folder.st_ino)
        self.flush_interval = float(flush_interval)
        self._streams: dict[str, _Stream] = {}
        self._units: dict[str, dict[str, str]] = {}
        self._surfaces: dict[str, dict] = {}
        self._files: dict[str, Path] = {}
        self._lock = threading.Lock()  # the flusher thread and the writer share the row blocks
        self._flush_lock = threading.Lock()  # one flush at a time: blocks reach the file in order
        self._next_flush = _time.monotonic() + self.flush_interval
        self._closed = False
        self._pid = os.getpid()  # a forked child must not flush (duplicate) the parent's pending rows
        self._stop = threading.Event()
        #: a SurfaceWriter (orchestration/surface_writer.py): surface frames go to its process, which
        #: this recorder closes; None: write_surface writes the frame before it returns
        self._surface_writer = surface_writer
        #: what the writer process could not write (set by close)
        self.surface_errors: list[str] = []
        #: a RowWriter (orchestration/row_writer.py): row blocks go to its process as bytes, which this
        #: recorder closes; None: the flush writes the text itself
        self._row_writer = row_writer
        #: what the row writer process could not write (set by close, or when it is gone)
        self.row_errors: list[str] = []
        #: called once, with a sentence, when results are first found lost during the run (a write
        #: failed, the folder was deleted); from the thread that finds it: set flags only
        self.on_loss = None
        #: what was lost, one sentence per file or cause (set by close); [] when everything is on disk
        self.losses: list[str] = []
        self._loss_lock = threading.Lock()
        self._first_loss: str | None = None
        self._folder_gone = False
        #: per surface: why frames may be missing (a frame could not be written, the writer died)
        self._surface_causes: dict[str, str] = {}
        # The writers' notices: a file they could not write, as it happens.
        for writer, handler in ((surface_writer, self._surface_notice), (row_writer, self._row_notice)):
            helper = getattr(writer, "helper", None)
            if helper is not None:
                helper.on_notice = handler
        self._closed_files = False
        self._flusher = threading.Thread(target=self._flush_periodically, name="recorder-flush", daemon=True)
        self._flusher.start()
        atexit.register(self.close)

    # ------------------------------------------------------------------ CSV streams
    def add_stream(self, component: str, columns: list[tuple[str, int, str | None]]) -> Path:
        """Declare ``component``'s recorded ports as ``(port name, size, unit)``; writes the header at once."""
        self._check_open("add_stream")
        if not isinstance(component, str) or not component or any(c in component for c in '/\\\0'):
            raise RecordingError(f"component must be a non-empty name usable as a file name (got {component!r})")
        if component in self._streams:
            raise RecordingError(f"stream {component!r} is already declared: declare each component once")
        if component in self._surfaces or component == "units" or f"{component}.csv" in self._taken_names():
            raise RecordingError(f"stream name {component!r} clashes with another recorded file: rename it")
        ports: list[tuple[str, int]] = []
        header = ["time"]
        units: dict[str, str] = {"time": "s"}
        for entry in columns:
            try:
                name, size, unit = entry
            except (TypeError, ValueError):
                raise RecordingError(f"{component}: column entries are (port name, size, unit) tuples (got {entry!r})")
            if not isinstance(name, str) or not name or name == "time" or "[" in name:
                raise RecordingError(f"{component}: port name {name!r} is not usable as a column: give the port's "
                                     "name without brackets ('time' is reserved for the first column)")
            if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
                raise RecordingError(f"{component}.{name}: size must be an integer >= 1 (got {size!r})")
            if any(name == p for p, _ in ports):
                raise RecordingError(f"{component}: port {name!r} is listed twice")
            if unit is not None and not isinstance(unit, str):
                raise RecordingError(f"{component}.{name}: unit must be a string or None (got {unit!r})")
            ports.append((name, int(size)))
            names = _column_names(name, int(size))
            header.extend(names)
            if unit:
                units.update(dict.fromkeys(names, unit))
        path = self.out_dir / f"{component}.csv"
        head = io.StringIO()
        csv.writer(head, quoting=csv.QUOTE_NONNUMERIC, lineterminator="\n").writerow(header)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        except OSError as exc:
            raise ResultsWriteError(f"cannot create {path} ({io_problem(exc)})") from None
        try:
            write_all(fd, head.getvalue().encode("utf-8"))
        except OSError as exc:
            os.close(fd)
            raise ResultsWriteError(f"cannot write the header of {path} ({io_problem(exc)})") from None
        stream = self._streams[component] = _Stream(component, path, ports, fd)
        if self._row_writer is not None:  # the writer process appends the rows
            os.close(fd)
            stream.fd = -1
            self._row_writer.add_stream(component, path, stream.n_values)
        self._files[component] = path
        self._units[component] = units
        units_path = self.out_dir / "units.json"
        try:
            _atomic_write_text(units_path, json.dumps(self._units, indent=1, sort_keys=True) + "\n")
        except OSError as exc:
            raise ResultsWriteError(f"cannot write {units_path} ({io_problem(exc)})") from None
        self._files["units"] = units_path
        log.debug("recording %s: %d columns -> %s", component, len(header), path)
        return path

    def write(self, component: str, time: float, values: dict[str, np.ndarray]) -> None:
        """Append one row: ``time`` then every declared port's values (float64 arrays of the declared size)."""
        # Hot path (called at up to 1 kHz per stream): copy the floats into the stream's block;
        # anything unusual drops to _write_slow, which converts or explains the error.
        if self._closed:
            self._check_open("write")
        try:
            stream = self._streams[component]
            with self._lock:
                row = stream.rows[stream.filled]
                row[0] = time
                for name, columns, size in stream.columns:
                    value = values[name]
                    if value.size != size:  # a single value would fill every column
                        raise ValueError
                    row[columns] = value
                stream.advance()
        except (KeyError, TypeError, ValueError, AttributeError):
            self._write_slow(component, time, values)
        if self._row_writer is None and _time.monotonic() >= self._next_flush:
            self.flush()

    def write_rows(self, component: str, times: np.ndarray, values: dict[str, np.ndarray]) -> None:
        """Append ``len(times)`` rows at once: ``values[port]`` holds one row of the port's values per
        time (a 2-D array). The same rows as ``write`` called for each time."""
        if self._closed:
            self._check_open("write_rows")
        stream = self._streams.get(component)
        try:
            with self._lock:
                block = stream.reserve(len(times))
                for name, columns, size in stream.columns:
                    value = values[name]
                    if value.shape != (len(times), size):
                        raise ValueError
                    block[:, columns] = value
                block[:, 0] = times
                stream.filled += len(times)
        except (KeyError, TypeError, ValueError, AttributeError):  # write explains what is wrong
            for i, time in enumerate(times):
                self.write(component, float(time), {name: np.asarray(v)[i] for name, v in values.items()})
            return
        if self._row_writer is None and _time.monotonic() >= self._next_flush:
            self.flush()

    def _write_slow(self, component, time, values) -> None:
        self._check_open("write")
        stream = self._streams.get(component)
        if stream is None:
            raise RecordingError(f"no stream {component!r}: call add_stream({component!r}, columns) before write "
                                 f"(declared: {sorted(self._streams)})")
        try:
            row = [float(time)]
        except (TypeError, ValueError):
            raise RecordingError(f"{component}: time must be a number of seconds (got {time!r})") from None
        for name, size in stream.ports:
            if name not in values:
                raise RecordingError(f"{component} at t = {row[0]!r}: no value for recorded port {name!r}; "
                                     f"got {sorted(values)}")
            try:
                arr = np.asarray(values[name], dtype=np.float64).ravel()
            except (TypeError, ValueError):
                raise RecordingError(f"{component}.{name} at t = {row[0]!r}: value is not numeric "
                                     f"({type(values[name]).__name__})") from None
            if arr.size != size:
                raise RecordingError(f"{component}.{name} at t = {row[0]!r}: expected {size} values, got {arr.size}; "
                                     "the port size must match the one given to add_stream")
            row.extend(arr.tolist())
        with self._lock:
            stream.rows[stream.filled] = row
            stream.advance()

    # ------------------------------------------------------------------ surfaces
    def add_surface_series(self, name: str, triangles: np.ndarray) -> Path:
        """Declare a surface time series with fixed ``(m, 3)`` triangle connectivity; returns the ``.pvd`` path."""
        self._check_open("add_surface_series")
        if not isinstance(name, str) or not name or any(c in name for c in '/\\\0'):
            raise RecordingError(f"surface name must be a non-empty name usable as a file name (got {name!r})")
        taken = self._taken_names()
        if name in self._surfaces or name in self._streams or name == "units" or name in taken \
                or f"{name}.pvd" in taken:
            raise RecordingError(f"surface series {name!r} clashes with another recorded file (its {name}.pvd or its "
                                 f"frame folder {name}/): rename it")
        tri = np.asarray(triangles)
        if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] == 0 or not np.issubdtype(tri.dtype, np.integer):
            raise RecordingError(f"surface {name!r}: triangles must be a non-empty (m, 3) integer array "
                                 f"(got shape {tri.shape}, dtype {tri.dtype})")
        if tri.min() < 0:
            raise RecordingError(f"surface {name!r}: triangle vertex indices must be >= 0 (got {int(tri.min())})")
        frame_dir = self.out_dir / name
        pvd = self.out_dir / f"{name}.pvd"
        try:
            frame_dir.mkdir(exist_ok=True)
            write_pvd(pvd, self.out_dir, [])
        except OSError as exc:
            raise ResultsWriteError(f"cannot create the surface series {pvd} ({io_problem(exc)})") from None
        triangles = np.ascontiguousarray(tri, dtype=np.int64)
        # "given": frames handed in (each must be on disk at the end), "frames": those in the .pvd
        self._surfaces[name] = {"triangles": triangles, "frames": [], "dir": frame_dir, "pvd": pvd, "given": 0}
        if self._surface_writer is not None:
            self._surface_writer.add_series(name, triangles, pvd)
        self._files[name] = pvd
        return pvd

    def _taken_names(self) -> set[str]:
        """The names in ``out_dir`` this recorder writes (and the run's summary.json): one writer each."""
        return ({"summary.json", "units.json"} | {stream.path.name for stream in self._streams.values()}
                | {f"{name}.pvd" for name in self._surfaces} | set(self._surfaces))

    def write_surface(self, name: str, time: float, positions: np.ndarray,
                      point_data: dict[str, np.ndarray] | None = None) -> None:
        """Write one frame ``<name>/<name>_NNNNN.vtu`` and rewrite ``<name>.pvd`` to list it (with a
        ``surface_writer``, by its process: on disk by ``close``)."""
        self._check_open("write_surface")
        series = self._surfaces.get(name)
        if series is None:
            raise RecordingError(f"no surface series {name!r}: call add_surface_series first "
                                 f"(declared: {sorted(self._surfaces)})")
        t = float(time)
        if not math.isfinite(t):
            raise RecordingError(f"surface {name!r}: time must be finite (got {time!r})")
        pts = np.asarray(positions, dtype=np.float64)
        if pts.ndim == 1 and pts.size % 3 == 0:
            pts = pts.reshape(-1, 3)  # flat port layout x0, y0, z0, x1, ...
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise RecordingError(f"surface {name!r} at t = {t!r}: positions must be (n, 3) or flat 3n "
                                 f"(got shape {np.shape(positions)})")
        tri = series["triangles"]
        if int(tri.max()) >= pts.shape[0]:
            raise RecordingError(f"surface {name!r} at t = {t!r}: triangles index vertex {int(tri.max())} "
                                 f"but only {pts.shape[0]} positions were given")
        data = {}
        for key, value in (point_data or {}).items():
            arr = np.asarray(value, dtype=np.float64)
            if arr.ndim == 1 and arr.size == 3 * pts.shape[0] and arr.size != pts.shape[0]:
                arr = arr.reshape(-1, 3)
            if arr.shape not in ((pts.shape[0],), (pts.shape[0], 3)):
                raise RecordingError(f"surface {name!r} point data {key!r}: expected shape ({pts.shape[0]},) or "
                                     f"({pts.shape[0]}, 3), got {arr.shape}")
            data[key] = arr
        index = len(series["frames"])
        frame = series["dir"] / f"{name}_{index:05d}.vtu"
        series["given"] += 1
        if self._surface_writer is not None:
            # a copy: the caller's arrays are views of buffers its next step overwrites
            self._surface_writer.write(name, frame, t, np.array(pts), {k: np.array(v) for k, v in data.items()})
            series["frames"].append((t, frame))
        else:
            try:
                write_frame(frame, series["pvd"], self.out_dir, series["frames"], t, pts, tri, data)
            except OSError as exc:
                self._surface_causes.setdefault(name, io_problem(exc))
                self._lost_now(f"{frame} could not be written ({io_problem(exc)})")
                raise ResultsWriteError(f"surface {name!r} at t = {t!r}: cannot write {frame} "
                                        f"({io_problem(exc)})") from None
        self._files[f"{name}[{index}]"] = frame

    # ------------------------------------------------------------------ flushing and closing
    def flush(self) -> None:
        """Hand every row collected so far on (whole lines only): to the row writer, or to the OS.

        Never raises for a write that fails: the file keeps its whole rows, nothing more is written
        to it, and the loss is told to ``on_loss`` and listed by close()."""
        with self._flush_lock:
            with self._lock:  # only to take the blocks: the text is made while the writer goes on
                self._next_flush = _time.monotonic() + self.flush_interval
                taken = [(stream, rows) for stream in self._streams.values()
                         if (rows := stream.take()) is not None]
            for stream, rows in taken:
                stream.handed += len(rows)
                if self._row_writer is not None:
                    if self._row_writer.write(stream.component, rows.tobytes()):
                        continue
                    self._lose_row_writer()
                if stream.failed or self._closed_files:
                    continue
                try:
                    if stream.fd < 0:  # the row writer had it
                        stream.fd = os.open(stream.path, os.O_WRONLY | os.O_APPEND)
                    append_lines(stream.fd, format_rows(rows.ravel().tolist(), stream.n_values).encode("ascii"))
                except OSError as exc:
                    stream.failed = True
                    stream.cause = stream.cause or io_problem(exc)
                    self._lost_now(f"{stream.path} could not be written ({io_problem(exc)})")

    def _lose_row_writer(self) -> None:
        """The row writer process is gone (killed): this process writes the rows from now on, so
        only those the writer had taken and not yet written are missing (close() reports it)."""
        writer, self._row_writer = self._row_writer, None
        self.row_errors = writer.close()
        self.row_errors.append("the run's own process wrote the rows from then on")
        for error in self.row_errors:
            log.error("CSV rows: %s", error)
        how = writer.helper.exit_description() if hasattr(writer, "helper") else "it ended"
        for stream in self._streams.values():
            stream.cause = stream.cause or f"the row writer process ended ({how}) with rows it had not written"
            # A writer killed while writing a block leaves part of a row: the rows appended from
            # now on start on a line of their own.
            try:
                _cut_to_whole_lines(stream.path)
            except OSError as exc:
                log.warning("%s: could not cut a part of a row off its end (%s)", stream.path, exc.strerror or exc)

    def _row_notice(self, notice: dict) -> None:
        """The row writer could not write a stream's rows (its first error for that stream)."""
        name, reason = notice.get("name"), _notice_reason(notice)
        stream = self._streams.get(name)
        if stream is not None:
            stream.cause = stream.cause or reason
        path = notice.get("path") or name
        if "rows_kept" in notice:
            kept, last = notice["rows_kept"], notice.get("last_time")
            upto = f", up to t = {last:.6g} s" if kept and last is not None else ""
            self._lost_now(f"{path} could not be written ({reason}); it keeps {kept} rows{upto}")
        else:
            self._lost_now(f"rows of {path} could not be written ({reason})")

    def _surface_notice(self, notice: dict) -> None:
        """A surface frame could not be written (the first error of that surface)."""
        name, reason = notice.get("name"), _notice_reason(notice)
        self._surface_causes.setdefault(name, reason)
        kept = f"; {name}.pvd keeps {notice['frames_kept']} frames" if "frames_kept" in notice else ""
        self._lost_now(f"{notice.get('path') or name} could not be written ({reason}){kept}")

    def _lost_now(self, text: str) -> None:
        """Results were lost while the run goes on: tell ``on_loss`` (once)."""
        with self._loss_lock:
            if self._first_loss is not None:
                return
            self._first_loss = text
        log.error("results lost: %s", text)
        if self.on_loss is not None:
            try:
                self.on_loss(text)
            except Exception:  # never cost the recording: the loss is listed at close anyway
                log.exception("recorder: on_loss failed")

    def _check_folder(self) -> None:
        """A results folder deleted or replaced under the run: the files written into it are gone."""
        if self._folder_gone:
            return
        try:
            folder = os.stat(self.out_dir)
            if (folder.st_dev, folder.st_ino) == self._folder_id:
                return
        except FileNotFoundError:
            pass
        except OSError:  # cannot look (a volume gone away): the writes will say what they find
            return
        self._folder_gone = True
        self._lost_now(f"the results folder {self.out_dir} was deleted (or replaced) during the run: the files "
                       "written into it are gone")

    def _flush_periodically(self) -> None:
        while not self._stop.wait(self.flush_interval / 2):
            try:
                self._check_folder()
                self.flush()
                for writer in (self._row_writer, self._surface_writer):
                    helper = getattr(writer, "helper", None)
                    if helper is not None:
                        helper.poll()  # notices of a writer that is not being sent anything now
            except Exception:  # the flusher must go on: close() flushes and reports again
                log.exception("recorder: periodic flush failed")

    def close(self) -> None:
        """Flush and close every file, wait for the writer processes, then check what is on disk
        (:attr:`losses`); safe to call more than once, never raises for a file that cannot be written."""
        if self._closed:
            return
        self._closed = True
        if os.getpid() != self._pid:
            return
        self._stop.set()
        if self._flusher.is_alive() and self._flusher is not threading.current_thread():
            self._flusher.join(timeout=5)
        try:
            self._check_folder()
            self.flush()
        finally:
            with self._lock:
                self._closed_files = True
                for stream in self._streams.values():
                    if stream.fd >= 0:
                        with contextlib.suppress(OSError):
                            os.close(stream.fd)
                        stream.fd = -1
            if self._row_writer is not None:
                self.row_errors = self._row_writer.close()
                for error in self.row_errors:
                    log.error("CSV rows: %s", error)
                if self.row_errors:
                    for stream in self._streams.values():
                        stream.cause = stream.cause or self.row_errors[0]
            if self._surface_writer is not None:
                self.surface_errors = self._surface_writer.close()
                for error in self.surface_errors:
                    log.error("surface frames: %s", error)
                if self.surface_errors:
                    for name in self._surfaces:
                        self._surface_causes.setdefault(name, self.surface_errors[0])
            atexit.unregister(self.close)
            try:
                self.losses = self._check_files()
            except Exception as exc:  # a check that fails must not hide the results it could not check
                log.exception("recorder: checking the files failed")
                self.losses = [f"the result files could not be checked ({type(exc).__name__}: {exc})"]
            for loss in self.losses:
                log.error("results lost: %s", loss)

    def _check_files(self) -> list[str]:
        """What is missing on disk of what the recorder was given, one sentence per file; the files
        that are gone are taken off :attr:`files`, each ``.pvd`` made to list the frames on disk."""
        losses = []
        gone = [label for label, path in self._files.items() if not label.endswith("]") and not path.exists()]
        if self._folder_gone or not self.out_dir.is_dir():
            names = ", ".join(self._files[label].name for label in gone) or "nothing else"
            losses.append(f"the results folder {self.out_dir} was deleted (or replaced) during the run; gone: {names}")
        elif gone:
            losses.append("gone from the results folder during the run: "
                          + ", ".join(str(self._files[label]) for label in gone))
        for label in gone:
            del self._files[label]
        for stream in self._streams.values():
            if stream.cause is None or stream.component in gone:
                continue
            kept, last = _count_rows(stream.path)
            if kept < stream.handed:
                upto = f" (the last at t = {last:.6g} s)" if last is not None else ""
                losses.append(f"{stream.path} keeps {kept} of {stream.handed} rows{upto}: {stream.cause}")
        for name, series in self._surfaces.items():
            present = []
            for index, (t, frame) in enumerate(series["frames"]):
                if frame.exists():
                    present.append((t, frame))
                else:
                    self._files.pop(f"{name}[{index}]", None)
            missing = series["given"] - len(present)
            if name in gone or (not missing and name not in self._surface_causes):
                continue
            try:
                write_pvd(series["pvd"], self.out_dir, present)  # lists exactly the frames on disk
            except OSError as exc:
                losses.append(f"{series['pvd']} could not be rewritten to list the frames on disk ({io_problem(exc)})")
            if missing:
                cause = self._surface_causes.get(name, "frames could not be written")
                losses.append(f"{series['pvd']} lists {len(present)} of {series['given']} frames, {missing} could "
                              f"not be written: {cause}")
        return losses

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _check_open(self, call: str) -> None:
        if self._closed:
            raise RecordingError(f"Recorder.{call}: the recorder for {self.out_dir} is closed")

    @property
    def files(self) -> dict[str, Path]:
        """Every file written so far, by label.

        Labels: the component name (its CSV), ``units``, the surface name (its .pvd), ``name[i]`` (frame i).
        """
        return dict(self._files)


def _notice_reason(notice: dict) -> str:
    """Why a writer process could not write, from its notice (see helper_process.serve)."""
    if notice.get("errno") is not None and notice.get("reason"):
        return io_problem(OSError(notice["errno"], notice["reason"]))
    return notice.get("reason") or notice.get("error") or "unknown error"


def _count_rows(path: Path) -> tuple[int, float | None]:
    """The complete rows of a recorded CSV (lines after the header ending in a newline) and the
    time of the last one; (0, None) for a file that is gone or holds no row."""
    try:
        with open(path, "rb") as handle:
            lines, tail = 0, b""
            while chunk := handle.read(1 << 20):
                lines += chunk.count(b"\n")
                tail = (tail + chunk)[-(1 << 20):]  # the last two lines, unless a row is longer than this
    except OSError:
        return 0, None
    rows = max(0, lines - 1)
    if not rows:
        return 0, None
    complete = tail[:tail.rfind(b"\n")]
    start = complete.rfind(b"\n")
    if start < 0:  # the last row began before the tail: its time is not in it
        return rows, None
    try:
        return rows, float(complete[start + 1:].split(b",", 1)[0])
    except ValueError:
        return rows, None


def _cut_to_whole_lines(path: Path) -> None:
    """Cut a file back to the end of its last complete line (a writer killed mid-row)."""
    with open(path, "rb+") as handle:
        end = handle.seek(0, os.SEEK_END)
        pos = end
        while pos > 0:
            start = max(0, pos - (1 << 16))
            handle.seek(start)
            chunk = handle.read(pos - start)
            newline = chunk.rfind(b"\n")
            if newline >= 0:
                if start + newline + 1 != end:
                    handle.truncate(start + newline + 1)
                return
            pos = start


# ---------------------------------------------------------------------- reading back
def read_stream(path: Path | str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Time array and ``{column: values}`` from a recorded CSV.

    A truncated last line (the run was killed while writing it) is skipped; a malformed line in the
    middle is skipped with a warning.
    """
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    end = text.rfind("\n")
    if end < 0:
        raise RecordingError(f"{path}: no complete header line; the file is empty or was cut before the header")
    if end != len(text) - 1:
        log.info("%s: skipping truncated last line (%d characters)", path, len(text) - 1 - end)
    text = text[:end + 1]
    first = text.index("\n")
    header = next(csv.reader([text[:first]]))
    if not header or header[0] != "time":
        raise RecordingError(f"{path}: not a recorded stream (first column is {header[:1]}, expected 'time')")
    body = text[first + 1:]
    n = len(header)
    if body:
        try:
            data = np.loadtxt(io.StringIO(body), delimiter=",", dtype=np.float64, ndmin=2)
            if data.shape[1] != n:
                raise ValueError
        except ValueError:
            data = _parse_rows_leniently(path, body, n)
    else:
        data = np.empty((0, n))
    return data[:, 0].copy(), {name: data[:, i].copy() for i, name in enumerate(header[1:], start=1)}


def _parse_rows_leniently(path: Path, body: str, n: int) -> np.ndarray:
    rows = []
    for number, line in enumerate(body.splitlines(), start=2):
        fields = line.split(",")
        try:
            if len(fields) != n:
                raise ValueError(f"{len(fields)} fields, expected {n}")
            rows.append([float(x) for x in fields])
        except ValueError as exc:
            log.warning("%s line %d skipped: %s", path, number, exc)
    return np.array(rows, dtype=np.float64).reshape(-1, n)


def port_values(columns: dict[str, np.ndarray], port: str) -> np.ndarray:
    """A port's samples as ``(n_rows, size)``: the column itself, or ``port[0]``, ``port[1]``, ... stacked."""
    if port in columns:
        return columns[port][:, None]
    parts = []
    while f"{port}[{len(parts)}]" in columns:
        parts.append(columns[f"{port}[{len(parts)}]"])
    if not parts:
        raise KeyError(port)
    return np.column_stack(parts)


# ---------------------------------------------------------------------- summary
def _to_json(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"summary value of type {type(value).__name__} is not JSON serialisable")


#: Room kept for the summary from the start of a run (a summary is a few KB).
SUMMARY_RESERVE_BYTES = 64 * 1024


def reserve_summary_space(out_dir: Path | str) -> None:
    """Keep room for ``summary.json`` on the results volume from the start of a run: its temporary
    file (the one :func:`write_summary` writes it into, then renames) is created now with its space
    allocated, so that a volume the run's rows fill up still takes the summary that says so (the
    write truncates the file and reuses its space). Best effort: a volume that cannot reserve is
    told at the end, when the summary is written."""
    tmp = Path(out_dir) / ".summary.json.tmp"
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    except OSError as exc:
        log.debug("no room reserved for the summary in %s: %s", out_dir, exc)
        return
    try:
        os.posix_fallocate(fd, 0, SUMMARY_RESERVE_BYTES)
    except (OSError, AttributeError) as exc:
        log.debug("no room reserved for the summary in %s: %s", out_dir, exc)
    finally:
        os.close(fd)


def write_summary(out_dir: Path | str, summary: dict) -> Path:
    """Save ``summary`` as ``out_dir/summary.json`` (atomically; numpy values become plain numbers;
    into the room :func:`reserve_summary_space` kept, if it did)."""
    if not isinstance(summary, dict):
        raise RecordingError(f"summary must be a dict (got {type(summary).__name__})")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "summary.json"
    _atomic_write_text(path, json.dumps(summary, indent=2, default=_to_json) + "\n")
    return path

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
  copies a row's floats (3-5 us instead of 8-12); without one, the flush writes the text itself;
* units are kept apart in ``units.json`` so the CSV header stays plain;
* a tissue surface is a series of ``.vtu`` files plus a ParaView collection ``<name>.pvd`` that is
  rewritten atomically after every frame, so a killed run still opens in ParaView; during a run a
  process of its own writes them (:mod:`.surface_writer`), so the 1 kHz loop does not wait 8 ms
  for each.
"""
from __future__ import annotations

import atexit
import csv
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

from .row_writer import format_rows, write_all
from .surface_writer import write_frame, write_pvd

log = logging.getLogger(__name__)

#: Rows a stream's block holds at first (a fifth of a second at 1 kHz, the default flush interval).
_BLOCK_ROWS = 256


class RecordingError(ValueError):
    """A stream or surface series was declared or written inconsistently."""


def _atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` so readers see either the old or the new file, never half of one."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", encoding="utf-8", newline="\n") as handle:
        handle.write(text)  # no fsync: this guards against the process dying, not the machine
    os.replace(tmp, path)


def _column_names(name: str, size: int) -> list[str]:
    return [name] if size == 1 else [f"{name}[{i}]" for i in range(size)]


class _Stream:
    """One component's CSV file: fixed port list, the rows not yet handed on (a float64 block)."""

    __slots__ = ("component", "path", "ports", "columns", "n_values", "fd", "rows", "filled")

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
        self.out_dir.mkdir(parents=True, exist_ok=True)
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
        if component in self._surfaces or component == "units":
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
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        write_all(fd, head.getvalue().encode("utf-8"))
        stream = self._streams[component] = _Stream(component, path, ports, fd)
        if self._row_writer is not None:  # the writer process appends the rows
            os.close(fd)
            stream.fd = -1
            self._row_writer.add_stream(component, path, stream.n_values)
        self._files[component] = path
        self._units[component] = units
        units_path = self.out_dir / "units.json"
        _atomic_write_text(units_path, json.dumps(self._units, indent=1, sort_keys=True) + "\n")
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
        if name in self._surfaces or name in self._streams or name == "units":
            raise RecordingError(f"surface series {name!r} clashes with another recorded file: rename it")
        tri = np.asarray(triangles)
        if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] == 0 or not np.issubdtype(tri.dtype, np.integer):
            raise RecordingError(f"surface {name!r}: triangles must be a non-empty (m, 3) integer array "
                                 f"(got shape {tri.shape}, dtype {tri.dtype})")
        if tri.min() < 0:
            raise RecordingError(f"surface {name!r}: triangle vertex indices must be >= 0 (got {int(tri.min())})")
        frame_dir = self.out_dir / name
        frame_dir.mkdir(exist_ok=True)
        pvd = self.out_dir / f"{name}.pvd"
        triangles = np.ascontiguousarray(tri, dtype=np.int64)
        self._surfaces[name] = {"triangles": triangles, "frames": [], "dir": frame_dir, "pvd": pvd}
        write_pvd(pvd, self.out_dir, [])
        if self._surface_writer is not None:
            self._surface_writer.add_series(name, triangles, pvd)
        self._files[name] = pvd
        return pvd

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
        if self._surface_writer is not None:
            # a copy: the caller's arrays are views of buffers its next step overwrites
            self._surface_writer.write(name, frame, t, np.array(pts), {k: np.array(v) for k, v in data.items()})
            series["frames"].append((t, frame))
        else:
            write_frame(frame, series["pvd"], self.out_dir, series["frames"], t, pts, tri, data)
        self._files[f"{name}[{index}]"] = frame

    # ------------------------------------------------------------------ flushing and closing
    def flush(self) -> None:
        """Hand every row collected so far on (whole lines only): to the row writer, or to the OS."""
        with self._flush_lock:
            with self._lock:  # only to take the blocks: the text is made while the writer goes on
                self._next_flush = _time.monotonic() + self.flush_interval
                taken = [(stream, rows) for stream in self._streams.values()
                         if (rows := stream.take()) is not None]
            for stream, rows in taken:
                if self._row_writer is not None:
                    if self._row_writer.write(stream.component, rows.tobytes()):
                        continue
                    self._lose_row_writer()
                if stream.fd < 0 and not self._closed_files:  # the row writer had it
                    stream.fd = os.open(stream.path, os.O_WRONLY | os.O_APPEND)
                if stream.fd >= 0:
                    write_all(stream.fd, format_rows(rows.ravel().tolist(), stream.n_values).encode("ascii"))

    def _lose_row_writer(self) -> None:
        """The row writer process is gone (killed): this process writes the rows from now on, so
        only those the writer had taken and not yet written are missing (close() reports it)."""
        writer, self._row_writer = self._row_writer, None
        self.row_errors = writer.close()
        self.row_errors.append("the run's own process wrote the rows from then on")
        for error in self.row_errors:
            log.error("CSV rows: %s", error)

    def _flush_periodically(self) -> None:
        while not self._stop.wait(self.flush_interval / 2):
            try:
                self.flush()
            except OSError as exc:  # e.g. disk full; the writer's own flush will raise it to the caller
                log.error("recorder: periodic flush failed: %s", exc)

    def close(self) -> None:
        """Flush and close every file; safe to call more than once."""
        if self._closed:
            return
        self._closed = True
        if os.getpid() != self._pid:
            return
        self._stop.set()
        if self._flusher.is_alive() and self._flusher is not threading.current_thread():
            self._flusher.join(timeout=5)
        try:
            self.flush()
        finally:
            with self._lock:
                self._closed_files = True
                for stream in self._streams.values():
                    if stream.fd >= 0:
                        os.close(stream.fd)
                        stream.fd = -1
            if self._row_writer is not None:
                self.row_errors = self._row_writer.close()
                for error in self.row_errors:
                    log.error("CSV rows: %s", error)
            if self._surface_writer is not None:
                self.surface_errors = self._surface_writer.close()
                for error in self.surface_errors:
                    log.error("surface frames: %s", error)
            atexit.unregister(self.close)

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


def write_summary(out_dir: Path | str, summary: dict) -> Path:
    """Save ``summary`` as ``out_dir/summary.json`` (atomically; numpy values become plain numbers)."""
    if not isinstance(summary, dict):
        raise RecordingError(f"summary must be a dict (got {type(summary).__name__})")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "summary.json"
    _atomic_write_text(path, json.dumps(summary, indent=2, default=_to_json) + "\n")
    return path

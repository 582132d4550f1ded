"""Built-in (non-FMU) components of the orchestrator: signal sources and the haptic device plant.

Sources are *continuous*: they have outputs only and ``evaluate(t)`` returns their exact values at
any time t (a pure function of t), so the master reads them where it needs them, with no step and
no rate transition.
- ``PiecewiseLinearSource``: scripted operator motion (e.g. a catheter insertion ramp).
- ``CsvSource``: playback of recorded motion from a CSV file.
- ``RigidSurfaceSource``: constant geometry (plane or tube) for the Contact FMU when no Tissue FMU runs.

``DevicePlant`` is a stepped component with the master's ``ComponentHost`` protocol (in process,
synchronous): the haptic device as a damped mass, integrated exactly over each step with its input
forces held (zero-order hold), with exact energy bookkeeping.

``make_block(name, table, base_dir)`` builds any of them from a scene's TOML table and reports every
configuration problem at once (``BlockConfigError``). All port values are 1-D float64 arrays.
"""
from __future__ import annotations

import bisect
import csv
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from orchestration.checks import is_int, is_real
from orchestration.hosts.description import MAX_PORT_VALUES, PortInfo

try:
    from orchestration.errors import FmuCallError
except ImportError:  # errors.py is written in parallel; same constructor and attributes
    class FmuCallError(RuntimeError):
        """A component call failed (local stand-in for orchestration.errors.FmuCallError)."""

        def __init__(self, component: str, call: str, time: float | None, reason: str, status: int | None = None):
            self.component, self.call, self.time, self.reason, self.status = component, call, time, reason, status
            at = "" if time is None else f" at t = {time:.6f} s"
            super().__init__(f"{component}: {call}{at} failed: {reason}")

logger = logging.getLogger(__name__)

INTERPOLATIONS = ("linear", "hold")
SURFACE_SHAPES = ("plane", "tube")


class BlockConfigError(ValueError):
    """A block's options are invalid; ``problems`` lists every problem found, each naming the key."""

    def __init__(self, problems: list[str], block: str | None = None):
        self.problems = list(problems)
        self.block = block
        where = f"block '{block}'" if block else "block"
        lines = "\n".join(f"  - {p}" for p in self.problems)
        super().__init__(f"{where}: {len(self.problems)} configuration problem(s):\n{lines}")


# ---------------------------------------------------------------------------------- value checks
# Each checker appends readable problems to `problems` and returns the clean value (or None).

def _real(problems, key, value, fix, *, low=None, strict=True):
    if not (is_real(value) and math.isfinite(value)):
        problems.append(f"{key} must be a finite number (got {value!r}): {fix}")
        return None
    value = float(value)
    if low is not None and (value <= low if strict else value < low):
        problems.append(f"{key} must be {'>' if strict else '>='} {low:g} (got {value!r}): {fix}")
        return None
    return value


def _int(problems, key, value, fix, *, low=1):
    if not is_int(value) or value < low:
        problems.append(f"{key} must be an integer >= {low} (got {value!r}): {fix}")
        return None
    return int(value)


def _vector(problems, key, value, n, fix):
    try:
        arr = np.asarray(value, dtype=np.float64)
    except OverflowError:  # an integer no float holds (TOML integers have no size limit)
        problems.append(f"{key} must hold finite numbers (got {value!r}): {fix}")
        return None
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != (n,) or isinstance(value, (str, bytes)) or (
            not isinstance(value, np.ndarray) and not all(is_real(v) for v in value)):
        problems.append(f"{key} must be a list of {n} numbers (got {value!r}): {fix}")
        return None
    if not np.isfinite(arr).all():
        problems.append(f"{key} must hold finite numbers (got {value!r}): {fix}")
        return None
    return arr


def _choice(problems, key, value, options):
    if value not in options:
        problems.append(f"{key} must be one of {list(options)} (got {value!r})")
        return None
    return value


def _units(problems, key, value, names):
    if value is None:
        return {}
    if not isinstance(value, dict) or not all(isinstance(u, str) for u in value.values()):
        problems.append(f"{key} must be a table output name -> unit string (got {value!r}), e.g. {{ insertion = \"m\" }}")
        return {}
    unknown = sorted(set(value) - set(names))
    if unknown:
        problems.append(f"{key} names unknown outputs {unknown}: the outputs are {sorted(names)}")
    return dict(value)


def _check_finite_t(t) -> float:
    if not (is_real(t) and math.isfinite(t)):
        raise ValueError(f"t must be a finite time in s (got {t!r})")
    return float(t)


# ---------------------------------------------------------------------------------- sources
class Source:
    """A continuous source: outputs only, ``evaluate(t)`` exact at any t."""

    name: str
    ports: dict[str, PortInfo]
    continuous = True
    #: the outputs never change: the master sets them once, at initialization
    constant = False

    def evaluate(self, t: float) -> dict[str, np.ndarray]:  # pragma: no cover - interface
        raise NotImplementedError

    def evaluate_many(self, times: np.ndarray) -> dict[str, np.ndarray]:
        """The outputs at each of ``times`` (s): ``{name: array of one flat row per time}``, each row
        bit for bit ``evaluate(t)[name]`` (the compiled loop fills a stretch's inputs with it)."""
        rows = [self.evaluate(float(t)) for t in times]
        return {name: np.array([np.asarray(row[name], dtype=np.float64).reshape(-1) for row in rows])
                for name in self.ports}


def _check_times(problems, times, key="times"):
    """Knot times: a non-empty list of finite, strictly increasing numbers; the array or None."""
    if isinstance(times, (str, bytes)) or not hasattr(times, "__len__"):
        problems.append(f"{key} must be a list of knot times in s (got {times!r}), e.g. [0.0, 1.0, 3.0]")
        return None
    t = [float(v) if is_real(v) else math.nan for v in times]
    bad = [i for i, v in enumerate(t) if not math.isfinite(v)]
    if len(t) == 0:
        problems.append(f"{key} must hold at least one time (got an empty list)")
        return None
    if bad:
        problems.append(f"{key}[{bad[0]}] must be a finite number (got {list(times)[bad[0]]!r}): give knot times in s")
        return None
    dec = [i for i in range(1, len(t)) if not t[i] > t[i - 1]]
    if dec:
        i = dec[0]
        problems.append(f"{key} must be strictly increasing ({key}[{i}] = {t[i]!r} after {key}[{i - 1}] = "
                        f"{t[i - 1]!r}): give each knot time once, in order")
        return None
    return np.asarray(t, dtype=np.float64)


def _check_outputs(problems, outputs, n_times, key="outputs"):
    """Per-output knot values: {name: ((n_times, width) array, is_scalar)}; n_times None skips the count."""
    clean = {}
    if not isinstance(outputs, dict) or not outputs:
        problems.append(f"{key} must be a non-empty table output name -> list of values, one per time "
                        f"(got {outputs!r}), e.g. {{ insertion = [0.0, 0.05] }}")
        return clean
    for name, values in outputs.items():
        where = f"{key}.{name}"
        if not isinstance(name, str) or not name:
            problems.append(f"{key} has an invalid output name {name!r}: use a non-empty string")
            continue
        if isinstance(values, (str, bytes)) or not hasattr(values, "__len__") or len(values) == 0:
            problems.append(f"{where} must be a non-empty list of values, one per time (got {values!r})")
            continue
        rows, kinds, ok = [], set(), True
        for i, v in enumerate(values):
            scalar = is_real(v)
            row = [v] if scalar else (list(v) if hasattr(v, "__len__") and not isinstance(v, (str, bytes)) else None)
            if row is None or not row or not all(is_real(x) and math.isfinite(x) for x in row):
                problems.append(f"{where}[{i}] must be a finite number or a list of finite numbers (got {v!r})")
                ok = False
                break
            rows.append(row)
            kinds.add((len(row), scalar))
        if not ok:
            continue
        if len(kinds) > 1:
            problems.append(f"{where} mixes values of different lengths: give every knot the same number of "
                            f"components (all numbers, or all lists of one length)")
            continue
        if n_times is not None and len(rows) != n_times:
            problems.append(f"{where} has {len(rows)} values but times has {n_times}: give one value per knot time")
            continue
        width, scalar = next(iter(kinds))
        clean[name] = (np.asarray(rows, dtype=np.float64).reshape(len(rows), width), scalar)
    return clean


class PiecewiseLinearSource(Source):
    """Outputs interpolated between knots (``"linear"``) or held from the last knot (``"hold"``).

    Before the first knot the first value is held, after the last knot the last value. The value at
    a knot time is the knot value exactly.
    """

    def __init__(self, name: str, times, outputs: dict, interpolation: str = "linear",
                 units: dict[str, str] | None = None):
        problems: list[str] = []
        clean_times = _check_times(problems, times)
        clean = _check_outputs(problems, outputs, None if clean_times is None else len(clean_times))
        _choice(problems, "interpolation", interpolation, INTERPOLATIONS)
        units = _units(problems, "units", units, list(outputs) if isinstance(outputs, dict) else [])
        if problems:
            raise BlockConfigError(problems, name)
        self._build(name, clean_times, clean, interpolation, units)

    def _build(self, name, times, clean, interpolation, units):
        self.name = name
        self.interpolation = interpolation
        self.times = times
        self._t = times.tolist()  # bisect on a list is the fastest scalar lookup
        self._names = list(clean)
        self._slices = {}
        columns, start = [], 0
        self.ports = {}
        for out, (values, scalar) in clean.items():
            width = values.shape[1]
            self._slices[out] = slice(start, start + width)
            start += width
            columns.append(values)
            self.ports[out] = PortInfo(name=out, causality="output", type="Float64",
                                       variability="continuous" if interpolation == "linear" else "discrete",
                                       unit=units.get(out), shape=() if scalar else (width,),
                                       start=values[0, 0] if scalar else values[0].tolist())
        self._values = np.ascontiguousarray(np.concatenate(columns, axis=1))  # (n_times, total width)
        # evaluate() works on plain floats (a few values per tick: numpy's per-call cost would dominate);
        # the same IEEE operations, so the same values as the array formula in _row
        self._rows = self._values.tolist()
        self._hold = interpolation == "hold"
        self._slice_list = list(self._slices.items())

    def _row(self, t: float) -> np.ndarray:
        i = bisect.bisect_right(self._t, t)  # times[i-1] <= t < times[i]
        if i == 0:
            return self._values[0].copy()
        if i == len(self._t) or self.interpolation == "hold":
            return self._values[i - 1].copy()
        t0, t1 = self._t[i - 1], self._t[i]
        w = (t - t0) / (t1 - t0)
        # (1-w) v0 + w v1 is v0 exactly at w = 0 (knots are hit through w = 0 only)
        return (1.0 - w) * self._values[i - 1] + w * self._values[i]

    def evaluate_many(self, times: np.ndarray) -> dict[str, np.ndarray]:
        times = np.asarray(times, dtype=np.float64)
        if not np.isfinite(times).all():
            return super().evaluate_many(times)  # evaluate says what is wrong
        knots, values = self.times, self._values
        i = np.searchsorted(knots, times, side="right")  # as bisect_right: knots[i-1] <= t < knots[i]
        out = values[np.maximum(i - 1, 0)]  # held: the first row before the first knot, the last after
        if not self._hold:
            inner = (i > 0) & (i < len(knots))
            if inner.any():
                k = i[inner]
                w = (times[inner] - knots[k - 1]) / (knots[k] - knots[k - 1])
                # the IEEE operations of evaluate, elementwise: (1 - w) v0 + w v1
                out[inner] = (1.0 - w)[:, None] * values[k - 1] + w[:, None] * values[k]
        return {out_name: out[:, s] for out_name, s in self._slice_list}

    def evaluate(self, t: float) -> dict[str, np.ndarray]:
        if not (type(t) is float and math.isfinite(t)):
            t = _check_finite_t(t)
        rows = self._rows
        i = bisect.bisect_right(self._t, t)  # times[i-1] <= t < times[i]
        if i == 0:
            row = rows[0]
        elif i == len(rows) or self._hold:
            row = rows[i - 1]
        else:
            t0, t1 = self._t[i - 1], self._t[i]
            w = (t - t0) / (t1 - t0)
            v = 1.0 - w
            row = [v * a + w * b for a, b in zip(rows[i - 1], rows[i])]
        return {out: np.array(row[s]) for out, s in self._slice_list}


#: The longest line a CSV signal may have, in bytes: a row of numbers is a few hundred; a longer
#: line is no signal (a binary file, a file without line breaks) and would only fill the memory.
CSV_MAX_LINE = 1 << 20


class _CsvUnreadable(Exception):
    """A line of a CSV file that cannot be read as text: ``line`` and what is wrong and the fix."""

    def __init__(self, line: int, reason: str):
        super().__init__(reason)
        self.line, self.reason = line, reason


#: A line ends at LF, CR LF or a lone CR (as in text mode with newline=""; old spreadsheet exports end
#: lines with CR alone): the split keeps each line's end for csv.reader.
_CR_LINE_END = re.compile(r"(?<=\r)(?!\n)")


def _csv_lines(fh, position: list[int]):
    """The text lines of the binary file ``fh`` for csv.reader, each checked: UTF-8 (a byte-order
    mark, as spreadsheet programs write one, skipped), no NUL, at most CSV_MAX_LINE bytes.
    ``position[0]`` is the number of the line last read (csv.reader's own count lags on errors)."""
    while True:
        raw = fh.readline(CSV_MAX_LINE + 1)
        if not raw:
            return
        line = position[0] + 1
        if len(raw) > CSV_MAX_LINE:
            raise _CsvUnreadable(line, f"is longer than {CSV_MAX_LINE} bytes, which no row of numbers is: the file "
                                       "is binary or has no line breaks; give a CSV text file, one row per line")
        if line == 1 and raw.startswith(b"\xef\xbb\xbf"):
            raw = raw[3:]
        nul = raw.find(b"\0")
        if nul >= 0:
            raise _CsvUnreadable(line, f"holds a NUL byte at column {nul + 1}: the file is binary or not UTF-8 "
                                       "(UTF-16, as some spreadsheet programs write 'Unicode text'?); save it as "
                                       "CSV in UTF-8")
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise _CsvUnreadable(line, f"is not UTF-8 text (byte {raw[exc.start]:#04x} at column {exc.start + 1}); "
                                       "save the file as CSV in UTF-8") from None
        for part in _CR_LINE_END.split(text) if "\r" in text else (text,):
            if part:
                position[0] += 1
                yield part


def _csv_rows(problems, path: Path, key: str) -> list[list[str]] | None:
    """The rows of the CSV file ``path``, or None with the problem (naming the file, the line and
    the fix) in ``problems``: a file that cannot be opened or read, a line that is no text, a field
    longer than the csv module's limit."""
    position = [0]
    where = f"{key}: CSV file {str(path)!r}"
    try:
        with path.open("rb") as fh:
            return list(csv.reader(_csv_lines(fh, position)))
    except OSError as exc:
        problems.append(f"{where}: cannot read it ({exc.strerror or exc}): make it readable for this user "
                        f"(e.g. `chmod a+r {path}`) or give a copy that is")
    except _CsvUnreadable as exc:
        problems.append(f"{where} line {exc.line} {exc.reason}")
    except csv.Error as exc:
        fix = ("a field of a signal is a number: close the quote opened before it (or remove it), or give a CSV of "
               "numbers") if "field limit" in str(exc) else "give a CSV of numbers, one row per line"
        problems.append(f"{where} line {position[0]}: {exc}; {fix}")
    return None


def _read_csv(problems, path: Path, columns: dict, time_column: str, key="path"):
    """Read the CSV into (times, {output: (values, scalar)}); every problem goes to `problems`."""
    try:
        found = path.is_file()
    except OSError as exc:  # a folder on the way that this user may not enter (EACCES is not "missing")
        problems.append(f"{key}: cannot read the CSV file {str(path)!r} ({exc.strerror or exc}): make it and its "
                        "folders readable for this user, or give a copy that is")
        return None, {}
    if not found:
        problems.append(f"{key}: CSV file {str(path)!r} does not exist: give a path to a CSV file with a header "
                        f"row (relative paths are relative to the scene file)")
        return None, {}
    rows = _csv_rows(problems, path, key)
    if rows is None:
        return None, {}
    if not rows:
        problems.append(f"{key}: CSV file {str(path)!r} is empty: it needs a header row and numeric rows")
        return None, {}
    header = [h.strip() for h in rows[0]]
    index = {h: i for i, h in enumerate(header)}
    wanted = {}
    if time_column not in index:
        problems.append(f"time_column: column {time_column!r} is not in the header of {path.name} "
                        f"(columns: {header}): name the time column")
    for out, cols in columns.items():
        names = [cols] if isinstance(cols, str) else list(cols)
        missing = [c for c in names if c not in index]
        if missing:
            problems.append(f"columns.{out}: column(s) {missing} not in the header of {path.name} (columns: {header})")
        else:
            wanted[out] = (names, isinstance(cols, str))
    if time_column not in index or len(wanted) != len(columns):
        return None, {}
    data = rows[1:]
    used = [time_column] + [c for names, _ in wanted.values() for c in names]
    table = np.empty((len(data), len(header)))
    n_bad = 0
    for r, row in enumerate(data):
        line = r + 2
        if len(row) != len(header):
            problems.append(f"{key}: {path.name} line {line} has {len(row)} fields but the header has {len(header)}")
            n_bad += 1
            if n_bad >= 10:
                break
            continue
        for c in used:
            cell = row[index[c]].strip()
            try:
                value = float(cell)
            except ValueError:
                value = math.nan
            if not math.isfinite(value):
                problems.append(f"{key}: {path.name} line {line}, column {c!r}: {cell!r} is not a finite number")
                n_bad += 1
            table[r, index[c]] = value
        if n_bad >= 10:
            problems.append(f"{key}: {path.name}: stopped after 10 bad cells")
            break
    if n_bad:
        return None, {}
    if not data:
        problems.append(f"{key}: {path.name} has a header but no data rows")
        return None, {}
    t = table[:, index[time_column]]
    dec = np.flatnonzero(~(t[1:] > t[:-1]))
    if dec.size:
        i = int(dec[0]) + 1
        problems.append(f"{key}: time column {time_column!r} of {path.name} must strictly increase: line {i + 2} "
                        f"has {t[i]!r} after {t[i - 1]!r} on line {i + 1}")
        return None, {}
    clean = {out: (np.ascontiguousarray(table[:, [index[c] for c in names]]), scalar)
             for out, (names, scalar) in wanted.items()}
    return t.copy(), clean


def _check_columns(problems, columns):
    if not isinstance(columns, dict) or not columns:
        problems.append(f"columns must be a non-empty table output name -> column name or list of column names "
                        f"(got {columns!r}), e.g. {{ insertion = \"z\", position = [\"x\", \"y\", \"z\"] }}")
        return False
    ok = True
    for out, cols in columns.items():
        if isinstance(cols, str):
            continue
        if not (isinstance(cols, (list, tuple)) and cols and all(isinstance(c, str) for c in cols)):
            problems.append(f"columns.{out} must be a column name or a non-empty list of column names (got {cols!r})")
            ok = False
    return ok


class CsvSource(PiecewiseLinearSource):
    """Playback of recorded motion: a ``PiecewiseLinearSource`` whose knots are the rows of a CSV file.

    ``columns`` maps each output to one column (a scalar output) or a list of columns (a vector).
    """

    def __init__(self, name: str, path, columns: dict, time_column: str = "time",
                 interpolation: str = "linear", units: dict[str, str] | None = None):
        problems: list[str] = []
        if not isinstance(time_column, str):
            problems.append(f"time_column must be a column name (got {time_column!r})")
        _choice(problems, "interpolation", interpolation, INTERPOLATIONS)
        units = _units(problems, "units", units, list(columns) if isinstance(columns, dict) else [])
        times, clean = None, {}
        if not isinstance(path, (str, Path)):
            problems.append(f"path must be a file path (got {path!r})")
        elif _check_columns(problems, columns) and isinstance(time_column, str):
            times, clean = _read_csv(problems, Path(path), columns, time_column)
        if problems:
            raise BlockConfigError(problems, name)
        self.path = Path(path)
        self._build(name, times, clean, interpolation, units)


@dataclass(frozen=True)
class _Geometry:
    positions: np.ndarray   # (n, 3)
    triangles: np.ndarray   # (m, 3) int


def plane_geometry(center, normal, size, divisions) -> _Geometry:
    """A rectangle of size[0] x size[1] centred on `center`, split into divisions[0] x divisions[1]
    cells of two triangles, each with its normal along +normal.

    In-plane axes: u = normalize(normal x e) with e the coordinate axis least aligned with the normal,
    v = normal x u, so (u, v, normal) is right-handed; size[0] runs along u, size[1] along v.
    """
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    e = np.zeros(3)
    e[int(np.argmin(np.abs(n)))] = 1.0
    u = np.cross(n, e)
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    na, nb = divisions
    a = np.linspace(-0.5 * size[0], 0.5 * size[0], na + 1)
    b = np.linspace(-0.5 * size[1], 0.5 * size[1], nb + 1)
    A, B = np.meshgrid(a, b, indexing="ij")  # node (i, j) has id i * (nb + 1) + j
    pos = np.asarray(center, np.float64) + A.reshape(-1, 1) * u + B.reshape(-1, 1) * v
    i, j = np.meshgrid(np.arange(na), np.arange(nb), indexing="ij")
    p00 = (i * (nb + 1) + j).ravel()
    p10, p01 = p00 + nb + 1, p00 + 1
    p11 = p10 + 1
    # edges along u then v: (u x v) = +normal
    tri = np.concatenate([np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1)])
    return _Geometry(pos, tri)


def tube_geometry(start, end, radius, n_circumferential, n_axial) -> _Geometry:
    """An open cylinder around the axis start -> end: n_axial + 1 rings of n_circumferential nodes,
    two triangles per quad, normals pointing to the axis (the tool is inside the tube)."""
    start = np.asarray(start, np.float64)
    axis = np.asarray(end, np.float64) - start
    a = axis / np.linalg.norm(axis)
    e = np.zeros(3)
    e[int(np.argmin(np.abs(a)))] = 1.0
    e1 = np.cross(a, e)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)  # (e1, e2, a) right-handed
    theta = 2.0 * np.pi * np.arange(n_circumferential) / n_circumferential
    s = np.linspace(0.0, 1.0, n_axial + 1)
    radial = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
    pos = (start + s[:, None, None] * axis + radius * radial[None, :, :]).reshape(-1, 3)
    k, j = np.meshgrid(np.arange(n_axial), np.arange(n_circumferential), indexing="ij")
    jn = (j + 1) % n_circumferential
    p00 = (k * n_circumferential + j).ravel()            # ring k, angle j
    p01 = (k * n_circumferential + jn).ravel()           # ring k, angle j+1
    p10, p11 = p00 + n_circumferential, p01 + n_circumferential
    # edges along the axis then around: a x t_theta = -radial, i.e. towards the axis
    tri = np.concatenate([np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1)])
    return _Geometry(pos, tri)


_PLANE_DEFAULTS = {"center": (0.0, 0.0, 0.0), "normal": (0.0, 0.0, 1.0), "size": 0.1, "divisions": 10}
_TUBE_DEFAULTS = {"start": (0.0, 0.0, 0.0), "end": (0.0, 0.0, 0.1), "radius": 0.01,
                  "n_circumferential": 32, "n_axial": 20}


def _check_surface(problems, shape, given: dict) -> dict:
    """Validate rigid-surface options for `shape`; return the full option dict with defaults."""
    if _choice(problems, "shape", shape, SURFACE_SHAPES) is None:
        return {}
    defaults, other = (_PLANE_DEFAULTS, _TUBE_DEFAULTS) if shape == "plane" else (_TUBE_DEFAULTS, _PLANE_DEFAULTS)
    for key in given:
        if key in other:
            problems.append(f"{key} applies to shape = '{'tube' if shape == 'plane' else 'plane'}' only; "
                            f"options of shape = '{shape}' are {list(defaults)}")
    opts = {k: given.get(k, d) for k, d in defaults.items()}
    out = {}
    if shape == "plane":
        out["center"] = _vector(problems, "center", opts["center"], 3, "give the plane centre in m, e.g. [0, 0, 0]")
        normal = _vector(problems, "normal", opts["normal"], 3,
                         "give the normal (the side where the tool is allowed), e.g. [0, 0, 1]")
        if normal is not None and not np.linalg.norm(normal) > 0:
            problems.append("normal must not be zero: give the direction of the allowed side, e.g. [0, 0, 1]")
            normal = None
        out["normal"] = normal
        size = opts["size"]
        size = [size, size] if is_real(size) else size
        size = _vector(problems, "size", size, 2, "give the side length in m, or [length_u, length_v], e.g. 0.1")
        if size is not None and not (size > 0).all():
            problems.append(f"size must be > 0 (got {opts['size']!r}): give side lengths in m, e.g. 0.1")
            size = None
        out["size"] = size
        div = opts["divisions"]
        div = [div, div] if is_int(div) else div
        if not (isinstance(div, (list, tuple)) and len(div) == 2 and all(is_int(d) and d >= 1 for d in div)):
            problems.append(f"divisions must be an integer >= 1 or a list of two (got {opts['divisions']!r}): "
                            f"cells per side, e.g. 10")
            div = None
        out["divisions"] = None if div is None else (int(div[0]), int(div[1]))
    else:
        out["start"] = _vector(problems, "start", opts["start"], 3, "give the first axis point in m")
        out["end"] = _vector(problems, "end", opts["end"], 3, "give the last axis point in m")
        if out["start"] is not None and out["end"] is not None and not np.linalg.norm(out["end"] - out["start"]) > 0:
            problems.append("end must differ from start: give two distinct axis points in m")
        out["radius"] = _real(problems, "radius", opts["radius"], "give the tube radius in m, e.g. 0.01", low=0.0)
        out["n_circumferential"] = _int(problems, "n_circumferential", opts["n_circumferential"],
                                        "nodes around each ring, e.g. 32", low=3)
        out["n_axial"] = _int(problems, "n_axial", opts["n_axial"], "segments along the axis, e.g. 20", low=1)
    _check_surface_size(problems, shape, out)
    return out


#: A rigid surface lies within this distance of the origin, m: the scenes model a vessel or a
#: device workspace (0.1-0.2 m); coordinates of kilometres cannot be meant, and far larger ones
#: overflow the contact model's squared distances.
SURFACE_MAX_EXTENT = 10.0


def _check_surface_size(problems, shape, out: dict) -> None:
    """The surface's node coordinates must fit a port (MAX_PORT_VALUES) and lie within
    SURFACE_MAX_EXTENT of the origin: anything else is a typo."""
    for key in ("center", "start", "end", "size", "radius"):
        value = out.get(key)
        if value is not None and float(np.max(np.abs(value))) > SURFACE_MAX_EXTENT:
            problems.append(f"{key} must be within {SURFACE_MAX_EXTENT:g} m (got {np.asarray(value).tolist()!r}): "
                            "give lengths in m; the scenes model a vessel or a device workspace of 0.1-0.2 m")
    if shape == "plane" and out.get("divisions") is not None:
        na, nb = out["divisions"]
        nodes, fix = (na + 1) * (nb + 1), "fewer divisions"
    elif shape == "tube" and out.get("n_circumferential") is not None and out.get("n_axial") is not None:
        nodes, fix = out["n_circumferential"] * (out["n_axial"] + 1), "fewer n_circumferential or n_axial"
    else:
        return
    if 3 * nodes > MAX_PORT_VALUES:
        problems.append(f"the surface would have {nodes} nodes, more than {MAX_PORT_VALUES // 3} ({MAX_PORT_VALUES} "
                        f"coordinates, the most a port holds); give {fix}")


class RigidSurfaceSource(Source):
    """Constant surface geometry for the Contact FMU: outputs ``positions`` (n,3), ``velocities``
    (zeros, n,3) and ``triangles`` (Int32 (m,3), carried as float64).

    Orientation contract of the Contact FMU: triangle normals (right-hand rule) point to the side
    where the tool is allowed: along ``normal`` for a plane, towards the axis for a tube.
    """

    constant = True

    def __init__(self, name: str, shape: str = "plane", **options):
        problems: list[str] = []
        unknown = sorted(set(options) - set(_PLANE_DEFAULTS) - set(_TUBE_DEFAULTS))
        if unknown:
            problems.append(f"unknown options {unknown}: valid are ['shape', {', '.join(map(repr, _PLANE_DEFAULTS))}] "
                            f"for a plane and {list(_TUBE_DEFAULTS)} for a tube")
        clean = _check_surface(problems, shape, {k: v for k, v in options.items() if v is not None})
        if problems:
            raise BlockConfigError(problems, name)
        self.name = name
        self.shape = shape
        self.options = clean
        geom = plane_geometry(**clean) if shape == "plane" else tube_geometry(**clean)
        self.triangle_ids = geom.triangles.astype(np.int32)
        self.n_nodes = int(geom.positions.shape[0])
        self.n_triangles = int(geom.triangles.shape[0])
        logger.debug("rigid %s '%s': %d nodes, %d triangles", shape, name, self.n_nodes, self.n_triangles)
        self._values = {
            "positions": geom.positions.ravel(),
            "velocities": np.zeros(3 * self.n_nodes),
            "triangles": geom.triangles.astype(np.float64).ravel(),
        }
        nodes, tris = (self.n_nodes, 3), (self.n_triangles, 3)
        self.ports = {
            "positions": PortInfo("positions", "output", "Float64", "constant", "m", nodes,
                                  description="surface node positions"),
            "velocities": PortInfo("velocities", "output", "Float64", "constant", "m/s", nodes,
                                   description="surface node velocities (zero: rigid)"),
            "triangles": PortInfo("triangles", "output", "Int32", "constant", None, tris,
                                  description="node ids per triangle, normals towards the allowed side"),
        }

    @property
    def positions(self) -> np.ndarray:
        return self._values["positions"].reshape(-1, 3).copy()

    def evaluate(self, t: float) -> dict[str, np.ndarray]:
        _check_finite_t(t)
        return {k: v.copy() for k, v in self._values.items()}


# ---------------------------------------------------------------------------------- device plant
def _series(a: float, coefficient) -> float:
    """sum_k coefficient(k) (-a)^k for small a (converged well before 30 terms for a < 0.5)."""
    total, power = 0.0, 1.0
    for k in range(30):
        total += coefficient(k) * power
        power *= -a
    return total


def exact_step_factors(a: float) -> tuple[float, float, float, float]:
    """Factors of the exact solution of m v' = F - b v over a step h, with a = b h / m >= 0.

    E1 = (1 - e^-a)/a, E2 = (a - 1 + e^-a)/a^2, E1(2a), J2 = (1 - 2 E1(a) + E1(2a))/a^2; each -> its
    limit as a -> 0 (1, 1/2, 1, 1/3), by series where the closed form cancels.
    """
    if a < 0.5:
        e1 = _series(a, lambda k: 1.0 / math.factorial(k + 1))
        e2 = _series(a, lambda k: 1.0 / math.factorial(k + 2))
        e1_2a = _series(2.0 * a, lambda k: 1.0 / math.factorial(k + 1))
        j2 = _series(a, lambda k: (2.0 ** (k + 2) - 2.0) / math.factorial(k + 3))
        return e1, e2, e1_2a, j2
    e1 = -math.expm1(-a) / a
    e1_2a = -math.expm1(-2.0 * a) / (2.0 * a)
    e2 = (a + math.expm1(-a)) / (a * a)
    j2 = (1.0 - 2.0 * e1 + e1_2a) / (a * a)
    return e1, e2, e1_2a, j2


_PLANT_PARAMETERS = ("mass", "damping", "step", "initial_position", "initial_velocity")
_PLANT_INPUTS = ("operator_force", "wall_force")
_PLANT_OUTPUTS = ("position", "velocity", "wall_energy", "operator_energy", "dissipated_energy", "kinetic_energy")


#: Plausibility limits of the device plant: values outside cannot be meant, and some overflow the
#: exact step (mass = 1e-300 kg makes F/m and the energy integrals inf, then NaN, silently).
#: mass: 1e-10 kg is 100x below the lightest device the stability study models (the passivity worst
#: case, m = 1e-3 bound T: about 1.6e-8 kg), 1000 kg far above any haptic device (0.01-1 kg).
#: damping: 1e6 N s/m is 1e5 times a desktop device's. Initial state: a desktop device's workspace
#: is about 0.2 m and its speeds below 1 m/s; 10 m and 100 m/s cannot be meant.
PLANT_LIMITS = {"mass": (1e-10, 1e3), "damping": (0.0, 1e6)}
PLANT_MAX_POSITION = 10.0       # m, |initial_position|
PLANT_MAX_SPEED = 100.0         # m/s, |initial_velocity|


def _check_plant_limits(problems, out: dict) -> None:
    for key, (low, high) in PLANT_LIMITS.items():
        value = out.get(key)
        if value is not None and not low <= value <= high:
            problems.append(f"{key} must be within {low:g} to {high:g} (got {value!r}): see blocks.PLANT_LIMITS for why")
    for key, limit, unit in (("initial_position", PLANT_MAX_POSITION, "m"),
                             ("initial_velocity", PLANT_MAX_SPEED, "m/s")):
        value = out.get(key)
        if value is not None and float(np.linalg.norm(value)) > limit:
            problems.append(f"{key} must have a magnitude of at most {limit:g} {unit} (got {value.tolist()!r}): "
                            "a desktop haptic device's workspace is about 0.2 m")


def _check_plant(problems, values: dict) -> dict:
    out = {}
    checks = {
        "mass": lambda v: _real(problems, "mass", v, "give the device's moving mass in kg, e.g. 0.1", low=0.0),
        "damping": lambda v: _real(problems, "damping", v, "give the device's physical damping b_dev in N s/m, "
                                                            "e.g. 1.0", low=0.0, strict=False),
        "step": lambda v: _real(problems, "step", v, "give the haptic step in s, e.g. 0.001", low=0.0),
        "initial_position": lambda v: _vector(problems, "initial_position", v, 3, "give [x, y, z] in m"),
        "initial_velocity": lambda v: _vector(problems, "initial_velocity", v, 3, "give [vx, vy, vz] in m/s"),
    }
    for key, value in values.items():
        if isinstance(value, np.ndarray) and value.size == 1 and key in ("mass", "damping", "step"):
            value = float(value.reshape(-1)[0])
        out[key] = checks[key](value)
    _check_plant_limits(problems, out)
    return out


class DevicePlant:
    """The haptic device: a mass with physical damping, ``m x'' = F_operator + F_wall - b_dev x'``.

    Both forces are held constant over each step (zero-order hold, as a sampled haptic loop applies
    them) and the linear ODE is integrated exactly over the step (closed form). The energy outputs
    are the exact integrals over the steps: ``operator_energy`` and ``wall_energy`` (work of each
    force, F . dx), ``dissipated_energy`` (integral of b v^2, computed from v(t) independently) and
    ``kinetic_energy``; kinetic(t) - kinetic(0) = operator + wall - dissipated to round-off.

    Host protocol (``ComponentHost``): in process and synchronous, ``step_done()`` is True.
    """

    continuous = False
    asynchronous = False

    def __init__(self, name: str, mass: float = 0.1, damping: float = 1.0, step: float = 0.001,
                 initial_position=(0.0, 0.0, 0.0), initial_velocity=(0.0, 0.0, 0.0)):
        problems: list[str] = []
        clean = _check_plant(problems, {"mass": mass, "damping": damping, "step": step,
                                        "initial_position": initial_position, "initial_velocity": initial_velocity})
        if problems:
            raise BlockConfigError(problems, name)
        self.name = name
        self.messages: list[tuple[int, str]] = []
        self._params = clean
        vec = dict(shape=(3,))
        self.ports = {
            "mass": PortInfo("mass", "parameter", "Float64", "fixed", "kg", start=clean["mass"]),
            "damping": PortInfo("damping", "parameter", "Float64", "fixed", "N.s/m", start=clean["damping"]),
            "step": PortInfo("step", "parameter", "Float64", "fixed", "s", start=clean["step"]),
            "initial_position": PortInfo("initial_position", "parameter", "Float64", "fixed", "m",
                                         start=clean["initial_position"].tolist(), **vec),
            "initial_velocity": PortInfo("initial_velocity", "parameter", "Float64", "fixed", "m/s",
                                         start=clean["initial_velocity"].tolist(), **vec),
            "operator_force": PortInfo("operator_force", "input", "Float64", "continuous", "N",
                                       start=[0.0] * 3, **vec),
            "wall_force": PortInfo("wall_force", "input", "Float64", "continuous", "N", start=[0.0] * 3, **vec),
            "position": PortInfo("position", "output", "Float64", "continuous", "m", **vec),
            "velocity": PortInfo("velocity", "output", "Float64", "continuous", "m/s", **vec),
        }
        for out in _PLANT_OUTPUTS[2:]:
            self.ports[out] = PortInfo(out, "output", "Float64", "continuous", "J")
        self._inputs = {k: np.zeros(3) for k in _PLANT_INPUTS}
        self._configured_inputs = list(_PLANT_INPUTS)
        self._observed = list(_PLANT_OUTPUTS)
        self._state = "created"
        self._time = 0.0
        self._pending = None
        self._factors = None
        self._reset()

    # -- protocol -----------------------------------------------------------------------------
    @property
    def step(self) -> float:
        """The fixed step the plant expects from the master, s."""
        return self._params["step"]

    @property
    def default_step(self) -> float:
        return self._params["step"]

    def instantiate(self) -> None:
        if self._state != "created":
            raise FmuCallError(self.name, "instantiate", None, f"already instantiated (state {self._state})")
        self._state = "instantiated"

    def set_values(self, values: dict[str, object]) -> None:
        self._require(("instantiated", "initialization"), "setValues", None)
        params = {k: v for k, v in values.items() if k in _PLANT_PARAMETERS}
        inputs = {k: v for k, v in values.items() if k in _PLANT_INPUTS}
        unknown = sorted(set(values) - set(params) - set(inputs))
        if unknown:
            raise FmuCallError(self.name, f"setValues({', '.join(unknown)})", None,
                               f"no such variable(s) {unknown}: settable are "
                               f"{list(_PLANT_PARAMETERS) + list(_PLANT_INPUTS)}")
        problems: list[str] = []
        clean = _check_plant(problems, params)
        if problems:
            raise FmuCallError(self.name, f"setValues({', '.join(params)})", None, "; ".join(problems))
        self._params.update(clean)
        self._set_inputs(inputs, "setValues", None)
        self._reset()

    def enter_initialization(self, start_time: float) -> None:
        self._require(("instantiated",), "enterInitializationMode", start_time)
        if not (is_real(start_time) and math.isfinite(start_time)):
            raise FmuCallError(self.name, "enterInitializationMode", None,
                               f"start_time must be a finite time in s (got {start_time!r})")
        self._start_time = float(start_time)
        self._state = "initialization"
        self._reset()

    def configure(self, inputs: list[str], observed: list[str]) -> None:
        bad_in = [n for n in inputs if n not in _PLANT_INPUTS]
        bad_obs = [n for n in observed if n not in self.ports]
        if bad_in or bad_obs:
            raise FmuCallError(self.name, "configure", None,
                               (f"not inputs: {bad_in} (inputs are {list(_PLANT_INPUTS)}); " if bad_in else "")
                               + (f"no such ports: {bad_obs} (ports are {list(self.ports)})" if bad_obs else ""))
        self._configured_inputs = list(inputs)
        self._observed = list(observed)

    def set_inputs(self, values: dict[str, np.ndarray]) -> None:
        self._require(("instantiated", "initialization", "stepping"), "setInputs", self._time)
        self._set_inputs(values, "setFloat64", self._time)

    def get_outputs(self) -> dict[str, np.ndarray]:
        self._require(("initialization", "stepping"), "getFloat64", self._time)
        return self._read(self._observed)

    def get_values(self, names: list[str]) -> dict[str, np.ndarray]:
        """Current values of any ports (parameters, inputs, outputs), fresh float64 copies."""
        self._require(("instantiated", "initialization", "stepping"), "getValues", self._time)
        unknown = [n for n in names if n not in self.ports]
        if unknown:
            raise FmuCallError(self.name, "getValues", self._time,
                               f"no such ports: {unknown} (ports are {list(self.ports)})")
        return self._read(names)

    def exit_initialization(self) -> None:
        self._require(("initialization",), "exitInitializationMode", self._time)
        self._state = "stepping"

    def start_step(self, t: float, h: float, inputs: dict[str, np.ndarray]) -> None:
        self._require(("stepping",), "doStep", t)
        step = self._params["step"]
        if not (is_real(h) and math.isclose(h, step, rel_tol=1e-9, abs_tol=0.0)):
            raise FmuCallError(self.name, "doStep", t,
                               f"communication step {h!r} s differs from the plant's step {step!r} s: "
                               f"set the plant's step to the step the scene gives it (or the other way round)")
        if not (is_real(t) and math.isclose(t, self._time, rel_tol=1e-9, abs_tol=1e-12)):
            raise FmuCallError(self.name, "doStep", t,
                               f"step starts at t = {t!r} s but the plant is at t = {self._time!r} s")
        self._set_inputs(inputs, "setFloat64", t)
        self._advance(float(h))
        self._time = float(t) + float(h)
        self._pending = self._read(self._observed)

    def finish_step(self) -> dict[str, np.ndarray]:
        if self._pending is None:
            raise FmuCallError(self.name, "doStep", self._time, "finish_step called without start_step")
        out, self._pending = self._pending, None
        return out

    def step_done(self) -> bool:
        return True  # synchronous: start_step did the step

    def terminate(self) -> None:
        self._state = "terminated"
        self._pending = None

    # -- model --------------------------------------------------------------------------------
    def _require(self, states, call, t):
        if self._state not in states:
            raise FmuCallError(self.name, call, t, f"not allowed in state '{self._state}' (allowed in {list(states)})")

    def _set_inputs(self, values, call, t):
        for key, value in values.items():
            if key not in _PLANT_INPUTS:
                raise FmuCallError(self.name, f"{call}({key})", t,
                                   f"{key!r} is not an input: the inputs are {list(_PLANT_INPUTS)}")
            arr = np.asarray(value, dtype=np.float64).reshape(-1)
            if arr.shape != (3,) or not np.isfinite(arr).all():
                raise FmuCallError(self.name, f"{call}({key})", t,
                                   f"{key} must be 3 finite numbers in N (got {value!r})")
            self._inputs[key][:] = arr

    def _reset(self):
        self._x = self._params["initial_position"].copy()
        self._v = self._params["initial_velocity"].copy()
        self._time = getattr(self, "_start_time", 0.0)
        self._energy = {"wall_energy": 0.0, "operator_energy": 0.0, "dissipated_energy": 0.0}

    def _advance(self, h: float) -> None:
        m, b = self._params["mass"], self._params["damping"]
        f_op, f_wall = self._inputs["operator_force"], self._inputs["wall_force"]
        g = (f_op + f_wall) / m
        v0 = self._v
        a = b * h / m
        if self._factors is None or self._factors[0] != a:  # constant over a run: computed once
            self._factors = (a, exact_step_factors(a), math.exp(-a))
        (e1, e2, e1_2a, j2), decay = self._factors[1], self._factors[2]
        # v(s) = v0 e^{-bs/m} + g (1 - e^{-bs/m}) m/b ; x(h) - x0 = v0 h E1 + g h^2 E2
        dx = v0 * (h * e1) + g * (h * h * e2)
        v1 = v0 * decay + g * (h * e1)
        # int_0^h |v|^2 ds = |v0|^2 h E1(2a) + 2 v0.g h^2 E1(a)^2/2 + |g|^2 h^3 J2
        int_v2 = (v0 @ v0) * h * e1_2a + (v0 @ g) * h * h * e1 * e1 + (g @ g) * h ** 3 * j2
        self._energy["operator_energy"] += float(f_op @ dx)
        self._energy["wall_energy"] += float(f_wall @ dx)
        self._energy["dissipated_energy"] += b * float(int_v2)
        self._x = self._x + dx
        self._v = v1

    def _read(self, names) -> dict[str, np.ndarray]:
        out = {}
        for n in names:
            if n == "position":
                out[n] = self._x.copy()
            elif n == "velocity":
                out[n] = self._v.copy()
            elif n == "kinetic_energy":
                out[n] = np.array([0.5 * self._params["mass"] * float(self._v @ self._v)])
            elif n in self._energy:
                out[n] = np.array([self._energy[n]])
            elif n in self._inputs:
                out[n] = self._inputs[n].copy()
            else:
                out[n] = np.atleast_1d(np.asarray(self._params[n], dtype=np.float64)).copy()
        return out


# ---------------------------------------------------------------------------------- factory
REQUIRED = type("Required", (), {"__repr__": lambda self: "required"})()

BLOCK_KINDS: dict[str, str] = {
    "piecewise_linear": "scripted signal: values at knot times, linear or held between them (e.g. insertion ramp)",
    "csv": "recorded signal: columns of a CSV file played back against its time column",
    "rigid_surface": "constant rigid plane or tube (positions, velocities, triangles) for the Contact FMU",
    "device_plant": "haptic device: damped mass driven by operator and wall forces, exact over each step",
}

_OPTIONS: dict[str, list[tuple[str, object, str]]] = {
    "piecewise_linear": [
        ("times", REQUIRED, "knot times in s, strictly increasing, e.g. [0.0, 1.0, 3.0]"),
        ("outputs", REQUIRED, "table output -> one value per knot (number, or list for a vector), "
                              "e.g. { insertion = [0.0, 0.0, 0.05] }"),
        ("interpolation", "linear", "'linear' between knots, or 'hold' the last knot's value"),
        ("units", None, "table output -> unit string, e.g. { insertion = \"m\" }"),
    ],
    "csv": [
        ("path", REQUIRED, "CSV file with a header row (relative to the scene file)"),
        ("columns", REQUIRED, "table output -> column name (scalar) or list of column names (vector)"),
        ("time_column", "time", "name of the time column (s, strictly increasing)"),
        ("interpolation", "linear", "'linear' between rows, or 'hold' the last row's value"),
        ("units", None, "table output -> unit string"),
    ],
    "rigid_surface": [
        ("shape", "plane", "'plane' or 'tube'"),
        ("center", list(_PLANE_DEFAULTS["center"]), "plane: centre in m"),
        ("normal", list(_PLANE_DEFAULTS["normal"]), "plane: normal, pointing to the side where the tool is allowed"),
        ("size", _PLANE_DEFAULTS["size"], "plane: side length in m, or [length_u, length_v]"),
        ("divisions", _PLANE_DEFAULTS["divisions"], "plane: cells per side, or [n_u, n_v] (2 triangles per cell)"),
        ("start", list(_TUBE_DEFAULTS["start"]), "tube: first axis point in m"),
        ("end", list(_TUBE_DEFAULTS["end"]), "tube: last axis point in m"),
        ("radius", _TUBE_DEFAULTS["radius"], "tube: radius in m (normals point to the axis: tool inside)"),
        ("n_circumferential", _TUBE_DEFAULTS["n_circumferential"], "tube: nodes around each ring (>= 3)"),
        ("n_axial", _TUBE_DEFAULTS["n_axial"], "tube: segments along the axis (>= 1)"),
    ],
    "device_plant": [
        ("mass", 0.1, "moving mass of the device in kg (> 0)"),
        ("damping", 1.0, "physical damping b_dev in N s/m (>= 0)"),
        ("step", 0.001, "haptic step in s; must equal the step the scene gives the plant"),
        ("initial_position", [0.0, 0.0, 0.0], "position at the start in m"),
        ("initial_velocity", [0.0, 0.0, 0.0], "velocity at the start in m/s"),
    ],
}


def block_options(kind: str) -> list[tuple[str, object, str]]:
    """The options of a block kind as (name, default, meaning); default ``REQUIRED`` when required."""
    if kind not in _OPTIONS:
        raise KeyError(f"unknown block kind {kind!r}: kinds are {list(BLOCK_KINDS)}")
    return list(_OPTIONS[kind])


def _collect(kind, opts, base_dir) -> list[str]:
    """Every value problem of the present options (missing required keys are reported elsewhere)."""
    problems: list[str] = []
    if kind == "piecewise_linear":
        times = _check_times(problems, opts["times"]) if "times" in opts else None
        if "outputs" in opts:
            _check_outputs(problems, opts["outputs"], None if times is None else len(times))
        _choice(problems, "interpolation", opts.get("interpolation", "linear"), INTERPOLATIONS)
        if isinstance(opts.get("outputs"), dict):
            _units(problems, "units", opts.get("units"), list(opts["outputs"]))
    elif kind == "csv":
        _choice(problems, "interpolation", opts.get("interpolation", "linear"), INTERPOLATIONS)
        time_column = opts.get("time_column", "time")
        if not isinstance(time_column, str):
            problems.append(f"time_column must be a column name (got {time_column!r})")
        columns_ok = "columns" in opts and _check_columns(problems, opts["columns"])
        if columns_ok:
            _units(problems, "units", opts.get("units"), list(opts["columns"]))
        if "path" in opts and not isinstance(opts["path"], str):
            problems.append(f"path must be a file path string (got {opts['path']!r})")
        elif "path" in opts and columns_ok and isinstance(time_column, str):
            _read_csv(problems, _resolve(opts["path"], base_dir), opts["columns"], time_column)
    elif kind == "rigid_surface":
        _check_surface(problems, opts.get("shape", "plane"), {k: v for k, v in opts.items() if k != "shape"})
    elif kind == "device_plant":
        _check_plant(problems, opts)
    return problems


def _resolve(path, base_dir) -> Path:
    p = Path(path)
    return p if p.is_absolute() else Path(base_dir) / p


def make_block(name: str, table: dict, base_dir: Path):
    """Build the block described by a scene's TOML table (``kind`` plus the kind's options).

    Raises ``BlockConfigError`` listing every problem at once (unknown, missing or invalid keys).
    """
    kind = table.get("kind")
    if not isinstance(kind, str) or kind not in BLOCK_KINDS:
        got = "no 'kind' key" if "kind" not in table else f"kind = {kind!r}"
        raise BlockConfigError([f"kind must be one of {list(BLOCK_KINDS)} ({got})"], name)
    opts = {k: v for k, v in table.items() if k != "kind"}
    valid = [o[0] for o in _OPTIONS[kind]]
    problems = [f"unknown key {k!r} for kind = {kind!r}: valid keys are {valid}" for k in opts if k not in valid]
    problems += [f"missing required key {o[0]!r}: {o[2]}" for o in _OPTIONS[kind]
                 if o[1] is REQUIRED and o[0] not in opts]
    known = {k: v for k, v in opts.items() if k in valid}
    problems += _collect(kind, known, base_dir)
    if problems:
        raise BlockConfigError(problems, name)
    if kind == "piecewise_linear":
        return PiecewiseLinearSource(name, **known)
    if kind == "csv":
        known["path"] = _resolve(known["path"], base_dir)
        return CsvSource(name, **known)
    if kind == "rigid_surface":
        return RigidSurfaceSource(name, **known)
    return DevicePlant(name, **known)

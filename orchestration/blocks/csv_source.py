"""Playback of recorded motion from a CSV file, read as data: bounded lines, every field checked."""
from __future__ import annotations

import csv
import math
import re
from pathlib import Path

import numpy as np

from orchestration.blocks.options import BlockConfigError, check_choice, check_units
from orchestration.blocks.sources import INTERPOLATIONS, PiecewiseLinearSource


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


def read_csv(problems, path: Path, columns: dict, time_column: str, key="path"):
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


def check_columns(problems, columns):
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
        check_choice(problems, "interpolation", interpolation, INTERPOLATIONS)
        units = check_units(problems, "units", units, list(columns) if isinstance(columns, dict) else [])
        times, clean = None, {}
        if not isinstance(path, (str, Path)):
            problems.append(f"path must be a file path (got {path!r})")
        elif check_columns(problems, columns) and isinstance(time_column, str):
            times, clean = read_csv(problems, Path(path), columns, time_column)
        if problems:
            raise BlockConfigError(problems, name)
        self.path = Path(path)
        self._build(name, times, clean, interpolation, units)

"""PNG plots of recorded signals, read back from the streamed CSV files.

Uses matplotlib's object API with the Agg canvas directly (no pyplot, no display, no global
backend switch), so it is safe in a headless run and in worker processes.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from orchestration.observers.recorder import RecordingError, port_values, read_stream

log = logging.getLogger(__name__)

#: An array port plotted component by component draws at most this many lines (a surface has thousands).
MAX_COMPONENT_LINES = 12


def _load_units(out_dir: Path) -> dict:
    try:
        return json.loads((out_dir / "units.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def _check_figure(index: int, figure) -> None:
    if not isinstance(figure, dict) or not isinstance(figure.get("file"), str) or not figure["file"]:
        raise RecordingError(f"figure {index}: needs a 'file' name such as 'forces.png' (got {figure!r})")
    file = figure["file"]
    if any(c in file for c in "/\\\0") or file.startswith(".") or not file.lower().endswith(".png"):
        # anything else could overwrite another result in the folder (units.json, a CSV) or leave it
        raise RecordingError(f"figure {index}: file {file!r} is not a plain .png file name in the result folder "
                             "(e.g. 'forces.png')")
    panels = figure.get("panels")
    if not isinstance(panels, list) or not panels:
        raise RecordingError(f"figure {figure['file']!r}: 'panels' must be a non-empty list of "
                             "{'ylabel': ..., 'series': [...]}")
    for panel in panels:
        if not isinstance(panel, dict) or not isinstance(panel.get("series", []), list):
            raise RecordingError(f"figure {figure['file']!r}: each panel is a dict with a 'series' list "
                                 f"(got {panel!r})")
        for series in panel.get("series", []):
            if not isinstance(series, dict) or "stream" not in series or "column" not in series:
                raise RecordingError(f"figure {figure['file']!r}: each series needs 'stream' and 'column' "
                                     f"(got {series!r})")


def _series_lines(series: dict, streams: dict, out_dir: Path, figure_file: str):
    """The (time, values, label) lines of one series, or [] with a warning if its data is missing."""
    name, column = series["stream"], series["column"]
    if name not in streams:
        path = out_dir / f"{name}.csv"
        try:
            streams[name] = read_stream(path)
        except (OSError, ValueError) as exc:
            log.warning("%s: stream %r not plotted: %s", figure_file, name, exc)
            streams[name] = None
    if streams[name] is None:
        return []
    t, columns = streams[name]
    try:
        values = port_values(columns, column)
    except KeyError:
        log.warning("%s: stream %r has no column %r (has %s); series skipped",
                    figure_file, name, column, ", ".join(sorted(columns)) or "none")
        return []
    label = series.get("label") or f"{name}.{column}"
    if values.shape[1] == 1:
        return [(t, values[:, 0], label)]
    if series.get("norm", False):
        return [(t, np.sqrt(np.einsum("ij,ij->i", values, values)), f"|{label}|")]
    if values.shape[1] > MAX_COMPONENT_LINES:
        log.warning("%s: %s has %d components; plotting the first %d (use norm=True for the magnitude)",
                    figure_file, label, values.shape[1], MAX_COMPONENT_LINES)
    return [(t, values[:, i], f"{label}[{i}]") for i in range(min(values.shape[1], MAX_COMPONENT_LINES))]


def plot_signals(out_dir: Path | str, figures: list[dict]) -> list[Path]:
    """Draw each figure spec into ``out_dir/<file>``; returns the PNG paths written.

    A figure is ``{"file", "title", "panels": [{"ylabel", "series": [{"stream", "column",
    "label", "norm"}]}]}``; panels stack vertically on a shared time axis. A missing stream or
    column is logged as a warning and skipped; the panel then says "no data".
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    out_dir = Path(out_dir)
    files: dict[str, int] = {}
    for index, figure in enumerate(figures):
        _check_figure(index, figure)
        # Two figures into one file: the second would overwrite the first without a word.
        # Compared without case: many file systems do not tell Forces.png from forces.png.
        first = files.setdefault(figure["file"].casefold(), index)
        if first != index:
            raise RecordingError(f"figure {index} ({figure['file']!r}): figure {first} is drawn into the same file; "
                                 "give each figure a file of its own")
    units = _load_units(out_dir)
    streams: dict = {}
    written = []
    for spec in figures:
        path = out_dir / spec["file"]
        if path.is_symlink() or (path.exists() and not path.is_file()):
            # another result (a surface's frame folder) has that name: keep it, draw the others
            log.warning("%s: not drawn, %s is already something else (a folder?); give the figure another file name",
                        spec["file"], path)
            continue
        panels = spec["panels"]
        fig = Figure(figsize=(9, 2.4 * len(panels) + 0.8), layout="constrained")
        FigureCanvasAgg(fig)
        axes = fig.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
        for ax, panel in zip(axes, panels):
            drawn = 0
            unit = None
            for series in panel.get("series", []):
                for t, y, label in _series_lines(series, streams, out_dir, spec["file"]):
                    ax.plot(t, y, label=label, linewidth=1.0)
                    drawn += 1
                unit = unit or _unit_of(units, series)
            if drawn:
                ax.legend(loc="best", fontsize="small")
            else:
                ax.text(0.5, 0.5, "no data", transform=ax.transAxes, ha="center", va="center", color="grey")
            ax.set_ylabel(panel.get("ylabel") or unit or "")
            ax.grid(True, alpha=0.3)
        axes[-1].set_xlabel("time (s)")
        if spec.get("title"):
            fig.suptitle(spec["title"])
        fig.savefig(path, format="png", dpi=100)
        written.append(path)
        log.debug("plot written: %s", path)
    return written


def _unit_of(units: dict, series: dict) -> str | None:
    stream_units = units.get(series["stream"], {})
    column = series["column"]
    return stream_units.get(column) or stream_units.get(f"{column}[0]")

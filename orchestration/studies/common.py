"""What the studies share: running one scene point and writing tables."""
from __future__ import annotations

import csv
import logging
import tempfile
from pathlib import Path

import numpy as np

from orchestration.scene.model import Hosting

logger = logging.getLogger(__name__)


def run_point(scene: str, overrides: dict | None = None, *, duration: float | None = None,
              observe: dict[str, list[str]] | None = None, out_dir: Path | str | None = None,
              hosting: str = Hosting.IN_PROCESS):
    """Run a shipped scene (or a scene file) with parameter overrides; no plots, no VTU, no progress.

    Returns ``(summary, simulation)``: ``simulation.final_outputs[component][port]`` holds the
    last outputs (ports in ``observe`` included) and CSVs are in ``out_dir`` (a temp folder when
    None, removed afterwards). A scene problem raises ``SceneError``; an FMU failure is reported
    in ``summary["status"]`` / ``summary["error"]``.
    """
    from orchestration.run.simulation import Simulation
    from orchestration.scene.loading import load_scene

    loaded = load_scene(scene, dict(overrides or {}))
    with tempfile.TemporaryDirectory(prefix="study_point_") as tmp:
        target = Path(out_dir) if out_dir is not None else Path(tmp)
        simulation = Simulation(loaded, target, hosting=hosting, progress=False, duration=duration,
                                plots=False, vtu=False, observe=observe)
        summary = simulation.run()
        if out_dir is None:
            simulation.streams = {}
            for comp in loaded.record:
                path = target / f"{comp}.csv"
                if path.exists():
                    from orchestration.observers.recorder import read_stream

                    simulation.streams[comp] = read_stream(path)
    return summary, simulation


def write_table(path: Path | str, rows: list[dict]) -> Path:
    """Rows (dicts with the same keys) as a CSV with quoted headers."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    keys: list[str] = []
    for row in rows:
        for key in row:
            if key not in keys:
                keys.append(key)
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=keys, quoting=csv.QUOTE_NONNUMERIC)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: _plain(row.get(k)) for k in keys})
    return path


def _plain(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return "" if value is None else value

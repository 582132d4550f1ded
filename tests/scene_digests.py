"""Digests of what a shipped scene's run writes, the guard of changes that must not change results.

A run's CSVs, units, wall files and summary are reduced to SHA-256 digests; the summary first loses
what depends on the machine's speed and the folder (wall-clock times, real-time factor, paths).
`tests/data/shipped_scene_digests.json` holds the digests of every shipped scene; a change that
means to change results regenerates it, and its commit says why:

    .venv/bin/python tests/scene_digests.py --update
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from project import shipped_scenes

ROOT = Path(__file__).resolve().parent.parent
STORED = Path(__file__).resolve().parent / "data" / "shipped_scene_digests.json"
# Summary fields measured by the clock, not computed by the models.
CLOCK_FIELDS = {"wall_time_s", "setup_time_s", "real_time_factor", "busy_wall_s", "step_cost"}
# Files whose bytes depend on the plotting library's renderer, not on the results.
SKIPPED_SUFFIXES = {".png"}


def _without_clock(value, folder: str):
    if isinstance(value, dict):
        return {key: _without_clock(item, folder) for key, item in value.items() if key not in CLOCK_FIELDS}
    if isinstance(value, list):
        return [_without_clock(item, folder) for item in value]
    if isinstance(value, str) and value.startswith(folder):
        return value[len(folder):]
    return value


def folder_digests(folder: Path) -> dict[str, str]:
    """SHA-256 of every file a run wrote into `folder`, by its path relative to the folder."""
    digests = {}
    for path in sorted(folder.rglob("*")):
        if not path.is_file() or path.suffix in SKIPPED_SUFFIXES:
            continue
        data = path.read_bytes()
        if path.name == "summary.json":
            summary = _without_clock(json.loads(data), str(folder))
            data = json.dumps(summary, indent=1, sort_keys=True).encode()
        digests[path.relative_to(folder).as_posix()] = hashlib.sha256(data).hexdigest()
    return digests


def run_scene(name: str, out: Path) -> None:
    """Runs a shipped scene as a user does, from the command line."""
    subprocess.run([sys.executable, "-m", "orchestration", "run", name, "--out", str(out), "--quiet"],
                   cwd=ROOT, check=True, capture_output=True, text=True)


def scene_digests(name: str, workdir: Path) -> dict[str, str]:
    out = workdir / name
    run_scene(name, out)
    return folder_digests(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--update", action="store_true", help=f"write {STORED.relative_to(ROOT)}")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as workdir:
        digests = {name: scene_digests(name, Path(workdir)) for name in shipped_scenes()}
    text = json.dumps(digests, indent=1, sort_keys=True) + "\n"
    if args.update:
        STORED.write_text(text)
    else:
        sys.stdout.write(text)


if __name__ == "__main__":
    main()

"""Studies: measurements of the speed/accuracy trade and of numerical stability (issue 6).

``python -m orchestration study tradeoff | stability | extremes`` runs one; each writes a CSV of
every point, PNG figures and a short Markdown report into ``results/study_<name>/``. Points run
in parallel through ``orchestration.studies.sweep`` (a local process pool, or a Dask cluster with
``--scheduler``), are resumable, and a failed point is recorded and does not stop the study.
``--quick`` runs the reduced version the tests run.
"""
from __future__ import annotations

import importlib
import sys
from pathlib import Path

STUDIES = ("tradeoff", "stability", "extremes")


def run_study(name: str, *, out: Path | str | None = None, quick: bool = False, workers: int | None = None,
              scheduler: str | None = None, fresh: bool = False, quiet: bool = False) -> int:
    """Run study ``name`` into ``out`` (default results/study_<name>); returns an exit code.

    The FMUs must be built (``orchestration.app.warmup.ensure_fmus_built``).
    """
    if name not in STUDIES:
        raise ValueError(f"no study {name!r}; studies: {', '.join(STUDIES)}")
    if workers is not None and (not isinstance(workers, int) or isinstance(workers, bool) or workers < 1):
        raise ValueError(f"workers = {workers!r}: give a whole number of processes >= 1, or None for the CPU count")
    module = importlib.import_module(f"{__name__}.{name}")
    out = Path(out) if out else Path("results") / f"study_{name}"
    finished = out / "points.jsonl"
    if fresh and finished.exists():
        # Resuming keys points by their parameters only: after a change to the code, start over.
        finished.rename(finished.with_suffix(".jsonl.old"))
    try:
        report = module.run(out, quick=quick, workers=workers, scheduler=scheduler, progress=not quiet)
    except KeyboardInterrupt:
        print(f"interrupted: finished points are kept in {out}; run the same command again to resume",
              file=sys.stderr)
        return 1
    if not quiet:
        print(report.read_text() if hasattr(report, "read_text") else report)
    print(f"study results: {out}/")
    return 0

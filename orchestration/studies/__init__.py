"""Studies: measurements of the speed/accuracy trade and of numerical stability (issue 6).

``python -m orchestration study tradeoff | stability | extremes`` runs one; each writes a CSV of
every point, PNG figures and a short Markdown report into ``results/study_<name>/``. Points run
in parallel through ``orchestration.sweep`` (a local process pool, or a Dask cluster with
``--scheduler``), are resumable, and a failed point is recorded and does not stop the study.
``--quick`` runs the reduced version the tests run.
"""
from __future__ import annotations

import importlib
import sys
from pathlib import Path

STUDIES = ("tradeoff", "stability", "extremes")


def run_study(args) -> int:
    """CLI entry: ``args`` has name, out, quick, workers, scheduler, fresh, quiet."""
    from ..cli import ensure_fmus_built

    ensure_fmus_built(args.quiet)
    module = importlib.import_module(f"{__name__}.{args.name}")
    out = Path(args.out) if args.out else Path("results") / f"study_{args.name}"
    finished = out / "points.jsonl"
    if getattr(args, "fresh", False) and finished.exists():
        # Resuming keys points by their parameters only: after a change to the code, start over.
        finished.rename(finished.with_suffix(".jsonl.old"))
    try:
        report = module.run(out, quick=args.quick, workers=args.workers, scheduler=args.scheduler,
                            progress=not args.quiet)
    except KeyboardInterrupt:
        print(f"interrupted: finished points are kept in {out}; run the same command again to resume",
              file=sys.stderr)
        return 1
    if not args.quiet:
        print(report.read_text() if hasattr(report, "read_text") else report)
    print(f"study results: {out}/")
    return 0

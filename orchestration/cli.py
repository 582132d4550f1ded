"""Command-line interface of the project (``python -m orchestration ...``)."""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

logger = logging.getLogger("orchestration")


def _cmd_build(args) -> int:
    from .build import BuildError, available_fmus, build_all

    names = args.fmus or available_fmus()
    try:
        for path in build_all(names, Path(args.dest)):
            print(f"built {path}")
    except BuildError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def _cmd_run(args) -> int:
    from .mainjob import run_main_job

    return run_main_job(args)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m orchestration", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command")

    p_build = sub.add_parser("build", help="build the FMUs into fmus/")
    p_build.add_argument("fmus", nargs="*", help="FMUs to build (default: all available)")
    p_build.add_argument("--dest", default=str(Path(__file__).resolve().parent.parent / "fmus"))
    p_build.set_defaults(func=_cmd_build)

    p_run = sub.add_parser("run", help="run the default AAA simulation (builds the FMUs if needed)")
    p_run.add_argument("--duration", type=float, default=2.0, help="simulated seconds (default 2)")
    p_run.add_argument("--out", default="results/aaa_tissue", help="result folder")
    p_run.add_argument("--quiet", action="store_true", help="no progress bar")
    p_run.set_defaults(func=_cmd_run)

    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if args.command is None:
        # No arguments: the main job.
        args = parser.parse_args(["run", *(argv or [])])
    return args.func(args)

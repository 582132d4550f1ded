"""Command-line interface of the project (``python -m orchestration ...``).

``build`` builds the FMUs, ``validate SCENE`` checks a scene and lists every problem, ``run
[SCENE]`` runs one (default: the AAA endovascular scene), ``export SCENE --ssp OUT.ssp`` writes one
as an SSP package (which ``validate`` and ``run`` take as a scene), ``study NAME`` runs a study. A
user's mistake gives a message and a non-zero exit code, never a traceback.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from fmu_build.paths import DEFAULT_FMU_DIR
from orchestration.hosts.native_threads import limit_native_threads
from orchestration.run.status import COMPLETE
from orchestration.scene.model import HOSTINGS
from orchestration.studies import STUDIES

logger = logging.getLogger("orchestration")

DEFAULT_SCENE = "aaa_endovascular"
#: Exit codes: 0 the command did what was asked (a run "completed" or "terminated" by an FMU, its
#: results in the result folder); 1 a run or study started and failed (what was recorded is kept);
#: 2 nothing was run: a usage or scene error, with "error: ..." on stderr; 130 / 143 a run stopped
#: by Ctrl-C / SIGTERM (see RUN_EPILOG).
EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2

RUN_EPILOG = """\
exit codes:
  0    the run completed (or an FMU ended it with terminateSimulation)
  1    the run failed (an FMU error, a crashed worker, a worker that stopped answering)
  2    a usage error: the scene, an argument, or an --out that cannot be used (read-only, a file in the
       way, another run using it, files in it that no run wrote, /, ., the project's folder); nothing ran
  130  stopped by Ctrl-C (SIGINT)
  143  stopped by SIGTERM
       The run stops between two steps (status "interrupted"; "completed" if the simulation had already
       reached its end, then only the plots are skipped); the summary is written and printed either
       way. A second Ctrl-C stops faster (workers are killed instead of waited for).

results: the run writes into OUT.running and moves it into place when it ends, so earlier results are
never overwritten by a run that did not finish:
  completed         OUT (the earlier OUT is replaced)
  interrupted       OUT.interrupted, and OUT keeps the last complete run
  failed            OUT.failed, and OUT keeps the last complete run
  killed (SIGKILL)  OUT.running, renamed OUT.killed by the next run into OUT
Why beside and not in place: the partial rows are results and are kept, but a Ctrl-C must never cost
the last complete results. OUT.lock holds the PID of the run using OUT; a second run into the same
OUT is refused (a lock left by a dead run is taken over).
A run deletes only what runs wrote: an OUT holding anything else (your notes, an analysis folder) is
refused before the run, naming what it holds; move those files out or choose another OUT. OUT is a
folder of its own: not /, not the current folder or one that holds it, not the project's folder. An
OUT that is a symbolic link is followed: the results replace its target, the link stays.
"""


def _cmd_build(args) -> int:
    from fmu_build.errors import BuildError
    from fmu_build.package import build_all
    from fmu_build.portable_runtime import prepare_carried_runtime
    from fmu_build.report import first_load_seconds, fmu_contents
    from fmu_build.specs import available_fmus
    from orchestration.app.warmup import add_carried_kernels

    names = args.fmus or available_fmus()
    try:
        prepare_carried_runtime()
        built = build_all(names, Path(args.dest))
        add_carried_kernels(built)
        for path in built:
            first = first_load_seconds(path)
            load = (f"; first load {first:.1f} s (instantiation to the first step's end, as on a machine that "
                    "never ran it)" if first is not None else "; carries no Python runtime (needs the build's)")
            print(f"built {path}: {path.stat().st_size / 1e6:.0f} MB ({fmu_contents(path)}){load}")
    except BuildError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    return EXIT_OK


def parse_assignments(items: list[str]) -> dict:
    """``["contact.stiffness=800", "scene.duration=2"]`` -> typed overrides (TOML value syntax).

    ValueError names the item and the fix; whether the parameter exists is the scene's check.
    """
    import tomllib

    overrides = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or key.count(".") != 1 or not all(part.strip() for part in key.split(".")):
            raise ValueError(f"--set {item!r}: write component.parameter=value, e.g. contact.stiffness=800")
        if any(c in text for c in "\n\r\0"):
            # "v = 1\nw = 2" would parse as TOML and silently drop the rest
            raise ValueError(f"--set {item!r}: the value has a line break or NUL; give one TOML value, "
                             "e.g. 800, \"probe\" or [0.0, 0.1]")
        if key in overrides:
            raise ValueError(f"--set {key}: given twice; give each parameter once")
        try:
            value = tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError:
            value = text  # a bare word: a string
        overrides[key] = value
    return overrides


def _duration(text: str):
    """``--duration``: a finite positive time in seconds, exact ("0.5", "1e-3", "1/30")."""
    from orchestration.scene.timing import parse_time

    problems: list[str] = []
    value = parse_time(text, "--duration", problems)
    if problems:
        raise argparse.ArgumentTypeError(problems[0].removeprefix("--duration: "))
    return value


def _workers(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number of processes, e.g. --workers 2") from None
    if not 1 <= value <= 256:
        raise argparse.ArgumentTypeError(f"{value} processes: give 1 to 256 (default: the CPU count)")
    return value


def _scheduler(text: str) -> str:
    from urllib.parse import urlsplit

    try:
        parts = urlsplit(text)
        port = parts.port
    except ValueError:
        port = None
        parts = None
    if parts is None or not parts.scheme or not parts.hostname or port is None:
        raise argparse.ArgumentTypeError(f"{text!r} is not a Dask scheduler address; write tcp://host:8786")
    return text


EMPTY_OUT = "--out: empty; give a folder, e.g. --out results/mine"  # Path("") would be ".", the current folder


def _out_problem(out: str) -> str | None:
    """Why ``--out`` cannot be a study's result folder, or None; creates it (as the study would) to know."""
    if not out.strip():
        return EMPTY_OUT
    path = Path(out)
    try:
        if path.exists() and not path.is_dir():
            return f"--out {out}: exists and is not a folder; give a folder for the results"
        path.mkdir(parents=True, exist_ok=True)
    except (OSError, ValueError) as exc:
        return f"--out {out!r}: cannot create the result folder ({getattr(exc, 'strerror', None) or exc})"
    return None


def _load(scene_arg: str, overrides: dict | None = None):
    from orchestration.scene.model import SceneError
    from orchestration.scene.loading import load_scene

    try:
        return load_scene(scene_arg, overrides)
    except SceneError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None


def _scene_of(args):
    """The scene ``args.scene`` with the overrides of ``--set`` and ``--duration`` (checked with the
    scene: whole steps, the run-size limit), and those overrides; None after saying what is wrong."""
    try:
        overrides = parse_assignments(args.set)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None
    if args.duration is not None:
        overrides["duration"] = args.duration
    scene = _load(args.scene, overrides)
    return None if scene is None else (scene, overrides)


def _cmd_validate(args) -> int:
    from orchestration.scene.model import SceneError
    from orchestration.scene.loading import load_scene

    try:
        overrides = parse_assignments(args.set)
        if args.duration is not None:
            overrides["duration"] = args.duration
        scene = load_scene(args.scene, overrides)
    except (SceneError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(f"{scene.path}: OK")
    for comp in scene.components.values():
        rate = "continuous" if comp.step is None else f"step {comp.step} s ({float(1 / comp.step):g} Hz)"
        print(f"  {comp.name:12s} {comp.kind:18s} {rate}")
    for conn in scene.connections:
        extra = f", {conn.transition}" if conn.transition else ""
        print(f"  {conn.source}.{conn.source_port} -> {conn.target}.{conn.target_port} ({conn.ordering}{extra})")
    for note in scene.notes:
        print(f"  note: {note}")
    return EXIT_OK


def _cmd_export(args) -> int:
    from fmu_build.errors import BuildError
    from orchestration.app.scene_fmu import SceneFmuError, export_scene_fmu
    from orchestration.scene.ssp import SspExportError, export_ssp

    if args.ssp is None and args.fmu is None:
        print("error: export: say which format to write: `export SCENE --ssp out.ssp` (an SSP package) or "
              "`export SCENE --fmu out.fmu` (the scene as one FMU)", file=sys.stderr)
        return EXIT_USAGE
    if args.ssp is not None and (args.outputs or args.horizon is not None):
        print("error: export: --outputs and --horizon are options of --fmu", file=sys.stderr)
        return EXIT_USAGE
    loaded = _scene_of(args)
    if loaded is None:
        return EXIT_USAGE
    scene, overrides = loaded
    if args.fmu is not None:
        try:
            print(f"exporting {scene.name} as one FMU (a Python runtime of its own: a minute the first time) ...",
                  flush=True)
            out = export_scene_fmu(scene, Path(args.fmu), outputs=args.outputs, horizon=args.horizon,
                                   overrides=overrides, force=args.force)
        except (SceneFmuError, BuildError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return EXIT_USAGE
        print(f"wrote {out}: {scene.name} as one FMU, {out.stat().st_size / 1e6:.0f} MB (its ports: "
              "modelDescription.xml; docs/composition.md)")
        return EXIT_OK
    try:
        out = export_ssp(scene, Path(args.ssp), force=args.force)
    except SspExportError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    fmus = sum(1 for c in scene.components.values() if c.is_fmu)
    print(f"wrote {out}: {scene.name}, {fmus} FMU{'s' if fmus != 1 else ''}, {out.stat().st_size / 1e6:.0f} MB "
          f"(run it with `python -m orchestration run {out}`)")
    return EXIT_OK


def _cmd_run(args) -> int:
    from orchestration.stopping import stop_signals

    # From here to the exit code, Ctrl-C and SIGTERM only set a flag (python -m orchestration
    # installed the handlers before its imports; main() called from Python installs them here).
    with stop_signals() as stop:
        return _run_command(args, stop)


def _run_command(args, stop) -> int:
    from orchestration.app.result_folder import OutputFolderError, ResultFolder

    # An --out that cannot be used is refused first, before a build or a scene load can take a
    # minute (the default folder needs the scene's name: it is checked once the scene is loaded).
    if args.out is not None and not args.out.strip():
        print(f"error: {EMPTY_OUT}", file=sys.stderr)
        return EXIT_USAGE
    try:
        if args.out is None:
            return _prepare_and_run(args, stop, None)
        with ResultFolder(args.out) as folder:
            return _prepare_and_run(args, stop, folder)
    except OutputFolderError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE


def _prepare_and_run(args, stop, folder) -> int:
    """Build, load the scene, run it into ``folder`` (None: the default ``results/<scene>``)."""
    from fmu_build.errors import BuildError
    from orchestration.app.warmup import ensure_fmus_built
    from orchestration.run.simulation import Simulation
    from orchestration.app.result_folder import ResultFolder

    try:
        ensure_fmus_built(args.quiet)
    except BuildError as exc:
        if stop.requested:  # the build's compiler got the Ctrl-C too
            print(f"error: {stop.reason} while building the FMUs; nothing ran", file=sys.stderr)
            return stop.exit_code
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    loaded = _scene_of(args)
    if loaded is None:
        return EXIT_USAGE
    scene, _ = loaded
    if folder is None:
        with ResultFolder(Path("results") / scene.name) as folder:
            return _simulate(args, stop, scene, folder, Simulation)
    return _simulate(args, stop, scene, folder, Simulation)


def _simulate(args, stop, scene, folder, Simulation) -> int:
    try:
        simulation = Simulation(scene, folder.out, hosting=args.hosting, realtime=args.realtime or None,
                                progress=not args.quiet, vtu=not args.no_vtu, folder=folder,
                                compiled_loop=not args.python_loop)
    except ValueError as exc:  # Simulation checks the duration again (the scene did: not reached)
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if not args.quiet:
        print(f"running {scene.name} ({scene.description or scene.path}) for {float(simulation.duration):g} s, "
              f"{simulation.hosting} ...", flush=True)
    summary = simulation.run()
    text = simulation.summary_text
    ok = summary["status"] in COMPLETE
    # The exit code tells what the summary says: a signal that came after it was written (while
    # printing) changes nothing that happened.
    stopped = "stop_request" in summary
    if not args.quiet or not ok or stopped:
        print(text, flush=True)
    results = simulation.results_dir
    if stopped:
        kept = f"; {folder.out} keeps the last complete run" if not ok and folder.out.exists() else ""
        print(f"{stop.reason}: status {summary['status']}, results in {results}{kept}", file=sys.stderr)
        return stop.exit_code
    if not ok:
        kept = f" ({folder.out} keeps the last complete run)" if folder.out.exists() else ""
        print(f"error: {summary['error']}\nresults up to the failure are in {results}{kept}", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK


def _cmd_study(args) -> int:
    from fmu_build.errors import BuildError
    from orchestration.app.warmup import ensure_fmus_built
    from orchestration.studies import run_study

    problem = _out_problem(args.out) if args.out is not None else None
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return EXIT_USAGE
    try:
        ensure_fmus_built(args.quiet)
    except BuildError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    return run_study(args.name, out=args.out, quick=args.quick, workers=args.workers, scheduler=args.scheduler,
                     fresh=args.fresh, quiet=args.quiet)


def _cmd_scene_from_anatomy(args) -> int:
    import time

    from anatomy.errors import AnatomyError
    from orchestration.app.anatomy_scene import write_anatomy_scene

    started = time.perf_counter()

    def stage(text: str) -> None:
        if not args.quiet:
            print(f"[{time.perf_counter() - started:6.1f} s] {text}", flush=True)

    try:
        surface, name = _anatomy_surface(args, stage)
        anatomy = _build_anatomy(args, surface, stage)
        out = Path(args.out) if args.out else Path(name)
        stage(f"writing the scene into {out}/")
        written = write_anatomy_scene(anatomy, out, name, duration=args.duration, contact_time=args.contact_time,
                                      force=args.force)
    except (AnatomyError, FileExistsError, OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if not args.quiet:
        print(anatomy.surface.report())
        quality = anatomy.wall.quality()
        print(f"wall: {anatomy.wall.n_nodes} nodes, {anatomy.wall.n_tets} tetrahedra, worst radius ratio "
              f"{quality['min_radius_ratio']:.3f}; centerline {anatomy.centerline.length() * 1e3:.1f} mm, the sac "
              f"reaches {anatomy.sac_reach * 1e3:.1f} mm ({anatomy.sac_reach / anatomy.reference_radius:.2f}x the "
              f"neck's radius); the tip should meet the sac wall at about {written.contact_time:.2f} s")
        for note in anatomy.notes:
            print(f"note: {note}")
        print(f"wrote {written.scene}, {written.wall.name}, {written.lumen.name}, {written.centerline.name}")
        print(f"run it: python -m orchestration run {written.scene}")
    return EXIT_OK


def _anatomy_surface(args, stage):
    """The checked lumen surface the command was given (a file or family:<member>) and the scene's name."""
    from anatomy.surface import check_surface, read_surface

    if args.surface.startswith("family:"):
        from anatomy.family import lumen_surface

        kind = args.surface.split(":", 1)[1]
        stage(f"generating the parametric aneurysm {kind!r}")
        shape = parse_shape(args.shape)
        surface = check_surface(lumen_surface(kind, **shape), "m", source=args.surface)
        return surface, args.name or f"aaa_{kind}"
    stage(f"reading {args.surface}")
    return read_surface(args.surface, args.units), args.name or Path(args.surface).stem


def _build_anatomy(args, surface, stage):
    from anatomy.pipeline import WallOptions, build_anatomy

    options = WallOptions(thickness=args.thickness, sac_thickness=args.sac_thickness, layers=args.layers,
                          edge_length=args.edge_length, remesh=args.remesh)
    stage("building the wall and the centerline (remeshing first when the triangles do not fit)")
    return build_anatomy(surface, options, access=args.access, target=args.target)


def parse_shape(items: list[str] | None) -> dict:
    """``--shape aneurysm_radius=0.03``: a parametric aneurysm's parameters (TOML values)."""
    import tomllib

    from anatomy.errors import AnatomyError

    shape = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise AnatomyError(f"--shape {item!r}: write name=value, e.g. aneurysm_radius=0.03")
        try:
            shape[key.strip()] = tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError:
            raise AnatomyError(f"--shape {item!r}: the value must be a number (metres, degrees as named)") from None
    return shape


def _release_stop_signals() -> None:
    from orchestration import stopping

    stopping.uninstall()  # re-raises a Ctrl-C that arrived before the command was known


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m orchestration", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command")

    p_build = sub.add_parser("build", help="build the FMUs into fmus/")
    p_build.add_argument("fmus", nargs="*", help="FMUs to build (default: all available)")
    p_build.add_argument("--dest", default=str(DEFAULT_FMU_DIR))
    p_build.set_defaults(func=_cmd_build)

    p_val = sub.add_parser("validate", help="check a scene and list every problem")
    p_val.add_argument("scene", help="scene file, or the name of a shipped scene (scenes/<name>.toml)")
    p_val.add_argument("--set", action="append", metavar="COMP.PARAM=VALUE", help="override a parameter")
    p_val.add_argument("--duration", type=_duration, default=None,
                       help="check this duration in s instead of the scene's, as `run --duration` would run it")
    p_val.set_defaults(func=_cmd_validate)

    p_run = sub.add_parser("run", help="run a scene (default: the AAA endovascular scene; builds the FMUs if needed)",
                           epilog=RUN_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p_run.add_argument("scene", nargs="?", default=DEFAULT_SCENE, help=f"scene file or name (default {DEFAULT_SCENE})")
    p_run.add_argument("--duration", type=_duration, default=None,
                       help="simulated seconds, e.g. 0.5 or 1/30 (default: the scene's)")
    p_run.add_argument("--out", default=None, help="result folder (default results/<scene>); replaced only by a "
                                                  "run that completes, see below")
    p_run.add_argument("--hosting", choices=HOSTINGS, default=None,
                       help="run every FMU in this process or each in a worker process of its own (default: "
                            "the scene's choice per FMU; the shipped tissue scenes put the 30 Hz tissue in a worker)")
    p_run.add_argument("--realtime", action="store_true", help="pace to the wall clock and count missed haptic deadlines")
    p_run.add_argument("--set", action="append", metavar="COMP.PARAM=VALUE", help="override a parameter")
    p_run.add_argument("--no-vtu", action="store_true", help="do not write the surface time series")
    p_run.add_argument("--python-loop", action="store_true",
                       help="make every step from Python, not stretches of in-process steps in C (the same results, "
                            "slower; for comparison)")
    p_run.add_argument("--quiet", action="store_true", help="no progress bar and no summary unless it fails")
    p_run.set_defaults(func=_cmd_run)

    p_export = sub.add_parser("export", help="write a scene in another format: --ssp, an SSP package")
    p_export.add_argument("scene", help="scene file, or the name of a shipped scene (scenes/<name>.toml)")
    formats = p_export.add_mutually_exclusive_group()
    formats.add_argument("--ssp", metavar="OUT.ssp", default=None,
                         help="an SSP 1.0 package: SystemStructure.ssd and the FMUs (docs/ssp.md)")
    formats.add_argument("--fmu", metavar="OUT.fmu", default=None,
                         help="the scene as one FMI 3.0 FMU with scalar ports (docs/composition.md)")
    p_export.add_argument("--outputs", type=lambda text: [x.strip() for x in text.split(",") if x.strip()],
                          default=None, metavar="COMP.PORT,...",
                          help="--fmu: its outputs (default: the ports the scene records)")
    p_export.add_argument("--horizon", type=_duration, default=None, metavar="S",
                          help="--fmu: the simulated seconds it may run (default 1800)")
    p_export.add_argument("--force", action="store_true", help="replace the output file if it exists")
    p_export.add_argument("--set", action="append", metavar="COMP.PARAM=VALUE", help="override a parameter")
    p_export.add_argument("--duration", type=_duration, default=None, help="simulated seconds (default: the scene's)")
    p_export.set_defaults(func=_cmd_export)

    p_study = sub.add_parser("study", help="run a study: tradeoff, stability or extremes")
    p_study.add_argument("name", choices=STUDIES)
    p_study.add_argument("--out", default=None, help="result folder (default results/study_<name>)")
    p_study.add_argument("--quick", action="store_true", help="a reduced sweep (what the tests run)")
    p_study.add_argument("--workers", type=_workers, default=None, help="parallel processes (default: CPU count)")
    p_study.add_argument("--scheduler", type=_scheduler, default=None,
                         help="Dask scheduler address, e.g. tcp://host:8786")
    p_study.add_argument("--fresh", action="store_true",
                         help="run every point again (default: resume, keeping the points finished in --out)")
    p_study.add_argument("--quiet", action="store_true", help="no progress bar")
    p_study.set_defaults(func=_cmd_study)

    p_anatomy = sub.add_parser("scene-from-anatomy",
                               help="write a runnable scene from a lumen surface (STL, OBJ, PLY) or family:<member>")
    p_anatomy.add_argument("surface", help="the lumen surface file, or family:<member> for a parametric aneurysm "
                                           "(fusiform, saccular, eccentric, angulated_neck, tortuous, bifurcation)")
    p_anatomy.add_argument("--out", default=None, help="folder for the scene and its files (default ./<name>)")
    p_anatomy.add_argument("--name", default=None, help="scene name (default: the file's stem, or aaa_<member>)")
    p_anatomy.add_argument("--units", choices=("auto", "m", "cm", "mm"), default="auto",
                           help="the surface's length unit (default: detected from its size)")
    p_anatomy.add_argument("--thickness", type=float, default=0.0015, help="wall thickness in m (default 0.0015)")
    p_anatomy.add_argument("--sac-thickness", type=float, default=None,
                           help="wall thickness in the sac in m (default: --thickness)")
    p_anatomy.add_argument("--layers", type=int, default=2, help="element layers across the wall (default 2)")
    p_anatomy.add_argument("--edge-length", type=float, default=0.003,
                           help="the wall's element size along the surface in m (default 0.003)")
    p_anatomy.add_argument("--remesh", choices=("auto", "always", "never"), default="auto",
                           help="remesh the surface to --edge-length: when its triangles do not fit (auto), always, "
                                "never")
    p_anatomy.add_argument("--access", type=int, default=None,
                           help="the open end the catheter enters by (default: the lowest along z)")
    p_anatomy.add_argument("--target", type=int, default=None,
                           help="the open end the centerline goes to (default: the highest along z)")
    p_anatomy.add_argument("--shape", action="append", metavar="NAME=VALUE",
                           help="a parameter of the parametric aneurysm (family:<member>)")
    p_anatomy.add_argument("--duration", type=float, default=4.0, help="the scene's duration in s (default 4)")
    p_anatomy.add_argument("--contact-time", type=float, default=1.5,
                           help="when the operator's push brings the tip to the sac wall, in s (default 1.5)")
    p_anatomy.add_argument("--force", action="store_true", help="replace the scene's files if they exist")
    p_anatomy.add_argument("--quiet", action="store_true", help="no progress and no summary")
    p_anatomy.set_defaults(func=_cmd_scene_from_anatomy)

    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = parser.parse_args(argv)
        if args.command is None:
            # No command: the main job (top-level options such as -v still apply).
            args = parser.parse_args([*argv, "run"])
    except SystemExit as exc:  # argparse: usage errors exit 2 after "error: ..."; --help exits 0
        _release_stop_signals()
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    if args.command != "run":
        # Only a run stops on a flag; the other commands get Ctrl-C back as usual.
        _release_stop_signals()
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    limit_native_threads()  # before any FMU loads its libraries, here or in a process started from here
    return args.func(args)

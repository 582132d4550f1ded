"""One run of a scene: hosts, the multirate algorithm, observers, and the summary.

The algorithm (:mod:`.algorithm`) schedules and steps the components and routes values; the
observers (:mod:`.observers`) record, summarise, pace and show progress; :mod:`.summary` writes
the result. This module puts them together for one run and is where failures become a status:
a failure of any component (an error status, a crashed worker, a worker that stops answering),
Ctrl-C or SIGTERM ends the run with everything recorded so far on disk and a summary that says
which component, which call and at what simulated time; an FMU's ``terminateSimulation`` ends it
as "terminated".

Ctrl-C and SIGTERM (:mod:`.stopping`) only set ``algorithm.stop_reason`` from the moment the run
starts until its summary is written: the algorithm stops between ticks or between setup calls, an
FMU call never sees a ``KeyboardInterrupt``, and teardown, plots and the summary are never cut
short by an exception. A failure that follows a stop request (a worker killed on the second
Ctrl-C) is reported as "interrupted", with the failure in the error text. Called from Python
(not the command line), ``run()`` then delivers the signal to the caller as usual
(``KeyboardInterrupt`` for Ctrl-C) once the summary is written.

With a :class:`~.outfolder.ResultFolder` (the command line) the run writes into ``<out>.running``
and the folder is moved into place at the end (see :mod:`.outfolder`); the summary names the
final folder.

A run that lost results never ends "completed": results that cannot be kept (a full or read-only
volume, a file-size limit, the results folder deleted under the run) end the run as soon as the
recorder finds them, status "failed" (the project's statuses: :class:`~orchestration.run.status.RunStatus`), and
whatever is missing at the end (rows, frames a writer process could not write, files gone, a
``summary.json`` that could not be written) is listed in the summary's ``lost`` and named in its
error, with the path and what was kept; a run stopped by Ctrl-C or SIGTERM stays "interrupted"
and says the same. Writing the summary and moving the folder into place are attempted whatever
the volume does: what cannot be done is said, never a traceback.
"""
from __future__ import annotations

import logging
import signal
import threading
import time
from fractions import Fraction
from pathlib import Path

import numpy as np

from orchestration.run.algorithm import MultirateAlgorithm, RunInterrupted, RunTerminated
from orchestration.errors import OrchestrationError
from orchestration.observers.base import Observer
from orchestration.observers.progress import Progress
from orchestration.observers.pacing import RealtimePacing
from orchestration.observers.recording import Recording
from orchestration.observers.statistics import Statistics
from orchestration.scene.model import ComponentSpec, Hosting, Scene
from orchestration.scene.timing import duration_problem, float_time
from orchestration.stopping import stop_signals
from orchestration.observers.summary import fmu_messages, format_summary
from orchestration.run.status import COMPLETE, RunStatus

logger = logging.getLogger(__name__)


class Simulation:
    """One run of a scene. ``run()`` returns the summary dict (also written as JSON).

    ``duration`` overrides the scene's; it must be a whole number of every component's step
    (``ValueError`` otherwise, naming the durations that are).
    """

    def __init__(self, scene: Scene, out_dir: Path | str, *, hosting: str | None = None,
                 realtime: bool | None = None, progress: bool = True, duration: Fraction | float | None = None,
                 plots: bool = True, vtu: bool = True, observe: dict[str, list[str]] | None = None,
                 folder=None, compiled_loop: bool = True):
        self.scene = scene
        #: the command line's ResultFolder (lock, ``<out>.running``, replaced at the end) or None:
        #: then the run writes straight into ``out_dir``
        self.folder = folder
        self.out_dir = Path(out_dir) if folder is None else folder.staging
        #: where the results are once the run has ended
        self.results_dir = Path(out_dir) if folder is None else folder.out
        #: forced for every FMU (the command line's --hosting), else each FMU's own or the scene's
        self.forced_hosting = hosting
        self.realtime = scene.realtime if realtime is None else realtime
        self.progress = progress
        self.duration = float_time(duration) if isinstance(duration, float) else (
            Fraction(duration) if duration is not None else scene.duration)
        problem = duration_problem(scene.components.values(), self.duration)
        if problem:
            raise ValueError(f"duration: {problem}")
        self.make_plots = plots
        self.write_vtu = vtu
        #: extra ports to read after every step (studies): {component: [port, ...]}
        self.extra_observed = dict(observe or {})
        #: run stretches of in-process FMU steps in C (orchestration.run.compiled_loop); False: all in Python
        self.compiled_loop = compiled_loop
        #: the latest outputs of every component, {component: {port: array}}, kept after the run
        self.final_outputs: dict[str, dict[str, np.ndarray]] = {}
        self.summary_text = ""

    # -- hosting -----------------------------------------------------------------------------------
    def hosting_of(self, spec: ComponentSpec) -> str:
        if not spec.is_fmu:
            return Hosting.IN_PROCESS
        return self.forced_hosting or spec.hosting or self.scene.hosting

    @property
    def hosting(self) -> str:
        """"in-process", "out-of-process", or "mixed (out-of-process: a, b)"."""
        fmus = [c for c in self.scene.components.values() if c.is_fmu]
        kinds = {self.hosting_of(c) for c in fmus}
        if len(kinds) <= 1:
            return kinds.pop() if kinds else Hosting.IN_PROCESS
        workers = [c.name for c in fmus if self.hosting_of(c) == Hosting.OUT_OF_PROCESS]
        return f"mixed (out-of-process: {', '.join(workers)})"

    def _make_host(self, spec: ComponentSpec):
        if not spec.is_fmu:
            return spec.new_block()
        if self.hosting_of(spec) == Hosting.IN_PROCESS:
            from orchestration.hosts.in_process import InProcessFmu

            return InProcessFmu(spec.name, spec.description)
        from orchestration.hosts.worker import WorkerFmu

        return WorkerFmu(spec.name, spec.description, reply_timeout=self.scene.worker_timeout)

    # -- the run -----------------------------------------------------------------------------------
    def run(self) -> dict:
        _ignore_file_size_signal()
        with stop_signals() as stop:
            return self._run(stop)

    def _run(self, stop) -> dict:
        from orchestration.observers.recorder import reserve_summary_space

        for note in self.scene.notes:  # what validate says, for a run that was not validated first
            logger.warning("%s", note)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        reserve_summary_space(self.out_dir)  # a volume the rows fill up still takes the summary that says so
        recording = Recording(self.scene, self.out_dir, surfaces=self.write_vtu)
        statistics = Statistics(self.scene)
        pacing = RealtimePacing() if self.realtime else None
        progress = Progress(self.scene, self.duration, enabled=self.progress)
        _watch_helpers(recording, self.scene.worker_timeout)
        losses_watch = _LossWatch(recording)
        observers = [o for o in (recording, statistics, pacing, progress, losses_watch) if o is not None]
        try:
            algorithm = MultirateAlgorithm(self.scene, self.duration, self._make_host, observers, self.extra_observed,
                                           compiled_loop=self.compiled_loop)
        except BaseException:
            recording.close()  # its writer processes would keep this process from exiting
            raise
        self.algorithm = algorithm

        def on_stop(request):
            algorithm.request_stop(request.reason, min(request.count, 2))

        status, error = RunStatus.COMPLETED, None
        t_setup = time.perf_counter()
        loop_start = None
        wall = 0.0
        stop.listen(on_stop)
        try:
            algorithm.setup()
            algorithm.initialize()
            loop_start = time.perf_counter()
            algorithm.run(time.perf_counter, progress.advance)
        except RunTerminated as exc:
            status, error = RunStatus.TERMINATED, str(exc)
        except RunInterrupted as exc:
            status, error = RunStatus.INTERRUPTED, str(exc)
        except KeyboardInterrupt:  # off the main thread no handler is installed: Python's own
            status, error = RunStatus.INTERRUPTED, "interrupted by Ctrl-C"
        except OrchestrationError as exc:
            if stop.requested:  # e.g. a worker killed on the second Ctrl-C: the user's stop came first
                status, error = RunStatus.INTERRUPTED, f"{stop.reason}; then {exc}"
            else:
                status, error = RunStatus.FAILED, str(exc)
        finally:
            now = time.perf_counter()
            wall = now - loop_start if loop_start is not None else 0.0
            setup_time = (loop_start if loop_start is not None else now) - t_setup
            algorithm.finished()  # progress bar closed, CPUs given back
            self.final_outputs = algorithm.keep_outputs()
            recording.close()
            messages = algorithm.teardown()
        losses = list(recording.recorder.losses) if recording.recorder is not None else []
        if losses_watch.first is not None and not losses:  # told during the run, not found at the end
            losses.append(losses_watch.first)
        if losses:
            status, error = _account_for_losses(status, error, losses, stopped_by_user=stop.requested)
        summary = self._summary(algorithm, status, error, wall, setup_time, statistics, pacing, recording, messages)
        if losses:
            summary["lost"] = losses
        if stop.requested:
            summary["stop_request"] = stop.reason
        if self.make_plots and self.scene.plots and recording.recorder is not None:
            if stop.requested:  # the user wants out: the CSVs hold everything a figure would show
                summary["results"]["plots"] = "skipped (stop requested)"
            elif losses:  # a figure of rows with a gap would mislead, and the volume may refuse it
                summary["results"]["plots"] = "skipped (results lost)"
            else:
                try:
                    from orchestration.observers.plots import plot_signals

                    summary["results"]["plots"] = [str(p) for p in plot_signals(self.out_dir, self.scene.plots)]
                except Exception as exc:  # plots are a convenience: never lose the summary over them
                    logger.warning("plots failed: %s", exc)
        final_dir = self._save(summary)
        summary = _relocated(summary, self.out_dir, final_dir)
        self.results_dir = final_dir
        stop.unlisten(on_stop)
        self.summary_text = self.format(summary)
        return summary

    def _save(self, summary: dict) -> Path:
        """Write ``summary.json`` and move the results into place (``summary`` as the run ended, its
        paths in the folder written to); return where the results are. A volume that refuses either
        (full, read-only, the folder deleted) is said in the summary and the log and makes the run
        "failed" (its status and error are updated here), never a traceback."""
        from orchestration.observers.recorder import io_problem, write_summary

        final_dir = self.folder.destination(summary["status"]) if self.folder is not None else self.out_dir
        try:
            write_summary(self.out_dir, _relocated(summary, self.out_dir, final_dir))
        except OSError as exc:
            problem = f"{self.out_dir / 'summary.json'} could not be written ({io_problem(exc)})"
            logger.error("%s", problem)
            _add_loss(summary, problem)
            final_dir = self.folder.destination(summary["status"]) if self.folder is not None else self.out_dir
        if self.folder is None:
            return final_dir
        try:
            self.folder.publish(summary["status"])
        except OSError as exc:
            problem = (f"the results could not be moved from {self.out_dir} to {final_dir} ({io_problem(exc)}); "
                       f"they stay in {self.out_dir}")
            logger.error("%s", problem)
            _add_loss(summary, problem)
            final_dir = self.out_dir
            try:  # the summary there says so, if the volume lets it
                write_summary(self.out_dir, summary)
            except OSError:
                pass
        return final_dir

    def format(self, summary: dict) -> str:
        """The readable summary printed after a run (summary.json has everything)."""
        units = {f"{c.name}.{p.name}": p.unit for c in self.scene.components.values() for p in c.ports.values()
                 if p.unit}
        return format_summary(summary, units)

    def _summary(self, algorithm, status, error, wall, setup_time, statistics, pacing, recording, messages) -> dict:
        simulated = algorithm.seconds(algorithm.reached)
        summary = {
            "scene": self.scene.name,
            "description": self.scene.description,
            "status": status,
            "error": error,
            "hosting": self.hosting,
            "simulated_time_s": simulated,
            "requested_time_s": float(self.duration),
            "wall_time_s": wall,
            "setup_time_s": setup_time,
            "real_time_factor": simulated / wall if wall > 0 else None,
            "components": {
                c.name: {"step_s": algorithm.seconds(c.step), "rate_hz": algorithm.base / c.step, "steps": c.steps,
                         "busy_wall_s": c.busy, "hosting": self.hosting_of(c.spec),
                         **({"step_cost": c.costs.report()} if c.costs.count else {})}
                for c in algorithm.ordered
            },
            **statistics.report(),
            "fmu_messages": fmu_messages(messages),
        }
        if pacing is not None:
            summary["deadlines"] = pacing.report()
        # every file but the individual surface frames (the .pvd lists those)
        summary["results"] = {"folder": str(self.out_dir),
                              **{k: str(v) for k, v in recording.files.items() if not k.endswith("]")}}
        if recording.surface_errors:  # frames the surface writer could not write (a full disk)
            summary["results"]["surface_errors"] = recording.surface_errors
        if recording.row_errors:  # rows the row writer could not write (a full disk)
            summary["results"]["row_errors"] = recording.row_errors
        return summary


def _loss_text(losses: list[str]) -> str:
    more = f" (and {len(losses) - 1} more; summary.json lists them under 'lost')" if len(losses) > 1 else ""
    return f"results lost: {losses[0]}{more}"


def _account_for_losses(status: str, error: str | None, losses: list[str], stopped_by_user: bool):
    """The status and error of a run that lost results: never "completed"; "failed" unless the user
    stopped it ("interrupted" stays, and says what was lost too)."""
    text = _loss_text(losses)
    if status in COMPLETE:
        return RunStatus.FAILED, text if status == RunStatus.COMPLETED else f"{text}; {error}"
    if status == RunStatus.INTERRUPTED and not stopped_by_user:  # the recorder's stop: the run ended over the loss
        return RunStatus.FAILED, text
    return status, f"{error}; {text}" if error else text


def _add_loss(summary: dict, problem: str) -> None:
    """One more thing the run could not keep (the summary, the folder's move), found at the very end."""
    summary.setdefault("lost", []).append(problem)
    if summary["status"] in COMPLETE:
        summary["status"] = RunStatus.FAILED
        summary["error"] = _loss_text(summary["lost"])
    else:
        summary["error"] = f"{summary['error']}; {problem}" if summary["error"] else problem


class _LossWatch(Observer):
    """An observer that ends the run as soon as the recorder finds results lost (a write failed, the
    results folder was deleted): whatever the run computes from then on could not be kept."""

    def __init__(self, recording: Recording):
        self.recording = recording
        #: the first loss, as the recorder told it (None: none so far)
        self.first: str | None = None

    def initializing(self, algorithm) -> None:
        recorder = self.recording.recorder  # made by the Recording observer just before
        if recorder is None:
            return

        def lost(text: str) -> None:  # from the recorder's threads: flags only
            if self.first is None:
                self.first = text
                algorithm.request_stop(f"results lost: {text}", max(1, algorithm.stop_level))

        recorder.on_loss = lost


def _watch_helpers(recording: Recording, worker_timeout: float | None) -> None:
    """The writer processes get the workers' deadline: the scene's ``worker_timeout`` when it sets
    one (else their automatic one, see :mod:`.helper_process`)."""
    if worker_timeout is None:
        return
    for writer in recording.writers:
        helper = getattr(writer, "helper", None)
        if helper is not None:
            helper.timeout = float(worker_timeout)


def _ignore_file_size_signal() -> None:
    """A write past the file-size limit (``ulimit -f``) must fail with EFBIG, which the recorder
    reports, not kill the run with SIGXFSZ. Python ignores it at start-up; a program that embeds
    Python may not (only the main thread may change it)."""
    if (hasattr(signal, "SIGXFSZ") and threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGXFSZ) == signal.SIG_DFL):
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)


def _relocated(summary: dict, old: Path, new: Path) -> dict:
    """``summary`` with the paths in its ``results`` and its messages moved from the folder written
    to (``old``) to the final one (a copy; the same dict when they are the same)."""
    if old == new:
        return summary
    old_text, new_text = str(old), str(new)

    def move(value):
        if isinstance(value, str):
            if value == old_text or value.startswith(old_text + "/"):
                return new_text + value[len(old_text):]
            return value.replace(old_text + "/", new_text + "/")
        if isinstance(value, list):
            return [move(v) for v in value]
        return value

    moved = dict(summary)
    moved["results"] = {key: move(value) for key, value in summary["results"].items()}
    for key in ("error", "lost"):
        if key in moved:
            moved[key] = move(moved[key])
    return moved


def run_scene(scene: Scene, out_dir, **kwargs) -> tuple[dict, str]:
    """Run ``scene`` into ``out_dir``; return (summary dict, readable summary text)."""
    simulation = Simulation(scene, out_dir, **kwargs)
    summary = simulation.run()
    return summary, simulation.summary_text

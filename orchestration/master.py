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
"""
from __future__ import annotations

import logging
import time
from fractions import Fraction
from pathlib import Path

import numpy as np

from .algorithm import MultirateAlgorithm, RunInterrupted, RunTerminated, tick_base  # noqa: F401 (re-exported)
from .errors import OrchestrationError
from .observers import Progress, RealtimePacing, Recording, Statistics
from .scene import ComponentSpec, Scene, duration_problem, float_time
from .stopping import stop_signals
from .summary import fmu_messages, format_summary

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
        #: run stretches of in-process FMU steps in C (orchestration.compiled_loop); False: all in Python
        self.compiled_loop = compiled_loop
        #: the latest outputs of every component, {component: {port: array}}, kept after the run
        self.final_outputs: dict[str, dict[str, np.ndarray]] = {}
        self.summary_text = ""

    # -- hosting -----------------------------------------------------------------------------------
    def hosting_of(self, spec: ComponentSpec) -> str:
        if not spec.is_fmu:
            return "in-process"
        return self.forced_hosting or spec.hosting or self.scene.hosting

    @property
    def hosting(self) -> str:
        """"in-process", "out-of-process", or "mixed (out-of-process: a, b)"."""
        fmus = [c for c in self.scene.components.values() if c.is_fmu]
        kinds = {self.hosting_of(c) for c in fmus}
        if len(kinds) <= 1:
            return kinds.pop() if kinds else "in-process"
        workers = [c.name for c in fmus if self.hosting_of(c) == "out-of-process"]
        return f"mixed (out-of-process: {', '.join(workers)})"

    def _make_host(self, spec: ComponentSpec):
        if not spec.is_fmu:
            return spec.new_block()
        if self.hosting_of(spec) == "in-process":
            from .hosting import InProcessFmu

            return InProcessFmu(spec.name, spec.description)
        from .worker import WorkerFmu

        return WorkerFmu(spec.name, spec.description, reply_timeout=self.scene.worker_timeout)

    # -- the run -----------------------------------------------------------------------------------
    def run(self) -> dict:
        with stop_signals() as stop:
            return self._run(stop)

    def _run(self, stop) -> dict:
        from .recording import write_summary

        self.out_dir.mkdir(parents=True, exist_ok=True)
        recording = Recording(self.scene, self.out_dir, surfaces=self.write_vtu)
        statistics = Statistics(self.scene)
        pacing = RealtimePacing() if self.realtime else None
        progress = Progress(self.scene, self.duration, enabled=self.progress)
        observers = [o for o in (recording, statistics, pacing, progress) if o is not None]
        algorithm = MultirateAlgorithm(self.scene, self.duration, self._make_host, observers, self.extra_observed,
                                       compiled_loop=self.compiled_loop)
        self.algorithm = algorithm

        def on_stop(request):
            algorithm.request_stop(request.reason, min(request.count, 2))

        status, error = "completed", None
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
            status, error = "terminated", str(exc)
        except RunInterrupted as exc:
            status, error = "interrupted", str(exc)
        except KeyboardInterrupt:  # off the main thread no handler is installed: Python's own
            status, error = "interrupted", "interrupted by Ctrl-C"
        except OrchestrationError as exc:
            if stop.requested:  # e.g. a worker killed on the second Ctrl-C: the user's stop came first
                status, error = "interrupted", f"{stop.reason}; then {exc}"
            else:
                status, error = "failed", str(exc)
        finally:
            now = time.perf_counter()
            wall = now - loop_start if loop_start is not None else 0.0
            setup_time = (loop_start if loop_start is not None else now) - t_setup
            algorithm.notify("finished")  # progress bar closed, CPUs given back
            self.final_outputs = algorithm.keep_outputs()
            recording.close()
            messages = algorithm.teardown()
        final_dir = self.folder.destination(status) if self.folder is not None else self.out_dir
        summary = self._summary(algorithm, status, error, wall, setup_time, statistics, pacing, recording, messages)
        if stop.requested:
            summary["stop_request"] = stop.reason
        if self.make_plots and self.scene.plots and recording.recorder is not None:
            if stop.requested:  # the user wants out: the CSVs hold everything a figure would show
                summary["results"]["plots"] = "skipped (stop requested)"
            else:
                try:
                    from .plots import plot_signals

                    summary["results"]["plots"] = [str(p) for p in plot_signals(self.out_dir, self.scene.plots)]
                except Exception as exc:  # plots are a convenience: never lose the summary over them
                    logger.warning("plots failed: %s", exc)
        if final_dir != self.out_dir:
            _relocate(summary["results"], self.out_dir, final_dir)
        write_summary(self.out_dir, summary)
        if self.folder is not None:
            self.folder.publish(status)
        self.results_dir = final_dir
        stop.unlisten(on_stop)
        self.summary_text = self.format(summary)
        return summary

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
                         "busy_wall_s": c.busy, "hosting": self.hosting_of(c.spec)}
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


def _relocate(results: dict, old: Path, new: Path) -> None:
    """Rewrite the paths in the summary's ``results`` from the folder written to the final one."""
    old_text, new_text = str(old), str(new)
    for key, value in results.items():
        if isinstance(value, str) and (value == old_text or value.startswith(old_text + "/")):
            results[key] = new_text + value[len(old_text):]
        elif isinstance(value, list):
            results[key] = [new_text + v[len(old_text):] if isinstance(v, str) and v.startswith(old_text + "/") else v
                            for v in value]


def run_scene(scene: Scene, out_dir, **kwargs) -> tuple[dict, str]:
    """Run ``scene`` into ``out_dir``; return (summary dict, readable summary text)."""
    simulation = Simulation(scene, out_dir, **kwargs)
    summary = simulation.run()
    return summary, simulation.summary_text

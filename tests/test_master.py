"""The multirate master on small synthetic FMUs, against exact rational references.

Signal outputs y = a + b t + c t^2 at its communication points; Echo reports the input it had
during each step. Every expected value is computed here with ``fractions.Fraction`` from the
documented rule (evaluation tick, rate transition), independently of the master's code.
"""
from __future__ import annotations

import math
import os
import time
from fractions import Fraction

import numpy as np
import pytest

from orchestration.observers.base import Observer
from orchestration.run.simulation import run_scene
from orchestration.observers.recorder import read_stream
from orchestration.scene.model import SceneError
from orchestration.scene.loading import scene_from_dict

A, B, C = 1.0, 2.0, 3.0


def y(t: Fraction) -> Fraction:
    return A + B * t + C * t * t


def signal_echo_scene(fmus, signal_step, echo_step, transition, ordering, duration=0.5, extra=None):
    data = {
        "scene": {"name": "signal_echo", "duration": duration, "hosting": "in-process"},
        "fmu": {
            "signal": {"path": str(fmus["Signal"]), "step": signal_step,
                       "parameters": {"coefficients": [A, B, C]}},
            "echo": {"path": str(fmus["Echo"]), "step": echo_step},
        },
        "connection": [{"from": "signal.y", "to": "echo.u", "ordering": ordering,
                        **({"transition": transition} if transition else {})}],
        "record": {"echo": ["last_u", "last_t", "last_k", "last_b"], "signal": ["y", "count"]},
    }
    for key, value in (extra or {}).items():
        data[key] = value
    return data


def run(data, out, **kwargs):
    scene = scene_from_dict(data, out)
    summary, _ = run_scene(scene, out / "results", progress=False, plots=False, **kwargs)
    assert summary["status"] == "completed", summary["error"]
    return summary


def expected_input(t: Fraction, h_c: Fraction, H: Fraction, transition: str, ordering: str) -> Fraction:
    """The documented rule, written out independently of the master."""
    tau = t if ordering == "jacobi" else t + h_c
    last = math.floor(tau / H) * H
    if transition == "hold":
        return y(last)
    if transition == "interpolate":
        target = tau - H
        if target <= 0:
            return y(Fraction(0)) if target < 0 else y(target)
        s0 = math.floor(target / H) * H
        return y(s0) + (target - s0) / H * (y(s0 + H) - y(s0))
    if transition == "extrapolate":
        if last == 0:
            return y(Fraction(0))
        return y(last) + (tau - last) / H * (y(last) - y(last - H))
    if transition == "average":
        ks = [k for k in range(0, int(tau / H) + 1) if tau - h_c < k * H <= tau]
        return sum(y(k * H) for k in ks) / len(ks)
    raise AssertionError(transition)


@pytest.mark.parametrize("transition,ordering,signal_step,echo_step", [
    ("hold", "jacobi", "1/30", 0.01),
    ("hold", "gauss-seidel", "1/30", 0.01),
    ("interpolate", "jacobi", "1/30", 0.01),
    ("extrapolate", "jacobi", "1/30", 0.01),
    ("extrapolate", "gauss-seidel", "1/30", 0.01),
    ("average", "jacobi", 0.001, "1/30"),
    ("average", "gauss-seidel", 0.001, "1/30"),
    (None, "gauss-seidel", 0.01, 0.01),
    (None, "jacobi", 0.01, 0.01),
])
def test_rate_transitions_match_the_exact_rule(synthetic_fmus, tmp_path, transition, ordering, signal_step, echo_step):
    data = signal_echo_scene(synthetic_fmus, signal_step, echo_step, transition, ordering)
    run(data, tmp_path)
    t, cols = read_stream(tmp_path / "results" / "echo.csv")
    H = Fraction(signal_step) if isinstance(signal_step, str) else Fraction(repr(signal_step))
    h = Fraction(echo_step) if isinstance(echo_step, str) else Fraction(repr(echo_step))
    n_steps = len(t) - 1
    assert n_steps == math.ceil(Fraction("0.5") / h)
    for n in range(n_steps):
        start = n * h
        assert cols["last_t"][n + 1] == float(start)            # time from integer ticks, bit for bit
        want = float(expected_input(start, h, H, transition or "hold", ordering))
        assert cols["last_u"][n + 1] == pytest.approx(want, rel=1e-14, abs=1e-14), (n, start)


def test_average_windows_hold_33_or_34_haptic_samples(synthetic_fmus, tmp_path):
    """1 ms into 1/30 s: the mean of the count output is the mean of the sample indices in the window."""
    data = signal_echo_scene(synthetic_fmus, 0.001, "1/30", "average", "jacobi", duration=0.2)
    data["connection"].append({"from": "signal.count", "to": "echo.k", "transition": "hold", "ordering": "jacobi"})
    data["connection"][0]["from"] = "signal.y"
    run(data, tmp_path)
    _, cols = read_stream(tmp_path / "results" / "echo.csv")
    # count = number of steps done = tick / 3 at each sample; hold gives the count at the frame start
    frames = [int(k) for k in cols["last_k"][1:]]
    assert frames == [math.floor(Fraction(n, 30) / Fraction(1, 1000)) for n in range(6)]


def test_time_does_not_drift_over_ten_thousand_steps(synthetic_fmus, tmp_path):
    data = signal_echo_scene(synthetic_fmus, "1/30", 0.001, "hold", "jacobi", duration=10.0)
    data["record"] = {"echo": ["last_t"]}
    run(data, tmp_path)
    t, cols = read_stream(tmp_path / "results" / "echo.csv")
    n = np.arange(len(t))
    assert len(t) == 10001
    assert all(t[k] == float(Fraction(int(k), 1000)) for k in n)
    assert all(cols["last_t"][k + 1] == float(Fraction(int(k), 1000)) for k in n[:-1])


def test_integer_and_boolean_ports_cross_exactly(synthetic_fmus, tmp_path):
    data = signal_echo_scene(synthetic_fmus, 0.01, 0.01, None, "gauss-seidel", duration=0.1)
    data["connection"] += [{"from": "signal.count", "to": "echo.k"}, {"from": "signal.odd", "to": "echo.b"}]
    run(data, tmp_path)
    _, cols = read_stream(tmp_path / "results" / "echo.csv")
    steps = np.arange(1, 11)
    np.testing.assert_array_equal(cols["last_k"][1:], steps)
    np.testing.assert_array_equal(cols["last_b"][1:], steps % 2)


def test_initialization_propagates_outputs_before_the_first_step(synthetic_fmus, tmp_path):
    """Echo's first step sees y(0) = a, set during initialization (not Echo's start value)."""
    data = signal_echo_scene(synthetic_fmus, "1/30", 0.01, "hold", "jacobi", duration=0.1)  # a whole number of both steps
    run(data, tmp_path)
    _, cols = read_stream(tmp_path / "results" / "echo.csv")
    assert cols["last_u"][1] == A


def test_in_process_and_out_of_process_write_identical_files(synthetic_fmus, tmp_path):
    data = signal_echo_scene(synthetic_fmus, 0.001, "1/30", "average", "jacobi", duration=0.3)
    data["connection"].append({"from": "signal.y3", "to": "echo.v", "transition": "extrapolate", "ordering": "jacobi"})
    data["record"]["echo"].append("last_v")
    files = {}
    for hosting in ("in-process", "out-of-process", "in-process"):
        out = tmp_path / hosting
        out.mkdir(exist_ok=True)
        run(data, out, hosting=hosting)
        files.setdefault(hosting, []).append({name: (out / "results" / name).read_bytes()
                                              for name in ("echo.csv", "signal.csv")})
    first, second = files["in-process"]
    assert first == second                            # deterministic
    assert files["out-of-process"][0] == first        # and the same out of process


def test_an_fmu_error_mid_run_is_reported_and_results_are_kept(synthetic_fmus, tmp_path):
    data = {
        "scene": {"name": "faulty", "duration": 1.0, "hosting": "in-process"},
        "fmu": {"faulty": {"path": str(synthetic_fmus["Faulty"]), "step": 0.01,
                           "parameters": {"error_at": 0.25}}},
        "record": {"faulty": ["y"]},
    }
    scene = scene_from_dict(data, tmp_path)
    summary, text = run_scene(scene, tmp_path / "results", progress=False)
    assert summary["status"] == "failed"
    assert "faulty" in summary["error"] and "fmi3DoStep" in summary["error"] and "0.25" in summary["error"]
    assert "requested error" in summary["error"]
    t, cols = read_stream(tmp_path / "results" / "faulty.csv")
    assert t[-1] == pytest.approx(0.25) and len(t) == 26      # every step before the failure is on disk
    assert (tmp_path / "results" / "summary.json").exists()


def test_a_crashing_worker_is_reported_and_the_master_survives(synthetic_fmus, tmp_path):
    data = {
        "scene": {"name": "crash", "duration": 1.0, "hosting": "out-of-process"},
        "fmu": {"faulty": {"path": str(synthetic_fmus["Faulty"]), "step": 0.01,
                           "parameters": {"crash_at": 0.5}}},
        "record": {"faulty": ["y"]},
    }
    scene = scene_from_dict(data, tmp_path)
    summary, _ = run_scene(scene, tmp_path / "results", progress=False)
    assert summary["status"] == "failed"
    assert "faulty" in summary["error"] and "0.5" in summary["error"]
    assert "SIGABRT" in summary["error"] or "died" in summary["error"]
    t, _ = read_stream(tmp_path / "results" / "faulty.csv")
    assert t[-1] == pytest.approx(0.5)


def test_an_algebraic_loop_of_gauss_seidel_connections_is_rejected(synthetic_fmus, tmp_path):
    data = signal_echo_scene(synthetic_fmus, 0.01, 0.01, None, "gauss-seidel")
    data["fmu"]["echo2"] = {"path": str(synthetic_fmus["Echo"]), "step": 0.01}
    data["connection"] = [{"from": "echo.last_u", "to": "echo2.u"}, {"from": "echo2.last_u", "to": "echo.u"}]
    with pytest.raises(SceneError, match="algebraic loop"):
        scene_from_dict(data, tmp_path)
    data["connection"][1]["ordering"] = "jacobi"
    scene_from_dict(data, tmp_path)


def test_the_remembered_schedule_steps_exactly_as_deciding_afresh(synthetic_fmus, tmp_path, monkeypatch):
    """The schedule is decided once per relative state and then looked up; deciding every call
    afresh (no memory) must give byte-identical results, across rates that share no step."""
    from orchestration.plan import schedule

    data = signal_echo_scene(synthetic_fmus, 0.001, "1/30", "average", "jacobi", duration=0.6)
    data["fmu"]["echo2"] = {"path": str(synthetic_fmus["Echo"]), "step": "1/70"}
    data["connection"] += [{"from": "echo.last_u", "to": "echo2.u", "transition": "interpolate", "ordering": "jacobi"},
                           {"from": "signal.y3", "to": "echo2.v", "transition": "extrapolate", "ordering": "gauss-seidel"}]
    data["record"]["echo2"] = ["last_u", "last_t"]
    names = ("echo.csv", "echo2.csv", "signal.csv")
    (tmp_path / "cached").mkdir()
    run(data, tmp_path / "cached")
    monkeypatch.setattr(schedule, "MEMO_LIMIT", 0)
    (tmp_path / "fresh").mkdir()
    run(data, tmp_path / "fresh")
    for name in names:
        assert (tmp_path / "cached" / "results" / name).read_bytes() == (tmp_path / "fresh" / "results" / name).read_bytes()
    t, cols = read_stream(tmp_path / "cached" / "results" / "echo2.csv")
    assert len(t) == 43 and t[-1] == pytest.approx(0.6)                # 0.6 s of 1/70 s steps, and t = 0


def test_a_duration_off_the_step_grid_is_refused_with_the_durations_that_fit(synthetic_fmus, tmp_path):
    data = signal_echo_scene(synthetic_fmus, "1/30", 0.01, "hold", "jacobi", duration=0.25)
    with pytest.raises(SceneError) as info:
        scene_from_dict(data, tmp_path)
    (problem,) = info.value.problems
    assert "0.25 s is not a whole number of steps of signal (1/30 s)" in problem
    assert "0.2 or 0.3" in problem                                        # the multiples of 1/10 s around it
    data["scene"]["duration"] = 0.3
    scene = scene_from_dict(data, tmp_path)
    with pytest.raises(ValueError, match="not a whole number of steps"):
        run_scene(scene, tmp_path / "results", duration=0.05, progress=False)


def test_a_scene_object_runs_twice_with_the_same_results(fmus_in_repo, tmp_path):
    """Blocks and sources are created per run: the device plant starts from rest both times."""
    from orchestration.scene.loading import load_scene

    scene = load_scene("virtual_wall", {"duration": 0.2})
    files = []
    for k in range(2):
        summary, _ = run_scene(scene, tmp_path / str(k), progress=False, plots=False, hosting="in-process")
        assert summary["status"] == "completed", summary["error"]
        files.append({n: (tmp_path / str(k) / n).read_bytes() for n in ("device.csv", "contact.csv")})
    assert files[0] == files[1]


def test_a_run_whose_row_writer_dies_keeps_every_row_and_says_so(fmus_in_repo, tmp_path, monkeypatch):
    """The row writer process is killed (as by the out-of-memory killer) before the first rows reach
    it: the run's own process writes the rows from then on, none is lost, and the summary and the
    printed text say what happened."""
    import signal

    from orchestration.observers.row_writer import RowWriter
    from orchestration.scene.loading import load_scene

    write = RowWriter.write
    killed = []

    def write_once_the_writer_is_dead(self, name, rows):
        if not killed:
            os.kill(self.pid, signal.SIGKILL)
            self._helper._process.join(timeout=30)
            killed.append(self.pid)
        return write(self, name, rows)

    monkeypatch.setattr(RowWriter, "write", write_once_the_writer_is_dead)
    summary, text = run_scene(load_scene("virtual_wall", {"duration": 0.5}), tmp_path, progress=False, plots=False,
                              hosting="in-process")
    assert killed and summary["status"] == "completed", summary["error"]
    errors = summary["results"]["row_errors"]
    assert len(errors) == 2 and errors[0].startswith(
        "the row writer process ended before writing every row (exit code -9): BrokenPipeError"), errors
    assert errors[1] == "the run's own process wrote the rows from then on"
    assert f"CSV rows: {errors[0]}" in text and f"CSV rows: {errors[1]}" in text
    for name in ("device", "contact"):
        t, _ = read_stream(tmp_path / f"{name}.csv")
        assert np.array_equal(t, np.arange(501) / 1000), name  # every 1 kHz row, none twice


class _StepTrace(Observer):
    """An observer that notes when each component's step starts and when its outputs arrive."""

    times_steps = True
    names_its_ports = False

    def __init__(self):
        self.events: list[tuple[str, str, int]] = []

    def ports(self, component):
        return []

    def subscribes(self, component):
        return True

    def before_step(self, component, tick):
        self.events.append(("start", component.name, tick))

    def stepped(self, component, tick, outputs):
        self.events.append(("end", component.name, tick))


def _run_signal_echo(synthetic_fmus, tmp_path, hosts: dict, observers: list) -> None:
    """The signal -> echo scene (1/30 s producer, 1 ms consumer, hold, jacobi, 0.1 s) stepped by
    the algorithm itself, each component on the host class ``hosts`` names."""
    from orchestration.run.algorithm import MultirateAlgorithm

    data = signal_echo_scene(synthetic_fmus, "1/30", 0.001, "hold", "jacobi", duration=0.1)
    scene = scene_from_dict(data, tmp_path)
    algorithm = MultirateAlgorithm(scene, scene.duration, lambda spec: hosts[spec.name](spec.name, spec.description),
                                   observers)
    try:
        algorithm.setup()
        algorithm.initialize()
        algorithm.run(lambda: 0.0)
    finally:
        algorithm.finished()
        algorithm.teardown()


@pytest.mark.parametrize("signal_hosting", ["out-of-process", "in-process"])
def test_a_worker_step_starts_after_the_ticks_steps_and_is_collected_once_done(synthetic_fmus, tmp_path,
                                                                                signal_hosting):
    """A 1/30 s step in a worker is started after the 1 ms consumer's step of the same tick and
    collected once it is done, before the consumer needs it (jacobi), not at the tick that needs
    it. In ticks of 1/3000 s the worker steps [0, 100], [100, 200], ...; the consumer's steps
    [3, 6] ... [99, 102] need only the sample at 0, [102, 105] the one at 100. The consumer's steps
    take 2 ms each here and the worker's almost nothing, so its result arrives long before the
    33rd consumer step. In process the producer simply steps first (its rank), done when it starts."""
    from orchestration.hosts.in_process import InProcessFmu
    from orchestration.hosts.worker import WorkerFmu

    class SlowFmu(InProcessFmu):
        def start_step(self, t, h, inputs):
            time.sleep(0.002)
            super().start_step(t, h, inputs)

    trace = _StepTrace()
    hosts = {"signal": WorkerFmu if signal_hosting == "out-of-process" else InProcessFmu, "echo": SlowFmu}
    _run_signal_echo(synthetic_fmus, tmp_path, hosts, [trace])
    events = trace.events
    for k in range(3):  # each of the worker's steps
        begin = events.index(("start", "signal", 100 * k))
        end = events.index(("end", "signal", 100 * (k + 1)))
        if signal_hosting == "out-of-process":  # the tick's consumer step first
            assert events.index(("end", "echo", 3 * (100 * k // 3) + 3)) < begin
        needing = 3 * -(-100 * (k + 1) // 3)  # the first consumer step that reads the sample at 100 (k + 1)
        if needing < 300:  # the run ends at 300
            assert end < events.index(("start", "echo", needing))
        echo_steps = [e for e in events[begin:end] if e[:2] == ("end", "echo")]
        if signal_hosting == "out-of-process":
            assert len(echo_steps) < 25, (k, echo_steps)
        else:
            assert echo_steps == []


def test_a_paced_runs_clock_starts_at_its_first_step(synthetic_fmus, tmp_path):
    """--realtime: what the observers do when the run starts (the progress bar's import of tqdm
    took 6-7 ms) does not make the first haptic steps late."""
    from orchestration.hosts.in_process import InProcessFmu
    from orchestration.observers.pacing import RealtimePacing

    class SlowStart(Observer):
        def started(self, algorithm):
            time.sleep(0.05)

    pacing = RealtimePacing()
    _run_signal_echo(synthetic_fmus, tmp_path, {"signal": InProcessFmu, "echo": InProcessFmu}, [pacing, SlowStart()])
    assert len(pacing.lateness) == 100
    assert pacing.lateness[0] < 0.025, pacing.lateness[:5]


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs")
def test_a_paced_run_keeps_its_workers_off_the_masters_cpu(synthetic_fmus, tmp_path):
    """--realtime: this process keeps one CPU, the worker gets another, and this process has all
    its CPUs back once the run is finished (the master notifies "finished" however a run ends)."""
    from orchestration.hosts.in_process import InProcessFmu
    from orchestration.observers.pacing import RealtimePacing
    from orchestration.hosts.worker import WorkerFmu

    before = os.sched_getaffinity(0)
    seen = {}

    class Probe(Observer):
        def started(self, algorithm):
            seen["master"] = os.sched_getaffinity(0)
            seen["worker"] = os.sched_getaffinity(algorithm.components["signal"].host.pid)

    pacing = RealtimePacing()
    _run_signal_echo(synthetic_fmus, tmp_path, {"signal": WorkerFmu, "echo": InProcessFmu}, [pacing, Probe()])
    cpus = pacing.report()["cpus"]
    assert seen["master"] == {cpus["master"]} and seen["worker"] == {cpus["signal"]}
    assert cpus["master"] != cpus["signal"] and {cpus["master"], cpus["signal"]} <= before
    assert os.sched_getaffinity(0) == before

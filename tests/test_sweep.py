"""The parameter-sweep runner: values, failures, timeouts, resume, determinism, dask."""
from __future__ import annotations

import collections
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from orchestration.studies.sweep import SweepConfigError, load_results, point_key, results_table, run_sweep

TESTS_DIR = Path(__file__).resolve().parent
CALLS_ENV = "SWEEP_TEST_CALLS"  # file where tasks log "pid key" per call (inherited by workers)
HANG_ENV = "SWEEP_TEST_HANG_X"  # a "sleep" point with this x sleeps 60 s instead


# --- Tasks (top level, so worker processes can import them) ----------------------------------

def _log_call(point: dict) -> None:
    path = os.environ.get(CALLS_ENV)
    if path:
        with open(path, "a", encoding="utf-8") as stream:
            stream.write(f"{os.getpid()} {point_key(point)}\n")


def cantilever_task(point: dict) -> dict:
    """Tip deflection of an end-loaded cantilever by Mohr's second theorem, integrated numerically.

    delta = integral_0^L M(x) (L - x) / (E I) dx with M(x) = F (L - x): Simpson's rule on the
    quadratic integrand, to be compared with the closed form F L^3 / (3 E I).
    """
    _log_call(point)
    young, force, length = point["young_modulus"], point["force"], point["length"]
    if young <= 0:
        raise ValueError(f"young_modulus must be > 0 (got {young}): give Young's modulus in Pa")
    inertia = point["width"] * point["height"] ** 3 / 12.0
    n = 8
    h = length / n
    integrand = [force * (length - k * h) ** 2 / (young * inertia) for k in range(n + 1)]
    weights = [1] + [4 if k % 2 else 2 for k in range(1, n)] + [1]
    deflection = h / 3.0 * sum(w * f for w, f in zip(weights, integrand))
    return {"tip_deflection_m": deflection, "inertia_m4": inertia}


def mixed_task(point: dict) -> dict:
    _log_call(point)
    mode = point.get("mode", "ok")
    if mode == "raise":
        raise ValueError(f"young_modulus must be > 0 (got {point['x']}):\n"
                         "give Young's modulus in Pa, e.g. 1.044e6")
    if mode == "abort":
        os.abort()
    if mode == "numpy":
        import numpy as np
        return {"x_squared": np.float64(point["x"]) ** 2, "powers": np.arange(3) ** point["x"]}
    if mode == "not_a_dict":
        return [point["x"]]
    if mode == "not_json":
        return {"x": object()}
    if mode == "sleep":
        time.sleep(60.0 if os.environ.get(HANG_ENV) == str(point["x"]) else point["sleep_s"])
    x = point["x"]
    return {"x_squared": x * x, "multiples": [x * k for k in range(3)], "nested": {"half": x / 2}}


# --- Helpers ----------------------------------------------------------------------------------

def _calls(path: Path) -> list[tuple[int, str]]:
    if not path.exists():
        return []
    lines = path.read_text().splitlines()
    return [(int(pid), key) for pid, key in (line.split() for line in lines)]


def _alive(pid: int) -> bool:
    # A reaped process has no /proc entry; an unreaped orphan shows as a zombie ("Z").
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _wait_dead(pids, timeout_s=15.0) -> set[int]:
    deadline = time.monotonic() + timeout_s
    alive = {pid for pid in pids if _alive(pid)}
    while alive and time.monotonic() < deadline:
        time.sleep(0.05)
        alive = {pid for pid in alive if _alive(pid)}
    return alive


def _comparable(results) -> list[tuple]:
    return [(r.point, r.key, r.status, r.values, r.error) for r in results]


MIXED_POINTS = [
    {"x": 1.5},
    {"x": -3.0, "mode": "raise"},
    {"x": 2},
    {"x": 0.0, "mode": "abort"},
    {"x": 4.25},
    {"x": -1},
    {"x": 7.0, "mode": "abort"},
    {"x": 3},
]

EXTRA_POINTS = [{"x": 5, "mode": "not_a_dict"}, {"x": 6, "mode": "not_json"},
                {"x": 8, "mode": "numpy"}]


@pytest.fixture
def calls_file(tmp_path, monkeypatch) -> Path:
    path = tmp_path / "calls.txt"
    monkeypatch.setenv(CALLS_ENV, str(path))
    return path


# --- Tests ------------------------------------------------------------------------------------

def test_values_match_the_closed_form_in_point_order(tmp_path, calls_file):
    points = [{"young_modulus": e, "force": f, "length": l, "width": 0.01, "height": 0.002}
              for e in (1.044e6, 2.1e11) for f in (0.5, 3.0) for l in (0.05, 0.1, 0.2)]
    results = run_sweep(cantilever_task, points, tmp_path / "r.jsonl", workers=2, progress=False)

    assert [r.point for r in results] == points
    for point, result in zip(points, results):
        assert result.status == "ok" and result.error == ""
        assert result.key == point_key(point)
        inertia = point["width"] * point["height"] ** 3 / 12
        exact = point["force"] * point["length"] ** 3 / (3 * point["young_modulus"] * inertia)
        assert result.values["tip_deflection_m"] == pytest.approx(exact, rel=1e-12)
    # Every point ran exactly once, in worker processes, never in the test process.
    calls = _calls(calls_file)
    assert sorted(key for _, key in calls) == sorted(point_key(p) for p in points)
    assert os.getpid() not in {pid for pid, _ in calls}
    # The file holds the same results, in completion order.
    assert {r.key: r for r in load_results(tmp_path / "r.jsonl")} == {r.key: r for r in results}


def test_failures_are_recorded_and_the_sweep_goes_on(tmp_path, calls_file, caplog):
    with caplog.at_level(logging.WARNING, logger="orchestration.studies.sweep"):
        results = run_sweep(mixed_task, MIXED_POINTS + EXTRA_POINTS, tmp_path / "r.jsonl",
                            workers=2, progress=False)

    by_x = {r.point["x"]: r for r in results}
    assert by_x[-3.0].status == "failed"
    assert by_x[-3.0].error == ("ValueError: young_modulus must be > 0 (got -3.0): give Young's "
                                "modulus in Pa, e.g. 1.044e6")
    for x in (0.0, 7.0):
        assert by_x[x].status == "failed"
        assert by_x[x].error == "worker process died (killed by signal SIGABRT)"
        assert by_x[x].values == {}
    for x in (1.5, 2, 4.25, -1, 3):
        assert by_x[x].status == "ok"
        assert by_x[x].values == {"x_squared": x * x, "multiples": [0 * x, x, 2 * x],
                                  "nested": {"half": x / 2}}
    # What a task returns must be a dict of JSON-able values; numpy values are converted.
    assert by_x[5].error == "TypeError: task must return a dict of results (got list)"
    assert by_x[6].error.startswith("TypeError: task returned a value of type object, which is "
                                    "not JSON-able")
    assert by_x[8].values == {"x_squared": 64.0, "powers": [0, 1, 256]}
    # One warning per failed point, naming the reason.
    warnings = [rec.getMessage() for rec in caplog.records
                if rec.name == "orchestration.studies.sweep" and rec.levelno == logging.WARNING]
    assert len(warnings) == 5
    assert sum("signal SIGABRT" in w for w in warnings) == 2
    # Every line on disk, the failed ones too.
    assert {r.key: r for r in load_results(tmp_path / "r.jsonl")} == {r.key: r for r in results}
    assert sorted(key for _, key in _calls(calls_file)) == sorted(map(point_key, MIXED_POINTS +
                                                                      EXTRA_POINTS))


def test_a_point_over_the_time_limit_is_killed(tmp_path, calls_file):
    points = [{"x": 1}, {"x": 2, "mode": "sleep", "sleep_s": 60.0}, {"x": 3},
              {"x": 4, "mode": "sleep", "sleep_s": 0.1}]
    results = run_sweep(mixed_task, points, tmp_path / "r.jsonl", workers=2, timeout_s=1.0,
                        progress=False)

    assert [r.status for r in results] == ["ok", "failed", "ok", "ok"]
    assert results[1].error == "timed out after 1 s"
    assert 1.0 <= results[1].wall_time_s < 30.0
    assert [r.values.get("x_squared") for r in results] == [1, None, 9, 16]
    # The worker stuck in the 60 s sleep was killed, not left running.
    sleeper = [pid for pid, key in _calls(calls_file) if key == point_key(points[1])]
    assert len(sleeper) == 1 and not _alive(sleeper[0])


@pytest.mark.parametrize("interrupt", [signal.SIGKILL, signal.SIGINT], ids=["kill", "ctrl-c"])
def test_an_interrupted_sweep_resumes_without_redoing_finished_points(tmp_path, calls_file,
                                                                       interrupt):
    results_path = tmp_path / "r.jsonl"
    # The failing point is first (one worker runs points in order): it must be retried.
    points = [{"x": -3.0, "mode": "raise"}] + [{"x": x, "mode": "sleep", "sleep_s": 0.15}
                                               for x in range(12)]
    script = ("import json, sys\n"
              f"sys.path.insert(0, {str(TESTS_DIR)!r})\n"
              "from test_sweep import mixed_task, run_sweep\n"
              "run_sweep(mixed_task, json.loads(sys.argv[1]), sys.argv[2], workers=1, "
              "progress=False)\n")
    # In the interrupted run, x=3 (the fifth point) hangs: the interruption finds a worker busy
    # with a long point, which must not survive its sweep.
    # Ctrl-C must reach the sweep as KeyboardInterrupt even when this test runs with SIGINT ignored
    # (a background job of a non-interactive shell inherits SIG_IGN, and Python then installs no
    # handler): give the child the default disposition.
    sweep = subprocess.Popen([sys.executable, "-c", script, json.dumps(points), str(results_path)],
                             stderr=subprocess.DEVNULL, env={**os.environ, HANG_ENV: "3"},
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and sweep.poll() is None:
        if results_path.exists() and results_path.read_text().count("\n") >= 4:
            break
        time.sleep(0.02)
    os.kill(sweep.pid, interrupt)
    sweep.wait(120)  # exit latency is not what this test measures; a fresh CI venv imports slowly
    # No worker of the interrupted sweep may outlive it (a killed sweep's workers notice they
    # are orphans and exit).
    assert _wait_dead({pid for pid, _ in _calls(calls_file)}) == set()
    # Simulate a line cut off mid-write by the kill.
    with results_path.open("a") as stream:
        stream.write('{"point": {"x": 99}, "key": "0123')

    done_before = {r.key for r in load_results(results_path) if r.status == "ok"}
    calls_before = collections.Counter(key for _, key in _calls(calls_file))
    assert done_before == {point_key(p) for p in points[1:4]}

    results = run_sweep(mixed_task, points, results_path, workers=2, progress=False)

    assert [r.point for r in results] == points
    assert [r.status for r in results] == ["failed"] + ["ok"] * 12
    assert [r.values["x_squared"] for r in results[1:]] == [x * x for x in range(12)]
    new_calls = collections.Counter(key for _, key in _calls(calls_file)) - calls_before
    expected = {point_key(p): 1 for p in points if point_key(p) not in done_before}
    assert dict(new_calls) == expected  # unfinished and failed points ran once more, others not
    # The file stays readable: every point's final result is there, the broken line is skipped.
    final = {r.key: r for r in load_results(results_path)}
    assert [final[r.key] for r in results] == results


def test_results_do_not_depend_on_the_worker_count(tmp_path):
    one = run_sweep(mixed_task, MIXED_POINTS, tmp_path / "one.jsonl", workers=1, progress=False)
    two = run_sweep(mixed_task, MIXED_POINTS, tmp_path / "two.jsonl", workers=2, progress=False)
    assert _comparable(one) == _comparable(two)
    assert [r.status for r in one].count("failed") == 3


def test_dask_cluster_gives_the_same_results_as_local(tmp_path):
    distributed = pytest.importorskip(
        "distributed", reason='dask.distributed not installed (pip install -e ".[dask]")')
    points = MIXED_POINTS + [{"x": 5, "mode": "sleep", "sleep_s": 60.0}]
    local = run_sweep(mixed_task, points, tmp_path / "local.jsonl", workers=2, timeout_s=1.0,
                      progress=False)
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1,
                                  dashboard_address=None) as cluster:
        remote = run_sweep(mixed_task, points, tmp_path / "dask.jsonl",
                           scheduler=cluster.scheduler_address, timeout_s=1.0, progress=False)
    assert _comparable(remote) == _comparable(local)
    assert [r.error for r in remote if r.status == "failed"] == [
        local[1].error, "worker process died (killed by signal SIGABRT)",
        "worker process died (killed by signal SIGABRT)", "timed out after 1 s"]


def test_tasks_workers_cannot_import_are_refused_up_front(tmp_path):
    with pytest.raises(SweepConfigError, match="define it as a top-level function"):
        run_sweep(lambda point: {}, [{"x": 1}], tmp_path / "r.jsonl", progress=False)


def test_missing_dask_is_named_with_the_install_command(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # makes "import distributed" fail
    with pytest.raises(SweepConfigError, match=r'pip install -e "\.\[dask\]"'):
        run_sweep(mixed_task, [{"x": 1}], tmp_path / "r.jsonl", scheduler="tcp://127.0.0.1:1",
                  progress=False)


def test_points_are_validated_keyed_by_content_and_run_once(tmp_path, calls_file):
    np = pytest.importorskip("numpy")
    assert point_key({"a": 1, "b": "s"}) == point_key({"b": "s", "a": 1})
    assert point_key({"a": 1}) != point_key({"a": 1.0}) != point_key({"a": 2.0})
    # numpy scalars are accepted as their Python values.
    points = [{"x": np.float64(2.5)}, {"x": 2.5}, {"x": np.int64(3)}]
    results = run_sweep(mixed_task, points, tmp_path / "r.jsonl", workers=2, progress=False)
    assert results[0] == results[1] and results[0].values["x_squared"] == 6.25
    assert results[2].point == {"x": 3} and type(results[2].point["x"]) is int
    assert len(_calls(calls_file)) == 2  # the duplicate point ran once
    assert len(load_results(tmp_path / "r.jsonl")) == 2

    bad = [([{"x": [1, 2]}], r"points\[0\]\['x'\] must be a str, int, float, bool or None"),
           ([{"x": float("nan")}], r"must be a finite number"),
           ([("x", 1)], r"points\[0\] must be a dict"),
           ([{1: 2.0}], r"parameter names must be str")]
    for points, message in bad:
        with pytest.raises(SweepConfigError, match=message):
            run_sweep(mixed_task, points, tmp_path / "bad.jsonl", progress=False)
    for kwargs, message in [({"workers": 0}, "workers must be an int >= 1"),
                            ({"timeout_s": -1.0}, "timeout_s must be a finite number")]:
        with pytest.raises(SweepConfigError, match=message):
            run_sweep(mixed_task, [{"x": 1}], tmp_path / "bad.jsonl", progress=False, **kwargs)
    assert not (tmp_path / "bad.jsonl").exists()


def test_results_table_flattens_into_uniform_rows(tmp_path):
    results = run_sweep(mixed_task, [{"x": 2}, {"x": -3.0, "mode": "raise"}],
                        tmp_path / "r.jsonl", workers=1, progress=False)
    rows = results_table(results)
    assert [list(row) for row in rows] == [["key", "status", "x", "x_squared", "multiples",
                                            "nested.half", "mode", "error", "wall_time_s"]] * 2
    assert rows[0]["x_squared"] == 4 and rows[0]["nested.half"] == 1.0
    assert json.loads(rows[0]["multiples"]) == [0, 2, 4] and rows[0]["mode"] is None
    assert rows[1]["status"] == "failed" and rows[1]["x_squared"] is None
    assert rows[1]["error"].startswith("ValueError: young_modulus must be > 0")

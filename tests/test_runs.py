"""Whole runs of the shipped scenes with the real FMUs: determinism, hosting equivalence, the main
job, pacing, and what a killed or interrupted run leaves behind."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from process_helpers import assert_no_process_left

from orchestration.run.simulation import run_scene
from orchestration.observers.recorder import read_stream
from orchestration.scene.loading import load_scene

REPO = Path(__file__).resolve().parent.parent


def test_catheter_tube_is_deterministic_and_hosting_independent(fmus_in_repo, tmp_path):
    scene = load_scene("catheter_tube", {"duration": 1.6})
    outputs = {}
    for label, hosting in (("a", "in-process"), ("b", "in-process"), ("c", "out-of-process")):
        summary, _ = run_scene(scene, tmp_path / label, hosting=hosting, progress=False, plots=False)
        assert summary["status"] == "completed", summary["error"]
        outputs[label] = {name: (tmp_path / label / name).read_bytes() for name in ("catheter.csv", "contact.csv")}
    assert outputs["a"] == outputs["b"]
    assert outputs["a"] == outputs["c"]
    _, contact = read_stream(tmp_path / "a" / "contact.csv")
    assert np.max(contact["penetration_depth"]) > 0      # the run really reached the wall


def test_tissue_scene_out_of_process_equals_in_process(fmus_in_repo, tmp_path):
    """The 30 Hz tissue steps concurrently with the 1 kHz loop out of process (every FMU in a
    worker, or the scene's own choice: the tissue alone): same numbers as all in process."""
    scene = load_scene("tissue_indentation", {"duration": 0.8})
    for hosting in ("in-process", "out-of-process", None):
        summary, _ = run_scene(scene, tmp_path / str(hosting), hosting=hosting, progress=False, plots=False)
        assert summary["status"] == "completed", summary["error"]
    assert summary["hosting"] == "mixed (out-of-process: tissue)"
    for name in ("tissue.csv", "contact.csv"):
        expected = (tmp_path / "in-process" / name).read_bytes()
        assert (tmp_path / "out-of-process" / name).read_bytes() == expected
        assert (tmp_path / "None" / name).read_bytes() == expected
    _, contact = read_stream(tmp_path / "in-process" / "contact.csv")
    assert np.max(contact["penetration_depth"]) > 0
    frames = sorted((tmp_path / "in-process" / "aaa_wall").glob("*.vtu"))
    assert len(frames) == 1 + 24 // 3                       # the initial frame, then every 3rd of 24 steps


def test_main_job_runs_the_default_scene_and_prints_a_summary(fmus_in_repo, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "orchestration", "run", "--duration", "0.2", "--out", str(tmp_path)],
                          capture_output=True, text=True, cwd=REPO, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert "aaa_endovascular: completed" in proc.stdout and "real-time factor" in proc.stdout
    assert "peak contact.tool_force" in proc.stdout and "results in" in proc.stdout
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["simulated_time_s"] == pytest.approx(0.2)
    assert summary["components"]["tissue"]["steps"] == 6 and summary["components"]["contact"]["steps"] == 200
    for name in ("tissue.csv", "contact.csv", "catheter.csv", "aaa_wall.pvd", "forces.png", "tissue.png"):
        assert (tmp_path / name).exists(), name


def test_realtime_pacing_counts_missed_deadlines(fmus_in_repo, tmp_path):
    scene = load_scene("virtual_wall", {"duration": 0.3})
    start = time.perf_counter()
    summary, text = run_scene(scene, tmp_path, realtime=True, progress=False, plots=False)
    assert summary["status"] == "completed"
    assert summary["wall_time_s"] >= 0.3 * 0.98                   # paced: never ahead of the clock
    assert time.perf_counter() - start >= 0.3
    deadlines = summary["deadlines"]
    assert deadlines["haptic_steps"] == 600                        # device and contact, 300 each
    assert 0 <= deadlines["missed"] <= deadlines["haptic_steps"]
    # lateness of every haptic step, clipped at 0 (early is on time): ordered percentiles, and a
    # positive maximum exactly when a deadline was missed
    assert 0 <= deadlines["lateness_p50_s"] <= deadlines["lateness_p99_s"] <= deadlines["lateness_max_s"]
    assert (deadlines["lateness_max_s"] > 0) == (deadlines["missed"] > 0)
    assert deadlines["lateness_max_s"] == deadlines["worst_lateness_s"]
    assert "lateness p50" in text and "haptic deadlines missed" in text


def _start_long_run(out: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "orchestration", "run", "virtual_wall", "--duration", "60",
                             "--hosting", "out-of-process", "--quiet", "--out", str(out)],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # its process group: the run and its workers only


def _wait_for_rows(path: Path, rows: int, timeout: float = 120.0) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if path.exists() and path.read_text().count("\n") > rows:
            return
        time.sleep(0.2)
    raise AssertionError(f"{path} did not reach {rows} rows")


def test_a_killed_run_keeps_its_results(fmus_in_repo, tmp_path):
    """SIGKILL: no handler runs; the rows are in OUT.running and the next run keeps them as OUT.killed."""
    out = tmp_path / "out"
    proc = _start_long_run(out)
    running = tmp_path / "out.running"
    try:
        _wait_for_rows(running / "contact.csv", 500)
        time.sleep(0.5)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    t, cols = read_stream(running / "contact.csv")
    assert len(t) > 500
    np.testing.assert_allclose(np.diff(t), 0.001, rtol=1e-9)     # complete, consecutive rows
    assert np.all(np.isfinite(cols["tool_force[0]"]))
    rows = (running / "contact.csv").read_bytes()
    # The dead run's lock is taken over with a note, its rows moved aside, not lost.
    next_run = subprocess.run([sys.executable, "-m", "orchestration", "run", "virtual_wall", "--duration", "0.1",
                               "--hosting", "in-process", "--quiet", "--no-vtu", "--out", str(out)],
                              capture_output=True, text=True, cwd=REPO, timeout=300)
    assert next_run.returncode == 0, next_run.stderr
    assert f"moved to {tmp_path / 'out.killed'}" in next_run.stderr
    assert (tmp_path / "out.killed" / "contact.csv").read_bytes() == rows
    assert json.loads((out / "summary.json").read_text())["status"] == "completed"
    assert not running.exists() and not (tmp_path / "out.lock").exists()


def test_sigterm_ends_the_run_with_a_summary(fmus_in_repo, tmp_path):
    out = tmp_path / "out"
    proc = _start_long_run(out)
    try:
        _wait_for_rows(tmp_path / "out.running" / "contact.csv", 300)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143  # 128 + SIGTERM, documented in `run --help`
    assert "SIGTERM" in err and "Traceback" not in err
    interrupted = tmp_path / "out.interrupted"
    summary = json.loads((interrupted / "summary.json").read_text())
    assert summary["status"] == "interrupted"
    assert summary["results"]["folder"] == str(interrupted)
    assert not out.exists()  # nothing complete to keep: the partial run is beside, never in OUT
    t, _ = read_stream(interrupted / "contact.csv")
    assert t[-1] == pytest.approx(summary["simulated_time_s"], abs=0.002)
    assert_no_process_left(proc.pid)  # no worker left behind


def test_twenty_fresh_processes_run_a_short_scene_and_exit_normally(fmus_in_repo, tmp_path):
    def one(i: int):
        out = tmp_path / f"run{i}"
        return subprocess.run([sys.executable, "-m", "orchestration", "run", "catheter_tube", "--duration", "0.05",
                               "--quiet", "--hosting", "in-process", "--out", str(out)],
                              capture_output=True, text=True, cwd=REPO, timeout=300)

    with ThreadPoolExecutor(max_workers=2) as pool:
        results = list(pool.map(one, range(20)))
    codes = [r.returncode for r in results]
    assert codes == [0] * 20, [r.stderr[-500:] for r in results if r.returncode]


def _tool_force(out: Path):
    import csv

    rows = list(csv.reader((out / "contact.csv").open()))
    head, data = rows[0], np.array([[float(x) for x in r] for r in rows[1:] if len(r) == len(rows[0])])
    force = np.linalg.norm(data[:, [head.index(f"tool_force[{i}]") for i in range(3)]], axis=1)
    return data[:, 0], force


#: Simulated seconds of the default-scene runs below: past 7.4 s, where the port's created energy
#: used to trip the passivity observer's warning (the drift started at the contact, 1.5 s).
DEFAULT_SCENE_SECONDS = 10.0


@pytest.fixture(scope="module", params=[1000.0, 3000.0], ids=["1000N/m", "3000N/m"])
def default_scene_run(request, fmus_in_repo, tmp_path_factory):
    """aaa_endovascular at a desktop device's stiffness, run once per stiffness for the tests below
    (10 s simulated: about 10-15 s here)."""
    out = tmp_path_factory.mktemp(f"aaa_{int(request.param)}")
    scene = load_scene("aaa_endovascular", {"contact.stiffness": request.param, "duration": DEFAULT_SCENE_SECONDS})
    summary, _ = run_scene(scene, out, progress=False, plots=False, vtu=False)
    return summary, out


@pytest.mark.slow
def test_default_scene_renders_a_device_stiffness_without_chatter(default_scene_run):
    """Issue 12 on the main job: at a desktop device's stiffness the 30 Hz wall, yielding through
    its compliance at 1 kHz, neither limit-cycles once the controller holds the force (measured:
    the force varies by 0.05 % / 0.02 % of its mean after 3 s at 1000 / 3000 N/m; 1.6 % / 2.0 %, a
    500 Hz period-2 oscillation, while the contact normal jumped between the facets of the sac's
    crease; with "extrapolate" at 1000 N/m it chatters between 0 and 1.5 N) nor spikes at the
    onset of contact (largest drop from a running maximum in the first 0.4 s: 0.03 % / 0.14 %;
    40 % with the former 200 N/m "extrapolate")."""
    summary, out = default_scene_run
    assert summary["status"] == "completed"
    t, force = _tool_force(out)
    settled = force[t > 3.0]
    assert np.ptp(settled) < 0.05 * settled.mean(), (np.ptp(settled), settled.mean())
    onset = np.flatnonzero(force > 0)[0]
    window = force[(t >= t[onset]) & (t <= t[onset] + 0.4)]
    assert np.max(np.maximum.accumulate(window) - window) < 0.10 * window.max()


def test_a_duration_off_the_step_grid_is_a_usage_error_on_the_command_line(fmus_in_repo, tmp_path, capsys):
    from orchestration.app.cli import EXIT_USAGE, main

    assert main(["run", "virtual_wall", "--duration", "0.0015", "--quiet", "--out", str(tmp_path)]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert "0.0015 s is not a whole number of steps" in err and "0.001 or 0.002" in err
    assert not (tmp_path / "summary.json").exists()     # refused before anything ran


@pytest.mark.slow
def test_default_scene_creates_no_energy_and_warns_only_to_ease_off(default_scene_run):
    """Issue 12: the passivity observer's port energy (the work the catheter has done on the
    contact) never goes negative, and the only message is the order to ease off. Measured over
    60 s (docs/performance.md): final 1.8e-4 J / 1.4e-4 J at 1000 / 3000 N/m, never below 0; it used to drift
    to -0.090 J with a "created energy" warning at 7.4 s (the crease's relay, see
    haptic_fmu.narrow_phase)."""
    summary, out = default_scene_run
    assert summary["status"] == "completed"
    _, contact = read_stream(out / "contact.csv")
    energy = np.asarray(contact["passivity_energy"])
    assert energy.size == 1 + 1000 * DEFAULT_SCENE_SECONDS
    assert energy.min() >= 0.0, (energy.min(), np.argmin(energy) * 1e-3)
    assert summary["fmu_messages"] == []
    assert list(summary["operator_warnings"]) == ["catheter.effort_warning"]
    assert summary["operator_warnings"]["catheter.effort_warning"]["count"] == 1

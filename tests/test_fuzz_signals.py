"""Run-time faults of `python -m orchestration run` (issue 14: nothing recorded is lost).

A real run of the cheapest shipped scene (virtual_wall: a device block and the Contact FMU at
1 kHz; 2-5 s per run here), in this process's FMUs or with Contact in a worker process, gets
SIGINT (sent to its whole process group, as a terminal's Ctrl-C is) or SIGTERM after a random
delay: during start-up, setup, the loop or the end. Whatever the moment:

* the exit code is 130 (SIGINT) or 143 (SIGTERM), or 0 if the run had already finished;
* no traceback, no fatal error, no death by the signal;
* summary.json is there and parses, with status "interrupted" (or "completed" with a
  stop_request when the signal came after the simulation's end), in OUT.interrupted or OUT as
  documented in `run --help`; an older complete result in OUT is intact unless the new run
  completed;
* the CSV rows are whole lines, consecutive from t = 0, and end at the simulated time the
  summary reports (a component may be at most two steps ahead of the slowest);
* no worker or other process of the run is left, no OUT.lock, no OUT.running.

Also: two runs into one --out (the second is refused naming the folder and the PID), a worker
stopped with SIGSTOP (the run fails after the scene's worker_timeout, naming FMU, call and time),
and unusable output folders (exit 2 before anything runs, the old results untouched).

Case counts: the random-moment fuzzer runs half the profile's examples (12 with the "ci"
profile, about 45 s here); `--hypothesis-profile=long` runs 500.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from process_helpers import assert_no_process_left, group_members

REPO = Path(__file__).resolve().parent.parent
SCENE = "virtual_wall"
STEP = 0.001
#: simulated seconds: the loop is a good part of the run in both hostings (in process the loop
#: is fast, out of process every 1 ms step is a round trip to the worker)
DURATION = {"in-process": 4.0, "out-of-process": 2.0}
#: a little more than a whole run takes here, so delays cover start-up, setup, loop and end
SPAN = {"in-process": 4.0, "out-of-process": 6.0}
EXIT_FOR = {signal.SIGINT: 130, signal.SIGTERM: 143}


def _default_sigint():
    # A background job of a non-interactive shell inherits SIGINT ignored (and Python then keeps
    # ignoring it): give the run the disposition a terminal's foreground job has.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start_run(out: Path, hosting: str, duration: float, *extra: str) -> subprocess.Popen:
    """The run in a session of its own: its process group is the run and its workers only."""
    return subprocess.Popen([sys.executable, "-m", "orchestration", "run", SCENE, "--duration", str(duration),
                             "--hosting", hosting, "--out", str(out), "--no-vtu", "--quiet", *extra],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, preexec_fn=_default_sigint)


def wait_for_handlers(proc: subprocess.Popen, timeout: float = 30.0) -> None:
    """Until the run has installed its SIGTERM handler (the first thing `python -m orchestration`
    does): before that, the interpreter is starting and a signal ends it the default way."""
    bit = 1 << (signal.SIGTERM - 1)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            status = Path(f"/proc/{proc.pid}/status").read_text()
        except FileNotFoundError:
            return
        caught = int(next(line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:")), 16)
        if caught & bit:
            return
        time.sleep(0.002)
    raise AssertionError("the run did not install its signal handlers")


def read_rows(path: Path) -> tuple[list[str], list[list[float]]]:
    text = path.read_text()
    assert text.endswith("\n"), f"{path}: the last line is cut off: {text[-80:]!r}"
    lines = text.splitlines()
    header = lines[0].split(",")
    rows = []
    for number, line in enumerate(lines[1:], start=2):
        fields = line.split(",")
        assert len(fields) == len(header), f"{path}:{number}: {len(fields)} fields, header has {len(header)}"
        rows.append([float(f) for f in fields])
    return header, rows


def check_results(folder: Path, summary: dict) -> None:
    """Whole, consecutive rows from t = 0 up to the simulated time the summary reports."""
    simulated = summary["simulated_time_s"]
    for name in ("contact.csv", "device.csv"):
        path = folder / name
        if not path.exists():  # stopped before initialization: nothing was recorded yet
            assert simulated == 0.0, f"{path} is missing after {simulated} s simulated"
            continue
        _, rows = read_rows(path)
        times = [row[0] for row in rows]
        if not times:  # the header only: stopped while initializing, before this component's t = 0 row
            assert simulated == 0.0, f"{path} has no rows after {simulated} s simulated"
            continue
        assert times == pytest.approx([i * STEP for i in range(len(times))], abs=1e-9), f"{path}: rows not consecutive"
        assert simulated - 1e-9 <= times[-1] <= simulated + 2 * STEP + 1e-9, (path, times[-1], simulated)


def make_old_result(out: Path) -> bytes:
    """A complete earlier result in OUT (what a user keeps until a newer run completes)."""
    out.mkdir(parents=True)
    old = json.dumps({"status": "completed", "marker": "the older run"}).encode()
    (out / "summary.json").write_bytes(old)
    (out / "contact.csv").write_text('"time"\n0.0\n')
    return old


def interrupt_and_check(root: Path, hosting: str, signum: int, delay: float, group: bool, again: bool,
                        with_old: bool) -> str:
    out = root / "out"
    old = make_old_result(out) if with_old else None
    proc = start_run(out, hosting, DURATION[hosting])
    try:
        wait_for_handlers(proc)
        time.sleep(delay)
        sent = False
        if proc.poll() is None:
            if group:  # a terminal's Ctrl-C (or a service manager's stop) reaches every process
                os.killpg(proc.pid, signum)
            else:
                os.kill(proc.pid, signum)
            sent = True
            if again:
                time.sleep(0.05)
                if proc.poll() is None:
                    os.kill(proc.pid, signum)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode >= 0, f"the run died of signal {-proc.returncode}: {stderr[-2000:]}"
    assert "Traceback" not in stderr and "Fatal Python error" not in stderr, stderr[-3000:]
    assert proc.returncode in ((0, EXIT_FOR[signum]) if sent else (0,)), (proc.returncode, stderr[-2000:])
    interrupted = root / "out.interrupted"
    if interrupted.exists():
        summary = json.loads((interrupted / "summary.json").read_text())
        assert summary["status"] == "interrupted", summary["status"]
        assert proc.returncode == EXIT_FOR[signum]
        assert summary["stop_request"] in summary["error"]
        assert summary["results"]["folder"] == str(interrupted)
        assert summary["simulated_time_s"] < DURATION[hosting]
        check_results(interrupted, summary)
        if with_old:  # the older complete result survives an interrupted run byte for byte
            assert (out / "summary.json").read_bytes() == old
        else:
            assert not out.exists()
        outcome = "interrupted"
    else:
        summary = json.loads((out / "summary.json").read_text())
        assert summary["status"] == "completed", summary
        assert summary["simulated_time_s"] == pytest.approx(DURATION[hosting])
        assert summary["results"]["folder"] == str(out)
        # a signal after the simulation's end: the run is complete, the stop is noted, plots skipped
        assert ("stop_request" in summary) == (proc.returncode != 0)
        check_results(out, summary)
        outcome = "completed" if proc.returncode == 0 else "stopped after the end"
    if proc.returncode:
        assert summary["error"] is None or summary["stop_request"] in summary["error"]
        assert f"{summary['scene']}: {summary['status']}" in stdout  # the readable summary is printed
    leftovers = sorted(p.name for p in root.iterdir() if p.name not in ("out", "out.interrupted"))
    assert leftovers == [], f"left behind: {leftovers}"
    assert_no_process_left(proc.pid)
    return outcome


OUTCOMES: dict[str, int] = {}


@settings(max_examples=max(6, settings().max_examples // 2))
@given(hosting=st.sampled_from(["in-process", "out-of-process"]),
       signum=st.sampled_from([signal.SIGINT, signal.SIGTERM]),
       fraction=st.floats(0.0, 1.0),
       group=st.booleans(), again=st.booleans(), with_old=st.booleans())
def test_a_signal_at_any_moment_stops_the_run_cleanly(fmus_in_repo, hosting, signum, fraction, group, again, with_old):
    root = Path(tempfile.mkdtemp(prefix="fuzz_signals_"))
    case = (f"{hosting} {signal.Signals(signum).name} after {fraction * SPAN[hosting]:.3f} s "
            f"group={group} again={again} old={with_old}")
    try:
        outcome = interrupt_and_check(root, hosting, signum, fraction * SPAN[hosting], group, again, with_old)
    except BaseException as exc:
        # one line per case (seen with -s): a long run cut short still says what passed and failed
        print(f"signal case FAILED: {case}: {type(exc).__name__}: {str(exc)[:300]!r}", flush=True)
        raise
    finally:
        shutil.rmtree(root, ignore_errors=True)
    OUTCOMES[outcome] = OUTCOMES.get(outcome, 0) + 1
    print(f"signal case passed: {case}: {outcome}", flush=True)


def test_the_fuzzer_reached_both_ends(fmus_in_repo):
    """The delays are meant to cover an interrupted run and a finished one; say so if they did not."""
    if not OUTCOMES:
        pytest.skip("run together with the fuzzer")
    print(f"signal fuzz outcomes: {OUTCOMES}")
    assert OUTCOMES.get("interrupted", 0) > 0


def test_a_second_run_into_the_same_out_is_refused(fmus_in_repo, tmp_path):
    out = tmp_path / "out"
    first = start_run(out, "out-of-process", 30.0)
    try:
        deadline = time.monotonic() + 120
        rows = tmp_path / "out.running" / "contact.csv"
        while not rows.exists() or rows.read_text().count("\n") < 100:
            assert first.poll() is None and time.monotonic() < deadline, first.stderr.read() if first.poll() else ""
            time.sleep(0.05)
        second = subprocess.run([sys.executable, "-m", "orchestration", "run", SCENE, "--duration", "0.1",
                                 "--hosting", "in-process", "--out", str(out), "--no-vtu", "--quiet"],
                                cwd=REPO, capture_output=True, text=True, timeout=300)
        assert second.returncode == 2, second.stderr
        assert f"--out {out} is in use by another run (pid {first.pid}" in second.stderr
        assert "Traceback" not in second.stderr
        assert first.poll() is None  # the first run goes on, untouched
        os.killpg(first.pid, signal.SIGINT)
        _, stderr = first.communicate(timeout=120)
    finally:
        if first.poll() is None:
            os.killpg(first.pid, signal.SIGKILL)
            first.wait()
    assert first.returncode == 130, stderr
    summary = json.loads((tmp_path / "out.interrupted" / "summary.json").read_text())
    check_results(tmp_path / "out.interrupted", summary)   # one run's rows only, none interleaved
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.interrupted"]


def test_a_stale_lock_of_a_dead_run_is_taken_over_with_a_note(fmus_in_repo, tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    (tmp_path / "out.lock").write_text(f"{pid}\n")
    proc = subprocess.run([sys.executable, "-m", "orchestration", "run", SCENE, "--duration", "0.1", "--hosting",
                           "in-process", "--out", str(tmp_path / "out"), "--no-vtu", "--quiet"],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert f"took over the lock of an earlier run (pid {pid}, no longer running)" in proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_stopped_worker_ends_the_run_as_failed_after_the_scene_timeout(fmus_in_repo, tmp_path):
    out = tmp_path / "out"
    proc = start_run(out, "out-of-process", 60.0, "--set", "scene.worker_timeout=1.5")
    worker = None
    try:
        deadline = time.monotonic() + 120
        while not (tmp_path / "out.running" / "contact.csv").exists() or \
                (tmp_path / "out.running" / "contact.csv").stat().st_size < 20000:
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.05)
        workers = [line for line in group_members(proc.pid) if "spawn_main" in line and "-writer]" not in line]
        assert len(workers) == 1, workers
        worker = int(workers[0].split(":")[0])
        os.kill(worker, signal.SIGSTOP)
        stopped_at = time.monotonic()
        stdout, stderr = proc.communicate(timeout=60)
        waited = time.monotonic() - stopped_at
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        if worker is not None:
            try:
                os.kill(worker, signal.SIGCONT)
            except ProcessLookupError:
                pass
    assert proc.returncode == 1, stderr
    assert 1.5 <= waited < 15, waited
    assert "Traceback" not in stderr
    failed = tmp_path / "out.failed"
    summary = json.loads((failed / "summary.json").read_text())
    assert summary["status"] == "failed"
    error = summary["error"]
    assert error.startswith("contact: fmi3DoStep at t = "), error
    assert f"the worker (pid {worker}) did not answer within 1.5 s (the scene's [scene] worker_timeout)" in error
    assert "killed" in error and error in stderr
    t = float(error.split("at t = ")[1].split(" s")[0])
    assert 0 < t <= summary["simulated_time_s"] + 2 * STEP
    check_results(failed, summary)
    assert_no_process_left(proc.pid)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.failed"]


def test_the_automatic_worker_deadline_grows_with_the_slowest_recent_reply():
    from orchestration.stopping import DEADLINE_FLOOR, RecentSlowest
    from orchestration.hosts.worker import WorkerFmu

    host = WorkerFmu.__new__(WorkerFmu)
    host.reply_timeout, host.setup_timeout, host._in_setup = None, 600.0, True
    host.replies = RecentSlowest()
    assert host.reply_deadline()[0] == 600.0                     # first calls: the generous allowance
    host._in_setup = False
    assert host.reply_deadline()[0] == DEADLINE_FLOOR            # fast steps: the floor
    host.replies.before = 0.5
    timeout, why = host.reply_deadline()
    assert timeout == 50.0 and "0.5 s" in why and "worker_timeout" in why
    host.reply_timeout = 2.0
    assert host.reply_deadline() == (2.0, "the scene's [scene] worker_timeout")


def _unusable_out_cases(tmp_path: Path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    yield "a file in the way", blocker, "a file of that name is in the way"
    yield "under a file", blocker / "out", "cannot create its parent folder"
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "thesis.tex").write_text("precious")
    yield "a folder of other files", notes, "holds files that are not results of a run (thesis.tex)"


def test_an_unusable_out_is_refused_before_the_run(fmus_in_repo, tmp_path):
    for label, out, message in _unusable_out_cases(tmp_path):
        before = sorted(p.name for p in tmp_path.rglob("*"))
        proc = subprocess.run([sys.executable, "-m", "orchestration", "run", SCENE, "--duration", "0.1",
                               "--out", str(out), "--no-vtu", "--quiet"],
                              cwd=REPO, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 2, (label, proc.stderr)
        assert f"--out {out}" in proc.stderr and message in proc.stderr, (label, proc.stderr)
        assert "Traceback" not in proc.stderr
        assert sorted(p.name for p in tmp_path.rglob("*")) == before, label  # nothing written, nothing removed


def test_a_read_only_out_is_refused_and_its_results_kept(fmus_in_repo, tmp_path, monkeypatch, capsys):
    """chmod 555 on OUT. Root writes everywhere, so as root the permission check is made to see
    what an ordinary user's would (os.access says no); otherwise it is the real thing, in a
    subprocess."""
    out = tmp_path / "out"
    old = make_old_result(out)
    (out / "summary.json").chmod(0o444)
    out.chmod(0o555)
    argv = ["run", SCENE, "--duration", "0.1", "--out", str(out), "--no-vtu", "--quiet"]
    try:
        if os.geteuid() == 0:
            from orchestration.app import result_folder as outfolder
            from orchestration.app.cli import main

            real_access = os.access
            monkeypatch.setattr(outfolder.os, "access", lambda path, mode: (
                not (mode & os.W_OK and Path(path).stat().st_mode & 0o222 == 0) and real_access(path, mode)))
            code = main(argv)
            stderr = capsys.readouterr().err
        else:
            proc = subprocess.run([sys.executable, "-m", "orchestration", *argv],
                                  cwd=REPO, capture_output=True, text=True, timeout=300)
            code, stderr = proc.returncode, proc.stderr
        assert code == 2, stderr
        assert f"--out {out}: the folder is read-only" in stderr, stderr
        assert f"chmod -R u+w {out}" in stderr and "Traceback" not in stderr
        assert (out / "summary.json").read_bytes() == old and (out / "contact.csv").read_text() == '"time"\n0.0\n'
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    finally:
        out.chmod(0o755)


def test_a_library_run_stops_cleanly_on_sigint_then_hands_the_keyboardinterrupt_on(fmus_in_repo, tmp_path):
    """run_scene() from Python, in the main thread: Ctrl-C stops the run between ticks, its results
    and summary are written, and then the caller (a study's loop) gets its KeyboardInterrupt."""
    import threading

    from orchestration.run.simulation import run_scene
    from orchestration.scene.loading import load_scene

    # The premise: a program with Python's own Ctrl-C handling. A background job of a
    # non-interactive shell (CI started with `&`) inherits SIGINT ignored, and a run rightly
    # leaves an ignored signal ignored (see stopping._take_over).
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler)
    before = signal.getsignal(signal.SIGINT)
    done = threading.Event()

    def interrupt_when_rows_arrive():
        rows = tmp_path / "contact.csv"
        while not done.is_set():
            if rows.exists() and rows.read_text().count("\n") > 200:
                os.kill(os.getpid(), signal.SIGINT)
                return
            time.sleep(0.01)

    thread = threading.Thread(target=interrupt_when_rows_arrive, daemon=True)
    thread.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            run_scene(load_scene(SCENE), tmp_path, hosting="in-process", duration=60.0, progress=False,
                      plots=False, vtu=False)
    finally:
        done.set()
        thread.join()
        after = signal.signal(signal.SIGINT, inherited)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["status"] == "interrupted", summary["error"]
    assert summary["error"] == summary["stop_request"] == "interrupted by Ctrl-C (SIGINT)"
    assert 0.2 <= summary["simulated_time_s"] < 60
    assert after is before       # the run's handler is gone again
    check_results(tmp_path, summary)

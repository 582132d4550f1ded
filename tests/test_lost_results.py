"""Issue 33, second round: helper processes and lost results.

A run that cannot keep its results says so and never ends "completed": a full or read-only results
volume, a file-size limit, a results folder deleted under the run, a writer process that dies or
stops. The writer processes have a deadline as the workers do, Ctrl-C and SIGTERM still stop a run
whose writer is stuck, and shared memory that cannot be had is an error before the run starts (not
a SIGBUS later). Every run here is a fresh process (a hang or a crash is possible), each bounded
by a timeout; the mounts (a tiny tmpfs, a read-only bind mount, a small /dev/shm) are made in a
private mount namespace that vanishes with its process, and the tests that need one are skipped
where it cannot be made (not root, no unshare).
"""
from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from process_helpers import assert_no_process_left, group_pids

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture
def built(fmus_in_repo):
    """The shipped scenes use fmus/ (tests/conftest.py builds them): checked again before each test
    (a run under a file-size limit or on a tiny volume could not build them)."""
    from orchestration.app.warmup import ensure_fmus_built

    ensure_fmus_built(quiet=True)


# -- running the command line in a process group of its own ------------------------------------------------
def _run_args(*args: str) -> list[str]:
    return [sys.executable, "-m", "orchestration", "run", *args]


def _start(*args: str, **popen) -> subprocess.Popen:
    return subprocess.Popen(_run_args(*args), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, **popen)  # its group: the run, its workers, its writers


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)  # a stopped writer too
    except (ProcessLookupError, PermissionError):
        pass


def _finish(proc: subprocess.Popen, timeout: float) -> tuple[int, str, str]:
    """Wait for the run; a run that does not end in ``timeout`` s is killed (its whole group) and fails the test."""
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        _kill_group(proc.pid)
        out, err = proc.communicate()
        pytest.fail(f"the run did not end within {timeout:g} s (killed); stderr: {err[-2000:]}")
    return proc.returncode, out, err


def _wait_for(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"{what} within {timeout:g} s")


def _rows(path: Path) -> int:
    try:
        return max(0, path.read_bytes().count(b"\n") - 1)
    except OSError:
        return 0


def _whole_rows(path: Path) -> tuple[int, float]:
    """Assert ``path`` holds a header and whole rows only, times strictly increasing; (rows, last time)."""
    text = path.read_text()
    assert text.endswith("\n"), f"{path} ends in the middle of a row: {text[-80:]!r}"
    lines = text.splitlines()
    n = len(lines[0].split(","))
    times = []
    for number, line in enumerate(lines[1:], start=2):
        fields = line.split(",")
        assert len(fields) == n, f"{path} line {number}: {len(fields)} fields, expected {n}: {line[:120]!r}"
        times.append(float(fields[0]))
        [float(x) for x in fields]
    assert all(b > a for a, b in zip(times, times[1:])), f"{path}: times not strictly increasing"
    return len(times), times[-1] if times else float("nan")


def _kept_rows(text: str, name: str) -> int:
    """The rows the message says ``name`` keeps: "... /name keeps 1234 of 5678 rows ..."."""
    head, sep, tail = text.partition(f"{name} keeps ")
    assert sep, f"no '{name} keeps N of M rows' in: {text}"
    return int(tail.split()[0])


# -- a private mount namespace (root only) ------------------------------------------------------------------
#: The start of a driver script run in a private mount namespace: it makes the mounts, runs the
#: command line and reports what happened as JSON on its last line (the mounts vanish with it).
_DRIVER = textwrap.dedent('''
    import json, os, shutil, signal, subprocess, sys, time
    from pathlib import Path

    def mount(*args):
        proc = subprocess.run(["mount", *args], capture_output=True, text=True)
        if proc.returncode:
            print(json.dumps({"skip": f"mount {' '.join(args)}: {proc.stderr.strip()}"}))
            sys.exit(0)

    def start(*args):
        return subprocess.Popen([sys.executable, "-m", "orchestration", "run", *args], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, start_new_session=True)

    def finish(proc, timeout):
        try:
            out, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            out, err = proc.communicate()
            return {"rc": "timeout", "out": out, "err": err}
        return {"rc": proc.returncode, "out": out, "err": err}

    def wait_rows(path, rows, timeout=120):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                if path.read_bytes().count(b"\\n") > rows:
                    return
            except OSError:
                pass
            time.sleep(0.05)
        raise SystemExit(f"{path} did not reach {rows} rows")
''')


def _in_mount_namespace(tmp_path: Path, scenario: str, timeout: float = 240) -> dict:
    """Run ``scenario`` (Python, after :data:`_DRIVER`) in a private mount namespace; its report."""
    if os.geteuid() != 0 or shutil.which("unshare") is None or shutil.which("mount") is None:
        pytest.skip("needs root, unshare and mount (a private mount namespace)")
    unshare = ["unshare", "--mount", "--propagation", "private"]
    if subprocess.run([*unshare, "true"], capture_output=True).returncode:
        pytest.skip("unshare --mount is not permitted here")
    script = tmp_path / "driver.py"
    script.write_text(_DRIVER + textwrap.dedent(scenario))
    proc = subprocess.run([*unshare, sys.executable, str(script)], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    if "skip" in report:
        pytest.skip(report["skip"])
    assert report["rc"] != "timeout", f"the run did not end in time; stderr: {report['err'][-2000:]}"
    return report


# -- the writer processes, on their own ----------------------------------------------------------------------
def _python(code: str, timeout: float = 60, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout, start_new_session=True, **kwargs)


def test_a_stopped_row_writer_is_killed_at_its_deadline_and_reported(tmp_path):
    """SIGSTOP: the writer takes nothing more; a write that finds the pipe full waits at most the
    deadline without progress, then the writer is killed and close() says why."""
    proc = _python(f"""
        import os, signal, time
        import numpy as np
        from orchestration.observers.row_writer import RowWriter
        if __name__ == "__main__":
            writer = RowWriter()
            writer.helper.timeout = 1.0
            path = {str(tmp_path / "c.csv")!r}
            open(path, "w").close()
            writer.add_stream("c", path, 2)
            os.kill(writer.pid, signal.SIGSTOP)
            block = np.zeros((1000, 2)).tobytes()
            start = time.monotonic()
            sent = 0
            while writer.write("c", block):
                sent += 1
            waited = time.monotonic() - start
            print(sent, round(waited, 1), writer.close())
    """, timeout=60)
    assert proc.returncode == 0, proc.stderr
    sent, waited, errors = proc.stdout.split(" ", 2)
    assert int(sent) > 0 and float(waited) < 20
    assert "the row writer process" in errors and "was killed" in errors and "made no progress" in errors


def test_a_block_cut_by_a_file_size_limit_leaves_whole_rows_and_tells_at_once(tmp_path):
    """RLIMIT_FSIZE: the write fails with EFBIG (SIGXFSZ ignored, not a killed writer), the file is
    cut back to whole rows, nothing more is written to it, and a notice says what it keeps."""
    path = tmp_path / "c.csv"
    proc = _python(f"""
        import time
        import numpy as np
        from orchestration.observers.row_writer import RowWriter
        if __name__ == "__main__":
            writer = RowWriter()
            notices = []
            writer.helper.on_notice = notices.append
            path = {str(path)!r}
            open(path, "w").close()
            writer.add_stream("c", path, 3)
            for k in range(40):
                rows = np.column_stack([np.arange(k * 100, k * 100 + 100) / 1000, np.full(100, 1 / 3), np.full(100, k)])
                writer.write("c", rows.tobytes())
            time.sleep(1)
            writer.helper.poll()
            errors = writer.close()
            print(repr((notices, errors)))
    """, timeout=60, preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000)))
    assert proc.returncode == 0, proc.stderr
    notices, errors = eval(proc.stdout)
    rows, last = _whole_rows_of_floats(path)
    assert 0 < rows < 4000 and path.stat().st_size <= 20_000
    assert len(notices) == 1 and notices[0]["rows_kept"] == rows and notices[0]["last_time"] == last
    assert notices[0]["reason"] == "File too large" and notices[0]["path"] == str(path)
    assert errors and all(e.startswith("c: ") for e in errors) and "File too large" in errors[0]


def _whole_rows_of_floats(path: Path) -> tuple[int, float]:
    text = path.read_text()
    assert text.endswith("\n"), text[-80:]
    rows = [line.split(",") for line in text.splitlines()]
    assert all(len(r) == 3 for r in rows)
    return len(rows), float(rows[-1][0])


# -- whole runs ------------------------------------------------------------------------------------------------
def test_a_file_size_limit_mid_run_ends_it_failed_with_whole_rows(built, tmp_path):
    """``ulimit -f``: the CSV that reaches the limit keeps whole rows; the run stops, says which file
    and how many rows it keeps, exits 1 and its summary says "failed"."""
    out = tmp_path / "out"
    limit = 400_000  # bytes; above every file the run reads or writes but the rows (the FMUs' largest: 280 KB)
    proc = _start("virtual_wall", "--duration", "10", "--no-vtu", "--quiet", "--out", str(out),
                  preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)))
    rc, _, err = _finish(proc, 120)
    assert rc == 1, err[-3000:]
    assert "Traceback" not in err
    failed = tmp_path / "out.failed"
    summary = json.loads((failed / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["simulated_time_s"] < 10
    assert "File too large" in summary["error"] and "ulimit -f" in summary["error"]
    device = failed / "device.csv"
    rows, _ = _whole_rows(device)
    assert device.stat().st_size <= limit
    assert _kept_rows(summary["error"], "device.csv") == rows
    assert f"{failed}/device.csv keeps {rows} of" in err  # the message names the file where it now is
    _whole_rows(failed / "contact.csv")
    assert not out.exists()


def test_a_results_folder_deleted_mid_run_ends_it_failed(built, tmp_path):
    """The folder deleted under the run: it stops, exits 1, and the summary (written where it can
    be) says what is gone and lists no file that does not exist."""
    out = tmp_path / "out"
    running = tmp_path / "out.running"
    proc = _start("virtual_wall", "--duration", "6", "--realtime", "--no-vtu", "--quiet", "--out", str(out))
    try:
        _wait_for(lambda: _rows(running / "contact.csv") > 200, 120, "no rows")
        shutil.rmtree(running)
        rc, _, err = _finish(proc, 60)
    finally:
        _kill_group(proc.pid)
    assert rc == 1, err[-3000:]
    assert "Traceback" not in err and "deleted" in err
    failed = tmp_path / "out.failed"
    summary = json.loads((failed / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["simulated_time_s"] < 5
    assert any("was deleted" in loss for loss in summary["lost"])
    listed = [v for k, v in summary["results"].items() if k not in ("folder", "plots") and isinstance(v, str)]
    assert all(Path(p).exists() for p in listed), listed
    assert not out.exists()


def test_a_stopped_row_writer_ends_in_its_deadline_and_the_run_says_what_was_lost(built, tmp_path):
    """SIGSTOP on the row writer mid-run: killed once it made no progress for the deadline (the
    scene's worker_timeout), the run's own process writes the rows from then on, the run ends on
    time, "failed", naming what the writer took with it; the CSVs hold whole rows."""
    out = tmp_path / "out"
    proc = _start("virtual_wall", "--duration", "6", "--realtime", "--no-vtu", "--quiet", "--out", str(out),
                  "--set", "scene.worker_timeout=2")
    try:
        _wait_for(lambda: _rows(tmp_path / "out.running" / "contact.csv") > 200, 120, "no rows")
        writer, = _wait_for(lambda: group_pids(proc.pid, "row-writer"), 10, "no row writer")
        os.kill(writer, signal.SIGSTOP)
        rc, _, err = _finish(proc, 60)
    finally:
        _kill_group(proc.pid)
    assert rc == 1, err[-3000:]
    assert "Traceback" not in err and "made no progress" in err
    summary = json.loads((tmp_path / "out.failed" / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["simulated_time_s"] == pytest.approx(6)
    assert "the row writer process ended (killed by the run: it made no progress" in summary["error"]
    for name in ("device", "contact"):
        rows, last = _whole_rows(tmp_path / "out.failed" / f"{name}.csv")
        assert last == pytest.approx(6) and rows < 6001  # the rows after the kill, not those it took
    assert any("contact.csv keeps" in loss for loss in summary["lost"])
    assert_no_process_left(proc.pid)


def test_sigterm_stops_a_run_whose_row_writer_is_stopped(built, tmp_path):
    """SIGSTOP on the row writer, then SIGTERM twice: the run ends at once (the second signal kills
    the writer it waits for), exit 143, "interrupted", saying what was lost; nothing is left behind."""
    out = tmp_path / "out"
    proc = _start("virtual_wall", "--duration", "60", "--realtime", "--no-vtu", "--quiet", "--out", str(out),
                  "--set", "scene.worker_timeout=100")
    try:
        _wait_for(lambda: _rows(tmp_path / "out.running" / "contact.csv") > 200, 120, "no rows")
        writer, = _wait_for(lambda: group_pids(proc.pid, "row-writer"), 10, "no row writer")
        os.kill(writer, signal.SIGSTOP)
        time.sleep(2.0)  # the pipe fills
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.5)
        proc.send_signal(signal.SIGTERM)
        start = time.monotonic()
        rc, _, err = _finish(proc, 30)
        took = time.monotonic() - start
    finally:
        _kill_group(proc.pid)
    assert rc == 143, err[-3000:]
    assert took < 15 and "Traceback" not in err
    summary = json.loads((tmp_path / "out.interrupted" / "summary.json").read_text())
    assert summary["status"] == "interrupted" and "results lost" in summary["error"]
    assert "row writer" in " ".join(summary["lost"])
    for name in ("device", "contact"):
        _whole_rows(tmp_path / "out.interrupted" / f"{name}.csv")
    assert_no_process_left(proc.pid)


def test_a_surface_writer_killed_mid_run_is_a_failed_run_whose_pvd_lists_the_frames_on_disk(built, tmp_path):
    """SIGSTOP, then SIGKILL on the surface writer with frames in its pipe: the run's own process
    writes the frames from then on; those the writer took with it are missing, the run says how
    many ("failed", exit 1) and the .pvd lists exactly the frames on disk."""
    out = tmp_path / "out"
    proc = _start("tissue_indentation", "--duration", "3", "--realtime", "--quiet", "--out", str(out))
    try:
        frames = tmp_path / "out.running" / "aaa_wall"
        _wait_for(lambda: (frames / "aaa_wall_00001.vtu").exists(), 120, "no frame written")
        writer, = _wait_for(lambda: group_pids(proc.pid, "surface-writer"), 10, "no surface writer")
        os.kill(writer, signal.SIGSTOP)
        time.sleep(1.0)  # frames pile up in its pipe
        os.kill(writer, signal.SIGKILL)
        rc, _, err = _finish(proc, 120)
    finally:
        _kill_group(proc.pid)
    assert rc == 1, err[-3000:]
    assert "Traceback" not in err
    failed = tmp_path / "out.failed"
    summary = json.loads((failed / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["simulated_time_s"] == pytest.approx(3)
    datasets = ET.parse(failed / "aaa_wall.pvd").getroot().find("Collection").findall("DataSet")
    listed = sorted(d.get("file") for d in datasets)
    on_disk = sorted(f"aaa_wall/{p.name}" for p in (failed / "aaa_wall").glob("*.vtu"))
    assert listed == on_disk
    expected = 1 + 90 // 3  # the initial frame, then every 3rd of 90 steps
    loss = next(loss for loss in summary["lost"] if "aaa_wall.pvd lists" in loss)
    assert f"aaa_wall.pvd lists {len(listed)} of {expected} frames" in loss
    assert len(listed) < expected
    assert (failed / "aaa_wall" / f"aaa_wall_{expected - 1:05d}.vtu").exists()  # the last, written by the run
    assert "surface writer" in summary["error"]


def test_a_full_results_volume_ends_the_run_with_whole_rows_and_a_summary(built, tmp_path):
    """A 300 KB results volume fills up: the run stops, exit 1, no traceback; the message names the
    file and the rows it keeps; the summary is written (room for it was kept) in OUT.failed."""
    report = _in_mount_namespace(tmp_path, f'''
        volume = Path({str(tmp_path / "volume")!r})
        volume.mkdir()
        mount("-t", "tmpfs", "-o", "size=300k", "tmpfs", str(volume))
        proc = start("virtual_wall", "--duration", "10", "--no-vtu", "--quiet", "--out", str(volume / "out"))
        report = finish(proc, 120)
        shutil.copytree(volume, {str(tmp_path / "copy")!r})
        print(json.dumps(report))
    ''')
    assert report["rc"] == 1, report["err"][-3000:]
    assert "Traceback" not in report["err"]
    failed = tmp_path / "copy" / "out.failed"
    summary = json.loads((failed / "summary.json").read_text())
    assert summary["status"] == "failed" and "No space left on device" in summary["error"]
    for name in ("device", "contact"):
        rows, _ = _whole_rows(failed / f"{name}.csv")
        if f"{name}.csv keeps" in summary["error"]:
            assert _kept_rows(summary["error"], f"{name}.csv") == rows
    assert "keeps" in summary["error"] and "rows" in summary["error"]
    assert str(tmp_path / "volume" / "out.failed") in report["err"]  # the message names where the files are


@pytest.mark.parametrize("which", ["running", "parent"])
def test_a_results_volume_made_read_only_mid_run_ends_it_failed_without_a_traceback(built, tmp_path, which):
    """OUT.running (or the folder holding it) made read-only mid-run: the rows already open go on,
    the summary cannot be written nor the folder moved; the run says so, naming the path, exit 1."""
    base = tmp_path / "base"
    base.mkdir()
    target = base / "out.running" if which == "running" else base
    report = _in_mount_namespace(tmp_path, f'''
        base = Path({str(base)!r})
        proc = start("virtual_wall", "--duration", "3", "--realtime", "--no-vtu", "--quiet", "--out", str(base / "out"))
        wait_rows(base / "out.running" / "contact.csv", 200)
        target = {str(target)!r}
        mount("--bind", target, target)
        mount("-o", "remount,bind,ro", target)
        print(json.dumps(finish(proc, 60)))
    ''')
    assert report["rc"] == 1, report["err"][-3000:]
    err = report["err"]
    assert "Traceback" not in err
    assert f"{base}/out.running/summary.json could not be written (Read-only file system" in err
    assert f"they stay in {base}/out.running" in err
    rows, last = _whole_rows(base / "out.running" / "contact.csv")  # every row kept, whole
    assert rows == 3001 and last == pytest.approx(3)


def test_shared_memory_that_cannot_be_had_is_an_error_before_the_run(built, tmp_path):
    """/dev/shm nearly full (the tissue worker's values live there): a clear error before the run
    (exit 1), not a SIGBUS in the middle of it, and no shared memory segment left behind."""
    report = _in_mount_namespace(tmp_path, f'''
        mount("-t", "tmpfs", "-o", "size=256k", "tmpfs", "/dev/shm")
        with open("/dev/shm/filler", "wb") as filler:  # leaves 24 KB: too little for the wall's values
            filler.write(b"x" * (232 * 1024))
        proc = start("tissue_indentation", "--duration", "0.1", "--no-vtu", "--quiet", "--out",
                     {str(tmp_path / "out")!r})
        report = finish(proc, 120)
        report["left"] = sorted(p.name for p in Path("/dev/shm").iterdir() if p.name != "filler")
        print(json.dumps(report))
    ''')
    assert report["rc"] == 1, report["err"][-3000:]
    err = report["err"]
    assert "Traceback" not in err
    assert "cannot reserve" in err and "shared memory" in err and "/dev/shm" in err and "--hosting in-process" in err
    assert report["left"] == []
    summary = json.loads((tmp_path / "out.failed" / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["simulated_time_s"] == 0

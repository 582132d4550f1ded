"""Result recording: exact CSV round trip, crash safety, VTU/PVD series, summary, plots."""
from __future__ import annotations

import csv
import json
import logging
import math
import os
import signal
import subprocess
import sys
import textwrap
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np
import pytest

from orchestration.observers.plots import _series_lines, plot_signals
from orchestration.observers.recorder import Recorder, RecordingError, port_values, read_stream, write_summary

REPO = Path(__file__).resolve().parent.parent
AWKWARD = np.array([1 / 3, 1e-300, -0.0, 5e-324, 1.7976931348623157e308, 0.1 + 0.2, -2.5e-17, math.pi,
                    float("inf"), float("-inf"), float("nan"), 123456789.123456789])


def bits(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64).view(np.uint64)


def test_round_trip_is_bitwise_exact(tmp_path):
    rng = np.random.default_rng(7)
    with Recorder(tmp_path) as rec:
        rec.add_stream("c", [("x", 1, "m"), ("f", 3, "N"), ("n", 1, None)])
        times, xs, fs = [], [], []
        for k in range(200):
            t = k / 3 * 1e-3
            x = AWKWARD[k % AWKWARD.size] if k < 50 else rng.standard_normal() * 10.0 ** rng.integers(-300, 300)
            f = rng.standard_normal(3) * 10.0 ** rng.integers(-20, 20, size=3)
            rec.write("c", t, {"x": np.array([x]), "f": f, "n": np.array([k], dtype=np.int32)})
            times.append(t), xs.append(x), fs.append(f)
    t, cols = read_stream(tmp_path / "c.csv")
    assert np.array_equal(bits(t), bits(times))
    assert np.array_equal(bits(cols["x"]), bits(xs))  # includes -0.0, subnormals, inf and nan
    assert np.array_equal(bits(port_values(cols, "f")), bits(np.array(fs)))
    assert np.array_equal(cols["n"], np.arange(200.0))  # Int32 carried exactly as float64


def test_header_is_quoted_with_time_first_and_units_apart(tmp_path):
    rec = Recorder(tmp_path)
    path = rec.add_stream("contact", [("depth", 1, "m"), ("tool_force", 3, "N"), ("count", 1, None)])
    # The header is on disk before the first row and before close.
    assert path.read_text() == '"time","depth","tool_force[0]","tool_force[1]","tool_force[2]","count"\n'
    rec.write("contact", 0.5, {"depth": np.array([-1e-3]), "tool_force": np.array([1.0, 2.0, 3.0]),
                               "count": np.array([True])})
    rec.close()
    lines = path.read_text().splitlines()
    assert lines[1] == "0.5,-0.001,1.0,2.0,3.0,1.0"  # unquoted numbers, so QUOTE_NONNUMERIC reads floats
    rows = list(csv.reader(lines, quoting=csv.QUOTE_NONNUMERIC))
    assert rows[1] == [0.5, -0.001, 1.0, 2.0, 3.0, 1.0]
    units = json.loads((tmp_path / "units.json").read_text())
    assert units == {"contact": {"time": "s", "depth": "m", "tool_force[0]": "N", "tool_force[1]": "N",
                                 "tool_force[2]": "N"}}
    assert rec.files == {"contact": path, "units": tmp_path / "units.json"}


def test_bad_writes_are_rejected_with_the_port_named(tmp_path):
    with Recorder(tmp_path) as rec:
        rec.add_stream("c", [("f", 3, "N")])
        with pytest.raises(RecordingError, match=r"c\.f .*expected 3 values, got 2"):
            rec.write("c", 0.0, {"f": np.zeros(2)})
        with pytest.raises(RecordingError, match=r"c\.f .*expected 3 values, got 1"):  # not spread over 3
            rec.write("c", 0.0, {"f": np.ones(1)})
        with pytest.raises(RecordingError, match="no value for recorded port 'f'"):
            rec.write("c", 0.0, {"g": np.zeros(3)})
        with pytest.raises(RecordingError, match="add_stream\\('d'"):
            rec.write("d", 0.0, {"f": np.zeros(3)})
        with pytest.raises(RecordingError, match="already declared"):
            rec.add_stream("c", [("f", 3, "N")])
        with pytest.raises(RecordingError, match="size must be an integer >= 1"):
            rec.add_stream("e", [("f", 0, "N")])
    t, cols = read_stream(tmp_path / "c.csv")
    assert t.size == 0 and cols["f[0]"].size == 0  # no partial rows from the rejected writes
    with pytest.raises(RecordingError, match="closed"):
        rec.write("c", 1.0, {"f": np.zeros(3)})


def test_rows_reach_the_os_within_flush_interval_without_close(tmp_path):
    rec = Recorder(tmp_path, flush_interval=0.05)
    rec.add_stream("c", [("x", 1, None)])
    for k in range(10):
        rec.write("c", k * 1e-3, {"x": np.array([float(k)])})
    time.sleep(0.3)  # the caller is busy elsewhere: the background flusher must hand the rows over
    t, cols = read_stream(tmp_path / "c.csv")  # a separate open of the file
    assert np.array_equal(cols["x"], np.arange(10.0))
    rec.close()


CHILD = textwrap.dedent("""
    import os, sys, time
    import numpy as np
    from orchestration.observers.recorder import Recorder
    mode, out, interval = sys.argv[1], sys.argv[2], float(sys.argv[3])
    rec = Recorder(out, flush_interval=interval)
    rec.add_stream("c", [("wall", 1, "s"), ("v", 3, None)])
    def row(k):
        rec.write("c", k * 1e-3, {"wall": np.array([time.time()]), "v": np.array([k, k / 3, -k * 1e-300])})
    if mode == "stall_then_exit":
        for k in range(100):
            row(k)
        time.sleep(3 * interval)
        os._exit(1)                 # no atexit, no close: only what was flushed survives
    if mode == "exception":
        for k in range(100):
            row(k)
        raise RuntimeError("caller failed")   # atexit must close the recorder
    k = 0
    while True:                     # "forever": the parent sends SIGKILL
        row(k)
        k += 1
        if k == 50:
            print("ready", flush=True)
        time.sleep(5e-4)
""")


def run_child(mode, out, interval):
    return subprocess.Popen([sys.executable, "-c", CHILD, mode, str(out), str(interval)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def assert_complete_rows(t, cols):
    k = np.arange(t.size)
    assert np.array_equal(t, k * 1e-3)
    assert np.array_equal(port_values(cols, "v"), np.column_stack([k, k / 3, -k * 1e-300]))


def test_child_killed_with_os_exit_after_a_stall_keeps_every_row(tmp_path):
    child = run_child("stall_then_exit", tmp_path, 0.1)
    assert child.wait(timeout=60) == 1
    t, cols = read_stream(tmp_path / "c.csv")
    assert t.size == 100
    assert_complete_rows(t, cols)


def test_exception_in_the_caller_still_closes_the_recorder(tmp_path):
    child = run_child("exception", tmp_path, 30.0)  # long interval: only close() can have flushed
    _, err = child.communicate(timeout=60)
    assert child.returncode == 1 and "caller failed" in err
    t, cols = read_stream(tmp_path / "c.csv")
    assert t.size == 100
    assert_complete_rows(t, cols)


def test_sigkill_mid_run_keeps_rows_older_than_flush_interval(tmp_path):
    interval = 0.1
    child = run_child("forever", tmp_path, interval)
    try:
        assert child.stdout.readline().strip() == "ready"
        time.sleep(0.35)
        t_kill = time.time()
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(timeout=30)
    t, cols = read_stream(tmp_path / "c.csv")
    assert t.size >= 50
    assert_complete_rows(t, cols)  # contiguous, every row complete, no partial last row
    # Everything written before t_kill - interval is on disk; 0.1 s extra for scheduling on a busy machine.
    assert cols["wall"][-1] >= t_kill - interval - 0.1
    assert cols["wall"][-1] <= t_kill


def test_read_stream_skips_a_truncated_last_line_and_malformed_lines(tmp_path, caplog):
    path = tmp_path / "c.csv"
    path.write_text('"time","a","b"\n0.0,1.0,2.0\n0.001,1.5,2.5\n0.002,oops\n0.003,3.0,4.0\n0.004,5.0,6')
    with caplog.at_level(logging.WARNING, logger="orchestration.observers.recorder"):
        t, cols = read_stream(path)
    assert np.array_equal(t, [0.0, 0.001, 0.003])
    assert np.array_equal(cols["b"], [2.0, 2.5, 4.0])
    assert "line 4 skipped" in caplog.text
    path.write_text('"time","a"\n0.0,1.0\n0.0')  # cut inside the last number
    t, cols = read_stream(path)
    assert np.array_equal(t, [0.0]) and np.array_equal(cols["a"], [1.0])


def test_surface_series_frames_read_back_and_pvd_lists_every_frame(tmp_path):
    rng = np.random.default_rng(3)
    triangles = np.array([[0, 1, 2], [0, 2, 3], [1, 3, 2], [0, 3, 1]])
    rec = Recorder(tmp_path)
    pvd = rec.add_surface_series("tissue", triangles)
    assert ET.parse(pvd).getroot().find("Collection") is not None  # valid (empty) before the first frame
    times = [0.0, 1 / 30, 2 / 30, 0.1]
    frames = []
    for k, t in enumerate(times):
        pos = rng.standard_normal((4, 3))
        force = rng.standard_normal((4, 3))
        depth = rng.standard_normal(4)
        flat = k % 2 == 1  # the flat port layout x0, y0, z0, x1, ... is accepted too
        rec.write_surface("tissue", t, pos.ravel() if flat else pos,
                          {"force": force.ravel() if flat else force, "depth": depth})
        frames.append((pos, force, depth))
        root = ET.parse(pvd).getroot()  # after every frame, not only at close
        assert len(root.find("Collection").findall("DataSet")) == k + 1
    rec.close()
    root = ET.parse(pvd).getroot()
    assert root.get("type") == "Collection"
    datasets = root.find("Collection").findall("DataSet")
    assert [float(d.get("timestep")) for d in datasets] == times
    for d, (pos, force, depth) in zip(datasets, frames):
        mesh = meshio.read(tmp_path / d.get("file"))
        assert np.array_equal(mesh.points, pos)
        assert np.array_equal(mesh.cells_dict["triangle"], triangles)
        assert np.array_equal(mesh.point_data["force"], force)
        assert np.array_equal(mesh.point_data["depth"], depth)
    assert rec.files["tissue"] == pvd and rec.files["tissue[3]"] == tmp_path / "tissue" / "tissue_00003.vtu"
    assert not list(tmp_path.rglob("*.tmp"))
    with Recorder(tmp_path / "bad") as bad:
        bad.add_surface_series("s", triangles)
        with pytest.raises(RecordingError, match="only 3 positions"):
            bad.write_surface("s", 0.0, np.zeros((3, 3)))
        with pytest.raises(RecordingError, match=r"expected shape \(4,\) or \(4, 3\)"):
            bad.write_surface("s", 0.0, np.zeros((4, 3)), {"depth": np.zeros(5)})


def _surface_frames(tmp_path, writer):
    """Four frames of a small surface through a recorder (with ``writer`` or without), read back."""
    rng = np.random.default_rng(5)
    triangles = np.array([[0, 1, 2], [0, 2, 3], [1, 3, 2], [0, 3, 1]])
    with Recorder(tmp_path, surface_writer=writer) as rec:
        pvd = rec.add_surface_series("tissue", triangles)
        for k in range(4):
            rec.write_surface("tissue", k / 30, rng.standard_normal((4, 3)), {"depth": rng.standard_normal(4)})
        files = rec.files
    datasets = ET.parse(pvd).getroot().find("Collection").findall("DataSet")
    meshes = [meshio.read(tmp_path / d.get("file")) for d in datasets]
    return files, [float(d.get("timestep")) for d in datasets], meshes


def test_surface_frames_written_by_the_writer_process_equal_those_written_in_process(tmp_path):
    from orchestration.observers.surface_writer import SurfaceWriter

    (tmp_path / "a").mkdir()
    writer = SurfaceWriter(tmp_path / "b")
    pid = writer.pid
    files_a, times_a, meshes_a = _surface_frames(tmp_path / "a", None)
    files_b, times_b, meshes_b = _surface_frames(tmp_path / "b", writer)   # close() waited for every frame
    assert times_b == times_a == [k / 30 for k in range(4)]
    assert [f.relative_to(tmp_path / "b") for f in files_b.values()] == [f.relative_to(tmp_path / "a")
                                                                          for f in files_a.values()]
    for a, b in zip(meshes_a, meshes_b):
        assert np.array_equal(a.points, b.points) and np.array_equal(a.point_data["depth"], b.point_data["depth"])
        assert np.array_equal(a.cells_dict["triangle"], b.cells_dict["triangle"])
    assert not list(tmp_path.rglob("*.tmp"))
    with pytest.raises(ProcessLookupError):  # the writer has ended
        os.kill(pid, 0)


#: The end of a recording script: Ctrl-C to the whole process group (which the script ignores),
#: then SIGKILL to itself: no close, no atexit.
KILLED_WITH_THE_GROUP_INTERRUPTED = textwrap.indent(textwrap.dedent("""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.killpg(0, signal.SIGINT)
    os.kill(os.getpid(), signal.SIGKILL)
"""), " " * 4)


def _run_until_killed_and_wait_for_the_writer(script: str) -> None:
    """Run ``script`` (it prints its writer's pid, then kills itself) in a session of its own;
    return once the writer process has ended, at most 30 s later."""
    proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120,
                          start_new_session=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    pid = int(proc.stdout.split()[0])
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.05)
    raise AssertionError("the writer outlived the recording process by 30 s")


def test_surface_frames_sent_before_the_recording_process_dies_are_all_written(tmp_path):
    """SIGKILL right after the last frame is queued: the writer writes every frame it was sent
    and ends; Ctrl-C sent to the group does not stop it first."""
    script = textwrap.dedent(f"""
        import os, signal, sys, time
        import numpy as np
        from pathlib import Path
        from orchestration.observers.recorder import Recorder
        from orchestration.observers.surface_writer import SurfaceWriter
        if __name__ == "__main__":
            out = Path({str(tmp_path)!r})
            writer = SurfaceWriter(out)
            rec = Recorder(out, surface_writer=writer)
            rec.add_surface_series("wall", np.array([[0, 1, 2], [0, 2, 3]]))
            for k in range(20):
                rec.write_surface("wall", k / 30, np.full((4, 3), float(k)))
            while writer._outbox.qsize():  # every frame handed to the pipe
                time.sleep(0.001)
            print(writer.pid, flush=True)
    """) + KILLED_WITH_THE_GROUP_INTERRUPTED
    _run_until_killed_and_wait_for_the_writer(script)
    frames = sorted((tmp_path / "wall").glob("*.vtu"))
    assert len(frames) == 20
    assert np.all(meshio.read(frames[-1]).points == 19.0)
    datasets = ET.parse(tmp_path / "wall.pvd").getroot().find("Collection").findall("DataSet")
    assert len(datasets) == 20


def test_a_frame_the_writer_process_cannot_write_is_reported_and_the_others_are_kept(tmp_path, caplog):
    from orchestration.observers.surface_writer import SurfaceWriter

    rec = Recorder(tmp_path, surface_writer=SurfaceWriter(tmp_path))
    rec.add_surface_series("wall", np.array([[0, 1, 2], [0, 2, 3]]))
    rec.write_surface("wall", 0.0, np.zeros((4, 3)))
    deadline = time.monotonic() + 60
    while not (tmp_path / "wall" / "wall_00000.vtu").exists():  # frame 0 written before its folder goes
        assert time.monotonic() < deadline, "the writer wrote no frame in 60 s"
        time.sleep(0.01)
    blocked = tmp_path / "wall_moved"
    (tmp_path / "wall").rename(blocked)
    (tmp_path / "wall").write_text("a file where the frames' folder was")
    rec.write_surface("wall", 1 / 30, np.ones((4, 3)))
    with caplog.at_level(logging.ERROR, logger="orchestration.observers.recorder"):
        rec.close()
    assert len(rec.surface_errors) == 1 and "wall" in rec.surface_errors[0]
    assert "surface frames: wall" in caplog.text
    assert [p.name for p in blocked.glob("*.vtu")] == ["wall_00000.vtu"]      # the frame before is kept


def _awkward_rows(rec):
    rec.add_stream("c", [("x", 1, "m"), ("f", 3, "N"), ("n", 1, None)])
    rng = np.random.default_rng(11)
    for k in range(1000):
        x = AWKWARD[k % AWKWARD.size] if k < 50 else rng.standard_normal() * 10.0 ** rng.integers(-300, 300)
        rec.write("c", k * 1e-3, {"x": np.array([x]), "f": rng.standard_normal(3) * 10.0 ** rng.integers(-20, 20, 3),
                                  "n": np.array([k], dtype=np.int32)})
        if k % 300 == 0:
            rec.flush()  # several blocks, in order


def test_rows_written_by_the_row_writer_process_are_the_bytes_written_in_process(tmp_path):
    from orchestration.observers.row_writer import RowWriter

    writer = RowWriter()
    pid = writer.pid
    with Recorder(tmp_path / "a") as rec:
        _awkward_rows(rec)
    with Recorder(tmp_path / "b", row_writer=writer) as rec:
        _awkward_rows(rec)   # close() waited for every row
    text = (tmp_path / "a" / "c.csv").read_bytes()
    assert text.count(b"\n") == 1001 and b"nan" in text and b"-0.0," in text
    assert (tmp_path / "b" / "c.csv").read_bytes() == text
    with pytest.raises(ProcessLookupError):  # the writer has ended
        os.kill(pid, 0)


def test_rows_sent_before_the_recording_process_dies_are_all_written(tmp_path):
    """The recording process dies right after handing its rows on (no close, no atexit): the row
    writer writes every row it was sent and ends; Ctrl-C sent to the group does not stop it first."""
    script = textwrap.dedent(f"""
        import os, signal
        import numpy as np
        from orchestration.observers.recorder import Recorder
        from orchestration.observers.row_writer import RowWriter
        if __name__ == "__main__":
            writer = RowWriter()
            rec = Recorder({str(tmp_path)!r}, flush_interval=30.0, row_writer=writer)
            rec.add_stream("c", [("wall", 1, "s"), ("v", 3, None)])
            for k in range(5000):
                rec.write("c", k * 1e-3, {{"wall": np.zeros(1), "v": np.array([k, k / 3, -k * 1e-300])}})
            rec.flush()
            print(writer.pid, flush=True)
    """) + KILLED_WITH_THE_GROUP_INTERRUPTED
    _run_until_killed_and_wait_for_the_writer(script)
    t, cols = read_stream(tmp_path / "c.csv")
    assert t.size == 5000
    assert_complete_rows(t, cols)


def test_rows_the_row_writer_cannot_write_are_reported_and_the_others_are_kept(tmp_path):
    from orchestration.observers.row_writer import RowWriter

    writer = RowWriter()
    good = tmp_path / "good.csv"
    good.write_text("")
    writer.add_stream("good", good, 2)
    writer.add_stream("lost", tmp_path / "no such folder" / "lost.csv", 2)
    for k in range(3):
        writer.write("good", np.array([[k, 0.5], [k, 0.25]]).tobytes())
        writer.write("lost", np.array([k, 1.0]).tobytes())
    errors = writer.close()
    assert len(errors) == 4 and all(e.startswith("lost: ") for e in errors)  # the open, then each block
    assert "FileNotFoundError" in errors[0]
    assert good.read_text().splitlines() == [f"{k}.0,{v}" for k in range(3) for v in (0.5, 0.25)]


def test_summary_json_round_trip(tmp_path):
    summary = {"title": "AAA run", "real_time_factor": np.float64(1.25), "steps": np.int64(30000),
               "peak_forces": {"contact.tool_force": {"value": 2.5, "unit": "N"}},
               "warnings": ["Catheter: effort warning at t = 1.2 s"], "energy_drift": np.array([0.1, -0.2]),
               "output_dir": tmp_path}
    path = write_summary(tmp_path, summary)
    assert path == tmp_path / "summary.json"
    assert json.loads(path.read_text()) == {
        "title": "AAA run", "real_time_factor": 1.25, "steps": 30000,
        "peak_forces": {"contact.tool_force": {"value": 2.5, "unit": "N"}},
        "warnings": ["Catheter: effort warning at t = 1.2 s"], "energy_drift": [0.1, -0.2],
        "output_dir": str(tmp_path)}


PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_plots_are_valid_pngs_and_missing_data_is_skipped_with_a_warning(tmp_path, caplog):
    k = np.arange(200)
    with Recorder(tmp_path) as rec:
        rec.add_stream("contact", [("tool_force", 3, "N"), ("depth", 1, "m")])
        for i in k:
            rec.write("contact", i * 1e-3, {"tool_force": np.array([3.0, 4.0, 12.0]) * i,
                                            "depth": np.array([-1e-5 * i])})
    figures = [
        {"file": "forces.png", "title": "Forces", "panels": [
            {"ylabel": "N", "series": [{"stream": "contact", "column": "tool_force", "label": "tool", "norm": True}]},
            {"series": [{"stream": "contact", "column": "tool_force"}, {"stream": "contact", "column": "depth"}]}]},
        {"file": "missing.png", "title": "Missing", "panels": [
            {"ylabel": "N", "series": [{"stream": "contact", "column": "no_such_port"},
                                       {"stream": "no_such_stream", "column": "x"}]}]},
    ]
    with caplog.at_level(logging.WARNING, logger="orchestration.observers.plots"):
        paths = plot_signals(tmp_path, figures)
    assert paths == [tmp_path / "forces.png", tmp_path / "missing.png"]
    for path in paths:
        data = path.read_bytes()
        assert data[:8] == PNG_MAGIC and len(data) > 5000
        width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
        assert width == 900 and height > 200
    assert "no column 'no_such_port'" in caplog.text and "'no_such_stream' not plotted" in caplog.text
    # The norm is the Euclidean norm of the components (3-4-12 -> 13).
    (t, y, label), = _series_lines({"stream": "contact", "column": "tool_force", "norm": True}, {}, tmp_path, "f")
    assert np.allclose(y, 13.0 * k, rtol=1e-15) and label == "|contact.tool_force|"
    lines = _series_lines({"stream": "contact", "column": "tool_force"}, {}, tmp_path, "f")
    assert [lab for *_, lab in lines] == [f"contact.tool_force[{i}]" for i in range(3)]
    assert np.array_equal(lines[2][1], 12.0 * k)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")
def test_a_forked_child_closing_the_recorder_does_not_duplicate_pending_rows(tmp_path):
    rec = Recorder(tmp_path, flush_interval=30.0)  # rows stay pending in memory across the fork
    rec.add_stream("c", [("x", 1, None)])
    for k in range(5):
        rec.write("c", k * 1e-3, {"x": np.array([float(k)])})
    pid = os.fork()
    if pid == 0:  # child: e.g. a worker process whose interpreter shutdown runs the inherited atexit hook
        rec.close()
        os._exit(0)
    assert os.waitpid(pid, 0)[1] == 0
    rec.close()
    t, cols = read_stream(tmp_path / "c.csv")
    assert np.array_equal(cols["x"], np.arange(5.0))

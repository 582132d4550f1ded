"""Issue 33, results and user files: a run deletes only what runs wrote, --out is a folder of its
own (not /, ., the project or a folder holding the current one; a symbolic link is followed), and
result names (surfaces, plots, streams, the fixed files) never collide; checked by `validate`.

Each test here failed before the fix (a user's files deleted with exit 0, a traceback, a plot lost
without an error) and passes after it. Most refuse before anything runs, so they are fast; the few
that run use the cheapest scene (virtual_wall, 10 ms, in process, no surfaces).
"""
from __future__ import annotations

import copy
import json
import logging
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from orchestration.app import cli, result_folder as outfolder
from orchestration.app.result_folder import OutputFolderError, ResultFolder
from orchestration.observers.recorder import Recorder, RecordingError
from fmu_build.paths import SCENE_DIR
from orchestration.scene.model import SceneError
from orchestration.scene.loading import scene_from_dict

REPO = Path(__file__).resolve().parent.parent
CHEAP = ["virtual_wall", "--duration", "0.01", "--no-vtu", "--quiet", "--hosting", "in-process"]


def tree(root: Path) -> dict[str, bytes | None]:
    """Every path under ``root`` (relative) with its bytes (None for a folder or a link)."""
    return {str(p.relative_to(root)): (None if p.is_dir() or p.is_symlink() else p.read_bytes())
            for p in sorted(root.rglob("*"))}


def earlier_result(out: Path, plots=("forces.png",), surface: str | None = "aaa_wall") -> None:
    """A folder as a completed run leaves it: summary.json listing its files, units.json, CSVs,
    plots, a surface (.pvd and its frame folder)."""
    out.mkdir(parents=True)
    results = {"folder": str(out), "contact": str(out / "contact.csv"), "units": str(out / "units.json"),
               "plots": [str(out / p) for p in plots]}
    (out / "contact.csv").write_text('"time","tool_force[0]"\n0.0,0.0\n')
    (out / "units.json").write_text(json.dumps({"contact": {"time": "s"}}))
    for plot in plots:
        (out / plot).write_bytes(b"\x89PNG\r\n\x1a\n")
    if surface:
        results[surface] = str(out / f"{surface}.pvd")
        (out / f"{surface}.pvd").write_text('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n')
        (out / surface).mkdir()
        (out / surface / f"{surface}_00000.vtu").write_text("<VTKFile/>")
    (out / "summary.json").write_text(json.dumps({"status": "completed", "results": results}))


def run_main(argv: list[str], capsys) -> tuple[int, str]:
    code = cli.main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


# -- a folder holding the user's own files is refused, and nothing in it is touched ------------------
def test_an_out_with_the_users_files_beside_results_is_refused_before_anything_runs(tmp_path, capsys):
    out = tmp_path / "out"
    earlier_result(out)
    (out / "my_notes.txt").write_text("what I saw at t = 1.5 s")
    (out / "analysis").mkdir()
    (out / "analysis" / "fit.py").write_text("import numpy\n")
    before = tree(tmp_path)
    code, err = run_main(["run", *CHEAP, "--out", str(out)], capsys)
    assert code == cli.EXIT_USAGE, err
    assert f"--out {out} holds files that are not results of a run (analysis/, my_notes.txt)" in err, err
    assert "move them out" in err and "choose a new or empty folder" in err
    assert tree(tmp_path) == before  # nothing deleted, nothing written beside (no .running, no .lock)


@pytest.mark.parametrize("extra, shown", [
    (lambda out: (out / "aaa_wall" / "notes.txt").write_text("mine"), "aaa_wall/notes.txt"),
    (lambda out: (out / "my_plot.png").write_bytes(b"\x89PNG"), "my_plot.png"),        # a PNG no summary lists
    (lambda out: (out / "data.csv").write_text("a,b\n1,2\n"), "data.csv"),            # not a recorded stream
    (lambda out: os.symlink(out.parent, out / "elsewhere"), "elsewhere"),             # runs write no links
    (lambda out: (out / "summary.json").write_text("[1, 2]"), "forces.png summary.json"),  # not a run's
    # summary, so the plot it listed is no longer known as a run's either
    (lambda out: (out / "units.json").write_text('"SI"'), "units.json"),
])
def test_whatever_a_run_did_not_write_is_recognised_as_the_users(tmp_path, extra, shown):
    out = tmp_path / "out"
    earlier_result(out)
    assert outfolder.foreign_entries(out) == []
    extra(out)
    assert outfolder.foreign_entries(out) == shown.split()
    before = tree(tmp_path)
    with pytest.raises(OutputFolderError, match="holds files that are not results of a run"):
        ResultFolder(out).acquire()
    assert tree(tmp_path) == before


def test_a_folder_of_earlier_results_only_is_still_replaced(tmp_path, caplog):
    out = tmp_path / "out"
    earlier_result(out)
    (out / ".summary.json.tmp").write_text("{")  # a write cut short by a kill
    folder = ResultFolder(out)
    with folder:
        (folder.staging / "summary.json").write_text('{"status": "completed"}')
        folder.publish("completed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert sorted(p.name for p in out.iterdir()) == ["summary.json"]
    assert "previous" not in caplog.text


def test_files_put_into_out_during_the_run_are_kept_not_deleted(tmp_path, caplog):
    """Checked before the run, but a user may save a note into OUT while it runs: the replaced
    folder is then kept as OUT.previous, with a warning, not removed."""
    out = tmp_path / "out"
    earlier_result(out)
    folder = ResultFolder(out)
    with caplog.at_level(logging.WARNING), folder:
        (out / "my_notes.txt").write_text("written during the run")
        (folder.staging / "summary.json").write_text('{"status": "completed"}')
        folder.publish("completed")
    assert (out / "summary.json").read_text() == '{"status": "completed"}'
    previous = tmp_path / "out.previous"
    assert (previous / "my_notes.txt").read_text() == "written during the run"
    assert f"it was kept as {previous}" in caplog.text and "my_notes.txt" in caplog.text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "out.previous"]  # no out.running left


@pytest.mark.parametrize("status", ["failed", "interrupted"])
def test_a_users_folder_named_like_a_failed_run_is_kept(tmp_path, status, caplog):
    out = tmp_path / "out"
    beside = tmp_path / f"out.{status}"
    beside.mkdir()
    (beside / "thesis.tex").write_text("precious")
    folder = ResultFolder(out)
    with caplog.at_level(logging.WARNING), folder:
        (folder.staging / "summary.json").write_text('{"status": "%s"}' % status)
        folder.publish(status)
    assert (tmp_path / "out.previous" / "thesis.tex").read_text() == "precious"
    assert json.loads((beside / "summary.json").read_text())["status"] == status


def test_without_an_atomic_exchange_a_users_folder_named_out_old_survives(tmp_path, monkeypatch):
    out = tmp_path / "out"
    earlier_result(out)
    mine = tmp_path / "out.old"
    mine.mkdir()
    (mine / "backup.txt").write_text("my backup of out")
    monkeypatch.setattr(outfolder, "exchange", lambda a, b: False)  # another kernel, another file system
    folder = ResultFolder(out)
    with folder:
        (folder.staging / "summary.json").write_text('{"status": "completed"}')
        folder.publish("completed")
    assert (mine / "backup.txt").read_text() == "my backup of out"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "out.old"]


def test_a_users_file_named_out_lock_is_neither_truncated_nor_removed(tmp_path):
    out = tmp_path / "out"
    lock = tmp_path / "out.lock"
    lock.write_text("my notes about the lock-in amplifier\n")
    with pytest.raises(OutputFolderError, match="is not the lock of a run"):
        ResultFolder(out).acquire()
    assert lock.read_text() == "my notes about the lock-in amplifier\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.lock"]


# -- --out must be a folder of its own -------------------------------------------------------------
@pytest.mark.parametrize("where, fragment", [
    ("/", "is the root folder of the file system"),
    (".", "is the current folder"),
    ("./", "is the current folder"),
    ("..", "holds the current folder"),
    ("sub/..", "is the current folder"),
    ("project", "is the project's own folder"),
    ("project/..", "holds the project's own folder"),
])
def test_out_cannot_be_root_the_current_folder_its_parents_or_the_project(tmp_path, monkeypatch, capsys,
                                                                           where, fragment):
    work = tmp_path / "work"
    (work / "sub").mkdir(parents=True)
    (work / "mine.txt").write_text("the user's")
    monkeypatch.chdir(work)
    out = where.replace("project", str(REPO))
    before = tree(tmp_path)
    code, err = run_main(["run", *CHEAP, "--out", out], capsys)
    assert code == cli.EXIT_USAGE, err
    assert f"error: --out {out}: {fragment}" in err, err
    assert "must be a folder of its own: give a new folder, e.g. --out results/mine" in err
    assert tree(tmp_path) == before


def test_a_symbolic_link_loop_as_out_is_refused(tmp_path, capsys):
    loop = tmp_path / "loop"
    os.symlink(loop, loop)
    code, err = run_main(["run", *CHEAP, "--out", str(loop)], capsys)
    assert code == cli.EXIT_USAGE and f"--out {loop}: cannot be used as a folder" in err, err
    assert loop.is_symlink()


def test_a_symbolic_link_out_is_followed_and_stays_a_link(fmus_in_repo, tmp_path):
    """The results land in the link's target, the link stays, nothing is left beside the link and
    the next run does not take anything for a killed run."""
    target = tmp_path / "store" / "wall"
    (tmp_path / "store").mkdir()
    link = tmp_path / "link"
    os.symlink(target, link)  # dangling until the first run creates the target

    def run():
        return subprocess.run([sys.executable, "-m", "orchestration", "run", *CHEAP, "--out", str(link)],
                              cwd=tmp_path, capture_output=True, text=True, timeout=300)

    for attempt in (1, 2):
        proc = run()
        assert proc.returncode == 0, proc.stderr
        assert "Traceback" not in proc.stderr and "killed" not in proc.stderr, proc.stderr
        assert link.is_symlink() and os.readlink(link) == str(target)
        summary = json.loads((link / "summary.json").read_text())
        assert summary["status"] == "completed" and summary["results"]["folder"] == str(target)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "store"], attempt
        assert sorted(p.name for p in target.parent.iterdir()) == ["wall"], attempt  # no .running, no .lock


# -- result names never collide (validate) -----------------------------------------------------------
def shipped(name: str = "aaa_endovascular") -> dict:
    return tomllib.loads((SCENE_DIR / f"{name}.toml").read_text())


def problems_of(data: dict) -> list[str]:
    with pytest.raises(SceneError) as info:
        scene_from_dict(data, SCENE_DIR, SCENE_DIR / "x.toml")
    return info.value.problems


def with_surface(data: dict, name: str) -> dict:
    data = copy.deepcopy(data)
    data["record"]["surfaces"].append({**data["record"]["surfaces"][0], "name": name})
    return data


@pytest.mark.parametrize("name, holder", [
    ("forces.png", "the figure of [record] plots[0]"),
    ("units.json", "units.json, the units of the CSV columns"),
    ("summary.json", "summary.json, the run's summary"),
    ("catheter.csv", "the CSV of [record] catheter"),
    ("aaa_wall.pvd", "the ParaView collection of [record] surfaces[0]"),
    ("Forces.png", "the figure of [record] plots[0] (the names differ only in case"),
])
def test_a_surface_named_like_another_result_is_a_scene_error(fmus_in_repo, name, holder):
    problems = problems_of(with_surface(shipped(), name))
    assert len(problems) == 1, problems
    assert problems[0].startswith(f"[record] surfaces[1] name: {name!r} would write its frame folder {name} in the "
                                  f"result folder, which is already {holder}"), problems
    assert problems[0].endswith("; give the surface another name")


def test_two_figures_into_one_file_is_a_scene_error(fmus_in_repo):
    data = shipped()
    data["record"]["plots"][1]["file"] = "forces.png"
    assert problems_of(data) == ["[record] plots[1] file: 'forces.png' would write forces.png in the result folder, "
                                 "which is already the figure of [record] plots[0]; give each figure a file of its own"]


@pytest.mark.parametrize("column, fragment", [
    ("bogus", "column: tissue records no column 'bogus' (it records strain_energy, kinetic_energy"),
    ("time", "column: tissue records no column 'time'"),
    ("strain_energy[0]", "column: tissue.strain_energy is a single value, its column is 'strain_energy'"),
])
def test_a_plot_of_a_column_its_stream_does_not_record_is_a_scene_error(fmus_in_repo, column, fragment):
    data = shipped()
    data["record"]["plots"][1]["panels"][0]["series"][0]["column"] = column
    problems = problems_of(data)
    assert len(problems) == 1 and problems[0].startswith(f"[record] plots[1] panels[0] series[0] {fragment}"), problems


def test_plot_columns_of_array_ports_and_their_elements_are_accepted(fmus_in_repo):
    data = shipped()
    series = data["record"]["plots"][0]["panels"][0]["series"]
    series.append({"stream": "contact", "column": "tool_force[2]"})
    scene_from_dict(data, SCENE_DIR, SCENE_DIR / "x.toml")
    series.append({"stream": "contact", "column": "tool_force[3]"})
    assert problems_of(data) == ["[record] plots[0] panels[0] series[3] column: 'tool_force[3]' is beyond "
                                 "contact.tool_force, which has 3 values ([0] to [2])"]


def test_a_plot_of_a_stream_that_is_not_recorded_is_a_scene_error(fmus_in_repo):
    data = shipped("virtual_wall")
    del data["record"]["device"]
    problems = problems_of(data)
    assert problems[0] == ('[record] plots[0] panels[0] series[0] stream: device is not recorded, so there is no '
                           'device.csv to plot: add device = ["position"] to [record]'), problems


def test_every_result_name_problem_is_reported_at_once(fmus_in_repo):
    data = with_surface(with_surface(shipped(), "summary.json"), "catheter.csv")
    data["record"]["plots"][1]["file"] = "forces.png"
    data["record"]["plots"][0]["panels"][1]["series"][0]["column"] = "bend"
    problems = problems_of(data)
    assert sorted(p.split(": ")[0] for p in problems) == [
        "[record] plots[0] panels[1] series[0] column", "[record] plots[1] file", "[record] surfaces[1] name",
        "[record] surfaces[2] name"], problems


def scene_file(tmp_path: Path, data_text: str) -> Path:
    """The shipped scene's text with a change, its FMU paths resolved from fmus/."""
    path = tmp_path / "scene.toml"
    path.write_text(data_text)
    return path


@pytest.mark.parametrize("command", ["validate", "run"])
def test_validate_and_run_refuse_a_surface_named_units_json_without_a_traceback(fmus_in_repo, tmp_path, capsys,
                                                                                command):
    text = (SCENE_DIR / "aaa_endovascular.toml").read_text().replace('name = "aaa_wall"', 'name = "units.json"')
    path = scene_file(tmp_path, text)
    extra = ["--out", str(tmp_path / "out"), "--quiet", "--duration", "0.1"] if command == "run" else []
    code, err = run_main([command, str(path), *extra], capsys)
    assert code == cli.EXIT_USAGE, err
    assert "[record] surfaces[0] name: 'units.json' would write its frame folder units.json" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.toml"]


# -- the same guarantees where the library is used directly ---------------------------------------
def test_the_recorder_refuses_a_surface_whose_folder_is_another_result(tmp_path):
    triangles = np.array([[0, 1, 2]])
    with Recorder(tmp_path) as recorder:
        recorder.add_stream("contact", [("tool_force", 3, "N")])
        for name in ("units.json", "summary.json", "contact.csv"):
            with pytest.raises(RecordingError, match=f"surface series '{name}' clashes with another recorded file"):
                recorder.add_surface_series(name, triangles)
        recorder.add_surface_series("wall", triangles)
        with pytest.raises(RecordingError, match="clashes"):
            recorder.add_surface_series("wall.pvd", triangles)
    assert (tmp_path / "units.json").is_file() and (tmp_path / "contact.csv").is_file()


def test_plots_refuse_two_figures_into_one_file_and_keep_a_folder_in_the_way(tmp_path, caplog):
    from orchestration.observers.plots import plot_signals

    (tmp_path / "contact.csv").write_text('"time","x"\n0.0,1.0\n0.1,2.0\n')
    panel = [{"series": [{"stream": "contact", "column": "x"}]}]
    with pytest.raises(RecordingError, match="figure 0 is drawn into the same file"):
        plot_signals(tmp_path, [{"file": "a.png", "panels": panel}, {"file": "A.png", "panels": panel}])
    with pytest.raises(RecordingError, match="not a plain .png file name"):
        plot_signals(tmp_path, [{"file": "units.json", "panels": panel}])
    (tmp_path / "wall.png").mkdir()  # a surface's frame folder of that name
    (tmp_path / "wall.png" / "wall.png_00000.vtu").write_text("frame")
    with caplog.at_level(logging.WARNING):
        written = plot_signals(tmp_path, [{"file": "wall.png", "panels": panel}, {"file": "b.png", "panels": panel}])
    assert written == [tmp_path / "b.png"] and "wall.png: not drawn" in caplog.text
    assert (tmp_path / "wall.png" / "wall.png_00000.vtu").read_text() == "frame"

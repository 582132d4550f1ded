"""Fuzzing the command line (issue 14): random argument lists for ``validate``, ``run`` and ``study``.

Whatever the arguments: no traceback, and the exit code means what ``orchestration.app.cli`` documents:
0 the command did what was asked (a run completed, its summary in the requested ``--out``), 1 a
run started and failed, 2 nothing ran (a usage or scene error, ``error: ...`` on stderr).

Most cases call ``cli.main([...])`` in process; a few go through ``python -m orchestration`` in a
subprocess. Runs are kept cheap: the virtual-wall scene (one FMU, 1 kHz), durations of at most
50 ms when valid, ``--no-vtu --quiet``. Studies are not run: ``run_study`` is replaced by a stub
that records what it was given, so the test checks the argument checks, not the studies (which
have tests of their own). Case counts come from the hypothesis profile (tests/conftest.py).

Issue 33 adds two probe classes: ``--out`` folders of every kind (earlier results, the user's own
files beside them, ``.``, ``..``, ``/``, the project, symbolic links: none may lose a file a run
did not write), and result names that collide (``validate`` must refuse exactly those scenes, an
independent oracle decides which).
"""
from __future__ import annotations

import itertools
import json
import math
import os
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import pytest
from hypothesis import event, given, note
from hypothesis import strategies as st

from orchestration.app import cli
from fmu_build.paths import SCENE_DIR

REPO = Path(__file__).resolve().parent.parent
CHEAP_SCENE = "virtual_wall"  # one FMU and a device block at 1 kHz: the cheapest shipped scene to run
_counter = itertools.count()


@pytest.fixture(scope="module")
def workdir(tmp_path_factory, fmus_in_repo):
    """A folder with a few scene files: broken ones and a copy of the cheap scene."""
    root = tmp_path_factory.mktemp("cli_fuzz")
    (root / "not_utf8.toml").write_bytes(b"[scene]\nname = \"\xff\"\n")
    (root / "syntax.toml").write_text("[scene\n")
    (root / "scene5.toml").write_text("scene = 5\n")
    (root / "dir.toml").mkdir()
    text = (SCENE_DIR / f"{CHEAP_SCENE}.toml").read_text()
    (root / "escape.toml").write_text(text.replace('name = "virtual_wall"', 'name = "../../escaped"'))
    return root


def fresh_out(workdir: Path) -> Path:
    return workdir / "out" / f"case{next(_counter)}"


def junk_text():
    return st.text(alphabet=st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=10)


#: durations: every valid one is short (a run of at most 50 ms), the rest are refused
DURATIONS = st.one_of(
    st.sampled_from(["nan", "inf", "-inf", "-1", "0", "1e9", "abc", "", "1e-999999999", "1e999", "0.0015",
                     "0.01", "0.02", "1/50", "1/30", "0.05", "2/100", " 0.01 ", "0x10", "1_0", "10000000"]),
    st.floats(min_value=0.0, max_value=0.05).map(repr),
    st.floats(min_value=1e5, max_value=1e300).map(repr),
    st.floats(max_value=0.0).map(repr),
    junk_text(),
)
#: valid and short: whole numbers of 1 ms up to 50 ms
GOOD_DURATIONS = st.one_of(st.sampled_from(["0.01", "1/50", "0.005", "2/100", " 0.03 "]),
                           st.integers(1, 50).map(lambda ms: repr(ms / 1000)))
GOOD_SETS = st.lists(st.sampled_from(["contact.stiffness=500", "contact.damping=0.5", "device.mass=0.2",
                                      "device.damping=2.0", "contact.margin=0.02", "scene.name=\"wall-copy.1\"",
                                      "contact.detection=\"continuous\"", "device.initial_position=[-0.01, 0, 0]"]),
                     max_size=3, unique_by=lambda item: item.split("=")[0])
SET_KEYS = ["contact.stiffness", "contact.damping", "device.mass", "device.step", "contact.step", "scene.name",
            "scene.duration", "contact", "contact.", ".x", "a.b.c", "ghost.x", "contact.no_such", "scene.bogus",
            "operator.times", "contact.n_tool_points", "contact.tool"]
SET_VALUES = ["800", "nan", "inf", "-1", "0", "1e9", "\"soft\"", "soft", "[1, 2, 3]", "{a = 1}", "true", "",
              "1\nw = 2", "../x", "0.002", "\"probe\"", "2**64", "18446744073709551616", "[[1, 2], [3]]"]
SETS = st.lists(st.one_of(
    st.tuples(st.sampled_from(SET_KEYS), st.sampled_from(SET_VALUES)).map(lambda kv: f"{kv[0]}={kv[1]}"),
    junk_text(),
), max_size=3)
UNKNOWN = st.sampled_from(["--bogus", "-x", "--duration", "--set", "--out", "extra_positional", "--hosting=sideways",
                           "--workers", "--realtime=1", "-v"])


def scene_args(workdir: Path):
    return st.sampled_from([CHEAP_SCENE, "no_such_scene", str(workdir / "not_utf8.toml"),
                            str(workdir / "syntax.toml"), str(workdir / "scene5.toml"), str(workdir / "dir.toml"),
                            str(workdir / "escape.toml"), "", "../scenes/virtual_wall", str(workdir / "missing.toml")])


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """Run the command line in this process; (exit code, stdout, stderr) once the outcome every
    case must have is checked: no traceback, a documented exit code, a usage error that says so."""
    note(repr(argv))
    code = cli.main(argv)
    out, err = capsys.readouterr()
    event(f"exit {code}")  # the spread of outcomes, shown by --hypothesis-show-statistics
    assert "Traceback" not in err and "Traceback" not in out, err
    assert code in (cli.EXIT_OK, cli.EXIT_FAILED, cli.EXIT_USAGE), code
    if code == cli.EXIT_USAGE:
        assert "error: " in err, err  # argparse: "prog: error: ...", ours: "error: ..."
    return code, out, err


# -- validate ----------------------------------------------------------------------------------------
@given(data=st.data())
def test_validate_with_random_arguments(workdir, capsys, data):
    argv = ["validate"]
    clean = data.draw(st.booleans())  # half the cases are well-formed, so acceptance is tested too
    if clean or data.draw(st.booleans()):
        argv.append(CHEAP_SCENE if clean else data.draw(scene_args(workdir)))
    if data.draw(st.booleans()):
        argv += ["--duration", data.draw(GOOD_DURATIONS if clean else DURATIONS)]
    for item in data.draw(GOOD_SETS if clean else SETS):
        argv += ["--set", item]
    if not clean and data.draw(st.integers(0, 4)) == 0:
        argv.append(data.draw(UNKNOWN))
    code, out, err = run_cli(argv, capsys)
    assert code != cli.EXIT_FAILED  # validate runs nothing
    if code == cli.EXIT_OK:
        assert out.splitlines()[0].endswith(": OK")


# -- run ---------------------------------------------------------------------------------------------
def _requested_duration(argv: list[str]) -> Fraction | None:
    if "--duration" not in argv:
        return None
    text = argv[argv.index("--duration") + 1].strip()
    if "/" in text:
        a, b = text.split("/")
        return Fraction(int(a), int(b))
    return Fraction(repr(float(text)))


@given(data=st.data())
def test_run_with_random_arguments_exits_0_only_with_a_completed_run_in_out(workdir, capsys, data):
    out_dir = fresh_out(workdir)
    clean = data.draw(st.booleans())  # half the cases are well-formed, so completed runs are tested too
    argv = ["run", CHEAP_SCENE if clean else data.draw(scene_args(workdir)), "--no-vtu", "--quiet"]
    # a valid run is always short: the scene's own 2 s is replaced by at most 50 ms (or a refused value)
    argv += ["--duration", data.draw(GOOD_DURATIONS if clean else DURATIONS)]
    hosting = data.draw(st.sampled_from([None, None, "in-process", "out-of-process"]))
    if hosting:
        argv += ["--hosting", hosting]
    for item in data.draw(GOOD_SETS if clean else SETS):  # a "scene.duration=" among them: --duration wins
        argv += ["--set", item]
    out_choice = data.draw(st.sampled_from(["fresh", "nested"] if clean else ["fresh", "empty", "file", "nested"]))
    if out_choice == "fresh":
        argv += ["--out", str(out_dir)]
    elif out_choice == "empty":
        argv += ["--out", ""]
    elif out_choice == "file":
        argv += ["--out", str(workdir / "syntax.toml")]
    else:
        out_dir = out_dir / "a" / "b"
        argv += ["--out", str(out_dir)]
    if not clean and data.draw(st.integers(0, 5)) == 0:
        argv.append(data.draw(UNKNOWN))
    code, out, err = run_cli(argv, capsys)
    if clean:
        assert code == cli.EXIT_OK, err  # a well-formed short run of the shipped scene completes
    if code == cli.EXIT_OK:
        # 0 only for a run that really completed, with its results inside the requested --out
        assert out_choice in ("fresh", "nested")
        summary = json.loads((out_dir / "summary.json").read_text())
        assert summary["status"] in ("completed", "terminated")
        duration = _requested_duration(argv)
        assert duration is not None and math.isclose(summary["simulated_time_s"], float(duration), rel_tol=1e-12)
        assert (out_dir / "contact.csv").is_file()
    elif code == cli.EXIT_USAGE and out_choice == "fresh":
        # a refused run writes no results
        assert not (out_dir / "summary.json").exists()


# -- study -------------------------------------------------------------------------------------------
@pytest.fixture
def study_stub(monkeypatch):
    """run_study replaced by a recorder: the arguments are what is tested, not the studies."""
    import orchestration.app.warmup
    import orchestration.studies

    calls = []

    def fake_run_study(name, **kwargs):
        calls.append((name, kwargs))
        return 0

    monkeypatch.setattr(orchestration.studies, "run_study", fake_run_study)
    monkeypatch.setattr(orchestration.app.warmup, "ensure_fmus_built", lambda quiet=False: None)
    return calls


@given(data=st.data())
def test_study_with_random_arguments(workdir, capsys, study_stub, data):
    study_stub.clear()
    clean = data.draw(st.booleans())  # half the cases are well-formed, so acceptance is tested too
    studies = ["tradeoff", "stability", "extremes"] + ([] if clean else ["bogus", ""])
    argv = ["study", data.draw(st.sampled_from(studies))]
    if data.draw(st.booleans()):
        good = st.integers(1, 256).map(str)
        argv += ["--workers", data.draw(good if clean else st.sampled_from(["0", "-1", "257", "abc", "1.5", ""])
                                        | st.integers(-10, 10**6).map(str))]
    if data.draw(st.booleans()):
        good = st.sampled_from(["tcp://host:8786", "tls://10.0.0.1:8786", "tcp://[::1]:8786"])
        argv += ["--scheduler", data.draw(good if clean else st.sampled_from(["foo", "tcp://host", "tcp://:1",
                                                                             "tcp://h:99999", "", "host:8786"])
                                          | junk_text())]
    if data.draw(st.booleans()):
        choice = "fresh" if clean else data.draw(st.sampled_from(["fresh", "", "file"]))
        argv += ["--out", {"fresh": str(fresh_out(workdir)), "": "", "file": str(workdir / "syntax.toml")}[choice]]
    for flag in ("--quick", "--fresh", "--quiet"):
        if data.draw(st.booleans()):
            argv.append(flag)
    if not clean and data.draw(st.integers(0, 4)) == 0:
        argv.append(data.draw(UNKNOWN))
    code, out, err = run_cli(argv, capsys)
    if clean:
        assert code == cli.EXIT_OK, err
    if code == cli.EXIT_OK:
        (name, kwargs), = study_stub
        assert name in ("tradeoff", "stability", "extremes")
        assert kwargs["workers"] is None or 1 <= kwargs["workers"] <= 256
        if kwargs["scheduler"] is not None:
            assert kwargs["scheduler"].split("://")[0] and ":" in kwargs["scheduler"].split("://")[1]
        if kwargs["out"] is not None:
            assert Path(kwargs["out"]).is_dir()
    else:
        assert not study_stub, "a refused study must not start"


# -- a few through the real entry point, in a subprocess ----------------------------------------------
@pytest.mark.parametrize("argv, code, fragment", [
    (["run", CHEAP_SCENE, "--duration", "nan"], 2, "argument --duration: 'nan' is not a time"),
    (["run", CHEAP_SCENE, "--duration", "-1"], 2, "argument --duration: must be positive"),
    (["run", CHEAP_SCENE, "--duration", "1e9"], 2, "more than the limit of 1e+07 steps per run"),
    (["validate", CHEAP_SCENE, "--duration", "6000"], 2, "at most 5000 s"),
    (["run", CHEAP_SCENE, "--set", "scene.name=../escaped"], 2, "[scene] name: '../escaped' is not a plain name"),
    (["validate", CHEAP_SCENE, "--set", "contact.step=1e9"], 2, "longer than 1 s"),
    (["study", "tradeoff", "--workers", "0"], 2, "argument --workers: 0 processes"),
    (["run", "--bogus"], 2, "unrecognized arguments: --bogus"),
    (["run", CHEAP_SCENE, "--duration", "0.01", "--out", ""], 2, "--out: empty"),
])
def test_refused_inputs_through_the_entry_point(fmus_in_repo, tmp_path, argv, code, fragment):
    result = subprocess.run([sys.executable, "-m", "orchestration", *argv], cwd=tmp_path, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == code, result.stderr
    assert "Traceback" not in result.stderr
    assert fragment in result.stderr, result.stderr
    assert not (tmp_path / "results").exists() and not (tmp_path.parent / "escaped").exists()


def test_a_short_run_through_the_entry_point_completes_into_out(fmus_in_repo, tmp_path):
    out = tmp_path / "wall"
    result = subprocess.run([sys.executable, "-m", "orchestration", "run", CHEAP_SCENE, "--duration", "1/50",
                             "--no-vtu", "--quiet", "--out", str(out)], cwd=tmp_path, capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["simulated_time_s"] == 0.02


def test_a_run_that_fails_exits_1_naming_the_fmu_and_keeps_its_results(fmus_in_repo, tmp_path):
    # exit 1: the scene is valid, the FMU refuses a value only it knows (no min/max or enumeration
    # in its modelDescription.xml for the scene to check)
    out = tmp_path / "failed"
    result = subprocess.run([sys.executable, "-m", "orchestration", "run", CHEAP_SCENE, "--duration", "0.01",
                             "--set", "contact.tool=\"bogus\"", "--no-vtu", "--quiet", "--out", str(out)],
                            cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 1, result.stderr
    assert "Traceback" not in result.stderr
    assert "error: contact: fmi3ExitInitializationMode" in result.stderr and "tool must be one of" in result.stderr
    # a failed run's results go beside OUT (OUT keeps the last complete run; here there is none)
    failed = tmp_path / "failed.failed"
    assert f"results up to the failure are in {failed}" in result.stderr
    assert json.loads((failed / "summary.json").read_text())["status"] == "failed"
    assert not out.exists()


def test_a_reader_that_goes_away_ends_validate_without_a_traceback(fmus_in_repo):
    """`validate SCENE | head -1`: the pipe closes before the output is written."""
    proc = subprocess.Popen([sys.executable, "-m", "orchestration", "validate", "aaa_endovascular"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 1
    assert "Traceback" not in err and "BrokenPipeError" not in err, err


# -- output folders (issue 33): whatever --out is, no file a run did not write is ever lost ------------
#: what a user keeps in a folder: plain files, a folder of them, names like results that are not
#: (a CSV that is no recorded stream, a PNG no summary lists), a file inside a surface's frame folder
USER_FILES = ["my_notes.txt", "analysis/fit.py", "data.csv", "figure.png", "aaa_wall/notes.txt", ".hidden",
              "deep/er/file.bin", "summary.json.bak", "forces.png"]
OUT_KINDS = ["fresh", "results", "results+user", "user", "dot", "dotdot", "root", "project", "link to results",
             "dangling link", "link loop", "link to user", "user lock"]


def _earlier_results(out: Path) -> None:
    """What a completed run leaves (its summary lists its files)."""
    out.mkdir(parents=True)
    (out / "contact.csv").write_text('"time","tool_force[0]"\n0.0,0.0\n')
    (out / "units.json").write_text('{"contact": {"time": "s"}}')
    (out / "aaa_wall.pvd").write_text('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n')
    (out / "aaa_wall").mkdir()
    (out / "aaa_wall" / "aaa_wall_00000.vtu").write_text("<VTKFile/>")
    (out / "summary.json").write_text(json.dumps({"status": "completed", "results": {
        "folder": str(out), "contact": str(out / "contact.csv"), "aaa_wall": str(out / "aaa_wall.pvd"),
        "plots": [str(out / "wall.png")]}}))
    (out / "wall.png").write_bytes(b"\x89PNG\r\n\x1a\n")


def _user_files(root: Path, names: list[str]) -> dict[Path, bytes]:
    files = {}
    for i, name in enumerate(names):
        path = root / name
        if path.exists():
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        files[path] = f"the user's {name} #{i}".encode()
        path.write_bytes(files[path])
    return files


@given(data=st.data())
def test_run_into_any_output_folder_never_loses_a_file_a_run_did_not_write(workdir, capsys, data):
    case = workdir / "outs" / f"case{next(_counter)}"
    (case / "cwd").mkdir(parents=True)
    kind = data.draw(st.sampled_from(OUT_KINDS))
    names = data.draw(st.lists(st.sampled_from(USER_FILES), min_size=1, max_size=3, unique=True))
    out = case / "out"
    users: dict[Path, bytes] = _user_files(case / "cwd", ["cwd_file.txt"])  # the current folder holds the user's
    replaceable = kind in ("fresh", "results", "link to results", "dangling link")
    if kind in ("results", "results+user", "link to results"):
        _earlier_results(case / "store" if kind == "link to results" else out)
    if kind in ("results+user", "user"):
        out.mkdir(exist_ok=True)
        users |= _user_files(out, names)
    if kind == "link to user":
        users |= _user_files(case / "store", names)
    if kind.startswith("link") or kind == "dangling link":
        os.symlink(out if kind == "link loop" else case / "store", out)
    if kind == "user lock":
        users |= _user_files(case, ["out.lock"])
    arg = {"dot": ".", "dotdot": "..", "root": "/", "project": str(REPO)}.get(kind, str(out))
    before = os.getcwd()
    os.chdir(case / "cwd")
    try:
        code, _, err = run_cli(["run", CHEAP_SCENE, "--duration", "0.01", "--no-vtu", "--quiet", "--hosting",
                                "in-process", "--out", arg], capsys)
    finally:
        os.chdir(before)
    event(f"{kind}: exit {code}")
    for path, content in users.items():  # refused or not, every file of the user's is where it was
        assert path.read_bytes() == content, (kind, path)
    if replaceable:
        assert code == cli.EXIT_OK, err
        summary = json.loads((out / "summary.json").read_text())
        assert summary["status"] == "completed"
        assert out.is_symlink() == (kind in ("link to results", "dangling link"))  # a link stays a link
        assert not (case / "out.running").exists() and not (case / "store.running").exists()
    else:
        assert code == cli.EXIT_USAGE and "error: --out" in err, err
        assert not os.path.lexists(case / "out.running")


# -- result names (issue 33): validate refuses exactly the scenes whose results would collide --------
SURFACE_NAMES = ["aaa_wall", "wall2", "forces.png", "Forces.png", "tissue.png", "units.json", "UNITS.JSON",
                 "summary.json", "catheter.csv", "contact.csv", "aaa_wall.pvd", "mesh.vtu", "x.pvd", "folder",
                 "plots", "units", "tissue", "surfaces"]
PLOT_FILES = ["forces.png", "tissue.png", "Forces.png", "wall2.png", "extra.png", "aaa_wall.png"]
COLUMNS = ["strain_energy", "max_strain", "bogus", "time", "strain_energy[0]", "kinetic_energy"]
RECORDED = {"tissue": ["strain_energy", "kinetic_energy", "max_strain", "nonlinear_fraction", "solver_iterations",
                       "solver_residual"], "contact": [], "catheter": []}


def _names_collide(surfaces: list[str], plots: list[str]) -> bool:
    """The oracle: do these result names claim one name twice (compared without case), or use a
    name the recording or the summary reserves?"""
    claims = ["summary.json", "units.json", *(f"{c}.csv" for c in RECORDED), *plots]
    for name in surfaces:
        claims += [f"{name}.pvd", name]
    reserved = {*RECORDED, "units", "folder", "plots", "surface_errors", "row_errors"}
    return len({c.casefold() for c in claims}) != len(claims) or any(s in reserved for s in surfaces)


@given(data=st.data())
def test_validate_refuses_exactly_the_result_names_that_collide(workdir, capsys, data):
    surfaces = data.draw(st.lists(st.sampled_from(SURFACE_NAMES), min_size=1, max_size=3))
    plots = [data.draw(st.sampled_from(PLOT_FILES)) for _ in range(2)]
    column = data.draw(st.sampled_from(COLUMNS))
    text = (SCENE_DIR / "aaa_endovascular.toml").read_text()
    text = text.replace('name = "aaa_wall"', f'name = "{surfaces[0]}"')
    text = text.replace('file = "forces.png"', f'file = "{plots[0]}"').replace('file = "tissue.png"',
                                                                               f'file = "{plots[1]}"')
    text = text.replace('column = "strain_energy", label = "strain energy"', f'column = "{column}"')
    for name in surfaces[1:]:
        text += ('\n[[record.surfaces]]\ncomponent = "tissue"\npositions = "surface_positions"\n'
                 f'triangles = "surface_triangles"\nname = "{name}"\n')
    path = workdir / f"names{next(_counter)}.toml"
    path.write_text(text)
    code, out, err = run_cli(["validate", str(path)], capsys)
    expected_ok = not _names_collide(surfaces, plots) and column in RECORDED["tissue"]
    event("accepted" if expected_ok else "refused")
    assert code == (cli.EXIT_OK if expected_ok else cli.EXIT_USAGE), (surfaces, plots, column, err)

"""Hostile or broken inputs get a clear message, not a traceback, a crash or 24 GB of memory:
deeply dotted TOML keys, control characters in a scene, broken CSV signals, implausible outputs,
unwritable build folders and a damaged numba cache, truncated FMU binaries."""
from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path
from types import SimpleNamespace

import pytest

from fmu_build import kernels, package
from fmu_build.errors import BuildError
from orchestration.blocks import csv_source
from orchestration.app import warmup
from orchestration.hosts import fmi3
from orchestration.scene.loading import load_scene
from orchestration.scene.model import SceneError
from orchestration.scene.text import nesting_problem
from orchestration.hosts.description import PortInfo
from project import FMU_NAMES, fmu_spec, scene_path, shipped_scenes

ROOT = Path(__file__).resolve().parents[1]


def _python(code: str, timeout: float = 30, memory: int = 2 << 30) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter limited to ``memory`` bytes of address space."""
    prelude = (f"import resource; resource.setrlimit(resource.RLIMIT_AS, ({memory}, {memory}))\n"
               f"import sys; sys.path.insert(0, {str(ROOT)!r})\n")
    return subprocess.run([sys.executable, "-c", prelude + textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT)


# 1 ------------------------------------------------------------------------------------------------
def test_deeply_dotted_key_is_refused_before_the_toml_parser(tmp_path):
    path = tmp_path / "dotted.toml"
    path.write_text(".".join(["x"] * 70_000) + " = 1\n")  # 140 KB; tomllib needed 24 GB for it
    proc = _python(f"""
        from orchestration.scene.loading import load_scene
        from orchestration.scene.model import SceneError
        try:
            load_scene({str(path)!r})
        except SceneError as exc:
            print("REFUSED", exc)
        """, timeout=30, memory=1536 << 20)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "REFUSED" in proc.stdout and "nested too deeply" in proc.stdout and "line 1" in proc.stdout
    # and the scenes of the project are not deeper than allowed
    for name in shipped_scenes():
        assert nesting_problem(scene_path(name).read_text()) is None, name


# 2 ------------------------------------------------------------------------------------------------
def test_control_characters_in_scene_strings_are_refused_naming_the_key(fmus_in_repo, tmp_path):
    text = (ROOT / "scenes" / "virtual_wall.toml").read_text()
    assert 'tool = "probe"' in text
    path = tmp_path / "virtual_wall.toml"
    path.write_text(text.replace('tool = "probe"', 'tool = "probe\\u0000garbage"'))
    shutil.copy(fmus_in_repo["Contact"], tmp_path / "Contact.fmu")
    with pytest.raises(SceneError) as info:
        load_scene(path)
    message = str(info.value)
    assert "[fmu.contact] parameters.tool" in message and "NUL (U+0000)" in message
    # the unchanged scene loads
    path.write_text(text)
    load_scene(path)


# 3 ------------------------------------------------------------------------------------------------
def test_broken_csv_signal_is_a_problem_naming_file_and_line(tmp_path):
    def read(content: bytes):
        path = tmp_path / "signal.csv"
        path.write_bytes(content)
        problems: list[str] = []
        csv_source.read_csv(problems, path, {"force": ["f"]}, "t")
        assert len(problems) == 1, problems
        assert str(path) in problems[0]
        return problems[0]

    assert "line 3" in read(b"t,f\n0,1\n1,\x002\n") and "NUL" in read(b"t,f\n0,1\n1,\x002\n")
    huge = read(b't,f\n0,1\n1,"' + b"9" * 200_000 + b"\n")  # an unclosed quote: one field past csv's limit
    assert "line" in huge and "field" in huge
    assert "longer than" in read(b"t,f\n" + b"1" * (csv_source.CSV_MAX_LINE + 10))
    folder = tmp_path / "folder.csv"
    folder.mkdir()
    problems: list[str] = []
    csv_source.read_csv(problems, folder, {"force": ["f"]}, "t")  # exists, cannot be read as a file
    assert problems and str(folder) in problems[0]


# 4 ------------------------------------------------------------------------------------------------
def test_implausible_output_makes_a_warning_and_a_count():
    ports = {"position": PortInfo("position", "output", "Float64", unit="m", shape=(3,)),
             "force": PortInfo("force", "output", "Float64", unit="N", shape=(3,))}
    spec = SimpleNamespace(name="device", is_continuous=False, ports=ports)
    from orchestration.observers.statistics import Statistics
    import numpy as np

    statistics = Statistics(SimpleNamespace(summary={}, components={"device": spec}))
    statistics.initializing(SimpleNamespace(seconds=lambda tick: tick / 1000))
    comp = SimpleNamespace(name="device", step=1)
    assert set(statistics.ports("device")) == {"position", "force"}
    statistics.stepped(comp, 1, {"position": np.array([0.1, 0.0, 0.0]), "force": np.zeros(3)})
    assert statistics.report()["implausible_outputs"]["count"] == 0 and "warnings" not in statistics.report()
    statistics.stepped(comp, 2, {"position": np.array([11.0, 0.0, 0.0]), "force": np.zeros(3)})
    statistics.stepped_block(comp, [3, 4], {"position": np.array([[12.0, 0, 0], [0, 0, 0]]),
                                            "force": np.zeros((2, 3))}, 3)
    report = statistics.report()
    assert report["implausible_outputs"]["count"] == 1
    entry = report["implausible_outputs"]["outputs"]["device.position"]
    assert entry["steps"] == 2 and entry["worst"] == 12.0 and entry["first_s"] == 0.002
    assert len(report["warnings"]) == 1 and "device.position" in report["warnings"][0]


# 5 ------------------------------------------------------------------------------------------------
def test_unwritable_fmu_folder_is_a_build_error_naming_it(tmp_path):
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("")
    spec = fmu_spec(FMU_NAMES[0])
    with pytest.raises(BuildError) as info:
        package.build_fmu_from_spec(spec, dest=blocker / "fmus")
    assert "cannot write" in str(info.value) and str(blocker) in str(info.value)


def test_damaged_numba_cache_names_the_folder_to_delete(fmus_in_repo, tmp_path, monkeypatch):
    spec = fmu_spec(FMU_NAMES[0])
    folder = tmp_path / kernels.kernel_cache_folders(spec)[0]  # a folder the FMU's kernels load from
    folder.mkdir()
    assert kernels.numba_cache_damage(tmp_path) is None
    (folder / "kernel.nbi").write_bytes(b"\x80\x04\x95\x10\x00")  # a pickle cut short
    damage = kernels.numba_cache_damage(tmp_path)
    assert damage and str(folder) in damage and "rm -rf" in damage
    monkeypatch.setenv("AAA_COSIM_NUMBA_CACHE", str(tmp_path))
    with pytest.raises(BuildError, match="numba cache is damaged"):
        warmup.warm_numba_cache(quiet=True)


# 6 ------------------------------------------------------------------------------------------------
def test_truncated_fmu_binary_is_refused_before_loading(fmus_in_repo, tmp_path):
    good = fmus_in_repo["Contact"]
    member = f"binaries/{fmi3.platform_tuple()}/Contact.so"
    with zipfile.ZipFile(good) as archive:
        data = archive.read(member)
    assert fmi3.elf_problem(data, fmi3.CORE_FUNCTIONS) is None
    truncated = tmp_path / "Contact.so"
    truncated.write_bytes(data[: len(data) // 2])
    assert "truncated" in fmi3.binary_problem(truncated)
    # in the orchestrator's own process: an error, not a SIGBUS
    proc = _python(f"""
        from orchestration.errors import FmuBinaryError
        from orchestration.hosts.fmi3 import Fmi3Library
        try:
            Fmi3Library({str(truncated)!r})
        except FmuBinaryError as exc:
            print("REFUSED", exc)
        """, timeout=30)
    assert proc.returncode == 0 and "REFUSED" in proc.stdout and str(truncated) in proc.stdout, proc.stderr[-2000:]
    # and in validate: the scene's FMU archive carries the truncated binary
    broken = tmp_path / "Contact.fmu"
    with zipfile.ZipFile(good) as src, zipfile.ZipFile(broken, "w") as dst:
        for item in src.infolist():
            payload = src.read(item)
            dst.writestr(item, payload[: len(payload) // 2] if item.filename == member else payload)
    text = (ROOT / "scenes" / "virtual_wall.toml").read_text()
    (tmp_path / "virtual_wall.toml").write_text(text)
    with pytest.raises(SceneError) as info:
        load_scene(tmp_path / "virtual_wall.toml")
    assert "truncated" in str(info.value) and str(broken) in str(info.value)


def test_device_driven_to_metres_away_warns_in_the_summary(fmus_in_repo, tmp_path):
    """The virtual wall scene with the operator pulling at 20 N away from the wall for 2 s: the
    device plant's position runs to tens of metres; the run completes but its summary says so."""
    from orchestration.run.simulation import run_scene

    text = (ROOT / "scenes" / "virtual_wall.toml").read_text()
    pushes = ("[[2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [2.0, 0.0, 0.0], "
              "[0.0, 0.0, 0.0]]")
    assert pushes in text
    (tmp_path / "wall.toml").write_text(text.replace(pushes, "[" + ", ".join(["[-20.0, 0.0, 0.0]"] * 6) + "]"))
    shutil.copy(fmus_in_repo["Contact"], tmp_path / "Contact.fmu")
    summary, _ = run_scene(load_scene(tmp_path / "wall.toml"), tmp_path / "out", progress=False, plots=False,
                           vtu=False)
    assert summary["implausible_outputs"]["count"] >= 1
    assert summary["implausible_outputs"]["outputs"]["device.position"]["worst"] < -10.0
    assert any("device.position" in line for line in summary["warnings"])


def test_unusable_home_skips_the_numba_cache_with_a_warning(fmus_in_repo, monkeypatch, caplog):
    """No home folder (RuntimeError of Path.home) or one this user may not enter (EACCES, as with
    plain sudo; faked, since the tests may run as root): a warning with the fix, no traceback."""
    def no_home():
        raise RuntimeError("Could not determine home directory.")

    class Forbidden(type(Path())):
        def exists(self):
            raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(kernels, "_numba_cache_root", no_home)
    with caplog.at_level("WARNING", logger=warmup.logger.name):
        assert warmup.warm_numba_cache(quiet=True) is False
    monkeypatch.setattr(kernels, "_numba_cache_root", lambda: Forbidden("/root/.cache/aaa-cosim/numba"))
    with caplog.at_level("WARNING", logger=warmup.logger.name):
        assert warmup.warm_numba_cache(quiet=True) is False
    text = caplog.text
    assert "no numba cache folder" in text and "cannot be used" in text and "AAA_COSIM_NUMBA_CACHE" in text

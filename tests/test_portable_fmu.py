"""An FMU copied alone onto a clean Debian system runs there and gives the numbers it gives here.

An FMU is a file that is handed to someone else: it must carry everything it needs. The nearest
"someone else's machine" at hand is a minbase root filesystem of this machine's distribution
(tests/rootfs.py: libc and the essential packages; no Python, no venv, no compiler, no caches),
entered with chroot. Each FMU is run there through the C importer tests/c_host/fmu_host.c (no Python
in it either) with only the .fmu beside it, and the same run is made on this machine with the .fmu
alone in a fresh folder and the project's venv out of sight. Both must succeed and print the same
outputs to the last bit (%.17g). A second test saves, serializes, restores and replays the FMU state
in the clean system.

The root filesystem is built once (debootstrap, about half a minute and 200 MB) and cached; see
tests/rootfs.py for where, and for why a test is skipped when it cannot be had. The wall times of
the runs are logged (``pytest -o log_cli=true --log-cli-level=INFO`` shows them).
"""
from __future__ import annotations

import io
import logging
import math
import shutil
import subprocess
import time
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import pytest

from project import FMU_NAMES, entry
from rootfs import c_host_argv, c_host_files, clean_rootfs, run_in_rootfs

pytestmark = pytest.mark.slow
log = logging.getLogger(__name__)

TIMEOUT = 900.0  # seconds per run: a cold start compiles the FMU's kernels (no cache in a fresh HOME)

# name -> (steps, step size, inputs {name: value}, outputs), for every FMU of the build's table
# (tests/project.py; a missing one fails its tests): the sizes of the ports are read from the
# FMU's modelDescription.xml. An input is set to value*(1 + k/steps) at step k (fmu_host's ramp), so
# every output below is non-zero: the tool points, all at (v, v, v), move from inside the default
# vessel's lumen into its wall (v = 0.0072); at 0.01, say, they never touch it and every output is 0.
CASES = {
    "Tissue": (3, 1.0 / 30.0, {"contact_force": 1e-4}, ["strain_energy", "kinetic_energy", "max_strain"]),
    "Contact": (50, 0.001, {"tool_positions": 0.0072}, ["tip_force", "penetration_depth", "contact_energy"]),
    "Catheter": (50, 0.001, {"insertion": 0.05, "tip_force": 0.3}, ["tip_position", "bend_angle", "total_bend"]),
}


def _float64_sizes(fmu: Path) -> dict[tuple[str, str], int]:
    """(causality, name) -> number of values of each Float64 input and output of the FMU: the product
    of its Dimensions, each a ``start`` or the start of the structural parameter it references."""
    with zipfile.ZipFile(fmu) as archive:
        root = ET.fromstring(archive.read("modelDescription.xml"))
    variables = root.find("ModelVariables")
    starts = {v.get("valueReference"): v.get("start") for v in variables if v.get("start") is not None}
    sizes = {}
    for variable in variables.iter("Float64"):
        if variable.get("causality") in ("input", "output"):
            dimensions = [int(d.get("start") or starts[d.get("valueReference")]) for d in variable.iter("Dimension")]
            sizes[(variable.get("causality"), variable.get("name"))] = math.prod(dimensions)
    return sizes


def _arguments(name: str, fmu: Path, state: bool = False) -> list[str]:
    """fmu_host's arguments (after the program), with the .fmu and the work folder relative to the
    folder it runs in, so that both runs print the very same text."""
    steps, h, inputs, outputs = entry(CASES, name, "CASES of tests/test_portable_fmu.py")
    sizes = _float64_sizes(fmu)
    args = [fmu.name, "work", str(steps), repr(h)]
    for port, value in inputs.items():
        assert ("input", port) in sizes, f"{name} has no Float64 input {port}"
        args += ["--input", f"{port}:{sizes['input', port]}={value!r}"]
    for port in outputs:
        assert ("output", port) in sizes, f"{name} has no Float64 output {port}"
        args += ["--output", f"{port}:{sizes['output', port]}"]
    return args + (["--state"] if state else [])


def _run_here(c_host: Path, fmu: Path, arguments: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    """fmu_host on this machine, in a folder holding the .fmu alone, with the environment of
    run_in_rootfs: no venv on PATH, no VIRTUAL_ENV/PYTHONPATH, and a fresh HOME (no user caches)."""
    run_dir, home = tmp_path / "here", tmp_path / "home"
    run_dir.mkdir()
    home.mkdir()
    shutil.copy2(fmu, run_dir / fmu.name)
    env = {"PATH": "/usr/bin:/bin", "HOME": str(home), "LANG": "C.UTF-8"}
    return subprocess.run([str(c_host), *arguments], cwd=run_dir, env=env, capture_output=True, text=True,
                          timeout=TIMEOUT)


def _run_in_clean_system(rootfs: Path, c_host: Path, fmu: Path, arguments: list[str]) -> subprocess.CompletedProcess:
    files = c_host_files(c_host, rootfs) | {fmu: fmu.name}
    return run_in_rootfs(rootfs, files, c_host_argv(files, arguments), timeout=TIMEOUT)


def _timed(where: str, name: str, run, *args) -> subprocess.CompletedProcess:
    started = time.monotonic()
    result = run(*args)
    log.info("%s %s: %.1f s, exit status %d", name, where, time.monotonic() - started, result.returncode)
    return result


def _report(where: str, result: subprocess.CompletedProcess) -> str:
    """The end of a run's output, for an assertion message."""
    return (f"\n--- {where}: exit status {result.returncode}\n--- stdout (end):\n{result.stdout[-1500:]}"
            f"\n--- stderr (end):\n{result.stderr[-3000:]}")


@pytest.fixture(scope="module")
def rootfs() -> Path:
    """The clean minbase root filesystem (built on first use, then cached; skips when unavailable)."""
    return clean_rootfs()


@pytest.mark.parametrize("name", FMU_NAMES)
def test_fmu_alone_on_a_clean_system_gives_the_numbers_of_the_build_machine(rootfs, c_host, fmus, name, tmp_path):
    arguments = _arguments(name, fmus[name])
    here = _timed("on the build machine", name, _run_here, c_host, fmus[name], arguments, tmp_path)
    there = _timed("in the clean root filesystem", name, _run_in_clean_system, rootfs, c_host, fmus[name], arguments)
    both = _report("build machine", here) + _report("clean root filesystem", there)  # a failure shows both runs
    assert here.returncode == 0 and "run completed" in here.stdout, f"{name} fails on the build machine:{both}"
    assert there.returncode == 0 and "run completed" in there.stdout, f"{name} fails on a clean system:{both}"
    assert there.stdout.splitlines() == here.stdout.splitlines(), f"{name} differs on a clean system:{both}"


@pytest.mark.parametrize("name", FMU_NAMES)
def test_state_round_trip_on_a_clean_system(rootfs, c_host, fmus, name):
    there = _timed("with --state in the clean root filesystem", name, _run_in_clean_system, rootfs, c_host,
                   fmus[name], _arguments(name, fmus[name], state=True))
    assert there.returncode == 0 and "run completed" in there.stdout, _report("clean root filesystem", there)
    assert "state replay: identical" in there.stdout, _report("clean root filesystem", there)


def test_the_clean_system_has_no_python_and_runs_see_no_environment(rootfs):
    """What makes the tests above mean something: the root filesystem has no Python to fall back on,
    and a run sees none of this machine's environment (no PYTHONPATH, LD_LIBRARY_PATH, VIRTUAL_ENV)."""
    assert not list((rootfs / "usr" / "bin").glob("python*")), "the clean root filesystem has a Python"
    assert not list((rootfs / "usr" / "lib").rglob("libpython*")), "the clean root filesystem has a libpython"
    result = run_in_rootfs(rootfs, {}, ["/usr/bin/env"], timeout=60)
    assert result.returncode == 0, result.stderr
    environment = dict(line.split("=", 1) for line in result.stdout.splitlines())
    assert environment.keys() == {"HOME", "LANG", "PATH"}, result.stdout
    assert environment["PATH"] == "/usr/bin:/bin" and environment["HOME"].startswith("/tmp/run-"), result.stdout


def _with_runtime(fmu: Path, out: Path, change) -> Path:
    """A copy of ``fmu`` whose resources/runtime.zip is ``change(bytes)``, everything else as built."""
    with zipfile.ZipFile(fmu) as source, zipfile.ZipFile(out, "w") as copy:
        for member in source.infolist():
            data = source.read(member)
            if member.filename == "resources/runtime.zip":
                data = change(data)
            copy.writestr(member, data)
    return out


def _flip_inside_an_entry(data: bytes) -> bytes:
    """One bit flipped in the compressed data of the archive's largest entry (its CRC must catch it)."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        largest = max(archive.infolist(), key=lambda e: e.compress_size)
    at = largest.header_offset + 30 + len(largest.filename.encode()) + largest.compress_size // 2 + 64
    return data[:at] + bytes([data[at] ^ 0x10]) + data[at + 1:]


@pytest.mark.parametrize("damage, words", [
    (_flip_inside_an_entry, "damaged"),
    (lambda data: data[: len(data) // 2], "not a complete runtime archive"),
])
def test_a_damaged_runtime_is_refused_at_instantiation_with_the_reason(damage, words, c_host, fmus, tmp_path):
    """The runtime crosses a trust boundary (an FMU file handed around): a flipped bit or a truncated
    archive fails fmi3InstantiateCoSimulation with a log line that says so and what to do, nothing
    half-unpacked stays in the cache, and the importer exits normally."""
    fmu = _with_runtime(fmus["Catheter"], tmp_path / "Catheter.fmu", damage)
    result = _run_here(c_host, fmu, _arguments("Catheter", fmu), tmp_path)
    assert result.returncode >= 0, result.stderr[-2000:]  # not killed by a signal
    assert "run completed" not in result.stdout
    output = result.stdout + result.stderr
    assert words in output and "build it again" in output, output[-2000:]
    cache = tmp_path / "home" / ".cache" / "aaa-cosim" / "runtime"
    assert not cache.exists() or not any(cache.iterdir()), list(cache.iterdir())

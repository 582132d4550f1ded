"""The FMUs in a non-Python importer: tests/c_host/fmu_host.c, compiled here with the system C compiler.

The host has no Python in it: it extracts the .fmu, loads the binary with dlopen, instantiates,
steps with inputs and reads outputs like any FMI 3.0 importer. The FMU finds the Python library
recorded at build time by itself (nothing preloaded, no environment variables). Every FMU runs in
30 fresh processes that must all exit with status 0, and gives the same numbers as in FMPy.
"""
from __future__ import annotations

import os
import shutil
import subprocess
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from fmu_harness import fmu_instance
from project import FMU_NAMES, entry

# every test twice: the model in the importer's process, and in the FMU's helper process
pytestmark = pytest.mark.usefixtures("model_process")

RUNS = 30

# name -> (steps, step size, inputs {name: (count, value)}, outputs {name: count}), for every FMU of the
# build's table (tests/project.py; a missing one fails its tests); the inputs ramp from value to 2*value
# (fmu_host): the tool points (v, v, v) of Contact go from the lumen into the wall
CASES = {
    "Catheter": (300, 0.001, {"insertion": (1, 0.05), "tip_force": (3, 0.3)}, {"tip_position": 3, "bend_angle": 1}),
    "Contact": (200, 0.001, {"tool_positions": (93, 0.0072)}, {"tool_force": 3, "penetration_depth": 1}),
    "Tissue": (6, 1.0 / 30.0, {"contact_force": (8064, 1e-4)}, {"strain_energy": 1, "kinetic_energy": 1}),
}


def _case(name: str) -> tuple:
    return entry(CASES, name, "CASES of tests/test_fmu_c_host.py")


def _arguments(name: str, fmu: Path, work: Path, state: bool = False) -> list[str]:
    steps, h, inputs, outputs = _case(name)
    args = [str(fmu), str(work), str(steps), repr(h)]
    for port, (count, value) in inputs.items():
        args += ["--input", f"{port}:{count}={value!r}"]
    for port, count in outputs.items():
        args += ["--output", f"{port}:{count}"]
    return args + (["--state"] if state else [])


def _run(c_host: Path, args: list[str]) -> subprocess.CompletedProcess:
    """fmu_host with ``args`` (the .fmu, the folder it extracts into, ...); the folder is removed
    afterwards (an extracted FMU is as large as the FMU: its runtime is in it)."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "LD_PRELOAD")}
    try:
        return subprocess.run([str(c_host), *args], capture_output=True, text=True, timeout=300, env=env)
    finally:
        shutil.rmtree(args[1], ignore_errors=True)


def _outputs(stdout: str) -> dict[str, np.ndarray]:
    values = {}
    for line in stdout.splitlines():
        name, *numbers = line.split()
        if name not in ("state", "misuse", "run"):  # the replay, misuse and run verdicts
            values[name] = np.array([float(x) for x in numbers])
    return values


def _fmpy_outputs(name: str, fmu: Path) -> dict[str, np.ndarray]:
    """The same input sequence through FMPy in this process."""
    steps, h, inputs, outputs = _case(name)
    with fmu_instance(fmu) as instance:
        instance.initialize()
        for k in range(steps):
            for port, (count, value) in inputs.items():
                instance.slave.setFloat64(instance.vr(port), [value * (1.0 + k / steps)] * count)
            instance.slave.doStep(k * h, h)
        return {port: np.atleast_1d(instance.get(port)) for port in outputs}


@pytest.mark.parametrize("name", FMU_NAMES)
def test_runs_in_a_c_host_with_the_numbers_of_fmpy(c_host, fmus, name, tmp_path):
    result = _run(c_host, _arguments(name, fmus[name], tmp_path / "run"))
    assert result.returncode == 0, result.stderr[-2000:]
    assert "run completed" in result.stdout and "logStatusError" not in result.stderr
    c_values = _outputs(result.stdout)
    for port, expected in _fmpy_outputs(name, fmus[name]).items():
        np.testing.assert_array_equal(c_values[port], expected, err_msg=f"{name}.{port}")


@pytest.mark.parametrize("name", FMU_NAMES)
def test_state_saved_serialized_and_replayed_bit_identically_in_a_c_host(c_host, fmus, name, tmp_path):
    result = _run(c_host, _arguments(name, fmus[name], tmp_path / "run", state=True))
    assert result.returncode == 0, result.stderr[-2000:]
    assert "state replay: identical" in result.stdout


@pytest.mark.parametrize("name", FMU_NAMES)
def test_illegal_calls_and_a_nan_input_are_refused_and_the_host_exits_normally(c_host, fmus, name, tmp_path):
    """fmi3DoStep and fmi3Terminate before initialization, and a NaN input halfway, each return
    fmi3Error with a reason; the run then goes on, frees the instance and exits with status 0 (the
    NaN input: when the case sets inputs)."""
    result = _run(c_host, _arguments(name, fmus[name], tmp_path / "run") + ["--misuse"])
    assert result.returncode == 0, result.stderr[-2000:]
    with_inputs = bool(_case(name)[2])
    assert ("misuse refused: 3 of 3" if with_inputs else "misuse refused: 2 of 2") in result.stdout
    assert "illegal call sequence" in result.stderr
    assert ("only finite numbers" in result.stderr) == with_inputs
    c_values = _outputs(result.stdout)  # the refused calls changed nothing
    for port, expected in _fmpy_outputs(name, fmus[name]).items():
        np.testing.assert_array_equal(c_values[port], expected, err_msg=f"{name}.{port}")


@pytest.mark.slow
@pytest.mark.parametrize("name", FMU_NAMES)
def test_thirty_fresh_c_host_processes_exit_normally(c_host, fmus, name, tmp_path):
    jobs = [_arguments(name, fmus[name], tmp_path / f"run{k}") for k in range(RUNS)]
    with ThreadPoolExecutor(max_workers=2) as pool:
        results = list(pool.map(lambda args: _run(c_host, args), jobs))
    failures = [(k, r.returncode, r.stderr[-300:]) for k, r in enumerate(results)
                if r.returncode != 0 or "run completed" not in r.stdout]
    assert failures == []
    first = _outputs(results[0].stdout)
    for r in results[1:]:  # and the same numbers every time
        for port, values in _outputs(r.stdout).items():
            np.testing.assert_array_equal(values, first[port])


@pytest.mark.parametrize("kind, at", [("error_at", 0.05), ("bad_at", 0.03)])
def test_a_step_that_fails_ends_the_run_and_the_host_still_exits_normally(c_host, synthetic_fmus, kind, at, tmp_path):
    """A model failure (an exception; a NaN output) in fmi3DoStep: fmi3Error with the reason, the
    instance in the Error state, and the importer's clean-up (fmi3FreeInstance, unload) works: the
    C host reports the status and exits with 0, in every one of several fresh processes."""
    args = [str(synthetic_fmus["Faulty"]), str(tmp_path / "run"), "100", "0.01", "--param", f"{kind}:1={at!r}"]
    for k in range(5):
        args[1] = str(tmp_path / f"run{k}")
        result = _run(c_host, args)
        assert result.returncode == 0, result.stderr[-2000:]
        assert "run ended: fmi3DoStep(" in result.stdout and "returned 3" in result.stdout
        assert "run completed" not in result.stdout
        assert "logStatusError" in result.stderr


@pytest.mark.parametrize("name", FMU_NAMES)
def test_a_state_saved_to_a_file_and_restored_as_fmusim_does_continues_the_run(c_host, fmus, name, tmp_path):
    """fmusim v0.0.39's --final-fmu-state-file and --initial-fmu-state-file: get, serialize, write
    and fmi3FreeFMUState(instance, state) (the state itself where its pointer is due); in a fresh
    process read, deserialize, set, free the same way, and step on without initialization. fmusim
    stops at any status but fmi3OK; the continued run must end where the whole run ends, to the bit."""
    steps = _case(name)[0]
    whole = _run(c_host, _arguments(name, fmus[name], tmp_path / "whole"))
    assert whole.returncode == 0 and "run completed" in whole.stdout, whole.stdout + whole.stderr[-2000:]
    state_file = tmp_path / "state.bin"
    first = _run(c_host, _arguments(name, fmus[name], tmp_path / "first")
                 + ["--stop-after", str(steps // 2), "--final-state-file", str(state_file)])
    assert first.returncode == 0 and "run completed" in first.stdout, first.stdout + first.stderr[-2000:]
    assert state_file.stat().st_size > 0
    second = _run(c_host, _arguments(name, fmus[name], tmp_path / "second")
                  + ["--from-step", str(steps // 2), "--initial-state-file", str(state_file)])
    assert second.returncode == 0 and "run completed" in second.stdout, second.stdout + second.stderr[-2000:]
    assert "fmusim would stop" not in first.stdout + second.stdout
    continued, expected = _outputs(second.stdout), _outputs(whole.stdout)
    assert continued.keys() == expected.keys()
    for port, values in expected.items():
        np.testing.assert_array_equal(continued[port], values, err_msg=port)


def test_another_installations_python_runs_the_model_or_is_refused_with_the_fix(c_host, fmus, tmp_path):
    """AAA_COSIM_LIBPYTHON names another installation's libpython (here the build's own, with the
    project's site-packages on PYTHONPATH): the model runs on it. A copy of that library whose
    standard library is not beside it is refused with the fix (AAA_COSIM_PYTHONHOME), where CPython
    would abort the importer ("init_fs_encoding")."""
    import sysconfig

    library = Path(sysconfig.get_config_var("LIBDIR")) / sysconfig.get_config_var("INSTSONAME")
    if not library.exists():
        pytest.skip(f"this Python has no shared library ({library})")
    site_packages = sysconfig.get_paths()["purelib"]
    base = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "AAA_COSIM_MODEL_PROCESS": "importer"}
    args = _arguments("Catheter", fmus["Catheter"], tmp_path / "work")
    ran = subprocess.run([str(c_host), *args], capture_output=True, text=True, timeout=300,
                         env={**base, "AAA_COSIM_LIBPYTHON": str(library), "PYTHONPATH": site_packages})
    assert ran.returncode == 0 and "run completed" in ran.stdout, ran.stdout + ran.stderr[-2000:]
    astray = tmp_path / "elsewhere" / "lib"
    astray.mkdir(parents=True)
    shutil.copy(library, astray / library.name)
    refused = subprocess.run([str(c_host), *_arguments("Catheter", fmus["Catheter"], tmp_path / "work2")],
                             capture_output=True, text=True, timeout=300,
                             env={**base, "AAA_COSIM_LIBPYTHON": str(astray / library.name)})
    assert refused.returncode >= 0, refused.stderr[-2000:]  # not killed by a signal (an abort)
    assert "set AAA_COSIM_PYTHONHOME" in refused.stdout + refused.stderr

"""The Ecos harness (tests/ecos_host.py) proven on the test suite's own small C FMUs
(tests/conformance/, built by tests/conformance_fmus.py): Ecos (ecospy 0.7.2), an independent C++
FMI importer, runs them and every expected value is the FMU's documented output, computed here.

Skipped, with the reason, where Ecos cannot run (ecospy not installed, libtbb12 or unzip missing).
"""
from __future__ import annotations

import math
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest

import ecos_host
from conformance_fmus import build_all
from ecos_host import EcosError, ecos_available, run_in_ecos


@pytest.fixture(scope="module")
def conformance_fmus(tmp_path_factory) -> dict[str, Path]:
    reason = ecos_available()
    if reason is not None:
        pytest.skip(reason)
    return build_all(tmp_path_factory.mktemp("conformance_fmus"))


def fixed_step_x(internal_steps: int, a: float = 2.0, dt: float = 0.002) -> float:
    """FixedStep's x after n internal steps: x <- x * (1 - a * dt) from 1 (tests/conformance/fixed_step.c)."""
    x = 1.0
    for _ in range(internal_steps):
        x = x * (1.0 - a * dt)
    return x


# -- FixedStep: fixedInternalStepSize = 2 ms ---------------------------------------------------------
@pytest.mark.parametrize("step, per_step", [(0.002, 1), (0.004, 2)])
def test_fixed_step_decays_exactly_with_a_parameter_from_the_harness(conformance_fmus, step, per_step):
    a = 3.0
    n = 25
    result = run_in_ecos(conformance_fmus["FixedStep"], step=step, stop_time=n * step, parameters={"a": a},
                         outputs=["x", "steps"])
    k = np.arange(n + 1)
    np.testing.assert_allclose(result["time"], k * step, rtol=0, atol=1e-12)
    assert result["steps"].tolist() == (per_step * k).tolist()
    # bit for bit the FMU's arithmetic, and (1 - a * 0.002) ** n up to rounding
    assert result["x"].tobytes() == np.array([fixed_step_x(per_step * i, a) for i in k]).tobytes()
    np.testing.assert_allclose(result["x"], (1 - a * 0.002) ** (per_step * k), rtol=1e-13)
    assert result["steps"].dtype == np.int64 and result["x"].dtype == np.float64
    assert result.ecos_version == "v0.7.2"
    assert result.fmu_messages == []


def test_a_component_step_steps_the_fmu_every_few_global_steps_from_the_start_of_its_period(conformance_fmus):
    """Ecos's per-component step (step_size_hint 6 ms under a 2 ms global step): the FMU is stepped at
    global steps 0, 3, 6, ... over 6 ms, so after k global steps it has taken ceil(k / 3) steps of
    3 internal steps, and its outputs are those at the end of its current step (ahead of Ecos's time)."""
    n = 12
    result = run_in_ecos(conformance_fmus["FixedStep"], step=0.002, stop_time=n * 0.002, component_step=0.006,
                         outputs=["x", "steps"])
    calls = [math.ceil(k / 3) for k in range(n + 1)]
    assert calls[:5] == [0, 1, 1, 1, 2]
    assert result["steps"].tolist() == [3 * c for c in calls]
    assert result["x"].tobytes() == np.array([fixed_step_x(3 * c) for c in calls]).tobytes()
    np.testing.assert_allclose(result["time"], np.arange(n + 1) * 0.002, rtol=0, atol=1e-12)


def test_a_step_the_fmu_refuses_raises_with_its_own_message(conformance_fmus):
    """Ecos steps on after fmi3Error (it ignores the status); the harness finds the FMU's Error message."""
    with pytest.raises(EcosError) as info:
        run_in_ecos(conformance_fmus["FixedStep"], step=0.003, stop_time=0.009, outputs=["x"])
    text = str(info.value)
    assert ("Error communication step 0.0030000000000000001 s is not a whole multiple of the fixed internal "
            "step 0.002 s") in text
    assert "--- Ecos log ---" in text and "[ecos] [debug] [model] Error" in info.value.log


# -- Ramp: any step, y = (t + h)^2, integral += u * h ---------------------------------------------------
def test_ramp_outputs_follow_its_formula_and_an_input_reaches_the_integral(conformance_fmus):
    h = 0.01
    n = 30

    def u(t):
        return 1.0 + math.sin(7.0 * t)

    result = run_in_ecos(conformance_fmus["Ramp"], step=h, stop_time=n * h, inputs={"u": u},
                         outputs=["y", "h_last", "calls", "integral"])
    time = result["time"]
    assert len(time) == n + 1
    np.testing.assert_allclose(time, np.arange(n + 1) * h, rtol=0, atol=1e-12)
    # the FMU's y = (t + h)^2 with Ecos's t, whose end t + h is also Ecos's next time: exactly time^2
    assert result["y"].tobytes() == (time * time).tobytes()
    assert result["h_last"].tolist() == [0.0] + [h] * n
    assert result["calls"].tolist() == list(range(n + 1))
    # the value set before the step from t_k = k * h is u(t_k): integral_k = sum_{j<k} u(j h) h, in order
    expected, total = [0.0], 0.0
    for j in range(n):
        total += u(j * h) * h
        expected.append(total)
    assert result["integral"].tobytes() == np.array(expected).tobytes()


def test_an_input_table_is_held_from_each_row(conformance_fmus):
    """A table of (time, value) rows: the value of the last row at or before the step's start."""
    h = 0.01
    table = [(0.0, 1.0), (0.05, 3.0), (0.1, -2.0)]
    result = run_in_ecos(conformance_fmus["Ramp"], step=h, stop_time=0.15, inputs={"u": table},
                         outputs=["integral"])
    held = [1.0] * 5 + [3.0] * 5 + [-2.0] * 5
    expected = np.cumsum([0.0] + [v * h for v in held])
    np.testing.assert_allclose(result["integral"], expected, rtol=0, atol=1e-15)


def test_a_discarded_step_is_stepped_over_by_ecos_and_only_its_warning_tells(conformance_fmus):
    """Ramp refuses a step longer than max_step with fmi3Discard (and a warning): Ecos 0.7.2 ignores
    the status and steps on, so calls stays 0; the warning is in fmu_messages (not an error)."""
    result = run_in_ecos(conformance_fmus["Ramp"], step=0.01, stop_time=0.03, parameters={"max_step": 0.005},
                         outputs=["calls", "y"])
    assert result["calls"].tolist() == [0, 0, 0, 0]
    assert result["y"].tolist() == [0.0] * 4
    assert result.fmu_messages == [("Warning", "a step of 0.01 s is longer than max_step = 0.005 s: not taken")] * 3


# -- Types: Int32, Boolean, Float64 and String through Ecos; the others refused ---------------------
def test_int32_boolean_float64_and_string_values_go_through(conformance_fmus):
    n = 6
    result = run_in_ecos(conformance_fmus["Types"], step=0.01, stop_time=n * 0.01,
                         parameters={"label": "through ecos"},  # the start value is "hello"
                         inputs={"n": lambda t: round(t * 1000), "x": lambda t: -2.5 * t},
                         outputs=["count", "flag", "speed", "n_echo", "x_echo", "label_length", "blob_sum"])
    k = np.arange(n + 1)
    assert result["count"].tolist() == k.tolist()
    assert result["flag"].tolist() == [c % 2 == 1 for c in k]
    assert result["speed"].tolist() == (0.5 * k).tolist()
    # the inputs' values during the last step, the one from t_{k-1}
    assert result["n_echo"].tolist() == [0] + [round((j * 0.01) * 1000) for j in range(n)]
    assert result["x_echo"].tolist() == [0.0] + [-2.5 * (j * 0.01) for j in range(n)]
    assert result["label_length"].tolist() == [len("through ecos")] * (n + 1)
    assert result["blob_sum"].tolist() == [0x0a + 0x0b + 0x0c + 0xff] * (n + 1)
    assert result["flag"].dtype == np.bool_


@pytest.mark.parametrize("kwargs, message", [
    ({"outputs": ["small"]}, "'small' is an Int8; through Ecos 0.7.2 only Float64, Int32 and Boolean"),
    ({"outputs": ["big"]}, "'big' is an Int64"),
    ({"outputs": ["mode_out"]}, "'mode_out' is an Enumeration"),
    ({"outputs": ["label_out"]}, "'label_out' is a String"),
    ({"outputs": ["count"], "inputs": {"count": lambda t: 1}}, "'count' has causality 'output', not an input"),
    ({"outputs": ["nope"]}, "no variable named 'nope' (the output)"),
    ({"outputs": ["count"], "inputs": {"n": lambda t: 0.5}}, "'n' is an Int32: 0.5 is not one"),
    ({"outputs": ["count"], "parameters": {"speed": 1.0}}, "'speed' (output, continuous) cannot be set"),
])
def test_what_ecos_cannot_pass_intact_is_refused_before_running(conformance_fmus, kwargs, message):
    with pytest.raises(EcosError) as info:
        run_in_ecos(conformance_fmus["Types"], step=0.01, stop_time=0.02, **kwargs)
    assert message in str(info.value)


def test_structural_parameters_and_arrays_are_refused(conformance_fmus):
    with pytest.raises(EcosError, match="'n' is a structural parameter; Ecos has no Configuration Mode"):
        run_in_ecos(conformance_fmus["Structural"], step=0.01, stop_time=0.02, parameters={"n": 4},
                    outputs=["configurations"])
    with pytest.raises(EcosError, match="'v' is an array; Ecos 0.7.2 handles scalar variables only"):
        run_in_ecos(conformance_fmus["Structural"], step=0.01, stop_time=0.02, outputs=["v"])
    with pytest.raises(EcosError, match="an output named 'time' would hide the result's sample times"):
        run_in_ecos(conformance_fmus["Structural"], step=0.01, stop_time=0.02, outputs=["time"])


def test_bad_arguments_are_refused(conformance_fmus, tmp_path):
    ramp = conformance_fmus["Ramp"]
    with pytest.raises(EcosError, match="stop_time 0.025 is not a whole number of steps of 0.01"):
        run_in_ecos(ramp, step=0.01, stop_time=0.025, outputs=["y"])
    with pytest.raises(EcosError, match="no FMU at"):
        run_in_ecos(tmp_path / "missing.fmu", step=0.01, stop_time=0.02, outputs=["y"])
    (tmp_path / "junk.fmu").write_bytes(b"not a zip")
    with pytest.raises(EcosError, match="junk.fmu: not a readable FMU"):
        run_in_ecos(tmp_path / "junk.fmu", step=0.01, stop_time=0.02, outputs=["y"])
    with pytest.raises(EcosError, match="input 'u': no row at or before t = 0"):
        run_in_ecos(ramp, step=0.01, stop_time=0.02, inputs={"u": [(0.005, 1.0)]}, outputs=["y"])


def test_a_crash_of_ecos_is_an_error_with_its_log(conformance_fmus, tmp_path):
    """An FMU without its binary: fmi4c fails to load it and Ecos 0.7.2 dereferences the null model
    (SIGSEGV) while building the simulation; the child process dies, the log says why."""
    with zipfile.ZipFile(conformance_fmus["Ramp"]) as archive:
        description = archive.read("modelDescription.xml")
    broken = tmp_path / "NoBinary.fmu"
    with zipfile.ZipFile(broken, "w") as archive:
        archive.writestr("modelDescription.xml", description)
    with pytest.raises(EcosError) as info:
        run_in_ecos(broken, step=0.01, stop_time=0.02, outputs=["y"])
    assert "Ecos running NoBinary.fmu was killed by SIGSEGV" in str(info.value)
    assert "Failed to load functions for FMI 3 CS." in info.value.log


# -- ecos_available -----------------------------------------------------------------------------------
def test_ecos_available_names_what_is_missing(monkeypatch):
    check = ecos_available.__wrapped__
    if (reason := check()) is not None:
        pytest.skip(reason)
    monkeypatch.setattr(ecos_host.shutil, "which", lambda name: None)
    assert check() == "Ecos unpacks FMUs with the `unzip` program, not found on PATH (apt-get install unzip)"
    monkeypatch.undo()

    def no_tbb(*args, **kwargs):
        return subprocess.CompletedProcess(args, 1, "", "Traceback ...\nOSError: libtbb.so.12: cannot open shared "
                                                        "object file: No such file or directory\n")
    monkeypatch.setattr(ecos_host.subprocess, "run", no_tbb)
    assert check() == ("Ecos's library needs libtbb.so.12 (apt-get install libtbb12): OSError: libtbb.so.12: "
                       "cannot open shared object file: No such file or directory")
    monkeypatch.undo()

    import importlib.util
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ecospy" else real(name, *a))
    assert check() == "ecospy is not installed (pip install ecospy==0.7.2, or the `test` extra)"

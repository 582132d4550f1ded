"""The orchestrator with FMI 3.0 Co-Simulation FMUs that are not the project's own (issue 11).

Small FMUs written in C (tests/conformance/, built here by tests/conformance_fmus.py) exercise
what "any conforming FMU" may do: every variable type (Int8/Int32/Int64, Boolean, Enumeration,
String, Binary), units declared on types, a fixed internal step, any communication step, a
structural parameter accepted only in Configuration Mode, terminateSimulation. They run through
the FMI 3.0 binding directly, through both hosts (in process and in a worker process), and
through scene validation and the real master. Every expected value is the FMU's documented
output, computed here independently.
"""
from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from conformance_fmus import build_all
from orchestration.errors import FMI_ERROR, FmuCallError
from orchestration.hosts.fmi3 import Fmi3Instance, Fmi3Library, resource_path
from orchestration.hosts.in_process import InProcessFmu, PortConfigurationError
from orchestration.run.simulation import run_scene
from orchestration.hosts.description import read_fmu
from orchestration.observers.recorder import read_stream
from orchestration.scene.model import SceneError
from orchestration.scene.loading import scene_from_dict
from orchestration.hosts.worker import WorkerFmu

HOSTS = {"in_process": InProcessFmu, "worker": WorkerFmu}


@pytest.fixture(scope="module")
def conformance_fmus(tmp_path_factory) -> dict[str, Path]:
    return build_all(tmp_path_factory.mktemp("conformance_fmus"))


@pytest.fixture(params=list(HOSTS))
def kind(request) -> str:
    return request.param


def hosted(kind: str, name: str, fmu: Path, structural: dict | None = None):
    return HOSTS[kind](name, read_fmu(fmu, structural))


# -- the binding ---------------------------------------------------------------------------------
def _extracted(fmu: Path, tmp_path: Path) -> Path:
    from fmpy import extract

    return Path(extract(str(fmu), str(tmp_path / "unzipped")))


def test_binding_gets_and_sets_every_type_and_reports_errors_with_the_logged_reason(conformance_fmus, tmp_path):
    unzipped = _extracted(conformance_fmus["Types"], tmp_path)
    library = Fmi3Library.from_extracted(unzipped, "Types")
    try:
        assert library.version() == "3.0"
        with pytest.raises(FmuCallError) as info:
            Fmi3Instance(library, "bad", "{not-the-token}", resource_path(unzipped))
        assert info.value.call == "fmi3InstantiateCoSimulation"
        assert "wrong instantiation token {not-the-token}" in info.value.reason

        instance = Fmi3Instance(library, "types", "{conformance-types-1}", resource_path(unzipped))
        try:
            assert instance.get("String", [14]) == ["hello"]
            assert instance.get("Binary", [16]) == [bytes.fromhex("0a0b0cff")]
            instance.set("String", [14], ["grüße"])
            instance.set("Binary", [16], [b"\x00\x01\xfe"])
            assert instance.get("String", [14]) == ["grüße"]
            assert instance.get("Binary", [16]) == [b"\x00\x01\xfe"]
            instance.set("Binary", [16], [b""])
            assert instance.get("Binary", [16]) == [b""]
            instance.set("Enumeration", [5], [2])
            instance.set("Int64", [4], [-(2**62)])
            assert instance.get("Int64", [4, 5]).tolist() == [-(2**62), 2]
            assert instance.get("Enumeration", [5]).dtype == np.int64

            # one error path: the function (and variable), the status and the FMU's own reason
            with pytest.raises(FmuCallError) as info:
                instance.set("Float64", [7], [1.0], label="speed")
            error = info.value
            assert (error.component, error.call, error.status) == ("types", "fmi3SetFloat64(speed)", FMI_ERROR)
            assert error.reason == "fmi3SetFloat64: speed is an output; it cannot be set"
            with pytest.raises(FmuCallError, match="no variable has value reference 99"):
                instance.get("Float64", [99])
            with pytest.raises(FmuCallError, match="illegal call sequence"):
                instance.do_step(0.0, 0.01)

            instance.enter_initialization_mode(0.0)
            instance.exit_initialization_mode()
            result = instance.do_step(0.0, 0.01)
            assert result == (False, False, False, 0.01)
            # count, the UTF-8 bytes of "grüße", sum and size of the (emptied) blob
            assert instance.get("Int32", [1, 15, 17, 18]).tolist() == [1, 7, 0, 0]
        finally:
            instance.free()
            instance.free()  # idempotent
    finally:
        library.close()
        library.close()


# -- the hosts: values of every type, exactly ------------------------------------------------------
TYPES_OBSERVED = ["count", "small", "big", "flag", "mode_out", "speed", "distance", "x_echo", "n_echo",
                  "label_length", "blob_sum", "blob_size"]


def test_every_variable_type_through_the_hosts(kind, conformance_fmus):
    host = hosted(kind, "types", conformance_fmus["Types"])
    try:
        host.instantiate()
        host.set_values({"label": "conformance", "blob": "00ff10", "big_offset": 2**40, "mode": "Fast"})
        host.enter_initialization(0.0)
        host.configure(["x", "n", "mode"], TYPES_OBSERVED)
        host.exit_initialization()
        initial = host.get_outputs()
        assert initial["label_length"].tolist() == [11.0]
        assert initial["blob_sum"].tolist() == [0.0 + 255 + 16] and initial["blob_size"].tolist() == [3.0]
        assert initial["mode_out"].tolist() == [3.0]   # the item name "Fast" became its value
        for k in range(1, 6):
            x = (-1) ** k * k / 3
            host.start_step((k - 1) * 0.01, 0.01, {"x": np.array([x]), "n": np.array([-(2**31)] if k == 5 else [k]),
                                                    "mode": np.array([1 + k % 3])})
            out = host.finish_step()
            assert all(v.dtype == np.float64 for v in out.values())
            assert out["count"].tolist() == [k] and out["small"].tolist() == [k % 100]
            assert out["big"].tolist() == [2**40 + k] and out["flag"].tolist() == [k % 2]
            assert out["speed"].tolist() == [0.5 * k] and out["distance"].tolist() == [0.25 * k]
            assert out["x_echo"].tobytes() == np.array([x]).tobytes()
            assert out["n_echo"].tolist() == [-(2**31) if k == 5 else k]
            assert out["mode_out"].tolist() == [1 + k % 3]
            assert not host.terminate_requested and not host.early_return
            assert host.last_successful_time == (k - 1) * 0.01 + 0.01
        native = host.get_native(["label", "blob", "label_out", "blob_out", "mode_out", "small"])
        assert native["label"] == native["label_out"] == ["conformance"]
        assert native["blob"] == native["blob_out"] == [b"\x00\xff\x10"]
        assert native["mode_out"].dtype == np.int64 and native["small"].dtype == np.int8
        # an enumeration value that is no item: the FMU refuses the step, and says why
        with pytest.raises(FmuCallError) as info:
            host.start_step(0.05, 0.01, {"mode": np.array([7.0])})
            host.finish_step()
        assert info.value.call == "fmi3DoStep" and "mode = 7 is not an item of Mode" in info.value.reason
    finally:
        host.terminate()


def test_values_a_float64_cannot_carry_exactly_are_refused(kind, conformance_fmus):
    host = hosted(kind, "types", conformance_fmus["Types"])
    try:
        host.instantiate()
        host.set_values({"big_offset": 2**53 - 1})
        host.enter_initialization(0.0)
        host.configure([], ["big"])
        host.exit_initialization()
        host.start_step(0.0, 0.01, {})
        assert host.finish_step()["big"].tolist() == [2**53]  # still exact
        with pytest.raises(FmuCallError, match=r"big = 9007199254740993 is beyond 2\*\*53"):
            host.start_step(0.01, 0.01, {})
            host.finish_step()
    finally:
        host.terminate()


def test_parameters_of_the_wrong_type_are_refused_with_the_port_named(conformance_fmus):
    host = hosted("in_process", "types", conformance_fmus["Types"])
    try:
        host.instantiate()
        for values, words in [({"blob": "xyz"}, "Binary parameter.*hexadecimal"),
                              ({"mode": "Medium"}, "not one of its items: Off, Slow, Fast"),
                              ({"big_offset": 2**63}, "out of its range"),
                              ({"label": 5}, "String")]:
            with pytest.raises(PortConfigurationError, match=words):
                host.set_values(values)
        with pytest.raises(PortConfigurationError, match="String variable.*set_values"):
            host.configure([], ["label"])
    finally:
        host.terminate()


# -- Configuration Mode ----------------------------------------------------------------------------
def test_structural_parameters_are_set_in_configuration_mode(kind, conformance_fmus):
    host = hosted(kind, "structural", conformance_fmus["Structural"], {"n": 5})
    try:
        assert host.ports["v"].size == 5
        host.instantiate()
        host.set_values({"n": 5, "gain": 2.0})   # the FMU refuses n anywhere but in Configuration Mode
        host.enter_initialization(0.0)
        host.configure([], ["v", "configurations"])
        host.exit_initialization()
        assert host.get_outputs()["configurations"].tolist() == [1.0]
        host.start_step(0.0, 0.25, {})
        assert host.finish_step()["v"].tolist() == [2.0 * (i + 1) * 0.25 for i in range(5)]
        # too late for a structural parameter: refused by the host before the FMU sees it
        with pytest.raises(PortConfigurationError, match="Configuration Mode.*before enter_initialization"):
            host.set_values({"n": 4})
    finally:
        host.terminate()


def test_the_structural_fmu_really_refuses_n_outside_configuration_mode(conformance_fmus, tmp_path):
    """The check above proves something: set directly, the FMU returns fmi3Error and says why."""
    unzipped = _extracted(conformance_fmus["Structural"], tmp_path)
    library = Fmi3Library.from_extracted(unzipped, "Structural")
    instance = Fmi3Instance(library, "structural", "{conformance-structural-1}", resource_path(unzipped))
    try:
        with pytest.raises(FmuCallError) as info:
            instance.set("UInt64", [1], [5], label="n")
        assert info.value.call == "fmi3SetUInt64(n)"
        assert "structural parameter n set outside Configuration Mode (in Instantiated Mode)" in info.value.reason
    finally:
        instance.free()
        library.close()


# -- steps -----------------------------------------------------------------------------------------
def fixed_step_x(internal_steps: int, a: float = 2.0, dt: float = 0.002) -> float:
    x = 1.0
    for _ in range(internal_steps):
        x = x * (1.0 - a * dt)
    return x


def test_fixed_internal_step_fmu_through_the_hosts(kind, conformance_fmus):
    host = hosted(kind, "fixed", conformance_fmus["FixedStep"])
    try:
        host.instantiate()
        host.enter_initialization(0.0)
        host.configure([], ["x", "steps"])
        host.exit_initialization()
        for k in range(5):
            host.start_step(k * 0.004, 0.004, {})
            out = host.finish_step()
            assert out["steps"].tolist() == [2 * (k + 1)]
            assert out["x"].tobytes() == np.array([fixed_step_x(2 * (k + 1))]).tobytes()
        with pytest.raises(FmuCallError, match="not a whole multiple of the fixed internal step"):
            host.start_step(0.02, 0.003, {})
            host.finish_step()
    finally:
        host.terminate()


def test_a_discarded_step_without_termination_is_an_error_that_says_why(kind, conformance_fmus):
    host = hosted(kind, "ramp", conformance_fmus["Ramp"])
    try:
        host.instantiate()
        host.set_values({"max_step": 0.01})
        host.enter_initialization(0.0)
        host.configure([], ["y"])
        host.exit_initialization()
        host.start_step(0.0, 0.01, {})
        assert host.finish_step()["y"].tolist() == [0.01 * 0.01]
        with pytest.raises(FmuCallError) as info:
            host.start_step(0.01, 0.02, {})
            host.finish_step()
        error = info.value
        assert (error.call, error.time, error.status) == ("fmi3DoStep", 0.01, 2)
        assert error.reason.startswith("a step of 0.02 s is longer than max_step = 0.01 s: not taken "
                                       "(fmi3Discard without terminateSimulation")
    finally:
        host.terminate()  # fmi3Terminate is still allowed after fmi3Discard
    assert not [text for status, text in host.messages if status >= FMI_ERROR]


def test_the_conformance_fmus_are_valid_for_fmpy(conformance_fmus):
    from fmpy import read_model_description
    from fmpy.validation import validate_fmu

    for name, path in conformance_fmus.items():
        assert validate_fmu(str(path)) == [], name
        read_model_description(str(path), validate_model_structure=True)


# -- terminateSimulation ---------------------------------------------------------------------------
@pytest.mark.parametrize("discard", [False, True])
def test_terminate_simulation_is_reported_by_the_hosts(kind, conformance_fmus, discard, caplog):
    stop_at = 0.045 if discard else 0.05
    host = hosted(kind, "term", conformance_fmus["Terminator"])
    try:
        host.instantiate()
        host.set_values({"stop_at": stop_at, "discard": discard})
        host.enter_initialization(0.0)
        host.configure([], ["y"])
        host.exit_initialization()
        assert host.terminate_requested is False and host.last_successful_time == 0.0
        for k in range(4):
            host.start_step(k * 0.01, 0.01, {})
            assert host.finish_step()["y"].tolist() == [k * 0.01 + 0.01]
            assert (host.terminate_requested, host.early_return) == (False, False)
            assert host.last_successful_time == k * 0.01 + 0.01
        host.start_step(0.04, 0.01, {})   # the step that reaches stop_at: no error, even with fmi3Discard
        out = host.finish_step()
        assert host.terminate_requested is True and host.early_return is False
        assert host.last_successful_time == (stop_at if discard else 0.04 + 0.01)
        assert out["y"].tolist() == [host.last_successful_time]
        assert any("terminateSimulation" in text for _, text in host.messages)
        # the FMU takes no further step (the master must stop), and says so
        with pytest.raises(FmuCallError, match="after terminateSimulation"):
            host.start_step(0.05, 0.01, {})
            host.finish_step()
    finally:
        host.terminate()


def test_fmi3_terminate_follows_a_requested_termination(conformance_fmus):
    host = hosted("in_process", "term", conformance_fmus["Terminator"])
    host.instantiate()
    host.enter_initialization(0.0)
    host.configure([], ["y"])
    host.exit_initialization()
    for k in range(5):
        host.start_step(k * 0.01, 0.01, {})
        host.finish_step()
    assert host.terminate_requested
    instance = host.instance
    host.terminate()  # fmi3Terminate is legal after terminateSimulation: it succeeds, then the instance is freed
    assert instance.freed and not instance.failed
    assert not [m for m in host.messages if m[0] >= FMI_ERROR]


# -- scenes: validation ----------------------------------------------------------------------------
def scene(conformance_fmus, fmu_tables: dict, connections=(), record=None, duration=0.1, hosting="in-process"):
    tables = {}
    for name, (model, extra) in fmu_tables.items():
        tables[name] = {"path": str(conformance_fmus[model]), **extra}
    return {"scene": {"name": "conformance", "duration": duration, "hosting": hosting},
            "fmu": tables,
            "connection": [{"from": a, "to": b} for a, b in connections],
            "record": record or {}}


def test_scene_validation_of_third_party_fmus(conformance_fmus, tmp_path):
    data = scene(conformance_fmus, {
        "a": ("Types", {"step": 0.01, "parameters": {"blob": "zz", "mode": "Medium", "label": "ok"}}),
        "b": ("Types", {"step": 0.01}),
        "c": ("Types", {"step": 0.01}),
        "fixed": ("FixedStep", {"step": 0.003}),
        "fixed_ok": ("FixedStep", {"step": 0.006}),
    }, connections=[
        ("a.speed", "b.position"),     # m/s -> m (units from the declared types)
        ("a.count", "b.x"),            # Int32 -> Float64: exact
        ("a.small", "b.n"),            # Int8 -> Int32: exact
        ("a.mode_out", "b.mode"),      # the same enumeration
        ("a.big", "fixed.a"),          # Int64 -> Float64 (a parameter): not exact
        ("a.speed", "c.n"),            # Float64 -> Int32: not exact
        ("a.flag", "c.x"),             # Boolean -> Float64
        ("a.label_out", "c.label"),    # String
    ], record={"a": ["count", "flag", "mode_out", "label_out"], "b": ["blob"]})
    with pytest.raises(SceneError) as info:
        scene_from_dict(data, tmp_path)
    problems = info.value.problems
    expected = [
        ("[fmu.a] parameters.blob", "Binary values, written in hexadecimal"),
        ("[fmu.a] parameters.mode", "an item name or its value ('Off' (1), 'Slow' (2), 'Fast' (3))"),
        ("connection 1 (a.speed -> b.position)", "unit mismatch, m/s -> m (a.speed is in m/s, b.position in m)"),
        ("connection 5 (a.big -> fixed.a)", "a.big is Int64 and fixed.a is Float64: Int64 -> Float64 is not exact"),
        ("connection 6 (a.speed -> c.n)", "a.speed is Float64 and c.n is Int32: Float64 -> Int32 is not exact"),
        ("connection 7 (a.flag -> c.x)", "a Boolean connects only to a Boolean"),
        ("connection 8 (a.label_out -> c.label)", "String variables are not moved through connections"),
        ("[record] a.label_out", "a String variable cannot be recorded"),
        ("[record] b.blob", "a Binary variable cannot be recorded"),
        ("[scene] duration", "0.1 s is not a whole number of steps of fixed (3/1000 s), fixed_ok (3/500 s)"),
    ]
    for where, what in expected:
        assert any(where in p and what in p for p in problems), (where, what, problems)
    assert len(problems) == len(expected), problems


def test_a_step_that_is_no_multiple_of_the_fmus_internal_step_is_passed_on(conformance_fmus, tmp_path):
    """FMI 3.0 leaves a communication step that is no whole multiple of fixedInternalStepSize to the
    FMU: the scene is valid, validate says what will happen, and the FMU's own answer decides (this
    one refuses: the run ends with its message)."""
    data = scene(conformance_fmus, {"fixed": ("FixedStep", {"step": 0.003})}, record={"fixed": ["x"]},
                 duration=0.006)
    loaded = scene_from_dict(data, tmp_path)
    assert loaded.components["fixed"].step == Fraction(3, 1000)
    assert loaded.notes == ["[fmu.fixed] step: 0.003 s is not a whole multiple of this FMU's fixed internal step "
                            "0.002 s (fixedInternalStepSize); FMI 3.0 leaves such a step to the FMU, so it is passed "
                            "on as it is: the FMU may cover it as it can or refuse it (then use step = 0.002 or "
                            "step = 0.004)"]
    summary, _ = run_scene(loaded, tmp_path / "results", progress=False)
    assert summary["status"] == "failed"
    assert "communication step 0.0030000000000000001 s is not a whole multiple of the fixed internal step 0.002 s" \
        in summary["error"]


def test_the_project_fmus_keep_their_internal_step_rule(contact_fmu, tmp_path):
    """FMUs with an internal_step parameter: the scene's step is their rate (unchanged)."""
    contact = contact_fmu
    data = {"fmu": {"contact": {"path": str(contact), "step": 0.002, "parameters": {"internal_step": 0.001}}}}
    with pytest.raises(SceneError, match="internal_step = 0.001 differs from step = 0.002"):
        scene_from_dict(data, tmp_path)
    assert scene_from_dict({"fmu": {"contact": {"path": str(contact), "step": 0.002}}}, tmp_path) \
        .components["contact"].parameters["internal_step"] == 0.002


# -- scenes: the real master -----------------------------------------------------------------------
def _run(data, out: Path) -> dict:
    summary, _ = run_scene(scene_from_dict(data, out), out / "results", progress=False)
    assert summary["status"] == "completed", summary["error"]
    return summary


def conformance_run_data(conformance_fmus, hosting: str) -> dict:
    return scene(conformance_fmus, {
        "a": ("Types", {"step": 0.01, "parameters": {"label": "conformance", "blob": "00ff10", "mode": "Fast"}}),
        "b": ("Types", {"step": 0.01}),
        "ramp": ("Ramp", {"step": 0.004}),             # not its default step (0.01): any step is allowed
        "fixed": ("FixedStep", {"step": 0.004}),       # two internal steps per call
        "structural": ("Structural", {"parameters": {"n": 4, "gain": 0.5}}),
    }, connections=[("a.count", "b.x"), ("a.small", "b.n"), ("a.mode_out", "b.mode"), ("a.distance", "b.position")],
        record={"a": ["count", "flag", "mode_out", "label_length", "blob_sum"],
                "b": ["x_echo", "n_echo", "mode_out"],
                "ramp": ["y", "h_last", "calls"], "fixed": ["x", "steps"], "structural": ["v", "configurations"]},
        hosting=hosting)


@pytest.mark.parametrize("hosting", ["in-process", "out-of-process"])
def test_third_party_fmus_run_in_the_master_with_their_exact_outputs(conformance_fmus, tmp_path, hosting):
    _run(conformance_run_data(conformance_fmus, hosting), tmp_path)
    results = tmp_path / "results"
    base = 500  # ticks per second: lcm of 1/100 s, 1/250 s and the duration's 1/10 s

    t, a = read_stream(results / "a.csv")
    k = np.arange(11)
    assert t.tolist() == (k / 100).tolist()
    assert a["count"].tolist() == k.tolist() and a["flag"].tolist() == (k % 2).tolist()
    assert set(a["mode_out"]) == {3.0} and set(a["label_length"]) == {11.0} and set(a["blob_sum"]) == {271.0}

    # gauss-seidel: b's step [t, t + h] sees a's outputs at t + h, carried exactly across the types
    t, b = read_stream(results / "b.csv")
    steps = k[1:]
    assert b["x_echo"][1:].tolist() == steps.astype(float).tolist()          # Int32 -> Float64
    assert b["n_echo"][1:].tolist() == (steps % 100).tolist()                # Int8 -> Int32
    assert b["mode_out"][1:].tolist() == [3.0] * 10                          # Enumeration -> Enumeration

    # Ramp at 4 ms (its default is 10 ms): y = (t + h)^2 with the master's exact times t = tick / base
    t, ramp = read_stream(results / "ramp.csv")
    assert len(t) == 26
    for j in range(1, 26):
        start, h = (2 * (j - 1)) / base, 2 / base
        assert ramp["y"][j] == (start + h) * (start + h) and ramp["h_last"][j] == h and ramp["calls"][j] == j

    t, fixed = read_stream(results / "fixed.csv")
    assert fixed["steps"].tolist() == [2.0 * j for j in range(26)]
    assert fixed["x"].tolist() == [fixed_step_x(2 * j) for j in range(26)]

    # a structural parameter set through the scene: the array has its new size, set in Configuration Mode
    t, structural = read_stream(results / "structural.csv")
    assert set(structural) == {"v[0]", "v[1]", "v[2]", "v[3]", "configurations"}
    assert set(structural["configurations"]) == {1.0}
    for j in range(1, len(t)):
        end = (5 * (j - 1)) / base + 5 / base
        assert [structural[f"v[{i}]"][j] for i in range(4)] == [0.5 * (i + 1) * end for i in range(4)]


def test_third_party_results_do_not_depend_on_hosting(conformance_fmus, tmp_path):
    for hosting in ("in-process", "out-of-process"):
        _run(conformance_run_data(conformance_fmus, hosting), tmp_path / hosting)
    for name in ("a", "b", "ramp", "fixed", "structural"):
        local = (tmp_path / "in-process" / "results" / f"{name}.csv").read_bytes()
        assert local == (tmp_path / "out-of-process" / "results" / f"{name}.csv").read_bytes(), name


def test_terminate_simulation_ends_the_run(conformance_fmus, tmp_path):
    data = scene(conformance_fmus, {"term": ("Terminator", {"step": 0.01, "parameters": {"stop_at": 0.05}}),
                        "ramp": ("Ramp", {"step": 0.01})},
                 record={"term": ["y"], "ramp": ["calls"]}, duration=1.0)
    summary, text = run_scene(scene_from_dict(data, tmp_path), tmp_path / "results", progress=False)
    assert summary["status"].startswith("terminated"), summary
    assert "term" in text and "0.05" in text
    assert summary["error"] is None or "term" in str(summary["error"])
    t, term = read_stream(tmp_path / "results" / "term.csv")
    assert t[-1] == 0.05 and term["y"][-1] == 0.05
    assert Fraction(summary["simulated_time_s"]).limit_denominator(1000) == Fraction(1, 20)

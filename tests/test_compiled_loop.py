"""The master's compiled loop (orchestration/compiled_loop.py, .c) against the Python path.

The compiled loop runs stretches of in-process FMU steps in C from a plan the Python master makes;
it must give the same run as the Python path, to the bit: every recorded row, every surface frame,
the summary's statistics and the final outputs. Each test runs the same scene both ways with the
real FMUs and the real master, and checks that the compiled loop really made the steps (a loop
that quietly stepped nothing would pass the comparison).
"""
from __future__ import annotations

import json
import math
from fractions import Fraction
from pathlib import Path

import pytest
from hypothesis import assume, event, given, note, settings
from hypothesis import strategies as st

from conformance_fmus import build_all
from orchestration.run.simulation import Simulation
from orchestration.observers.recorder import read_stream
from orchestration.scene.model import SceneError
from orchestration.scene.loading import load_scene, scene_from_dict
from orchestration.plan.transitions import Average
from project import entry, shipped_scenes

STATISTICS = ("peaks", "energy", "operator_warnings")


def _run(scene, out: Path, compiled: bool, **options):
    simulation = Simulation(scene, out, progress=False, plots=False, compiled_loop=compiled, **options)
    summary = simulation.run()
    return simulation, summary


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != "summary.json"}


def _same_run(scene, tmp_path: Path, **options):
    """Run ``scene`` compiled and in Python; assert the same results; return both simulations and summaries."""
    compiled, compiled_summary = _run(scene, tmp_path / "compiled", True, **options)
    python, python_summary = _run(scene, tmp_path / "python", False, **options)
    assert compiled_summary["status"] == python_summary["status"]
    assert compiled_summary["error"] == python_summary["error"]
    compiled_files, python_files = _files(tmp_path / "compiled"), _files(tmp_path / "python")
    assert sorted(compiled_files) == sorted(python_files)
    for name, data in compiled_files.items():
        assert data == python_files[name], f"{name} differs"
    for key in STATISTICS:
        assert compiled_summary.get(key) == python_summary.get(key), key
    for name, comp in compiled_summary["components"].items():
        assert comp["steps"] == python_summary["components"][name]["steps"], name
    for name, outputs in compiled.final_outputs.items():
        for port, value in outputs.items():
            assert value.tobytes() == python.final_outputs[name][port].tobytes(), f"{name}.{port}"
    assert python.algorithm.compiled_loop is None
    return (compiled, compiled_summary), (python, python_summary)


def _in_process_steps(simulation, summary) -> int:
    return sum(c["steps"] for name, c in summary["components"].items() if c["hosting"] == "in-process"
               and name in {m.comp.name for m in simulation.algorithm.compiled_loop.members.values()})


#: shipped scene -> the simulated seconds both paths run it for; None: nothing for the compiled loop
#: to run (virtual_wall: its device plant, a block of the master, steps with the contact FMU every
#: millisecond, so no stretch of FMU steps is left to compile). Every shipped scene has an entry.
COMPARED = {"aaa_endovascular": 1.0, "catheter_tube": 1.5, "tissue_indentation": 0.5, "virtual_wall": None}


# every shipped scene but those with nothing to compile (one without an entry fails, asking for it)
@pytest.mark.parametrize("scene_name", [name for name in shipped_scenes() if name not in COMPARED or COMPARED[name]])
def test_the_compiled_loop_gives_the_python_paths_run_bit_for_bit(fmus_in_repo, scene_name, tmp_path):
    duration = entry(COMPARED, scene_name, "COMPARED of tests/test_compiled_loop.py")
    scene = load_scene(scene_name, {"duration": duration})
    (compiled, summary), _ = _same_run(scene, tmp_path)
    assert summary["status"] == "completed"
    loop = compiled.algorithm.compiled_loop
    assert loop is not None and loop.members
    made = _in_process_steps(compiled, summary)
    # all but the steps at the edges of a stretch (a stretch needs two steps or more) run compiled
    assert loop.steps >= 0.95 * made, (loop.steps, made)


def test_the_default_scene_with_every_fmu_in_this_process(fmus_in_repo, tmp_path):
    """In process, the 30 Hz tissue steps in the program too: it reads the contact forces through an
    average, whose window the program sums and divides when the tissue steps. Its stretches then run
    whole hyperperiods (100 ms) of all three FMUs, each the same program."""
    scene = load_scene("aaa_endovascular", {"duration": 0.5})
    (compiled, summary), _ = _same_run(scene, tmp_path, hosting="in-process")
    loop = compiled.algorithm.compiled_loop
    assert {m.comp.name for m in loop.members.values()} == {"tissue", "catheter", "contact"}
    assert loop.steps >= 0.95 * sum(c["steps"] for c in summary["components"].values())
    period_steps = 3 + 100 + 100  # of the tissue, the catheter and the contact in 100 ms
    assert loop.steps >= period_steps * loop.stretches >= period_steps, (loop.steps, loop.stretches)
    assert len(loop._templates) <= 2  # the program of a stretch at the start of a hyperperiod, and the last one


def _tube_scene(tmp_path: Path, insertion: list[float], times: list[float]) -> Path:
    text = (Path(__file__).resolve().parent.parent / "scenes" / "catheter_tube.toml").read_text()
    text = text.replace('outputs = { insertion = [0.06, 0.06, 0.09, 0.09]',
                        f'outputs = {{ insertion = {insertion}')
    text = text.replace("times = [0.0, 0.2, 2.2, 3.0]", f"times = {times}")
    path = tmp_path / "tube.toml"  # its FMUs are looked up in fmus/
    path.write_text(text)
    return path


def test_a_call_that_fails_inside_a_stretch_is_reported_as_the_python_path_reports_it(fmus_in_repo, tmp_path):
    """The operator pushes the insertion out of the catheter's plausible range at about 0.52 s:
    fmi3SetFloat64 fails in the middle of a stretch. The same error (component, call, time, the
    FMU's reason) and the same rows up to it."""
    path = _tube_scene(tmp_path, [0.06, 0.06, 500.0, 500.0], [0.0, 0.5, 0.6, 3.0])
    scene = load_scene(path, {"duration": 1.0})
    (compiled, summary), _ = _same_run(scene, tmp_path)
    assert summary["status"] == "failed"
    assert "catheter" in summary["error"] and "fmi3SetFloat64(insertion)" in summary["error"]
    assert "plausible range" in summary["error"]
    t, _ = read_stream(tmp_path / "compiled" / "catheter.csv")
    assert 0.5 < t[-1] < 0.6  # the rows of every step before the failure are on disk
    assert compiled.algorithm.compiled_loop.steps > 900


def test_a_paced_run_is_paced_and_measured_by_the_compiled_loop(fmus_in_repo, tmp_path):
    """Real-time pacing in the program, a tick per stretch: the same results as the paced Python path;
    every haptic step waited for its time on the wall clock (none ended more than its own step early,
    so the run took its simulated time) and its lateness reached the summary."""
    scene = load_scene("catheter_tube", {"duration": 0.3})
    simulation, summary = _run(scene, tmp_path / "compiled", True, realtime=True)
    python, python_summary = _run(scene, tmp_path / "python", False, realtime=True)
    compiled_files, python_files = _files(tmp_path / "compiled"), _files(tmp_path / "python")
    assert compiled_files.keys() == python_files.keys()
    for name, data in compiled_files.items():
        assert data == python_files[name], f"{name} differs"
    loop = simulation.algorithm.compiled_loop
    haptic_steps = summary["components"]["catheter"]["steps"] + summary["components"]["contact"]["steps"]
    assert loop.steps >= 0.95 * haptic_steps  # paced in C, not stepped from Python
    assert loop.stretches >= 0.95 * 300  # a stretch per paced tick: the master's work goes in the waits
    deadlines = summary["deadlines"]
    assert deadlines["haptic_steps"] == python_summary["deadlines"]["haptic_steps"] == haptic_steps
    pacer = next(o for o in simulation.algorithm.observers if o.paces)
    assert len(pacer.lateness) == haptic_steps
    assert min(pacer.lateness) >= -0.001 - 1e-9  # a step starts at its time, so ends at most 1 ms early
    assert summary["wall_time_s"] >= 0.3 - 0.001


def test_a_paced_runs_clock_starts_at_its_first_paced_step_inside_a_program(fmus_in_repo, tmp_path):
    """With every FMU in process, the tissue's first step (its factorisations: most of its time in a
    short run) comes before the first haptic step in the same program. The clock starts at that
    haptic step, as the Python path starts it, so the first haptic steps are not late by the
    tissue's first step."""
    scene = load_scene("aaa_endovascular", {"duration": 0.1})
    simulation, summary = _run(scene, tmp_path, True, realtime=True, hosting="in-process")
    assert summary["status"] == "completed"
    assert "tissue" in {m.comp.name for m in simulation.algorithm.compiled_loop.members.values()}
    pacer = next(o for o in simulation.algorithm.observers if o.paces)
    tissue_busy = summary["components"]["tissue"]["busy_wall_s"]
    assert pacer.lateness[0] < 0.3 * tissue_busy, (pacer.lateness[:3], tissue_busy)


@pytest.fixture(scope="module")
def conformance_fmus(tmp_path_factory) -> dict[str, Path]:
    return build_all(tmp_path_factory.mktemp("conformance_fmus"))


def _component(fmu: Path, step: float, parameters: dict | None = None) -> dict:
    return {"path": str(fmu), "step": step, "parameters": parameters or {}}


def test_third_party_fmus_of_every_numeric_type_run_compiled(conformance_fmus, tmp_path):
    """FMUs written in C by others (tests/conformance): Int8 -> Int32 and Int32 -> Float64 inputs
    set from the samples of a stretch, Boolean, Int64 and enumeration outputs read; the same rows."""
    data = {
        "scene": {"name": "types", "duration": 0.2, "hosting": "in-process"},
        "fmu": {"a": _component(conformance_fmus["Types"], 0.01, {"label": "compiled", "blob": "00ff10",
                                                                   "mode": "Fast"}),
                "b": _component(conformance_fmus["Types"], 0.01),
                "ramp": _component(conformance_fmus["Ramp"], 0.004),
                "fixed": _component(conformance_fmus["FixedStep"], 0.004)},
        "connection": [{"from": "a.count", "to": "b.x"}, {"from": "a.small", "to": "b.n"},
                       {"from": "a.mode_out", "to": "b.mode"}, {"from": "a.distance", "to": "b.position"}],
        "record": {"a": ["count", "flag", "mode_out", "small"], "b": ["x_echo", "n_echo", "mode_out"],
                   "ramp": ["y", "calls"], "fixed": ["x", "steps"]},
    }
    scene = scene_from_dict(data, tmp_path)
    (compiled, summary), _ = _same_run(scene, tmp_path)
    assert summary["status"] == "completed"
    loop = compiled.algorithm.compiled_loop
    assert {"a", "b", "ramp", "fixed"} <= {m.comp.name for m in loop.members.values()}
    assert loop.steps >= 0.9 * sum(c["steps"] for c in summary["components"].values())
    t, b = read_stream(tmp_path / "compiled" / "b.csv")
    assert b["x_echo"][1:].tolist() == [float(k) for k in range(1, 21)]  # a's count, gauss-seidel, through C


@pytest.mark.parametrize("discard", [False, True])
def test_terminate_simulation_inside_a_stretch_ends_the_run_where_python_ends_it(conformance_fmus, tmp_path,
                                                                                  discard):
    data = {
        "scene": {"name": "terminator", "duration": 1.0, "hosting": "in-process"},
        "fmu": {"term": _component(conformance_fmus["Terminator"], 0.01, {"stop_at": 0.25, "discard": discard}),
                "ramp": _component(conformance_fmus["Ramp"], 0.01)},
        "record": {"term": ["y"], "ramp": ["calls"]},
    }
    scene = scene_from_dict(data, tmp_path)
    (compiled, summary), _ = _same_run(scene, tmp_path)
    assert summary["status"] == "terminated"
    assert summary["simulated_time_s"] == pytest.approx(0.25)
    assert compiled.algorithm.compiled_loop.steps > 20
    t, term = read_stream(tmp_path / "compiled" / "term.csv")
    assert t[-1] == 0.25 and term["y"][-1] == 0.25
    assert json.loads((tmp_path / "compiled" / "summary.json").read_text())["status"] == "terminated"


def test_a_64_bit_output_beyond_float64_is_refused_as_the_python_path_refuses_it(conformance_fmus, tmp_path):
    data = {
        "scene": {"name": "wide", "duration": 0.1, "hosting": "in-process"},
        "fmu": {"a": _component(conformance_fmus["Types"], 0.01, {"big_offset": 2 ** 53 - 5}),
                "ramp": _component(conformance_fmus["Ramp"], 0.01)},
        "record": {"a": ["big"], "ramp": ["calls"]},
    }
    scene = scene_from_dict(data, tmp_path)
    (compiled, summary), _ = _same_run(scene, tmp_path)
    assert summary["status"] == "failed" and "beyond 2**53" in summary["error"], summary["error"]
    assert "fmi3GetInt64(big)" in summary["error"] and "t = 0.06" in summary["error"]
    assert compiled.algorithm.compiled_loop.steps >= 8  # the five steps of each before, in stretches
    t, a = read_stream(tmp_path / "compiled" / "a.csv")
    assert a["big"].tolist()[-1] == 2 ** 53 and t[-1] == 0.05


# -- random multirate scenes of third-party FMUs -----------------------------------------------------
STEPS_MS = (1, 2, 3, 4, 5, 6, 10)


@st.composite
def ramp_chains(draw):
    """Two to four Ramp FMUs at random rates, each one's y or integral into the next one's u through a
    random transition and ordering, perhaps a jacobi loop back to the first, perhaps one in a
    worker, sometimes paced in real time; scenes the checks refuse are rejected."""
    n = draw(st.integers(2, 4))
    steps = [draw(st.sampled_from(STEPS_MS)) for _ in range(n)]
    worker = draw(st.one_of(st.none(), st.integers(0, n - 1))) if draw(st.booleans()) and draw(st.booleans()) else None
    connections = []
    for i in range(1, n):
        connections.append({"from": f"r{i - 1}.{draw(st.sampled_from(['y', 'integral']))}", "to": f"r{i}.u",
                            # hold (between two members) most often: the compiled loop's own routing
                            "transition": draw(st.sampled_from(["hold", "hold", "hold", "interpolate", "extrapolate",
                                                                "average"])),
                            "ordering": draw(st.sampled_from(["jacobi", "gauss-seidel"]))})
    if draw(st.booleans()):
        connections.append({"from": f"r{n - 1}.y", "to": "r0.u", "transition": "hold", "ordering": "jacobi"})
    lcm = math.lcm(*steps)
    duration = Fraction(lcm * draw(st.integers(1, max(1, 120 // lcm))), 1000)
    paced = draw(st.integers(0, 3)) == 0  # (a paced run takes its duration on the wall clock)
    return steps, connections, worker, duration, paced


@settings(deadline=None)
@given(case=ramp_chains())
def test_random_multirate_scenes_run_compiled_as_in_python(conformance_fmus, tmp_path_factory, case):
    steps, connections, worker, duration, paced = case
    note(repr(case))
    fmus = {f"r{i}": {"path": str(conformance_fmus["Ramp"]), "step": Fraction(ms, 1000).limit_denominator()}
            for i, ms in enumerate(steps)}
    for i, table in enumerate(fmus.values()):
        table["step"] = str(table["step"])
        if i == worker:
            table["hosting"] = "out-of-process"
    data = {"scene": {"name": "ramps", "duration": str(duration), "hosting": "in-process"}, "fmu": fmus,
            "connection": connections,
            "record": {name: ["y", "integral", "calls"] for name in fmus},
            "summary": {"peaks": [f"{name}.integral" for name in fmus]}}
    tmp = tmp_path_factory.mktemp("ramps")
    try:
        scene = scene_from_dict(data, tmp)
    except SceneError:
        assume(False)  # a transition these rates cannot take, an algebraic loop
    (compiled, summary), (_, python_summary) = _same_run(scene, tmp, realtime=paced)
    assert summary["status"] == "completed", summary["error"]
    if paced:  # every step of the fastest rate paced and measured, in C or in Python
        assert summary["deadlines"]["haptic_steps"] == python_summary["deadlines"]["haptic_steps"] > 0
        assert summary["wall_time_s"] >= float(duration) - min(steps) / 1000 - 1e-9
    loop = compiled.algorithm.compiled_loop
    event(f"compiled steps: {'none' if loop is None or not loop.steps else 'some'}{', paced' if paced else ''}")
    if loop is not None and loop.steps:
        averaged = any(isinstance(route.transition, Average) and route.producer.rank in loop.members
                       for member in loop.members.values() for route in member.routes)
        event(f"an average between two compiled FMUs: {'yes' if averaged else 'no'}")


def test_programs_made_afresh_for_each_stretch_give_the_same_run(fmus_in_repo, tmp_path, monkeypatch):
    """Past its budget of kept programs (a rate mix with many schedule states) each stretch gets a
    new program: the same run."""
    from orchestration.run import compiled_loop

    monkeypatch.setattr(compiled_loop, "PROGRAM_CACHE_OPS", 0)
    scene = load_scene("aaa_endovascular", {"duration": 0.5})
    (compiled, summary), _ = _same_run(scene, tmp_path)
    loop = compiled.algorithm.compiled_loop
    assert loop._cached_ops == 0 and loop.steps >= 0.95 * (summary["components"]["catheter"]["steps"]
                                                             + summary["components"]["contact"]["steps"])

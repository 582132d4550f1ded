"""Scene files: shipped scenes are valid; a broken scene lists every problem, with where and the fix."""
from __future__ import annotations

import math
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from fmu_build.paths import SCENE_DIR
from orchestration.scene.model import Scene, SceneError
from orchestration.scene.loading import load_scene, scene_from_dict
from project import entry, fmu_file_name, shipped_scenes

REPO = Path(__file__).resolve().parent.parent

# Most tests here load the shipped scenes, which find their FMUs in fmus/: built by tests/conftest.py.
pytestmark = pytest.mark.usefixtures("fmus_in_repo")

#: shipped scene -> the FMUs it models, no more: a scene that does without an FMU must not load it
SCENE_FMUS = {"aaa_endovascular": {"Tissue", "Contact", "Catheter"},
              "virtual_wall": {"Contact"},
              "tissue_indentation": {"Tissue", "Contact"},
              "catheter_tube": {"Catheter", "Contact"}}


def write_scene(tmp_path, fmus, body: str) -> Path:
    text = body
    for name, path in fmus.items():
        text = text.replace(f'"{name}.fmu"', f'"{path}"')
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("name", shipped_scenes())
def test_shipped_scenes_are_valid_and_model_only_what_they_need(name):
    scene = load_scene(name)
    fmus = {c.path.name for c in scene.components.values() if c.is_fmu}
    expected = {fmu_file_name(fmu) for fmu in entry(SCENE_FMUS, name, "SCENE_FMUS of tests/test_scene.py")}
    assert fmus == expected
    assert (SCENE_DIR / f"{name}.toml").exists()


def test_every_problem_is_reported_at_once(tmp_path, fmus):
    path = write_scene(tmp_path, fmus, '''
[scene]
duration = -1
[fmu.tissue]
path = "Tissue.fmu"
step = "1/30"
[fmu.tissue.parameters]
young_modulus = "soft"
poisons_ratio = 0.3
[fmu.contact]
path = "Contact.fmu"
step = 0.001
[fmu.catheter]
path = "Catheter.fmu"
step = 0
[fmu.ghost]
path = "Ghost.fmu"
[[connection]]
from = "tissue.surface_positions"
to = "contact.tissue_positions"
[[connection]]
from = "contact.tool_force"
to = "tissue.contact_force"
transition = "average"
ordering = "jacobi"
[[connection]]
from = "contact.penetration_depth"
to = "tissue.strain_energy"
[[connection]]
from = "contact.tip_force"
to = "nowhere.tip_force"
[[connection]]
from = "contact.tool_force"
to = "contact.tool_positions"
transition = "smooth"
[[connection]]
from = "contact.tissue_contact_force"
to = "tissue.contact_force"
transition = "average"
ordering = "jacobi"
''')
    with pytest.raises(SceneError) as info:
        load_scene(path)
    problems = info.value.problems
    expected = [
        ("[scene] duration", "positive"),
        ("[fmu.tissue] parameters.young_modulus", "Float64"),
        ("parameters.poisons_ratio", "poisson_ratio"),             # the fix lists the real names
        ("[fmu.catheter] step", "positive"),
        ("[fmu.ghost] path", "python -m orchestration build"),
        ("connection 1", "rate transition"),
        ("connection 2", "size mismatch"),
        ("connection 3", "output"),
        ("connection 4", "unknown component 'nowhere'"),
        ("connection 5", "'smooth'"),
        ("connection 6", "already driven"),
    ]
    for where, what in expected:
        assert any(where in p and what in p for p in problems), (where, what, problems)
    assert len(problems) == len(expected)


def test_size_mismatch_names_the_structural_parameter_to_set(tmp_path, fmus):
    path = write_scene(tmp_path, fmus, '''
[fmu.tissue]
path = "Tissue.fmu"
[fmu.tissue.parameters]
n_circumferential = 16
n_axial = 20
n_radial = 1
n_surface_nodes = 672
n_surface_triangles = 1344
[fmu.contact]
path = "Contact.fmu"
[[connection]]
from = "tissue.surface_positions"
to = "contact.tissue_positions"
transition = "hold"
''')
    with pytest.raises(SceneError) as info:
        load_scene(path)
    (problem,) = info.value.problems
    assert "size mismatch" in problem and "n_surface_nodes = 672" in problem


def test_unit_mismatch_and_algebraic_loop(tmp_path, fmus):
    path = write_scene(tmp_path, fmus, '''
[fmu.catheter]
path = "Catheter.fmu"
[fmu.contact]
path = "Contact.fmu"
[[connection]]
from = "catheter.tip_position"
to = "contact.tool_force_dummy"
[[connection]]
from = "catheter.bend_angle"
to = "catheter.insertion"
[[connection]]
from = "catheter.centerline_positions"
to = "contact.tool_positions"
[[connection]]
from = "contact.tip_force"
to = "catheter.tip_force"
[[connection]]
from = "contact.penetration_depth"
to = "catheter.rotation"
''')
    with pytest.raises(SceneError) as info:
        load_scene(path)
    text = "\n".join(info.value.problems)
    assert "no port 'tool_force_dummy'" in text
    assert "connects a component to itself" in text
    assert "unit mismatch, rad -> m" in text
    assert "unit mismatch, m -> rad" in text
    assert "algebraic loop" in text and "jacobi" in text


def test_cli_validate_reports_problems_without_a_traceback(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[scene]\nduration = 'x'\n[[connection]]\nfrom = 'a'\n")
    proc = subprocess.run([sys.executable, "-m", "orchestration", "validate", str(bad)],
                          capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert "duration" in proc.stderr and "component.port" in proc.stderr
    syntax = tmp_path / "syntax.toml"
    syntax.write_text("[scene\n")
    proc = subprocess.run([sys.executable, "-m", "orchestration", "validate", str(syntax)],
                          capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 2 and "TOML syntax error" in proc.stderr and "Traceback" not in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "orchestration", "validate", "no_such_scene"],
                          capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 2 and "aaa_endovascular" in proc.stderr


def test_overrides_replace_parameters_and_steps():
    scene = load_scene("tissue_indentation", {"tissue.step": "1/60", "contact.stiffness": 900.0, "duration": 0.5})
    assert scene.components["tissue"].step == pytest.approx(1 / 60) and scene.components["tissue"].step.denominator == 60
    assert scene.components["contact"].parameters["stiffness"] == 900.0
    assert float(scene.duration) == 0.5
    with pytest.raises(SceneError, match="no such component parameter"):
        load_scene("tissue_indentation", {"nobody.stiffness": 1.0})


def test_model_descriptions_carry_the_real_start_values(fmus):
    """The model descriptions carry the start values the FMUs start with (generated from the
    declarations)."""
    from orchestration.hosts.description import read_fmu

    contact = read_fmu(fmus["Contact"]).ports
    assert contact["stiffness"].start == 500.0 and contact["internal_step"].start == 0.001
    assert contact["tool_positions"].start in (0.0, [0.0] * 93)
    tissue = read_fmu(fmus["Tissue"]).ports
    assert tissue["young_modulus"].start == 1.044e6 and tissue["poisson_ratio"].start == 0.45


# -- issue 14: the findings of the hardening probes, one test each -----------------------------------
def shipped_data(name: str) -> dict:
    return tomllib.loads((SCENE_DIR / f"{name}.toml").read_text())


def _sound(scene) -> None:
    assert isinstance(scene, Scene) and scene.duration > 0


def _problems(data: dict, base_dir: Path = SCENE_DIR) -> list[str]:
    with pytest.raises(SceneError) as info:
        scene_from_dict(data, base_dir, SCENE_DIR / "x.toml")
    return info.value.problems


@pytest.mark.parametrize("key, value, expected", [
    ("scene", 5, "[scene]: must be a table"),
    ("fmu", "Tissue.fmu", "fmu: must be a table"),
    ("record", [1, 2], "[record]: must be a table"),
    ("summary", "x", "[summary]: must be a table"),
    ("source", 3.5, "source: must be a table"),
])
def test_a_value_where_a_table_is_expected_is_a_problem(key, value, expected):
    data = shipped_data("virtual_wall")
    data[key] = value
    assert any(p.startswith(expected) for p in _problems(data))


def test_parameters_that_are_not_a_table():
    data = shipped_data("virtual_wall")
    data["fmu"]["contact"]["parameters"] = [1, 2, 3]
    assert any(p.startswith("[fmu.contact] parameters: must be a table") for p in _problems(data))


def test_a_port_recorded_twice_is_refused_by_validate():
    data = shipped_data("virtual_wall")
    data["record"]["contact"].append("tool_force")
    assert "[record] contact: 'tool_force' is listed twice; list each port once" in _problems(data)


@pytest.mark.parametrize("name", ["../escape", "/tmp/abs", "a/b", "..", ".hidden", "", "a\\b", "x" * 101, 7])
def test_a_scene_name_is_a_name_not_a_path(name):
    data = shipped_data("virtual_wall")
    data["scene"]["name"] = name
    problems = _problems(data)
    assert len(problems) == 1 and problems[0].startswith("[scene] name: "), problems
    assert "--out" in problems[0] or "string" in problems[0]


@pytest.mark.parametrize("where, value", [("surface", "../../x"), ("figure", "/tmp/forces.png"),
                                          ("figure", "forces.svg")])
def test_files_the_recording_writes_stay_in_the_result_folder(where, value):
    data = shipped_data("aaa_endovascular")
    if where == "surface":
        data["record"]["surfaces"][0]["name"] = value
        expected = "[record] surfaces[0] name: "
    else:
        data["record"]["plots"][0]["file"] = value
        expected = "[record] plots[0] file: "
    assert any(p.startswith(expected) for p in _problems(data))


@pytest.mark.parametrize("step, fragment", [(1e9, "longer than 1 s"), (1e-9, "shorter than 1/1000000 s"),
                                            (-1, "must be positive"), ("abc", "is not a time")])
def test_implausible_steps_are_refused_with_the_limit(step, fragment):
    data = shipped_data("virtual_wall")
    data["block"]["device"]["step"] = step
    problems = _problems(data)
    assert any(p.startswith("[block.device] step: ") and fragment in p for p in problems), problems


def test_a_run_of_more_steps_than_the_limit_is_refused_naming_limit_and_longest_duration():
    data = shipped_data("virtual_wall")
    data["scene"]["duration"] = 6000.0  # 2 components at 1 kHz: 1.2e7 steps
    (problem,) = _problems(data)
    assert problem.startswith("[scene] duration: 6000 s means 1.2e+07 component steps")
    assert "limit of 1e+07 steps" in problem and "at most 5000 s" in problem
    data["scene"]["duration"] = 5000.0  # exactly the limit: accepted
    _sound(scene_from_dict(data, SCENE_DIR, SCENE_DIR / "x.toml"))


@pytest.mark.parametrize("value, fragment", [(math.nan, "not a finite number"), (math.inf, "not a finite number"),
                                             ("soft", "expects Float64")])
def test_fmu_parameters_are_checked_against_the_model_description(value, fragment):
    data = shipped_data("virtual_wall")
    data["fmu"]["contact"]["parameters"]["stiffness"] = value
    (problem,) = _problems(data)
    assert problem.startswith("[fmu.contact] parameters.stiffness: ") and fragment in problem


def test_integer_parameters_out_of_their_type_range_and_huge_array_sizes():
    data = shipped_data("virtual_wall")
    data["fmu"]["contact"]["parameters"]["n_tool_points"] = -1
    data["fmu"]["contact"]["parameters"]["compliance_force_lag"] = 2**40
    problems = _problems(data)
    assert any(p.startswith("[fmu.contact] parameters.n_tool_points: -1 is outside the range of UInt64")
               for p in problems), problems
    assert any(p.startswith("[fmu.contact] parameters.compliance_force_lag: 1099511627776 is outside the range "
                            "of Int32") for p in problems), problems
    data = shipped_data("virtual_wall")
    data["fmu"]["contact"]["parameters"]["n_surface_nodes"] = 10**9
    problems = _problems(data)
    assert any(p.startswith("[fmu.contact] parameters.n_surface_nodes: 1000000000 is more than 1000000")
               for p in problems), problems


def test_a_path_is_not_taken_for_a_shipped_scene_name(tmp_path):
    with pytest.raises(SceneError, match="scene file not found"):
        load_scene(tmp_path / "virtual_wall")


@pytest.mark.parametrize("key, value, fragment", [("n_circumferential", 32_000_000_000, "fewer n_circumferential"),
                                                  ("n_axial", 10**6, "fewer n_circumferential or n_axial")])
def test_a_rigid_surface_too_large_to_allocate_is_refused(key, value, fragment):
    # found by the fuzzer: a tube of 3.2e10 nodes was a MemoryError (238 GiB) instead of a problem
    data = shipped_data("catheter_tube")
    data["source"]["tube"][key] = value
    problems = _problems(data)
    assert any(p.startswith("[source.tube] the surface would have ") and fragment in p for p in problems), problems


def test_a_value_outside_the_declared_min_max_of_a_variable_is_a_problem():
    # The project's FMUs declare no min/max yet; an FMU that does has its range checked by validate.
    from orchestration.hosts.description import PortInfo
    from orchestration.scene.values import check_parameters

    ports = {"gain": PortInfo("gain", "parameter", "Float64", "fixed", minimum=0.0, maximum=10.0),
             "n": PortInfo("n", "parameter", "Int32", "fixed", minimum=1.0)}
    problems: list[str] = []
    check_parameters("[fmu.x]", {"gain": 11.0, "n": 0}, ports, problems)
    assert problems == ["[fmu.x] parameters.gain: 11.0 is outside the range the FMU declares for it, 0 to 10",
                        "[fmu.x] parameters.n: 0 is outside the range the FMU declares for it, 1 to inf"]
    problems.clear()
    check_parameters("[fmu.x]", {"gain": 10.0, "n": 1}, ports, problems)
    assert problems == []


@pytest.mark.parametrize("depth", [40, 900, 5000])
def test_deeply_nested_values_are_a_problem_not_a_recursion_error(tmp_path, depth):
    # 900 levels parse but would exhaust the recursion limit later; 5000 exhaust the TOML parser's
    path = tmp_path / "deep.toml"
    path.write_text('[scene]\nname = "x"\n[fmu.contact]\nparameters = { v = ' + "[" * depth + "]" * depth + " }\n")
    with pytest.raises(SceneError) as info:
        load_scene(path)
    (problem,) = info.value.problems
    assert "nested" in problem and "32 levels" in problem, problem


@pytest.mark.parametrize("section, component, key, value", [
    ("fmu", "contact", "parameters.stiffness", 10**400),
    ("block", "device", "mass", 10**400),
    ("block", "device", "initial_position", [10**400, 0, 0]),
    ("source", "operator", "times", [0, 10**400]),
])
def test_integers_no_float_holds_are_problems_not_overflow_errors(section, component, key, value):
    # TOML integers have no size limit: 10**400 made math.isfinite and numpy raise OverflowError
    data = shipped_data("virtual_wall")
    table = data[section][component]
    *parents, last = key.split(".")
    for part in parents:
        table = table[part]
    table[last] = value
    problems = _problems(data)
    assert any(p.startswith(f"[{section}.{component}] {key}") and "finite" in p for p in problems), problems


@pytest.mark.parametrize("key, value, fragment", [
    ("mass", 1e-300, "mass must be within 1e-10 to 1000"), ("mass", 1e4, "mass must be within 1e-10 to 1000"),
    ("damping", 1e300, "damping must be within 0 to 1e+06"),
    ("initial_position", [20.0, 0.0, 0.0], "initial_position must have a magnitude of at most 10 m"),
    ("initial_velocity", [0.0, 0.0, -1e3], "initial_velocity must have a magnitude of at most 100 m/s"),
])
def test_device_plant_values_that_cannot_be_meant_are_refused(key, value, fragment):
    # mass = 1e-300 kg ran to "completed" with NaN positions (F/m overflows the exact step)
    data = shipped_data("virtual_wall")
    data["block"]["device"][key] = value
    assert any(p.startswith(f"[block.device] {fragment}") for p in _problems(data))


@pytest.mark.parametrize("scene, source, key, value", [
    ("virtual_wall", "wall", "size", 1e300), ("virtual_wall", "wall", "center", [0.0, 1e5, 0.0]),
    ("catheter_tube", "tube", "radius", 20.0), ("catheter_tube", "tube", "end", [0.0, 0.0, -11.0]),
])
def test_rigid_surfaces_beyond_any_workspace_are_refused(scene, source, key, value):
    data = shipped_data(scene)
    data["source"][source][key] = value
    assert any(p.startswith(f"[source.{source}] {key} must be within 10 m") for p in _problems(data))


@pytest.mark.parametrize("surface, fragment", [
    ({"component": "contact", "positions": "stiffness", "triangles": "surface_triangles"},
     "[record] surfaces[0] positions: contact.stiffness is parameter Float64 scalar [N/m]; positions are numbers"),
    ({"component": "contact", "positions": "tissue_positions", "triangles": "tool_force"},
     "[record] surfaces[0] triangles: contact.tool_force is output Float64 3 [N]; triangles are integer node ids"),
    ({"component": "contact", "positions": "tissue_positions", "triangles": "surface_triangles",
      "point_data": ["tool_force"]}, "[record] surfaces[0] point_data: contact.tool_force holds 3 values"),
    ({"component": "wall", "positions": "positions", "triangles": "triangles"},
     "[record] surfaces[0]: wall is a continuous source, it has no steps to record frames at"),
    ({"component": "contact", "positions": "tissue_positions", "triangles": "surface_triangles", "name": "device"},
     "[record] surfaces[0] name: 'device' is already the name of another recorded file"),
])
def test_surfaces_validate_what_the_recording_needs(surface, fragment):
    # each of these passed validate and failed the run (a reshape error, a KeyError) or clashed with a file
    data = shipped_data("virtual_wall")
    data["record"]["surfaces"] = [surface]
    problems = _problems(data)
    assert any(p.startswith(fragment) for p in problems), problems


def test_a_surface_of_no_nodes_is_refused():
    data = shipped_data("virtual_wall")
    data["fmu"]["contact"]["parameters"]["n_surface_nodes"] = 0
    data["record"]["surfaces"] = [{"component": "contact", "positions": "tissue_positions",
                                   "triangles": "surface_triangles"}]
    assert any(p.startswith("[record] surfaces[0] positions: contact.tissue_positions is input Float64 0x3")
               for p in _problems(data))


def test_a_surface_of_the_right_shape_is_accepted():
    data = shipped_data("virtual_wall")
    data["record"]["surfaces"] = [{"component": "contact", "positions": "tissue_positions",
                                   "triangles": "surface_triangles", "name": "wall_seen_by_contact"}]
    scene = scene_from_dict(data, SCENE_DIR, SCENE_DIR / "x.toml")
    assert [s.name for s in scene.surfaces] == ["wall_seen_by_contact"]


@pytest.mark.parametrize("value", [[0.001], "1/30", True, 10**400, math.nan])
def test_internal_step_of_the_wrong_type_is_a_problem(value):
    # found by the scene fuzzer: internal_step = [list] was a TypeError in the step comparison
    data = shipped_data("virtual_wall")
    data["fmu"]["contact"]["parameters"]["internal_step"] = value
    problems = _problems(data)
    assert any(p.startswith("[fmu.contact] parameters.internal_step = ") and "remove the parameter" in p
               for p in problems), problems

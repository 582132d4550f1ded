"""Scene files: shipped scenes are valid; a broken scene lists every problem, with where and the fix."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from orchestration.scene import SCENE_DIR, SceneError, load_scene

REPO = Path(__file__).resolve().parent.parent
SHIPPED = ("aaa_endovascular", "virtual_wall", "tissue_indentation", "catheter_tube")


@pytest.fixture(scope="module")
def fmus(tissue_fmu, contact_fmu, catheter_fmu):
    return {"Tissue": tissue_fmu, "Contact": contact_fmu, "Catheter": catheter_fmu}


def write_scene(tmp_path, fmus, body: str) -> Path:
    text = body
    for name, path in fmus.items():
        text = text.replace(f'"{name}.fmu"', f'"{path}"')
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_scenes_are_valid_and_model_only_what_they_need(name):
    scene = load_scene(name)
    fmus = {c.path.name for c in scene.components.values() if c.is_fmu}
    expected = {"aaa_endovascular": {"Tissue.fmu", "Contact.fmu", "Catheter.fmu"},
                "virtual_wall": {"Contact.fmu"},
                "tissue_indentation": {"Tissue.fmu", "Contact.fmu"},
                "catheter_tube": {"Catheter.fmu", "Contact.fmu"}}[name]
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
    from orchestration.ports import read_fmu

    contact = read_fmu(fmus["Contact"]).ports
    assert contact["stiffness"].start == 500.0 and contact["internal_step"].start == 0.001
    assert contact["tool_positions"].start in (0.0, [0.0] * 93)
    tissue = read_fmu(fmus["Tissue"]).ports
    assert tissue["young_modulus"].start == 1.044e6 and tissue["poisson_ratio"].start == 0.45

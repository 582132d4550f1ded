"""The default scene exported as one FMU (``export SCENE --fmu``) gives the orchestrator's numbers in
three importers that could not use the project's FMUs themselves or that we did not write: FMPy's
``simulate_fmu``, a C importer without Python (the FMU's own runtime in its process, the scene's
FMUs nested in it), and Ecos (a C++ master that knows only scalars)."""
from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from fractions import Fraction

import numpy as np
import pytest
from fmpy import read_model_description, simulate_fmu
from fmpy.fmi1 import FMICallException
from fmpy.validation import validate_fmu

from ecos_host import ecos_available, run_in_ecos
from fuzz_hosts import ScriptHost, get_command, ports, set_command
from orchestration.app.scene_fmu import SceneFmuError, export_scene_fmu
from orchestration.scene.loading import load_scene
from project import REPO, scene_path

SCENE = "aaa_endovascular"
STEPS = 1700  # 1.7 s: past the first touch of the sac wall (about 1.5 s)
FORCE = [f"contact_tool_force_{i}" for i in range(3)]


@pytest.fixture(scope="module")
def scene(fmus_in_repo):
    return load_scene(SCENE)


@pytest.fixture(scope="module")
def scene_fmu(scene, tmp_path_factory):
    return export_scene_fmu(scene, tmp_path_factory.mktemp("scene_fmu") / f"{SCENE}.fmu")


@pytest.fixture(scope="module")
def orchestrator(fmus_in_repo, tmp_path_factory):
    """The orchestrator's run of the scene: the contact's and the catheter's recorded outputs per ms."""
    out = tmp_path_factory.mktemp("orchestrator") / "run"
    proc = subprocess.run([sys.executable, "-m", "orchestration", "run", str(scene_path(SCENE)), "--duration",
                           str(STEPS / 1000), "--out", str(out), "--quiet"], capture_output=True, text=True,
                          cwd=REPO, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    contact = np.genfromtxt(out / "contact.csv", delimiter=",", names=True)
    catheter = np.genfromtxt(out / "catheter.csv", delimiter=",", names=True)
    assert len(contact) == STEPS + 1
    force = np.stack([contact[f"tool_force{i}"] for i in range(3)], axis=1)
    assert np.abs(force).max() > 0.1  # the wall was touched
    return {"force": force, "warning": catheter["effort_warning"], "tip": catheter["tip_position2"]}


def operator_at(scene, k: int) -> dict[str, float]:
    """The operator's values for the FMU step k, [k h, (k + 1) h]: the script's at its end."""
    values = scene.components["operator"].new_block().evaluate((k + 1) / 1000)
    return {f"operator_{name}": float(np.ravel(value)[0]) for name, value in values.items()}


def test_the_scene_fmu_has_scalar_ports_and_validates(scene_fmu):
    assert validate_fmu(str(scene_fmu)) == []
    md = read_model_description(str(scene_fmu))
    assert float(md.coSimulation.fixedInternalStepSize) == 0.001
    assert md.coSimulation.canGetAndSetFMUstate is False
    assert all(not v.dimensions for v in md.modelVariables)  # masters without FMI 3 arrays take it
    names = {v.name: v for v in md.modelVariables}
    assert names["operator_insertion"].causality == "input" and names["operator_insertion"].unit == "m"
    assert names["contact_tool_force_0"].unit == "N" and names["catheter_effort_warning"].type == "Boolean"
    assert not any(v.causality == "structuralParameter" for v in md.modelVariables)
    with zipfile.ZipFile(scene_fmu) as archive:
        assert "FMU state cannot be saved" in archive.read("documentation/index.html").decode()
        inner = [n for n in archive.namelist() if n.startswith("resources/scene_fmu/fmus/")]
        assert len(inner) == 3
        for name in inner:  # the nested FMUs run in the scene FMU's interpreter: no runtime of their own
            with zipfile.ZipFile(archive.open(name)) as nested:
                assert "resources/runtime.zip" not in nested.namelist()


def test_fmpy_simulate_fmu_gives_the_orchestrators_haptic_force(scene, scene_fmu, orchestrator):
    result = simulate_fmu(str(scene_fmu), stop_time=STEPS / 1000, step_size=0.001, output_interval=0.001,
                          input=_operator_signals(scene), output=FORCE + ["catheter_effort_warning"])
    assert len(result) == STEPS + 1
    force = np.stack([result[name] for name in FORCE], axis=1)
    # FMPy adds up its communication points and interpolates the inputs there: round-off in the input
    assert np.abs(force - orchestrator["force"]).max() < 1e-12
    assert np.array_equal(result["catheter_effort_warning"].astype(float), orchestrator["warning"])


FOREIGN_SIMULATE = r"""
import json, sys
import numpy as np
from fmpy import simulate_fmu
fmu, signals, out, outputs = sys.argv[1], sys.argv[2], sys.argv[3], json.loads(sys.argv[4])
messages = []
result = simulate_fmu(fmu, stop_time=1.7, step_size=0.001, output_interval=0.001, input=np.load(signals),
                      output=outputs, debug_logging=True, logger=lambda *args: messages.append(str(args[-1])))
np.save(out, result, allow_pickle=False)
print(json.dumps(messages))
"""


def _operator_signals(scene) -> np.ndarray:
    rows = [(k / 1000, *operator_at(scene, k).values()) for k in range(STEPS + 1)]
    return np.array(rows, dtype=[("time", np.float64), ("operator_insertion", np.float64),
                                 ("operator_rotation", np.float64)])


@pytest.mark.slow
def test_fmpy_in_a_bare_environment_runs_the_scene_in_the_fmus_helper_process(scene, scene_fmu, orchestrator, tmp_path):
    """FMPy alone (none of the packages the model needs): the FMU starts its helper process on the
    runtime it carries and runs the scene's FMUs in it."""
    from test_foreign_python import _clean_environment, foreign_python

    python = foreign_python("fmpy-only")
    np.save(tmp_path / "signals.npy", _operator_signals(scene), allow_pickle=False)
    proc = subprocess.run([str(python), "-c", FOREIGN_SIMULATE, str(scene_fmu), str(tmp_path / "signals.npy"),
                           str(tmp_path / "result.npy"), json.dumps(FORCE)], capture_output=True, text=True,
                          timeout=900, env=_clean_environment())
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert any("runs in a helper process" in m for m in json.loads(proc.stdout.strip().splitlines()[-1]))
    result = np.load(tmp_path / "result.npy", allow_pickle=False)
    force = np.stack([result[name] for name in FORCE], axis=1)
    assert np.abs(force - orchestrator["force"]).max() < 1e-12


def test_a_c_importer_without_python_gives_the_orchestrators_numbers_bit_for_bit(scene, scene_fmu, orchestrator,
                                                                                 c_host, tmp_path):
    """The scene FMU's carried Python in the importer's process, the scene's FMUs loaded into it."""
    p = ports(scene_fmu)
    host = ScriptHost("c", scene_fmu, tmp_path, c_host, call_timeout=600)
    try:
        def inputs(k):
            return [set_command(p[name], value) for name, value in operator_at(scene, k).items()]

        reads = [get_command(p[name]) for name in FORCE]
        commands = ["instantiate", *inputs(-1), "enter_init", "exit_init", *reads]
        for k in range(STEPS):
            commands += [*inputs(k), f"step {k / 1000!r} 0.001", *reads]
        answers = host.run(commands + ["terminate", "free"])  # one case: one instance
    finally:
        host.close()
    assert all(a.status == 0 for a in answers), [a for a in answers if a.status != 0][:3]
    force = [float(a.values[0]) for a in answers if a.command.startswith("get ")]
    assert np.array(force).reshape(-1, 3).tobytes() == orchestrator["force"].tobytes()


def test_ecos_gives_the_orchestrators_haptic_force(scene, scene_fmu, orchestrator):
    reason = ecos_available()
    if reason is not None:
        pytest.skip(reason)
    inputs = {name: (lambda t, name=name: operator_at(scene, round(t * 1000))[name])
              for name in ("operator_insertion", "operator_rotation")}
    result = run_in_ecos(scene_fmu, step=0.001, stop_time=STEPS / 1000, inputs=inputs,
                         outputs=FORCE + ["catheter_effort_warning"], timeout=900)
    force = np.stack([result[name] for name in FORCE], axis=1)
    assert force.shape == orchestrator["force"].shape
    assert force.tobytes() == orchestrator["force"].tobytes()
    assert np.array_equal(result["catheter_effort_warning"].astype(float), orchestrator["warning"])


def test_export_refuses_what_it_cannot_make_with_the_fix(scene, tmp_path):
    with pytest.raises(SceneFmuError, match="contact.nothing: no output of an FMU of the scene"):
        export_scene_fmu(scene, tmp_path / "x.fmu", outputs=["contact.nothing"])
    with pytest.raises(SceneFmuError, match="tissue.surface_positions holds 8064 values, more than the 64"):
        export_scene_fmu(scene, tmp_path / "x.fmu", outputs=["tissue.surface_positions"])
    with pytest.raises(SceneFmuError, match="ends in .fmu"):
        export_scene_fmu(scene, tmp_path / "x.zip")
    (tmp_path / "taken.fmu").write_bytes(b"a user's file")
    with pytest.raises(SceneFmuError, match="exists; give --force"):
        export_scene_fmu(scene, tmp_path / "taken.fmu")
    assert (tmp_path / "taken.fmu").read_bytes() == b"a user's file"


def test_the_scene_fmu_refuses_to_save_its_state_saying_why(scene_fmu):
    from fmu_harness import fmu_instance

    with fmu_instance(scene_fmu) as fmu:
        fmu.slave.enterInitializationMode()
        fmu.slave.exitInitializationMode()
        fmu.slave.doStep(0.0, 0.001)
        with pytest.raises(FMICallException):
            fmu.slave.getFMUState()
        assert "cannot save its state" in " ".join(m for _, m in fmu.messages)


def test_an_input_a_component_of_the_scene_refuses_is_refused_with_its_reason(scene_fmu):
    """The importer hears the scene's component (the Catheter's plausible range of the insertion),
    not "an internal error" of the scene FMU."""
    from fmu_harness import fmu_instance

    with fmu_instance(scene_fmu) as fmu:
        fmu.slave.enterInitializationMode()
        fmu.slave.exitInitializationMode()
        fmu.slave.doStep(0.0, 0.001)
        fmu.set("operator_insertion", 1000.0)  # a kilometre of catheter: a unit mistake
        with pytest.raises(FMICallException):
            fmu.slave.doStep(0.001, 0.001)
        text = " ".join(m for _, m in fmu.messages)
    assert "catheter" in text and "insertion" in text and "no catheter" in text, text
    assert "internal error" not in text


def test_a_step_beyond_the_horizon_is_refused_saying_so(scene, tmp_path):
    """The FMU runs the scene for the horizon it was exported with (30 minutes by default, rounded up
    to whole steps of every component); a master that asks for more is told, not given a silent end."""
    from fmu_harness import fmu_instance

    short = export_scene_fmu(scene, tmp_path / "short.fmu", horizon=Fraction(1, 100))
    with fmu_instance(short) as fmu:
        fmu.slave.enterInitializationMode()
        fmu.slave.exitInitializationMode()
        for k in range(100):  # the horizon: 1/100 s rounded up to whole steps of 1/30 s and 1 ms, 1/10 s
            fmu.slave.doStep(k / 1000, 0.001)
        with pytest.raises(FMICallException):
            fmu.slave.doStep(0.1, 0.001)
        assert "beyond the 1/10 s this FMU was exported to run" in " ".join(m for _, m in fmu.messages)

"""The default scene exported as one FMU (``export SCENE --fmu``), embedded in an FMU container of
Renault's fmu-manipulation-toolbox 2.0 (``fmu_manipulation_toolbox.assembly``, what its
``fmucontainer`` command runs): an FMI 3.0 container with its own 1 ms step that exposes the
operator's two inputs, the haptic force and the effort warning as its own ports.

What the container adds: nothing to the numbers. Its C runtime (``container.so`` of the wheel,
``container/container.c`` on GitHub) keeps the container's ports in its own buffers; at each of its
internal 1 ms steps it sets the buffered inputs on the embedded FMU, calls the embedded FMU's
``fmi3DoStep`` over the same 1 ms, and reads the outputs back into its buffers, which the
container's getters return. With one embedded FMU and the container's step equal to the scene
FMU's, an input set before the container's step ``[t, t + h]`` reaches the scene FMU before that
same step, and the force read after it is the scene FMU's at ``t + h``: no step of delay, no
conversion (Float64 to Float64, Boolean to Boolean). The container drops the ports' units and
declares ``canHandleVariableCommunicationStepSize`` (it sub-steps a master's longer steps in 1 ms
steps, the inputs held); its step is in its ``DefaultExperiment`` and its ``container.txt``.

Measured over 1.7 s (the first touch of the sac wall included): under FMPy's ``simulate_fmu`` the
container gives the scene FMU's own numbers under the same master bit for bit (so the orchestrator's
within FMPy's input round-off, 1e-12 N); under a master that sets the operator's values exactly,
the orchestrator's force bit for bit."""
from __future__ import annotations

import json
import logging
import zipfile
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("fmu_manipulation_toolbox.assembly",
                    reason="fmu_manipulation_toolbox (Renault's FMU containers) is not installed: "
                           "pip install -e '.[test]'")

from fmpy import read_model_description, simulate_fmu  # noqa: E402
from fmpy.validation import validate_fmu  # noqa: E402
from fmu_manipulation_toolbox.assembly import Assembly  # noqa: E402

from fmu_harness import fmu_instance  # noqa: E402
from test_scene_fmu import FORCE, STEPS, _operator_signals, operator_at  # noqa: E402
# the scene, its FMU and the orchestrator's numbers: test_scene_fmu's fixtures (module-scoped: made again here)
from test_scene_fmu import orchestrator, scene, scene_fmu  # noqa: E402,F401

OPERATOR = ["operator_insertion", "operator_rotation"]
OUTPUTS = [*FORCE, "catheter_effort_warning"]
CONTAINER = "scene_container"


def build_container(scene_fmu: Path, directory: Path) -> tuple[Path, list[str]]:
    """The toolbox's container around the scene FMU, built as ``fmucontainer -fmu-directory DIR
    -container scene_container.json -fmi 3`` builds it, in ``directory``: the container's path and
    the errors the toolbox logged (it logs some faults, an unconnected input or a port it cannot
    expose, without raising)."""
    (directory / scene_fmu.name).symlink_to(scene_fmu)  # the toolbox takes its FMUs from one directory
    description = {
        "name": f"{CONTAINER}.fmu",
        "step_size": 0.001,
        "auto_link": False, "auto_input": False, "auto_output": False,  # only the ports named here
        "fmu": [scene_fmu.name],
        "input": [[name, scene_fmu.name, name] for name in OPERATOR],
        "output": [[scene_fmu.name, name, name] for name in OUTPUTS],
    }
    (directory / f"{CONTAINER}.json").write_text(json.dumps(description, indent=2))

    errors: list[str] = []

    class Errors(logging.Handler):
        def emit(self, record):
            errors.append(record.getMessage())

    handler = Errors(level=logging.ERROR)
    toolbox_logger = logging.getLogger("fmu_manipulation_toolbox")
    toolbox_logger.addHandler(handler)
    try:
        Assembly(f"{CONTAINER}.json", fmu_directory=directory).make_fmu(fmi_version=3)
    finally:
        toolbox_logger.removeHandler(handler)
    return directory / f"{CONTAINER}.fmu", errors


@pytest.fixture(scope="module")
def container(scene_fmu, tmp_path_factory):
    path, errors = build_container(scene_fmu, tmp_path_factory.mktemp("toolbox_container"))
    assert errors == []
    return path


def _outputs(result) -> tuple[np.ndarray, np.ndarray]:
    return np.stack([result[name] for name in FORCE], axis=1), result["catheter_effort_warning"].astype(float)


def test_the_container_is_fmi3_with_the_scene_fmus_ports_and_a_1_ms_step(container, scene_fmu):
    assert validate_fmu(str(container)) == []
    md = read_model_description(str(container))
    assert md.fmiVersion == "3.0" and md.generationTool == "FMUContainer-2.0"
    assert md.coSimulation.modelIdentifier == CONTAINER
    assert float(md.defaultExperiment.stepSize) == 0.001
    assert {v.name: (v.type, v.causality) for v in md.modelVariables} == {
        "time": ("Float64", "independent"),
        "operator_insertion": ("Float64", "input"), "operator_rotation": ("Float64", "input"),
        **{name: ("Float64", "output") for name in FORCE},
        "catheter_effort_warning": ("Boolean", "output"),
    }
    with zipfile.ZipFile(container) as archive, zipfile.ZipFile(scene_fmu) as scene_archive:
        assert f"binaries/x86_64-linux/{CONTAINER}.so" in archive.namelist()  # the toolbox's runtime
        # the scene FMU inside, unpacked as exported; the container's own step, 1 ms
        assert archive.read("resources/00/modelDescription.xml") == scene_archive.read("modelDescription.xml")
        assert "# Internal time step in seconds\n0.001\n" in archive.read("resources/container.txt").decode()


def test_fmpy_simulate_fmu_through_the_container_gives_the_orchestrators_haptic_force(
        scene, scene_fmu, container, orchestrator):
    """No step of delay: FMPy's run of the container is its run of the scene FMU, bit for bit."""
    options = dict(stop_time=STEPS / 1000, step_size=0.001, output_interval=0.001, input=_operator_signals(scene),
                   output=OUTPUTS)
    force, warning = _outputs(simulate_fmu(str(container), **options))
    direct_force, direct_warning = _outputs(simulate_fmu(str(scene_fmu), **options))
    assert force.shape == orchestrator["force"].shape == (STEPS + 1, 3)
    assert force.tobytes() == direct_force.tobytes() and np.array_equal(warning, direct_warning)
    # FMPy adds up its communication points and interpolates the inputs there: round-off in the input,
    # with the container as without it
    assert np.abs(force - orchestrator["force"]).max() < 1e-12
    assert np.array_equal(warning, orchestrator["warning"])
    # a step of delay would show: at the wall the force changes by more than 1 mN per ms
    assert np.abs(force[1:] - orchestrator["force"][:-1]).max() > 1e-3


def test_a_master_setting_the_operators_values_exactly_gets_the_orchestrators_force_bit_for_bit(
        scene, container, orchestrator):
    """The operator's values set before each container step [k h, (k + 1) h] (the script's at its end,
    as the C importer of test_scene_fmu sets them), the force read after it. FMPy raises on a call
    that returns fmi3Discard or worse (the container's log is no guide: it sends its banner and
    "Solver configure...." with the status fmi3Warning / fmi3Error)."""
    with fmu_instance(container) as fmu:
        force_vrs = [vr for name in FORCE for vr in fmu.vr(name)]

        def step_inputs(k):
            for name, value in operator_at(scene, k).items():
                fmu.set(name, value)

        step_inputs(-1)
        fmu.initialize()
        force = [fmu.slave.getFloat64(force_vrs)]
        warning = [fmu.slave.getBoolean(fmu.vr("catheter_effort_warning"))[0]]
        for k in range(STEPS):
            step_inputs(k)
            fmu.slave.doStep(k / 1000, 0.001)
            force.append(fmu.slave.getFloat64(force_vrs))
            warning.append(fmu.slave.getBoolean(fmu.vr("catheter_effort_warning"))[0])
    assert np.array(force).tobytes() == orchestrator["force"].tobytes()
    assert np.array_equal(np.array(warning, dtype=float), orchestrator["warning"])

"""The built Catheter.fmu: FMI conformance, ports, same answers as the model, bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest
from fmpy import read_model_description, simulate_fmu
from fmpy.validation import validate_fmu

from catheter_fmu.model import CatheterModel, CatheterParameters
from fmu_harness import fmu_instance

STEP = 0.001


def test_validates_and_declares_ports(catheter_fmu):
    assert validate_fmu(str(catheter_fmu)) == []
    md = read_model_description(str(catheter_fmu))
    assert math.isclose(float(md.defaultExperiment.stepSize), STEP)
    v = {x.name: x for x in md.modelVariables}
    n_tool = CatheterParameters().n_segments + 1
    assert v["centerline_positions"].shape == (n_tool, 3)
    assert v["tip_force"].shape == (3,) and v["tip_force"].causality == "input"
    for name in ("insertion", "rotation"):
        assert v[name].causality == "input"
    for name in ("tip_position", "bend_angle", "actuator_command", "effort_warning", "advised_insertion_scale"):
        assert v[name].causality == "output", name
    assert v["insertion"].unit == "m" and v["rotation"].unit == "rad" and v["tip_force"].unit == "N"


def test_simulates_standalone(catheter_fmu):
    result = simulate_fmu(str(catheter_fmu), stop_time=0.05, start_values={"insertion": 0.05},
                          output=["tip_position", "bend_angle"])
    assert len(result) == 51
    np.testing.assert_allclose(result["tip_position"][-1], [0.0, 0.0, 0.05], atol=1e-12)


def test_fmu_equals_model_under_a_tip_force(catheter_fmu):
    """A constant lateral tip force above the threshold: the regulator bends the tip and warns,
    and the FMU's outputs equal the model's run directly, step by step."""
    force = np.array([0.9, 0.0, 0.0])
    params = CatheterParameters()
    model = CatheterModel(params, dt=STEP)
    model.reset(0.06, 0.0)
    with fmu_instance(catheter_fmu) as fmu:
        fmu.set("insertion", 0.06)
        fmu.initialize()
        fmu.set("tip_force", force)
        np.testing.assert_array_equal(fmu.get("tip_force"), force)
        for k in range(200):
            fmu.slave.doStep(k * STEP, STEP)
            expected = model.step(k * STEP, STEP, 0.06, 0.0, force)
        np.testing.assert_allclose(fmu.get("centerline_positions"), expected.centerline_positions, rtol=0, atol=1e-15)
        assert fmu.get("bend_angle") == pytest.approx(expected.bend_angle, abs=1e-15)
        assert fmu.slave.getBoolean(fmu.vr("effort_warning"))[0] is True
        assert abs(expected.bend_angle) > 0.01  # the controller acted
        assert fmu.errors() == []


@pytest.mark.parametrize(
    "name, value, words",
    [
        ("segment_length", -0.005, "segment_length"),
        ("radius", -0.001, "radius"),
        ("bending_stiffness", 0.0, "bending_stiffness"),
        ("actuator_bandwidth", 600.0, "actuator_bandwidth"),
        ("controller_mode", "fuzzy", "controller_mode"),
    ],
)
def test_bad_parameter_gives_error_status(catheter_fmu, name, value, words):
    with fmu_instance(catheter_fmu) as fmu:
        if fmu.outside_range(name, value):  # refused when set, naming the range (the limit table)
            fmu.expect_error(lambda: fmu.set(name, value), words, "plausible range")
            return
        fmu.set(name, value)
        fmu.expect_error(fmu.initialize, words)  # the model is built there: the error comes at once
        fmu.expect_step_error(0.0, STEP, "Error mode", words)  # and the instance says why it cannot step


def test_nan_tip_force_is_refused_and_the_instance_goes_on(catheter_fmu):
    with fmu_instance(catheter_fmu) as fmu:
        fmu.initialize()
        fmu.slave.doStep(0.0, STEP)
        before = fmu.get("centerline_positions").copy()
        fmu.expect_error(lambda: fmu.set("tip_force", [0.0, np.nan, 0.0]), "tip_force", "finite")
        np.testing.assert_array_equal(fmu.get("tip_force"), [0.0, 0.0, 0.0])  # nothing was written
        np.testing.assert_array_equal(fmu.get("centerline_positions"), before)
        fmu.slave.doStep(STEP, STEP)  # a refused value changes nothing: the simulation goes on

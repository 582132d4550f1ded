"""The built Contact.fmu: FMI conformance, a probe against the default AAA wall, bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest
from fmpy import read_model_description, simulate_fmu
from fmpy.validation import validate_fmu

from fmu_harness import fmu_instance
from haptic_fmu.model import ContactModel, ContactParameters
from tissue_fmu.mesh import aaa_inner_radius, aaa_mesh

STEP = 0.001


def test_validates_and_matches_tissue_defaults(contact_fmu):
    assert validate_fmu(str(contact_fmu)) == []
    md = read_model_description(str(contact_fmu))
    assert math.isclose(float(md.defaultExperiment.stepSize), STEP)
    v = {x.name: x for x in md.modelVariables}
    nodes, triangles = aaa_mesh().surface()
    assert v["tissue_positions"].shape == (len(nodes), 3)
    assert v["tissue_contact_force"].shape == (len(nodes), 3)
    assert v["surface_triangles"].shape == (len(triangles), 3)
    assert v["tool_force"].shape == (3,) and v["tool_force"].unit == "N"


def test_simulates_standalone(contact_fmu):
    result = simulate_fmu(str(contact_fmu), stop_time=0.005, output=["contact_count", "tool_force"])
    assert len(result) == 6
    assert np.all(result["contact_count"] == 0)  # tool at the inlet centre, far from the wall


def _probe_run(fmu, mesh, probe_path):
    nodes, triangles = mesh.surface()
    fmu.set("tool", "probe")
    fmu.set("n_tool_points", 1)
    fmu.slave.enterInitializationMode()
    fmu.slave.exitInitializationMode()
    outputs = []
    for k, p in enumerate(probe_path):
        fmu.set("tool_positions", p)
        fmu.slave.doStep(k * STEP, STEP)
        outputs.append((fmu.get("tool_force").copy(), fmu.get("tissue_contact_force").copy(),
                        fmu.get("penetration_depth"), fmu.get("tip_force").copy()))
    return outputs


def test_probe_into_the_wall_equals_model_and_conserves_momentum(contact_fmu):
    """A probe moving radially from the lumen into the sac wall: the FMU's forces equal the model's
    run directly, the port's points back toward the axis with magnitude ~ k * depth (held over the
    predicted depths), and the tissue gets exactly the opposite of the law's force, the tip's."""
    mesh = aaa_mesh()
    nodes, triangles = mesh.surface()
    z = 0.065
    r_inner = float(aaa_inner_radius(z))
    radii = r_inner - 0.002 + 0.0001 * np.arange(30)  # 2 mm inside the lumen to 0.9 mm into the wall
    path = [np.array([r, 0.0, z]) for r in radii]
    with fmu_instance(contact_fmu) as fmu:
        outputs = _probe_run(fmu, mesh, path)
        assert fmu.errors() == []
    model = ContactModel(triangles, len(nodes), 1, ContactParameters(tool="probe"))
    model.set_tissue_frame(0.0, mesh.points[nodes], np.zeros((len(nodes), 3)))
    for k, p in enumerate(path):
        expected = model.step(k * STEP, STEP, p[None, :])
        force, tissue, depth, tip = outputs[k]
        np.testing.assert_allclose(force, expected.tool_force, rtol=0, atol=1e-12)
        np.testing.assert_allclose(tip, expected.tip_force, rtol=0, atol=1e-12)
        np.testing.assert_allclose(tissue.reshape(-1, 3).sum(axis=0), -tip, rtol=0, atol=1e-12)
    force, _, depth, _ = outputs[-1]
    assert depth > 0.0005
    k, b = ContactParameters().stiffness, ContactParameters().damping
    # back toward the axis, along a facet normal: the 32-gon's facets lean by at most 2 pi / 32
    assert force[0] < 0 and abs(force[1]) <= np.tan(2 * np.pi / 32) * abs(force[0])
    # the energy-consistent hold: k times the depth half a 0.1 mm step ahead, and the damping of 0.1 m/s
    assert np.linalg.norm(force) == pytest.approx(k * (depth + 0.5e-4) + b * 0.1, rel=0.02)


@pytest.mark.parametrize("name, value, words", [
    ("stiffness", 0.0, "stiffness"),
    ("damping", -1.0, "damping"),
    ("penalty_law", "cubic", "penalty_law"),
    ("n_tool_points", 3, "n_tool"),  # three points with tool = probe
])
def test_bad_parameter_gives_error_status(contact_fmu, name, value, words):
    with fmu_instance(contact_fmu) as fmu:
        fmu.set("tool", "probe")
        fmu.set("n_tool_points", 1)
        if fmu.outside_range(name, value):  # refused when set, naming the range (the limit table)
            fmu.expect_error(lambda: fmu.set(name, value), words, "plausible range")
            return
        fmu.set(name, value)
        fmu.expect_error(fmu.initialize, words)


def test_nan_tool_position_is_refused(contact_fmu):
    with fmu_instance(contact_fmu) as fmu:
        fmu.initialize()
        tool = np.zeros(fmu.size("tool_positions"))
        tool[4] = np.nan
        fmu.expect_error(lambda: fmu.set("tool_positions", tool), "tool_positions", "value 4 is NaN")
        fmu.slave.doStep(0.0, STEP)

"""The haptic device's limits (haptic_fmu.device): the rendered force never exceeds max_force (default
the PHANTOM Desktop's 7.9 N) nor changes faster than max_force_rate; when a limit engages the model
and the FMU say so (force_limited, a count, one log line per episode). Checked by hand numbers,
against the plain reference (haptic_helpers.limit_force_reference), through ContactModel and
through the built Contact.fmu, and on the default scene (never engaged)."""
import logging
from dataclasses import fields

import numpy as np
import pytest

from haptic_fmu.device import (DEFAULT_MAX_FORCE_RATE, MAGNITUDE_LIMITED, PHANTOM_DESKTOP_MAX_FORCE, RATE_LIMITED,
                               REPORT_SIZE, DeviceError, DeviceSpec, limit_force)
from haptic_fmu.model import ContactModel, ContactParameterError, ContactParameters
from haptic_helpers import PassivityObserver, limit_force_reference

T = 1e-3
WALL = np.array([[0.0, -0.05, -0.05], [0.0, 0.05, -0.05], [0.0, -0.05, 0.05], [0.0, 0.05, 0.05]])
WALL_TRIANGLES = np.array([[0, 2, 1], [1, 2, 3]])     # the plane x = 0, tissue on x > 0
#: The plain sampled wall (each sample's force K x held as it is), where the model offers an
#: energy-consistent hold instead: the hand numbers below are K x.
RAW = {"energy_consistent": False} if "energy_consistent" in {f.name for f in fields(ContactParameters)} else {}


def limited(force, prev, max_force, max_step):
    """The kernel on copies: (rendered, code, report)."""
    force = np.array(force, np.float64).reshape(-1, 3)
    report = np.zeros(REPORT_SIZE)
    code = limit_force(force, np.array(prev, np.float64).reshape(-1, 3), max_force, max_step, report)
    return force, code, report


# ------------------------------------------------------------------ the specification
def test_defaults_are_the_phantom_desktop_and_ten_newtons_per_millisecond():
    assert PHANTOM_DESKTOP_MAX_FORCE == 7.9 and DEFAULT_MAX_FORCE_RATE == 1e4
    p = ContactParameters()
    assert (p.max_force, p.max_force_rate) == (7.9, 1e4)
    assert DeviceSpec().max_step(1e-3) == pytest.approx(10.0)


@pytest.mark.parametrize("name, value", [("max_force", 0.0), ("max_force", -7.9), ("max_force", float("nan")),
                                         ("max_force", float("inf")), ("max_force", "7.9"), ("max_force", True),
                                         ("max_force_rate", 0.0), ("max_force_rate", float("nan"))])
def test_bad_limits_are_refused_naming_the_parameter(name, value):
    with pytest.raises(ContactParameterError, match=f"{name} must be a finite number > 0") as info:
        ContactParameters(**{name: value}).validate()
    assert "e.g." in str(info.value)
    with pytest.raises(DeviceError, match=name):
        DeviceSpec(**{name: value})


# ------------------------------------------------------------------ the limiter by hand
def test_magnitude_is_clamped_by_hand():
    force, code, report = limited([[45.0, 0.0, 0.0]], [[7.9, 0.0, 0.0]], 7.9, 100.0)
    np.testing.assert_allclose(force, [[7.9, 0.0, 0.0]], rtol=1e-15)           # to round-off
    assert code == MAGNITUDE_LIMITED
    np.testing.assert_array_equal(report[:3], [45.0, 0.0, 0.0])                 # the request is reported
    assert report[7] == pytest.approx(7.9 / 45.0, rel=1e-15)


def test_rate_then_magnitude_by_hand():
    # from (3, 0, 0) N toward (3, 8, 0) N with 4 N per step: half way, (3, 4, 0), |F| = 5 N: rate only
    force, code, _ = limited([[3.0, 8.0, 0.0]], [[3.0, 0.0, 0.0]], 7.9, 4.0)
    np.testing.assert_allclose(force, [[3.0, 4.0, 0.0]], rtol=0, atol=1e-15)
    assert code == RATE_LIMITED
    # the next step reaches (3, 8, 0) (a change of exactly 4 N is allowed), |F| = 8.544 N: scaled to 7.9 N
    force, code, _ = limited([[3.0, 8.0, 0.0]], [[3.0, 4.0, 0.0]], 7.9, 4.0)
    np.testing.assert_allclose(force, [[3.0, 8.0, 0.0]] * np.array(7.9 / np.sqrt(73.0)), rtol=1e-15)
    assert code == MAGNITUDE_LIMITED
    # a 45 N slam from rest: 10 N by the rate, then 7.9 N by the magnitude
    force, code, _ = limited([[-45.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]], 7.9, 10.0)
    np.testing.assert_allclose(force, [[-7.9, 0.0, 0.0]], rtol=1e-15)
    assert code == RATE_LIMITED | MAGNITUDE_LIMITED


def test_node_forces_are_shaped_alike_and_still_sum_to_the_port_force():
    """Two catheter nodes: request (2,0,0) + (0,6,0), previous (1,0,0) + (1,0,0). The total moves
    from (2,0,0) to (2,6,0), 6 N, twice the 3 N allowed: every node goes half way."""
    force, code, report = limited([[2.0, 0.0, 0.0], [0.0, 6.0, 0.0]], [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]], 7.9, 3.0)
    np.testing.assert_allclose(force, [[1.5, 0.0, 0.0], [0.5, 3.0, 0.0]], rtol=0, atol=1e-15)
    assert code == RATE_LIMITED
    np.testing.assert_array_equal(report[3:6], [0.0, 6.0, 0.0])     # the requested tip (last node)


def test_kernel_equals_the_plain_reference_and_keeps_both_limits():
    rng = np.random.default_rng(3)
    for case in range(500):
        n = int(rng.integers(1, 6))
        force = rng.normal(0.0, rng.choice([0.5, 5.0, 50.0]), (n, 3))
        prev = rng.normal(0.0, 2.0, (n, 3))
        max_force, rate = float(rng.choice([1.0, 7.9, 22.0])), float(rng.choice([1e3, 1e4, 1e5]))
        prev *= min(1.0, 0.999 * max_force / np.linalg.norm(prev.sum(axis=0)))   # a previous rendered force
        got, code, _ = limited(force, prev, max_force, rate * T)
        want, rate_hit, clamp_hit = limit_force_reference(force, prev, max_force, rate, T)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
        assert code == (RATE_LIMITED * rate_hit | MAGNITUDE_LIMITED * clamp_hit), case
        total = got.sum(axis=0)
        assert np.linalg.norm(total) <= max_force * (1 + 1e-12)
        assert np.linalg.norm(total - prev.sum(axis=0)) <= rate * T * (1 + 1e-12) + 1e-12
        if not code:
            np.testing.assert_array_equal(got, force)     # untouched when no limit engages


# ------------------------------------------------------------------ through the model
def wall_model(**params):
    p = ContactParameters(tool="probe", local_model="hold", detection="discrete", margin=0.01, damping=0.0,
                          **{**RAW, **params})
    model = ContactModel(WALL_TRIANGLES, 4, 1, p)
    model.set_tissue_frame(0.0, WALL, np.zeros((4, 3)))
    return model


def run(model, path, t0=0.0):
    outs = []
    for j, x in enumerate(path):
        out = model.step(t0 + j * T, T, [[x, 0.0, 0.0]])
        outs.append((out.tool_force.copy(), out.tip_force.copy(), out.tissue_contact_force.sum(axis=0),
                     out.node_forces.sum(axis=0), out.force_limited, out.force_limited_steps))
    return outs


def test_a_phantom_45_newton_request_is_clamped_to_7_9_newtons_with_a_warning(caplog):
    """A probe slammed 3 mm into a 15 kN/m wall asks for 45 N: the port renders 7.9 N (tool_force and
    the node forces), the catheter's tip and the tissue keep the physical 45 N, force_limited is on
    at every such step, one warning names the time, the request and the limit; the passivity
    observer integrates the rendered force."""
    model = wall_model(stiffness=15000.0)
    path = [-0.001] + [0.003] * 50 + [-0.002] * 5
    with caplog.at_level(logging.WARNING, logger="haptic_fmu.device"):
        outs = run(model, path)
    for tool, tip, tissue, nodes, flag, _ in outs[1:51]:
        np.testing.assert_allclose(tool, [-7.9, 0.0, 0.0], rtol=1e-15)
        np.testing.assert_array_equal(nodes, tool)
        np.testing.assert_allclose(tip, [-45.0, 0.0, 0.0], rtol=1e-12)                # physical
        np.testing.assert_allclose(tissue, [45.0, 0.0, 0.0], rtol=1e-12)
        assert flag
    assert [o[4] for o in outs[51:]] == [False] * 5             # released: 7.9 N -> 0 is within 10 N per step
    assert outs[-1][5] == 50
    lines = [r.getMessage() for r in caplog.records if r.name == "haptic_fmu.device"]
    assert len(lines) == 1, lines
    assert lines[0].startswith("haptic force limited at t = 0.002 s: 45 N requested")
    assert "max_force 7.9 N" in lines[0] and "max_force_rate 1e+04 N/s" in lines[0]
    # the observer saw what the device rendered
    plain = PassivityObserver()
    for x, (tool, *_) in zip(path, outs):
        plain.update([x, 0.0, 0.0], tool)
    assert model._renderer.energy == pytest.approx(plain.energy, rel=1e-12)


def test_one_log_line_per_episode(caplog):
    """Limited for 50 steps, released for 200 ms (longer than the 100 ms gap), limited again: two
    lines; a release of 20 ms within the episode adds none."""
    model = wall_model(stiffness=15000.0)
    path = [0.003] * 50 + [-0.002] * 20 + [0.003] * 10 + [-0.002] * 200 + [0.003] * 10
    with caplog.at_level(logging.WARNING, logger="haptic_fmu.device"):
        outs = run(model, path)
    lines = [r.getMessage() for r in caplog.records if r.name == "haptic_fmu.device"]
    assert len(lines) == 2 and "limiting episode 2" in lines[1] and "t = 0.281 s" in lines[1], lines
    assert outs[-1][5] == 70 and model._renderer.limiter.episodes == 2


def test_a_slam_on_a_strong_device_is_ramped_at_the_rate_limit(caplog):
    """max_force 100 N: the 45 N slam is ramped at 10 N per 1 ms step, 10, 20, 30, 40, 45 N, and
    released the same way, 35, 25, 15, 5, 0 N (the device still pushes while it ramps down; the
    contact and the tissue are at 0 already)."""
    model = wall_model(stiffness=15000.0, max_force=100.0)
    with caplog.at_level(logging.WARNING, logger="haptic_fmu.device"):
        outs = run(model, [0.003] * 6 + [-0.002] * 6)
    rendered = [-o[0][0] for o in outs]
    np.testing.assert_allclose(rendered, [10, 20, 30, 40, 45, 45, 35, 25, 15, 5, 0, 0], rtol=1e-12, atol=1e-12)
    assert [o[4] for o in outs] == [True] * 4 + [False] * 2 + [True] * 4 + [False] * 2
    np.testing.assert_allclose([o[1][0] for o in outs], [-45.0] * 6 + [0.0] * 6, rtol=1e-12)    # the tip
    lines = [r.getMessage() for r in caplog.records if r.name == "haptic_fmu.device"]
    assert len(lines) == 1 and "max_force_rate 1e+04 N/s" in lines[0] and "max_force 1" not in lines[0]


def test_the_limits_are_parameters():
    model = wall_model(stiffness=15000.0, max_force=3.3, max_force_rate=1e6)     # a PHANTOM Omni / Touch
    outs = run(model, [0.003] * 3)
    np.testing.assert_allclose([o[0][0] for o in outs], [-3.3] * 3, rtol=1e-15)
    unlimited = wall_model(stiffness=15000.0, max_force=1000.0, max_force_rate=1e7)
    assert not any(o[4] for o in run(unlimited, [0.003] * 3))


# ------------------------------------------------------------------ through the FMU
def test_the_fmu_clamps_reports_and_counts(contact_fmu):
    """Contact.fmu with a probe pressed 0.9 mm into the default AAA wall at 50 kN/m (a 45 N request):
    tool_force stays within 7.9 N, force_limited and force_limited_steps say so, the log has the
    warning; tip_force keeps the physical force; back in the lumen, the touch is one contact cycle."""
    from fmu_harness import fmu_instance
    from tissue_fmu.mesh import aaa_inner_radius

    z = 0.065
    r_inner = float(aaa_inner_radius(z))
    radii = list(r_inner - 0.002 + 0.0001 * np.arange(30)) + [r_inner - 0.002] * 3
    with fmu_instance(contact_fmu) as fmu:
        fmu.set("tool", "probe")
        fmu.set("n_tool_points", 1)
        fmu.set("stiffness", 5e4)
        fmu.initialize()
        flags, forces, tips = [], [], []
        for k, r in enumerate(radii):
            fmu.set("tool_positions", [r, 0.0, z])
            fmu.slave.doStep(k * T, T)
            flags.append(fmu.slave.getBoolean(fmu.vr("force_limited"))[0])
            forces.append(np.linalg.norm(fmu.get("tool_force")))
            tips.append(np.linalg.norm(fmu.get("tip_force")))
        steps, cycles = fmu.get("force_limited_steps"), fmu.get("contact_cycles")
        active = fmu.get("active_cycles")
        warnings = [m for status, m in fmu.messages if status == 1]
        assert fmu.errors() == []
    assert max(forces) <= 7.9 * (1 + 1e-12)
    assert max(tips) > 40.0                                      # the physical contact force
    assert any(flags) and steps == sum(flags) > 0
    limits = [m for m in warnings if "haptic force limited" in m]
    assert len(limits) == 1 and "max_force 7.9 N" in limits[0], warnings
    assert cycles == 1 and not flags[-1]
    # any other warning is the passivity observer's verdict on the touch (a sampled 50 kN/m wall)
    others = [m for m in warnings if m not in limits]
    assert len(others) == active and all("contact cycle from t =" in m for m in others), warnings


@pytest.mark.slow
def test_the_default_limits_never_engage_in_the_default_scene():
    """aaa_endovascular as shipped (4 s, the catheter into the sac at 1000 N/m): the force stays near
    0.6 N and changes by at most 0.011 N per step (measured), far inside 7.9 N and 10 N per step:
    force_limited never switches on and nothing is logged."""
    from orchestration.app.warmup import ensure_fmus_built
    from orchestration.studies.common import run_point

    ensure_fmus_built(quiet=True)
    summary, simulation = run_point("aaa_endovascular", observe={"contact": ["force_limited_steps",
                                                                             "force_limited"]})
    assert summary["status"] == "completed", summary.get("error")
    assert simulation.final_outputs["contact"]["force_limited_steps"][0] == 0
    assert summary["fmu_messages"] == []
    assert 0.3 < summary["peaks"]["contact.tool_force"]["value"] < 1.0

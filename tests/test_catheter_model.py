"""Catheter model: actuator, kinematics, controller modes against a wall, validation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from catheter_fmu import (
    Actuator,
    CatheterModel,
    CatheterParameterError,
    CatheterParameters,
    CenterlineCurve,
    CenterlineError,
    PlaneWall,
    simulate,
)
from catheter_fmu.analysis import linearise
from catheter_fmu.controller import EffortMonitor, insertion_scale

DT = 1e-3


def _ramp(points):
    ts, zs = zip(*points)
    return lambda t: float(np.interp(t, ts, zs))


def _curved_centerline() -> CenterlineCurve:
    """Coarse polyline of a planar S-bend plus an out-of-plane twist (vertices every ~10 mm)."""
    u = np.linspace(0.0, 1.0, 15)
    pts = np.stack([0.02 * np.sin(2.0 * np.pi * u), 0.01 * (1.0 - np.cos(np.pi * u)), 0.15 * u], axis=1)
    return CenterlineCurve(pts)


def _distance_to_polyline(p: np.ndarray, curve: CenterlineCurve) -> float:
    """Plain-numpy reference: distance from p to the (ray-extended) polyline."""
    v, d, length = curve.vertices[:-1], curve.directions, curve.segment_lengths
    sigma = np.einsum("ij,ij->i", p - v, d)
    lo = np.where(np.arange(len(v)) == 0, -np.inf, 0.0)
    hi = np.where(np.arange(len(v)) == len(v) - 1, np.inf, length)
    sigma = np.clip(sigma, lo, hi)
    return float(np.min(np.linalg.norm(v + sigma[:, None] * d - p, axis=1)))


# --------------------------------------------------------------------------------------
# Actuator
# --------------------------------------------------------------------------------------


def test_actuator_unit_step_is_exact_first_order():
    fb = 5.0
    act = Actuator(fb, max_angle=10.0, max_rate=1e9)
    t = DT * np.arange(1, 1001)
    theta = np.array([act.step(1.0, DT) for _ in t])
    np.testing.assert_allclose(theta, 1.0 - np.exp(-2.0 * np.pi * fb * t), rtol=0, atol=1e-14)


def test_actuator_angle_and_rate_saturation():
    max_angle, max_rate = 1.0, 2.0
    act = Actuator(20.0, max_angle=max_angle, max_rate=max_rate)
    theta = np.array([0.0] + [act.step(5.0, DT) for _ in range(1000)])
    steps = np.diff(theta)
    assert np.all(np.abs(steps) <= max_rate * DT * (1 + 1e-12))
    assert np.all(np.abs(theta) <= max_angle)
    # Slew-limited from rest: exactly max_rate * t until the angle limit (reached at 0.5 s).
    np.testing.assert_allclose(theta[:400], max_rate * DT * np.arange(400), atol=1e-12)
    # Then the first-order approach to the clipped command, from below.
    assert max_angle - 1e-12 < theta[-1] <= max_angle
    # Going back down the other way is slew limited too.
    back = np.array([act.step(-5.0, DT) for _ in range(2000)])
    assert np.all(np.abs(np.diff(back)) <= max_rate * DT * (1 + 1e-12)) and -max_angle <= back[-1] < -max_angle + 1e-12


# --------------------------------------------------------------------------------------
# Kinematics
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("curved", [False, True])
def test_segment_lengths_preserved_and_joints_on_curve(curved):
    params = CatheterParameters(centerline=_curved_centerline() if curved else None)
    model = CatheterModel(params, DT)
    kin, curve = model.kinematics, model.curve
    rng = np.random.default_rng(3)
    n_act = params.n_active_segments
    for _ in range(200):
        insertion = rng.uniform(-0.05, 0.2)
        bend = rng.uniform(-1.5, 1.5, size=2)
        pos = kin.shape(insertion, tuple(bend))
        lengths = np.linalg.norm(np.diff(pos, axis=0), axis=1)
        np.testing.assert_allclose(lengths, params.segment_length, rtol=1e-12)
        # Proximal joints and the base lie on the (extended) centerline.
        for p in pos[: params.n_segments - n_act + 1]:
            assert _distance_to_polyline(p, curve) < 1e-12
        # Active joints lie on the arc of radius R = l / (2 sin(phi / 2)), phi = beta / n_act.
        beta = float(np.hypot(*bend))
        base, t, e1, e2 = kin.base_frame(insertion)
        d = (bend[0] * e1 + bend[1] * e2) / beta
        radius = params.segment_length / (2.0 * math.sin(beta / (2 * n_act)))
        centre = base + radius * d
        np.testing.assert_allclose(np.linalg.norm(pos[-n_act - 1 :] - centre, axis=1), radius, rtol=1e-12)
        expected_tip = base + radius * (math.sin(beta) * t + (1.0 - math.cos(beta)) * d)
        np.testing.assert_allclose(pos[-1], expected_tip, atol=1e-14)


def test_straight_tip_on_default_centerline_is_at_insertion():
    model = CatheterModel(CatheterParameters(controller_mode="off"), DT)
    for s in (-0.01, 0.0, 0.037, 0.13, 0.2):
        out = model.step(0.0, DT, s, 0.7, np.zeros(3))
        np.testing.assert_allclose(out.tip_position, [0.0, 0.0, s], atol=1e-15)
        pos = out.centerline_positions.reshape(-1, 3)
        np.testing.assert_allclose(pos[:, 2], s - 0.005 * np.arange(30, -1, -1), atol=1e-15)


def test_planar_centerline_frames_and_rotation_plane():
    """On a planar arc (x-z plane) the parallel-transported frame keeps its out-of-plane vector
    fixed (here e1 = y, the entry frame's choice), so rotation = 0 bends the tip exactly out of
    the plane, all along the curve."""
    radius = 0.2
    curve = CenterlineCurve.from_function(
        lambda t: np.stack([radius * (1 - np.cos(t)), 0 * t, radius * np.sin(t)], axis=1), 0.0, 0.8, 400
    )
    params = CatheterParameters(centerline=curve, controller_mode="external", passive_time_constant=0.0)
    for s in (0.0, 0.05, 0.1234, 0.15):
        t, e1, e2 = curve.frame(s)
        np.testing.assert_allclose(np.stack([t, e1, e2]) @ np.stack([t, e1, e2]).T, np.eye(3), atol=1e-14)
        assert abs(e1[1] - 1.0) < 1e-12 and abs(e2[1]) < 1e-12
    model = CatheterModel(params, DT)
    model.actuator.angle = 0.5
    out = model.step(0.0, DT, 0.12, 0.0, np.zeros(3), 0.5)
    base, t, e1, e2 = model.kinematics.base_frame(0.12)
    beta, n_act = 0.5, params.n_active_segments
    r = params.segment_length / (2 * math.sin(beta / (2 * n_act)))
    np.testing.assert_allclose(out.tip_position, base + r * (math.sin(beta) * t + (1 - math.cos(beta)) * e1), atol=1e-15)
    assert abs(out.tip_position[1]) == pytest.approx(r * (1 - math.cos(beta)), rel=1e-12)


def test_tip_position_continuous_in_time_across_vertices():
    """Insertion ramp at v over a coarse curved polyline while the actuator slews: the tip moves
    per step by at most v dt (1 + L w_max) + (L / 2) rate dt, w_max the frame's turn rate per m."""
    curve = _curved_centerline()
    params = CatheterParameters(centerline=curve, controller_mode="external", max_bend_rate=4.0)
    model = CatheterModel(params, DT)
    speed = 0.05
    model.reset(0.0, 0.3)
    tips = [model.outputs.tip_position]
    for k in range(3000):
        t = k * DT
        out = model.step(t, DT, speed * t, 0.3, np.zeros(3), 1.2 * math.sin(8.0 * t))
        tips.append(out.tip_position)
    jumps = np.linalg.norm(np.diff(np.array(tips), axis=0), axis=1)
    # Frame turn rate: angle between consecutive vertex tangents over the segment length, times
    # 1 / cos(angle / 2) for the peak speed of the normalised linear blend.
    tv = curve.vertex_tangents
    ang = np.arccos(np.clip(np.einsum("ij,ij->i", tv[:-1], tv[1:]), -1, 1))
    w_max = float(np.max(ang / curve.segment_lengths / np.cos(ang / 2)))
    L = params.active_length
    bound = speed * DT * (1.0 + L * w_max) + 0.5 * L * params.max_bend_rate * DT
    assert jumps.max() <= bound
    assert np.all(np.isfinite(jumps))
    # The insertion passes ~14 vertices: with a jump at any of them the max would far exceed v dt.
    assert jumps.max() < 2.0 * speed * DT + 0.5 * L * params.max_bend_rate * DT


# --------------------------------------------------------------------------------------
# Controller modes against a wall
# --------------------------------------------------------------------------------------


def test_controller_off_force_grows_with_insertion_and_matches_static_equilibrium():
    params = CatheterParameters(controller_mode="off")
    wall = PlaneWall.inclined()
    model = CatheterModel(params, DT)
    model.reset(0.07)
    holds = [0.085, 0.095, 0.105]
    schedule = _ramp([(0.0, 0.07), (0.2, holds[0]), (0.6, holds[0]), (0.8, holds[1]), (1.2, holds[1]), (1.4, holds[2]), (1.8, holds[2])])
    traj = simulate(model, wall, 1.8, schedule)
    f = traj.force_magnitude
    ends = [np.searchsorted(traj.time, t) - 1 for t in (0.6, 1.2, 1.8)]
    static = [linearise(params, wall, s).force for s in holds]
    # The passive relaxation converges to the static equilibrium found by root finding.
    np.testing.assert_allclose(f[ends], static, rtol=1e-6)
    assert static[0] < static[1] < static[2] and static[2] > params.force_threshold
    # During a ramp the force only grows (in the holds it relaxes down by the passive lag).
    assert np.all(np.diff(f[traj.time <= 0.2]) >= 0.0) and f[traj.time <= 0.2][-1] > 0.2
    # The warning is on and the advice drops.
    assert traj.effort_warning[-1] and traj.advised_insertion_scale[-1] < 1.0
    assert traj.bend_angle.max() == 0.0


def test_regulate_settles_below_threshold_and_warning_clears():
    params = CatheterParameters(controller_mode="regulate")
    wall = PlaneWall.inclined()
    model = CatheterModel(params, DT)
    model.reset(0.07)
    ramp_end = 1.0
    traj = simulate(model, wall, 3.0, _ramp([(0.0, 0.07), (ramp_end, 0.11), (3.0, 0.11)]))
    f, t = traj.force_magnitude, traj.time
    setpoint = params.setpoint_fraction * params.force_threshold
    # Uncontrolled, this insertion would push with:
    uncontrolled = linearise(params, wall, 0.11).force
    assert uncontrolled > 2.5 * params.force_threshold
    outside = np.flatnonzero(np.abs(f - setpoint) > 0.02 * setpoint)
    settle = t[outside[-1] + 1] - ramp_end
    assert settle < 0.5  # measured 0.36 s after the ramp ends
    assert abs(f[-1] - setpoint) < 1e-6
    assert f[t > ramp_end + 0.5].max() < params.force_threshold
    assert not traj.effort_warning[-1] and traj.advised_insertion_scale[-1] > 0.85
    assert traj.bend_angle[-1] > 0.5  # bent away from the wall (toward +x)


def test_regulate_with_flipped_bending_plane_bends_the_other_way():
    params = CatheterParameters(controller_mode="regulate")
    wall = PlaneWall.inclined()
    model = CatheterModel(params, DT)
    model.reset(0.09, math.pi)
    traj = simulate(model, wall, 2.0, 0.09, rotation=math.pi)
    setpoint = params.setpoint_fraction * params.force_threshold
    assert abs(traj.force_magnitude[-1] - setpoint) < 1e-6
    assert traj.bend_angle[-1] < 0.0


def test_anti_windup_no_overshoot_after_slew_limited_phase():
    """A 3x-threshold push with a slow actuator: the command outruns the slew; with anti-windup
    the force comes down to the setpoint without passing it, without it the force overshoots."""
    from catheter_fmu.analysis import step_response

    wall = PlaneWall.inclined()
    results = {}
    for aw in (True, False):
        params = CatheterParameters(anti_windup=aw, max_bend_rate=3.0)
        results[aw] = step_response(params, wall, duration=3.0, insertion=0.1156)
    assert results[True].initial_force > 2.9 * 0.5
    assert results[True].overshoot < 1e-3  # measured 0
    assert results[False].overshoot > 0.1  # measured 0.21
    for r in results.values():
        assert abs(r.steady_state_error) < 1e-4


def test_anti_windup_after_angle_saturation():
    """Push beyond what the maximal bend relieves (angle-saturated for 1.5 s), then retract:
    with anti-windup the force returns to the setpoint as soon as it is feasible; without, the
    wound-up integral holds the tip fully bent and the force collapses for seconds."""
    wall = PlaneWall.inclined()
    schedule = _ramp([(0.0, 0.085), (0.5, 0.085), (1.0, 0.11), (2.5, 0.11), (4.5, 0.09), (8.0, 0.09)])
    below = {}
    for aw in (True, False):
        params = CatheterParameters(max_bend_angle=0.3, anti_windup=aw)
        model = CatheterModel(params, DT)
        model.reset(0.085)
        traj = simulate(model, wall, 8.0, schedule)
        setpoint = params.setpoint_fraction * params.force_threshold
        sat = (traj.time > 1.2) & (traj.time < 2.5)
        assert np.all(traj.actuator_command[sat] == 0.3) and np.all(traj.force_magnitude[sat] > setpoint)
        after = traj.time > 2.5
        below[aw] = float(np.sum(traj.force_magnitude[after] < 0.5 * setpoint) * DT)
        if aw:
            assert abs(traj.force_magnitude[traj.time > 5.5] - setpoint).max() < 1e-3
    assert below[True] == 0.0
    assert below[False] > 2.0  # measured ~3.4 s


def test_external_mode_passes_command_through_first_order():
    params = CatheterParameters(controller_mode="external")
    model = CatheterModel(params, DT)
    cmd = 0.2  # slow enough that the 10 rad/s slew limit never acts (peak rate 6.3 rad/s)
    t = DT * np.arange(1, 501)
    out = [model.step(tk - DT, DT, 0.05, 0.0, [0.3, 0.0, 0.0], cmd) for tk in t]
    theta = np.array([o.bend_angle for o in out])
    np.testing.assert_allclose(theta, cmd * (1.0 - np.exp(-2.0 * np.pi * params.actuator_bandwidth * t)), atol=1e-14)
    assert all(o.actuator_command == cmd for o in out)
    # Beyond the angle limit the command is clipped.
    assert model.step(0.5, DT, 0.05, 0.0, np.zeros(3), 3.0).actuator_command == params.max_bend_angle


def test_off_mode_never_commands():
    model = CatheterModel(CatheterParameters(controller_mode="off"), DT)
    outs = [model.step(k * DT, DT, 0.1, 0.0, [2.0, 0.0, -1.0], 1.0) for k in range(100)]
    assert all(o.actuator_command == 0.0 and o.bend_angle == 0.0 for o in outs)
    assert outs[-1].effort_warning and outs[-1].total_bend > 0.0  # the tip still deflects passively


def test_huge_force_folds_no_further_than_a_u_turn():
    model = CatheterModel(CatheterParameters(controller_mode="off", passive_time_constant=0.0), DT)
    out = model.step(0.0, DT, 0.1, 0.0, [50.0, 0.0, 0.0])
    assert out.total_bend == pytest.approx(math.pi, rel=1e-15)
    pos = out.centerline_positions.reshape(-1, 3)
    np.testing.assert_allclose(np.linalg.norm(np.diff(pos, axis=0), axis=1), 0.005, rtol=1e-12)
    # Joints on the circle of radius R = l / (2 sin(pi / 8)) (4 links): the tip ends 2 R beside
    # the base, toward the force.
    radius = 0.005 / (2.0 * math.sin(math.pi / 8))
    np.testing.assert_allclose(pos[-1] - pos[-5], [2.0 * radius, 0.0, 0.0], atol=1e-15)


def test_warning_hysteresis_and_insertion_scale():
    mon = EffortMonitor(threshold=0.5, hysteresis=0.05, start_fraction=0.5, stop_fraction=2.0)
    seq = [0.3, 0.5, 0.47, 0.451, 0.45, 0.49, 0.5]
    assert [mon.update(f)[0] for f in seq] == [False, True, True, True, False, False, True]
    f = np.linspace(0.0, 1.5, 3001)
    s = np.array([insertion_scale(x, 0.5, 0.5, 2.0) for x in f])
    assert np.all(s[f <= 0.25] == 1.0) and np.all(s[f >= 1.0] == 0.0)
    assert np.all(np.diff(s) <= 0.0)
    assert insertion_scale(0.625, 0.5, 0.5, 2.0) == pytest.approx(0.5, abs=1e-15)
    # C1: slope 0 at both ends, -1.5 / ((b - a) T) at the midpoint.
    h = 1e-7
    assert abs((insertion_scale(0.25 + h, 0.5, 0.5, 2.0) - 1.0) / h) < 1e-5
    mid = (insertion_scale(0.625 + h, 0.5, 0.5, 2.0) - insertion_scale(0.625 - h, 0.5, 0.5, 2.0)) / (2 * h)
    assert mid == pytest.approx(-1.5 / 0.75, rel=1e-6)


def test_state_rollback_reproduces_steps():
    wall = PlaneWall.inclined()
    model = CatheterModel(CatheterParameters(), DT)
    model.reset(0.1)
    simulate(model, wall, 0.2, 0.1)
    state = model.get_state()
    first = simulate(model, wall, 0.1, 0.1, t_start=0.2)
    model.set_state(state)
    second = simulate(model, wall, 0.1, 0.1, t_start=0.2)
    np.testing.assert_array_equal(first.force, second.force)
    np.testing.assert_array_equal(first.bend_angle, second.bend_angle)


# --------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "field, value",
    [
        ("segment_length", -0.005),
        ("segment_length", float("nan")),
        ("radius", -1e-3),
        ("radius", 0.0),
        ("bending_stiffness", 0.0),
        ("bending_stiffness", -3e-4),
        ("active_length", 0.012),
        ("active_length", 1.0),
        ("n_segments", 0),
        ("n_segments", 3.5),
        ("actuator_bandwidth", 500.0),
        ("actuator_bandwidth", float("inf")),
        ("max_bend_angle", 4.0),
        ("max_bend_rate", 0.0),
        ("controller_mode", "pid"),
        ("kp", -1.0),
        ("ki", float("nan")),
        ("force_threshold", 0.0),
        ("setpoint_fraction", 1.5),
        ("warning_hysteresis", 0.6),
        ("advice_stop_fraction", 0.4),
        ("passive_time_constant", -0.01),
        ("centerline", [[0, 0, 0], [0, 0, 0]]),
        ("centerline", [[0, 0, 0], [0, 0, 0.1], [0, 0, 0.05]]),
    ],
)
def test_bad_parameters_name_the_field(field, value):
    with pytest.raises(CatheterParameterError, match=field):
        CatheterModel(CatheterParameters().with_changes(**{field: value}), DT)


def test_nyquist_message_explains_the_fix():
    with pytest.raises(CatheterParameterError, match=r"actuator_bandwidth.*Nyquist.*500 Hz"):
        CatheterParameters(actuator_bandwidth=600.0).validate(1e-3)
    CatheterParameters(actuator_bandwidth=400.0).validate(1e-3)
    with pytest.raises(CatheterParameterError, match="unknown parameter"):
        CatheterParameters().with_changes(stiffness=1.0)


def test_centerline_errors():
    with pytest.raises(CenterlineError, match="shape"):
        CenterlineCurve(np.zeros((1, 3)))
    with pytest.raises(CenterlineError, match="turns by 180.0 deg at vertex 1"):
        CenterlineCurve([[0, 0, 0], [0, 0, 0.1], [0, 0, 0.05]])
    with pytest.raises(CenterlineError, match="non-finite"):
        CenterlineCurve([[0, 0, 0], [0, np.nan, 0.1]])


@pytest.mark.parametrize(
    "name, kwargs",
    [
        ("insertion", {"insertion": float("nan")}),
        ("rotation", {"rotation": float("inf")}),
        ("tip_force", {"tip_force": [0.0, float("nan"), 0.0]}),
        ("tip_force", {"tip_force": [0.0, 0.0]}),
        ("external_command", {"external_command": float("nan")}),
        ("dt", {"dt": float("nan")}),
        ("dt", {"dt": -1e-3}),
    ],
)
def test_bad_inputs_name_the_input(name, kwargs):
    model = CatheterModel(CatheterParameters(), DT)
    args = {"t": 0.0, "dt": DT, "insertion": 0.05, "rotation": 0.0, "tip_force": np.zeros(3), "external_command": 0.0}
    args.update(kwargs)
    with pytest.raises(CatheterParameterError, match=name):
        model.step(**args)
    # The failed call left the model usable and unchanged.
    assert model.time == 0.0


def test_chain_back_through_a_vertex_at_exactly_one_spacing():
    """Regression (found by the catheter_tube scene): the chain reached a vertex at exactly one
    joint spacing, the sphere root came out a rounding past the segment end and the search ran
    off the first segment (IndexError)."""
    import numpy as np

    from catheter_fmu.geometry import CenterlineCurve

    curve = CenterlineCurve(np.array([[0, 0, 0], [0, 0, 0.05], [0.0085, 0, 0.09]]))
    for s in (0.06, np.nextafter(0.06, 0.0), np.nextafter(0.06, 1.0)):
        chain = curve.chain_back(float(s), 26, 0.005)
        gaps = np.linalg.norm(np.diff(np.vstack([curve.point(float(s)), chain]), axis=0), axis=1)
        np.testing.assert_allclose(gaps, 0.005, rtol=1e-9)
        # every joint lies on the polyline (x = 0 on the first segment, z <= 0.05 there)
        assert np.all(np.abs(chain[2:, 0]) < 1e-12)

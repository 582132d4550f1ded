"""Controller-design tools: linearised plant vs simulation, loop stability, step metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from catheter_fmu import (
    CatheterModel,
    CatheterParameters,
    PlaneWall,
    compare_gains,
    contact_loop_gain,
    format_gain_table,
    linearise,
    open_loop_frequency_response,
    simulate,
    simulated_frequency_response,
    step_response,
)
from catheter_fmu.analysis import _metrics

DT = 1e-3


def test_linearisation_of_straight_tip_matches_closed_form():
    """At first contact (no force, no bend) h = L cos(a) / 2 and G = k cos(a)^2 L^3 / (4 EI)."""
    params = CatheterParameters()
    a = math.radians(20.0)
    wall = PlaneWall.inclined(contact_insertion=0.08, incline_deg=20.0, stiffness=500.0)
    lin = linearise(params, wall, 0.08)
    L, EI = params.active_length, params.bending_stiffness
    assert lin.force == 0.0 and lin.passive_bend == 0.0
    assert lin.lever == pytest.approx(0.5 * L * math.cos(a), rel=1e-8)
    assert lin.loop_gain == pytest.approx(500.0 * math.cos(a) ** 2 * L**3 / (4 * EI), rel=1e-8)
    assert lin.static_gain == pytest.approx(-500.0 * 0.5 * L * math.cos(a) / (1 + lin.loop_gain), rel=1e-8)


@pytest.mark.parametrize("active_angle, frequencies", [(0.0, (1.0, 3.0, 10.0)), (0.3, (3.0,))])
def test_analytic_frequency_response_matches_simulated_sine(active_angle, frequencies):
    params = CatheterParameters()
    wall = PlaneWall.inclined()
    insertion = 0.095
    fr = open_loop_frequency_response(params, frequencies, wall, insertion=insertion, active_angle=active_angle)
    for f, h in zip(frequencies, fr.response):
        measured = simulated_frequency_response(params, wall, insertion, f, amplitude=0.02, active_angle=active_angle)
        assert abs(measured) == pytest.approx(abs(h), rel=0.02)
        assert abs(np.angle(measured / h)) < 0.02
    # The response is dynamic, not a static gain: the phase lags by > 0.5 rad more at 10 Hz.
    if len(frequencies) > 1:
        assert fr.phase[0] < -math.pi and fr.phase[-1] - fr.phase[0] < -0.5


def test_loop_transfer_with_controller():
    params = CatheterParameters()
    fr = open_loop_frequency_response(params, [1e-3, 1.0, 1e3], with_controller=True)
    # Integral action: |L| grows without bound at low frequency, phase -pi/2 there. At high
    # frequency C -> kp (phase 0) and the actuator pole gives -pi/2; the passive zero/pole pair
    # adds atan(w tau) - atan(w tau / (1 + G)) ~ +0.05 rad at 1 kHz.
    assert fr.magnitude[0] > 1e2 and fr.phase[0] == pytest.approx(-math.pi / 2, abs=1e-3)
    assert fr.magnitude[-1] < 0.1 and fr.phase[-1] == pytest.approx(-math.pi / 2 + 0.05, abs=0.02)
    plant = open_loop_frequency_response(params, [1.0])
    s = 2j * math.pi
    assert complex(-(params.kp + params.ki / s) * plant.response[0]) == pytest.approx(complex(fr.response[1]), rel=1e-12)


@pytest.mark.parametrize("tau, stable", [(1.9e-3, True), (1.35e-3, False)])
def test_contact_loop_gain_predicts_cosimulation_stability(tau, stable):
    """Tip pressed 0.5 mm into a wall across it: G = k L^3 / (4 EI) = 3.33 for the defaults, and
    the explicit exchange converges iff (1 - exp(-dt / tau)) (1 + G) < 2, i.e. tau > 1.62 ms."""
    params = CatheterParameters(controller_mode="off", passive_time_constant=tau)
    wall = PlaneWall(point=(-0.0005, 0.0, 0.0), normal=(-1.0, 0.0, 0.0), stiffness=500.0)
    g, predicted_stable = contact_loop_gain(params, wall.stiffness, DT)
    assert g == pytest.approx(500.0 * 0.02**3 / (4 * 3e-4))
    assert predicted_stable == stable
    model = CatheterModel(params, DT)
    model.reset(0.05)
    traj = simulate(model, wall, 0.6, 0.05)
    tail = traj.force_magnitude[-100:]
    if stable:
        np.testing.assert_allclose(tail, linearise(params, wall, 0.05).force, rtol=1e-9)
    else:
        assert tail.max() - tail.min() > 0.5 * tail.mean()


@pytest.mark.parametrize("stiffness", [3000.0, 5000.0])
def test_implicit_passive_bend_is_stable_against_a_stiff_contact(stiffness):
    """Issue 12: the tip force reaches the catheter one step late (jacobi). The explicit passive
    bend multiplies the error by 1 - alpha (1 + G) per step (alpha = 1 - exp(-dt / tau) = 0.095,
    G = k L^3 / (4 EI) = 20 / 33 at 3000 / 5000 N/m): -0.998, a period-2 oscillation that barely
    decays, and -2.27, one that grows until the tip leaves the wall and bounces. With the
    contact's stiffness (the Contact FMU's tip_stiffness) the bend is solved against the force
    linearised at its new value and the error shrinks by (1 - alpha) / (1 + alpha G) = 0.31 / 0.22,
    monotonically, to the equilibrium. Both factors are measured on the model, after the wall
    moves 1 um toward the tip from a settled contact."""
    params = CatheterParameters(controller_mode="off")
    G, explicit_stable = contact_loop_gain(params, stiffness, DT)
    assert contact_loop_gain(params, stiffness, DT, implicit=True) == (G, True)
    alpha = 1.0 - math.exp(-DT / params.passive_time_constant)
    model = CatheterModel(params, DT)
    model.reset(0.05)
    wall = PlaneWall(point=(-0.0005, 0.0, 0.0), normal=(-1.0, 0.0, 0.0), stiffness=stiffness)
    simulate(model, wall, 0.3, 0.05, tip_stiffness=True)
    settled = model.get_state()
    moved = PlaneWall(point=(-0.000501, 0.0, 0.0), normal=(-1.0, 0.0, 0.0), stiffness=stiffness)
    equilibrium = linearise(params, moved, 0.05).force
    for implicit, factor in ((True, (1.0 - alpha) / (1.0 + alpha * G)), (False, 1.0 - alpha * (1.0 + G))):
        model.set_state(settled)
        traj = simulate(model, moved, 0.3, 0.05, t_start=0.3, tip_stiffness=implicit)
        error = traj.force_magnitude - equilibrium
        assert error[0] != 0.0
        assert error[1] / error[0] == pytest.approx(factor, rel=1e-2)
        tail = traj.force_magnitude[-100:]
        if implicit:
            ratios = error[1:10] / error[:9]
            assert np.all((ratios > 0.0) & (ratios < 0.35))           # monotone, fast
            np.testing.assert_allclose(tail, equilibrium, rtol=1e-9)
        else:
            assert not explicit_stable or factor < -0.99                # at or past the bound
            assert np.all(np.diff(np.sign(error[:4])) != 0)             # period 2 (in contact)
            assert np.ptp(tail) > 0.5 * abs(error[0])                   # still oscillating after 0.2 s


def test_step_metrics_on_known_curves():
    t = DT * np.arange(1, 3001)
    f0, sp, T = 1.0, 0.4, 0.1
    first = sp + (f0 - sp) * np.exp(-t / T)
    rise, overshoot, settling = _metrics(t, first, f0, sp, 0.02)
    assert rise == pytest.approx(T * math.log(9.0), abs=DT)
    assert settling == pytest.approx(T * math.log(50.0), abs=DT)
    assert overshoot == 0.0
    zeta, wn = 0.4, 20.0
    wd = wn * math.sqrt(1 - zeta**2)
    y = 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * t))
    _, overshoot, _ = _metrics(t, f0 + (sp - f0) * y, f0, sp, 0.02)
    assert overshoot == pytest.approx(math.exp(-math.pi * zeta / math.sqrt(1 - zeta**2)), rel=1e-3)


def test_default_step_response_settles_below_threshold():
    r = step_response(CatheterParameters(), duration=2.0)
    assert r.initial_force == pytest.approx(2.0 * r.threshold, rel=1e-6)
    assert abs(r.steady_state_error) < 1e-4 and r.final_force < r.threshold
    assert r.settling_time < 1.0 and r.overshoot < 0.02  # measured 0.445 s, 0
    assert r.warning_clear_time < r.settling_time


def test_compare_gains_table():
    rows = compare_gains([(0.3, 4.0), (0.3, 8.0), (0.3, 16.0)], duration=2.5)
    rises = [r["rise_time"] for r in rows]
    assert rises[0] > rises[1] > rises[2]  # more integral action, faster
    assert all(abs(r["steady_state_error"]) < 1e-3 for r in rows)
    table = format_gain_table(rows)
    assert len(table.splitlines()) == 4 and "settling_time" in table

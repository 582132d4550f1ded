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


@pytest.mark.parametrize("speed", [0.01, 0.05])
def test_regulated_tip_against_a_stiff_wall_does_not_alternate(speed):
    """Issue 28 (found by the operator-motion fuzzer): pushed at 10-50 mm/s into a 10 kN/m wall
    with the regulator on, the tip force alternated every step (11 reversals above 10 mN in a row
    at 50 mm/s). The regulator's command moves the tip through the actuator within the step; the
    passive bend was solved against the force linearised for its own change only, so the force
    the actuator's motion added came back one step late with a loop gain near 1. Solved against
    the whole bend change, the force rises without a reversal of more than 10 mN."""
    model = CatheterModel(CatheterParameters(controller_mode="regulate"), DT)
    model.reset(0.075)
    wall = PlaneWall.inclined(0.08, 20.0, 10000.0)
    traj = simulate(model, wall, 0.012 / speed + 0.2, lambda t: min(0.075 + speed * t, 0.087), tip_stiffness=True)
    force = traj.force_magnitude
    assert force.max() > 0.3                      # the tip did press on the wall
    step = np.diff(force)
    reversals = (step[1:] * step[:-1] < 0) & (np.abs(step[1:]) > 0.01) & (np.abs(step[:-1]) > 0.01)
    assert not reversals.any(), f"force reverses at t = {traj.time[1:-1][reversals][:5]} s"


@pytest.mark.parametrize("stiffness", [3000.0, 10000.0])
@pytest.mark.parametrize("mode", ["off", "regulate"])
def test_a_tip_released_by_a_fast_retraction_leaves_the_wall_without_bouncing(mode, stiffness):
    """Issue 28 (found by the operator-motion fuzzer): pressed on the wall, then pulled back at
    0.2 m/s, the tip springs back toward the wall by its passive relaxation (about 50 um in a
    millisecond). Knowing the wall only where the force was not zero, the passive bend sprang into
    it by a whole step, was thrown out the next step, and touched again (force reversals at 3000
    and 10000 N/m). With the tip's clearance (the Contact FMU's tip_gap, the plane's here) it meets
    the wall within the step and leaves it once: the force falls without a reversal."""
    model = CatheterModel(CatheterParameters(controller_mode=mode), DT)
    model.reset(0.075)
    wall = PlaneWall.inclined(0.08, 20.0, stiffness)
    traj = simulate(model, wall, 0.6, lambda t: float(np.interp(t, [0.0, 0.3, 0.32], [0.075, 0.083, 0.079])),
                    tip_stiffness=True)
    force = traj.force_magnitude
    assert force[:300].max() > 0.15 and force[-200:].max() == 0.0   # pressed, then released
    step = np.diff(force)
    reversals = (step[1:] * step[:-1] < 0) & (np.abs(step[1:]) > 0.01) & (np.abs(step[:-1]) > 0.01)
    assert not reversals.any(), f"force reverses at t = {traj.time[1:-1][reversals][:5]} s"


def test_the_regulator_holds_its_bending_side_while_the_force_wavers_about_the_perpendicular():
    """Issue 28 (found by the operator-motion fuzzer: the catheter in the tube rolled through a
    quarter turn at 5000 N/m): with the bending plane nearly perpendicular to the wall's force,
    the tip's own motion turned the force across the perpendicular every step (F . d between
    -0.03 and +0.03 |F|) and the regulator, taking the side at 1 % of |F|, flipped its whole
    command (+-0.56 rad): the actuator slewed from side to side at 500 Hz and the force buzzed by
    70 mN. During a contact the side is now held until the force is 11.5 degrees past the
    perpendicular; a new contact still takes its side at 1 %."""
    from catheter_fmu.controller import DIRECTION_HYSTERESIS, ForceRegulator

    regulator = ForceRegulator(kp=0.3, ki=0.0, setpoint=0.4, max_angle=1.5)
    full = 0.3 * (1.0 - 0.4)
    assert regulator.command(1.0, -0.02, DT) == pytest.approx(-full)      # a new contact: its side at 1 %
    wavering = [0.03, -0.03, 0.15, -0.19, 0.1, -0.05]
    assert [regulator.command(1.0, x, DT) for x in wavering] == pytest.approx([-full] * len(wavering))
    assert math.asin(DIRECTION_HYSTERESIS) == pytest.approx(math.radians(11.5), abs=0.01)
    assert regulator.command(1.0, 0.25, DT) == pytest.approx(full)         # clearly on the other side
    assert regulator.command(1.0, -0.1, DT) == pytest.approx(full)         # and held there
    # the contact ends: the side is held without force, and the next contact takes its own
    assert regulator.command(0.0, 0.0, DT) == 0.0 and regulator.direction == 1.0
    assert regulator.command(1.0, -0.05, DT) == pytest.approx(-full)

"""The passivity observer judges each contact cycle (a touch and its release) relative to the energy
it exchanged (haptic_fmu.passivity): by hand, against the plain reference (haptic_helpers.ContactCycles),
on a sampled penalty wall tapped at 5 Hz (active: the zero-order hold creates K T / 2 v^2 per unit
time) and on the same wall damped beyond K T / 2 (passive), and relative (a 1 uJ leak on a 10 uJ
cycle is reported, the round-off of a 1 J cycle is not)."""
import logging
import math
from dataclasses import fields

import numpy as np
import pytest

from haptic_fmu.model import ContactModel, ContactParameters
from haptic_fmu.device import DeviceSpec, ForceLimiter
from haptic_fmu.passivity import (LAST_IN, LAST_OUT, LAST_T_END, LAST_T_START, LAST_THRESHOLD, PassiveRenderer,
                                  PassivityError)
from haptic_helpers import ContactCycles

T = 1e-3
K = 1000.0
#: The plain sampled wall (the force of each sample held as it is), where the model offers an
#: energy-consistent hold instead: what the zero-order hold creates is what these tests measure.
RAW = {"energy_consistent": False} if "energy_consistent" in {f.name for f in fields(ContactParameters)} else {}
#: A flat wall in the plane x = 0, tissue on x > 0 (outward normal -x), 10 cm square.
WALL = np.array([[0.0, -0.05, -0.05], [0.0, 0.05, -0.05], [0.0, -0.05, 0.05], [0.0, 0.05, 0.05]])
WALL_TRIANGLES = np.array([[0, 2, 1], [1, 2, 3]])


def feed(renderer, samples):
    """Feed (x, F) samples along x (forces on the tool) to a renderer; t = sample index."""
    for j, (x, f) in enumerate(samples):
        renderer.render([x, 0.0, 0.0], [0.0, 0.0, 0.0], [f, 0.0, 0.0], t=float(j))


def test_a_touch_and_release_by_hand():
    """A probe 1 mm, 2 mm, 1 mm, 0 mm into a 1 kN/m wall sampled with a zero-order hold: the force
    held over each interval is the one of its start, so the wall takes 1 mJ on the way in and gives
    1 + 2 = 3 mJ back (hand sums below): the cycle is active by 2 mJ."""
    renderer = PassiveRenderer(T, controller=False)
    feed(renderer, [(0.0, 0.0), (0.001, -1.0), (0.002, -2.0), (0.001, -1.0), (0.0, 0.0)])
    # opens at sample 1 (first nonzero force); works of the held forces:
    # sample 2: -(-1 N)(+1 mm) = +1 mJ in; sample 3: -(-2 N)(-1 mm) = -2 mJ (out); sample 4: -(-1 N)(-1 mm) = -1 mJ;
    # closes at sample 4: no contact force and no held force from there on
    c = renderer.cycle
    assert (c[LAST_IN], c[LAST_OUT]) == pytest.approx((0.001, 0.003), rel=1e-15)
    assert (c[LAST_T_START], c[LAST_T_END]) == (1.0, 4.0)
    assert renderer.cycles == 1 and renderer.active_cycles == 1
    assert renderer.last_cycle_energy == pytest.approx(-0.002, rel=1e-12)
    assert renderer.energy == pytest.approx(-0.002, rel=1e-12)      # the run's observer agrees


def test_an_energy_consistent_touch_by_hand_is_passive():
    """The same path with each interval's force taken at its midpoint, F = -K (x(j) + x(j+1)) / 2:
    the work of each interval is minus the spring's energy change, 0.5 + 1.5 = 2 mJ in and
    1.5 + 0.5 = 2 mJ out; nothing created."""
    renderer = PassiveRenderer(T, controller=False)
    feed(renderer, [(0.0, -0.5), (0.001, -1.5), (0.002, -1.5), (0.001, -0.5), (0.0, 0.0)])
    c = renderer.cycle
    assert (c[LAST_IN], c[LAST_OUT]) == pytest.approx((0.002, 0.002), rel=1e-15)
    assert renderer.cycles == 1 and renderer.active_cycles == 0
    assert abs(renderer.last_cycle_energy) < 1e-18


def test_the_last_held_force_counts_and_a_lingering_force_keeps_the_cycle_open():
    """A contact force of 1 N for two samples, then none, through a device rate limit of 0.5 N per
    sample: the port renders 0.5, 1, 0.5, 0 N. The contact force is zero from sample 2, but the
    port still holds 0.5 N there: the cycle stays open until the held force is zero (sample 3),
    and the work of that last held force is in it."""
    renderer = PassiveRenderer(T, controller=False, limiter=ForceLimiter(DeviceSpec(100.0, 500.0)))
    rendered = []
    for j, (x, contact) in enumerate([(0.0, 1.0), (0.001, 1.0), (0.002, 0.0), (0.003, 0.0)]):
        force = np.array([[contact, 0.0, 0.0]])
        renderer.render_in_place(np.array([[x, 0.0, 0.0]]), np.zeros((1, 3)), force, float(j))
        rendered.append(force[0, 0])
        assert renderer.cycles == (j == 3)
    assert rendered == [0.5, 1.0, 0.5, 0.0]
    # the force pushes the tool along +x as it moves +1 mm a sample: all out, 0.5 + 1 + 0.5 mJ
    assert (renderer.cycle[LAST_IN], renderer.cycle[LAST_OUT]) == pytest.approx((0.0, 0.002), rel=1e-12)
    assert (renderer.cycle[LAST_T_START], renderer.cycle[LAST_T_END]) == (0.0, 3.0)


def test_the_judgement_is_relative():
    """A 1 uJ leak on a 10 uJ cycle is reported (10 %); the round-off of an energy-consistent 1 J
    cycle of 1000 samples is not, even with no relative tolerance at all; a 1e-9 leak of the same
    1 J cycle is reported without tolerance and not with a tolerance of 1e-6."""
    small = PassiveRenderer(T, controller=False)
    feed(small, [(0.0, -0.010), (0.001, -0.011), (0.0, 0.0)])      # 10 uJ in, 11 uJ out
    assert small.active_cycles == 1
    assert small.last_cycle_energy == pytest.approx(-1e-6, rel=1e-9)

    rng = np.random.default_rng(7)
    n = 1000
    x = 0.1 * np.sin(np.pi * np.arange(n + 1) / n) ** 2 + rng.uniform(0.0, 1e-4, n + 1)
    x[0] = x[-1] = 0.0
    k = 200.0                                       # K X^2 / 2 = 1 J at X = 0.1 m
    held = -k * (x[:-1] + x[1:]) / 2                # energy consistent: each interval's work = -dU exactly
    for tolerance, leak, active in ((0.0, 0.0, 0), (0.0, 1e-9, 1), (1e-6, 1e-9, 0)):
        renderer = PassiveRenderer(T, controller=False, cycle_tolerance=tolerance)
        forces = np.append(held * np.where(np.diff(x) < 0, 1.0 + leak, 1.0), 0.0)
        feed(renderer, zip(x, forces))
        exchanged = renderer.cycle[LAST_IN] + renderer.cycle[LAST_OUT]
        assert exchanged == pytest.approx(2.0, rel=0.05)       # 1 J in, 1 J out (and the jitter)
        assert renderer.cycles == 1 and renderer.active_cycles == active, (tolerance, leak, renderer.cycle)
        if leak == 0.0:
            # what round-off left: far below the floor, and the floor itself ~ 1e-12 of the exchange
            assert abs(renderer.last_cycle_energy) < 1e-13
            assert renderer.cycle[LAST_THRESHOLD] < 1e-12 * exchanged


def _tap(damping=0.0, taps=3, frequency=5.0, depth=0.003, **params):
    """A probe tapping a sampled penalty wall (hold, discrete detection, velocity differenced):
    x(t) = -1 mm + 4 mm sin^2(pi f t), 3 mm deep at the peak, in contact about half of each tap.
    Returns (model, plain ContactCycles fed the same samples, the probe positions)."""
    p = ContactParameters(stiffness=K, damping=damping, tool="probe", local_model="hold", detection="discrete",
                          margin=0.01, **{**RAW, **params})
    model = ContactModel(WALL_TRIANGLES, 4, 1, p)
    model.set_tissue_frame(0.0, WALL, np.zeros((4, 3)))
    plain = ContactCycles(p.passivity_cycle_tolerance)
    xs = []
    for j in range(int(round(taps / frequency / T)) + 2):
        t = j * T
        x = -0.001 + (depth + 0.001) * math.sin(math.pi * frequency * t) ** 2
        out = model.step(t - T, T, [[x, 0.0, 0.0]])
        plain.update(t, [x, 0.0, 0.0], out.node_forces, out.node_forces)   # no controller, no limit engaged
        assert not out.force_limited
        xs.append(x)
    return model, plain, np.array(xs)


def test_a_sampled_wall_tapped_at_5_hz_creates_energy_in_every_cycle(caplog):
    """K = 1000 N/m, B = 0: each tap returns more than it took, by what the zero-order hold creates:
    over each interval the spring's energy changes by the integral of K x+ dx while the held force
    does K x+(j-1) dx (exactly what the observer measures), about K T / 2 v^2 per unit time in
    contact; the kernel's per-cycle energies equal the plain reference's."""
    with caplog.at_level(logging.WARNING, logger="haptic_fmu.passivity"):
        model, plain, xs = _tap()
    renderer = model._renderer
    assert renderer.cycles == len(plain.closed) == 3 and renderer.active_cycles == 3
    assert all(c["active"] for c in plain.closed)
    last = plain.closed[-1]
    assert renderer.cycle[LAST_IN] == pytest.approx(last["energy_in"], rel=1e-13)
    assert renderer.cycle[LAST_OUT] == pytest.approx(last["energy_out"], rel=1e-13)
    created = last["energy_out"] - last["energy_in"]
    t = np.arange(xs.size) * T
    j = np.flatnonzero((t >= last["t_start"]) & (t <= last["t_end"]))   # intervals into and through the cycle
    x0, x1 = np.maximum(xs[j - 1], 0.0), np.maximum(xs[j], 0.0)
    hold = np.sum(K / 2 * (x1 ** 2 - x0 ** 2) - K * x0 * (xs[j] - xs[j - 1]))
    assert created == pytest.approx(hold, rel=1e-9), (created, hold)
    # ... about K T / 2 v^2 per unit time in contact, v from the motion's formula
    tc = t[j][xs[j] > 0]
    v = (0.004 * math.pi * 5.0) * np.sin(2 * math.pi * 5.0 * tc)
    assert created == pytest.approx(K * T / 2 * np.sum(v ** 2) * T, rel=0.1)
    assert 0.01 < created / (last["energy_in"] + last["energy_out"]) < 0.03   # 1.8 % of the 9 mJ exchanged
    assert model.step(xs.size * T, T, [[-0.001, 0.0, 0.0]]).last_cycle_energy == pytest.approx(-created, rel=1e-12)
    lines = [r.getMessage() for r in caplog.records if r.name == "haptic_fmu.passivity"]
    assert len(lines) == 1, lines                     # the first active cycle only
    assert "contact cycle from t = 0.034 s to 0.167 s" in lines[0] and "created" in lines[0]


def test_a_wall_damped_beyond_k_t_over_2_is_passive_in_every_cycle(caplog):
    """The same taps with wall damping B = 0.75 N s/m > K T / 2 = 0.5 N s/m: every cycle takes more
    than it returns; nothing is logged. (B = 0.25, below the bound, is still active.)"""
    with caplog.at_level(logging.WARNING, logger="haptic_fmu.passivity"):
        model, plain, _ = _tap(damping=0.75)
    renderer = model._renderer
    assert renderer.cycles == 3 and renderer.active_cycles == 0
    assert renderer.last_cycle_energy > 0
    assert not [r for r in caplog.records if r.name == "haptic_fmu.passivity"]
    below, _, _ = _tap(damping=0.25)
    assert below._renderer.active_cycles == 3


def test_active_cycles_are_counted_and_summarised_at_powers_of_ten(caplog):
    with caplog.at_level(logging.WARNING, logger="haptic_fmu.passivity"):
        model, plain, _ = _tap(taps=10)
    assert model._renderer.active_cycles == 10
    lines = [r.getMessage() for r in caplog.records if r.name == "haptic_fmu.passivity"]
    assert len(lines) == 2 and "10 of 10 contact cycles active" in lines[1], lines


def test_the_cycle_tolerance_is_a_parameter():
    model, _, _ = _tap(passivity_cycle_tolerance=0.05)        # 5 % of the exchange: the 1.8 % taps pass
    assert model._renderer.cycles == 3 and model._renderer.active_cycles == 0
    with pytest.raises(ValueError, match="passivity_cycle_tolerance"):
        ContactParameters(passivity_cycle_tolerance=-1e-6).validate()
    with pytest.raises(ValueError, match="passivity_cycle_tolerance"):
        ContactParameters(passivity_cycle_tolerance=float("nan")).validate()
    with pytest.raises(PassivityError, match="cycle_tolerance"):
        PassiveRenderer(T, cycle_tolerance=-1.0)


def test_cycles_survive_a_copy_of_the_model():
    """The open cycle is model state: a deep copy taken mid-tap closes it with the same numbers."""
    import copy

    p = ContactParameters(stiffness=K, tool="probe", local_model="hold", detection="discrete", margin=0.01, **RAW)
    model = ContactModel(WALL_TRIANGLES, 4, 1, p)
    model.set_tissue_frame(0.0, WALL, np.zeros((4, 3)))
    path = [-0.001, 0.001, 0.002, 0.003, 0.001, -0.001, -0.002]
    for j, x in enumerate(path[:3]):
        model.step(j * T, T, [[x, 0.0, 0.0]])
    twin = copy.deepcopy(model)
    for m in (model, twin):
        for j, x in enumerate(path[3:], start=3):
            out = m.step(j * T, T, [[x, 0.0, 0.0]])
    assert out.contact_cycles == 1 and model._renderer.cycles == 1
    np.testing.assert_array_equal(model._renderer.cycle, twin._renderer.cycle)

"""Sampled virtual wall (Colgate and Schenkel 1997) and the passivity observer/controller.

A 1-DOF device of mass m with physical damping b_dev is pushed by a constant operator force into
a one-sided wall (x > 0 is penetration) rendered at period T with the linear penalty law
F = -K x - B v, held constant between samples (zero-order hold). Between samples the device
m x'' + b_dev x' = F_held + F_op is integrated in closed form (exact). The wall is passive with the
device iff b_dev > K T / 2 + |B|.
"""
import math

import numpy as np
import pytest

from haptic_fmu.passivity import PassiveRenderer
from haptic_helpers import PassivityObserver, controller_damping
from haptic_fmu.penalty import normal_force

M = 0.05        # kg
K = 1000.0      # N/m (PHANTOM-class wall)
T = 1e-3        # s
F_OP = 1.0      # N, operator pushing into the wall
BOUND = K * T / 2


def exact_interval(x, v, force, b, dt):
    """Closed-form state after dt of m x'' + b x' = force, and the energy b int v^2 dissipated."""
    tau = M / b
    v_inf = force / b
    decay = math.exp(-dt / tau)
    dv = v - v_inf
    x_new = x + v_inf * dt + dv * tau * (1.0 - decay)
    v_new = v_inf + dv * decay
    dissipated = b * (v_inf ** 2 * dt + 2 * v_inf * dv * tau * (1.0 - decay)
                      + dv ** 2 * tau / 2 * (1.0 - decay ** 2))
    return x_new, v_new, dissipated


def wall_force(x, v, B):
    """Force on the device (along +x): the wall's outward normal is -x, depth x, depth rate v."""
    return -normal_force(x, v, "linear", K, B) if x > 0 else 0.0


def distance_from_rest(x, v):
    """Device + wall + operator energy above the resting state x_eq = F_OP / K."""
    wall = 0.5 * K * x * x if x > 0 else 0.0
    rest = -F_OP ** 2 / (2 * K)
    return 0.5 * M * v * v + wall - F_OP * x - rest


def simulate(b_dev, B, seconds=3.0, controller=None):
    x, v = -0.005, 0.1
    renderer = PassiveRenderer(T, controller=bool(controller), max_damping=M / T)
    plain = PassivityObserver()          # the plain-Python observer, fed the same samples
    energy, observed, peaks = [], [], []
    dissipated = 0.0
    xs = []
    for _ in range(int(round(seconds / T))):
        force = renderer.render([x, 0, 0], [v, 0, 0], [wall_force(x, v, B), 0, 0])[0, 0]
        plain.update([x], [force])
        energy.append(distance_from_rest(x, v))
        observed.append(renderer.energy)
        xs.append(x)
        x, v, d = exact_interval(x, v, force + F_OP, b_dev, T)
        dissipated += d
    xs = np.array(xs)
    energy = np.array(energy)
    # energy at each bounce: at the local maxima of the penetration
    peak = np.flatnonzero((xs[1:-1] > xs[:-2]) & (xs[1:-1] >= xs[2:])) + 1
    renderer.plain = plain
    return energy, np.array(observed), energy[peak], renderer, (x, v, dissipated)


def test_passive_wall_loses_energy_over_bounces():
    B = 0.2
    energy, _, peaks, _, _ = simulate(b_dev=1.5 * (BOUND + B), B=B)
    peaks = peaks[peaks > 1e-9 * energy[0]]               # bounces, not round-off wiggles at rest
    assert len(peaks) >= 5
    assert np.all(np.diff(peaks) < 0)                     # every bounce has less energy
    assert energy[-1] < 1e-3 * energy[0]


def test_wall_below_colgate_bound_gains_energy_and_observer_sees_it():
    energy, observed, peaks, renderer, _ = simulate(b_dev=0.2 * BOUND, B=0.0)
    assert len(peaks) >= 10
    assert np.all(np.diff(peaks) > 0)                     # every bounce gains energy
    assert peaks[-1] > 5 * peaks[0]
    # the observer: the environment has generated energy (active port), more than a bounce's worth
    assert renderer.min_energy < -energy[0]
    assert observed[-1] < 0


def test_observer_measures_the_port_energy_exactly():
    """Energy balance of the device: its energy change = work of the operator - device damping
    - energy into the environment (the observer), to round-off (ZOH + exact integration)."""
    x0, v0 = -0.005, 0.1
    energy, observed, _, renderer, (x, v, dissipated) = simulate(b_dev=0.3, B=0.1, seconds=1.0)
    # the last interval's work is not yet recorded by the observer: include it
    port = renderer.observe([x, 0.0, 0.0])
    assert renderer.plain.observe([x]) == pytest.approx(port, rel=1e-12)   # kernel == plain Python
    kinetic_change = 0.5 * M * (v * v - v0 * v0)
    assert kinetic_change == pytest.approx(-port + F_OP * (x - x0) - dissipated, abs=1e-12)


def test_passivity_controller_makes_the_unstable_wall_dissipative():
    energy_off, _, _, renderer_off, _ = simulate(b_dev=0.2 * BOUND, B=0.0)
    energy, observed, peaks, renderer, _ = simulate(b_dev=0.2 * BOUND, B=0.0, controller=True)
    assert energy[-1] < 0.05 * energy[0]
    assert np.all(np.diff(peaks) < 0)                     # every bounce loses energy
    # the energy the environment generates stays more than 100x below the uncontrolled run's
    assert renderer.min_energy > 0.01 * renderer_off.min_energy


def test_observer_and_controller_by_hand():
    obs = PassivityObserver()
    obs.update([0.0, 0.0, 0.0], [1.0, 0.0, -2.0])        # force held from here
    assert obs.update([0.001, 0.0, 0.002], [0.0, 0.0, 0.0]) == pytest.approx(-(0.001 - 0.004))
    assert controller_damping(-0.5, [0.1, 0.0, 0.0], 1e-3) == pytest.approx(0.5 / (1e-3 * 0.01))
    assert controller_damping(0.5, [0.1, 0.0, 0.0], 1e-3) == 0.0
    with pytest.raises(ValueError, match="period"):
        controller_damping(-1.0, [1.0, 0, 0], 0.0)


def _tube_wall(n_around=32, radius=0.010, length=0.04, n_along=5):
    """Inner wall of a faceted tube (tissue outside, normals toward the axis)."""
    theta = np.arange(n_around) * 2 * np.pi / n_around
    z = np.linspace(-length / 2, length / 2, n_along)
    th, zz = np.meshgrid(theta, z, indexing="ij")
    pos = np.stack([radius * np.cos(th), radius * np.sin(th), zz], axis=-1).reshape(-1, 3)
    tris = []
    for i in range(n_around):
        for j in range(n_along - 1):
            a, b = i * n_along + j, ((i + 1) % n_around) * n_along + j
            tris += [[a, a + 1, b + 1], [a, b + 1, b]]
    return pos, np.array(tris, np.int64)


@pytest.mark.parametrize("controller, energy_consistent", [(False, False), (True, False), (False, True)])
def test_contact_model_probe_bouncing_on_tube_wall(controller, energy_consistent):
    """The same sampled wall, rendered by ContactModel: a device probe moving along a facet's
    normal into the tube wall, with b_dev = 0.2 K T / 2. Held at its sampled value (Colgate's
    sampled wall), the force makes the bounces grow (the port turns active) without the passivity
    controller, and dissipative with it. Held at its mean over the predicted depths (the
    energy-consistent hold, the default), the bounces die out without any controller."""
    from haptic_fmu.model import ContactModel, ContactParameters
    pos, tri = _tube_wall()
    params = ContactParameters(stiffness=K, damping=0.0, tool="probe", local_model="hold",
                               detection="discrete", passivity_controller=controller,
                               passivity_max_damping=M / T, energy_consistent=energy_consistent)
    model = ContactModel(tri, pos.shape[0], 1, params)
    model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
    phi = 0.5 * 2 * np.pi / 32
    e = np.array([np.cos(phi), np.sin(phi), 0.0])           # radial through the middle of facet 0
    plane = 0.010 * math.cos(math.pi / 32)
    x, v = -0.005, 0.1
    energy, passivity = [], []
    xs = []
    for k in range(3000):
        out = model.step(k * T, T, (plane + x) * e, v * e)
        force = out.tool_force @ e
        energy.append(distance_from_rest(x, v))
        passivity.append(out.passivity_energy)
        xs.append(x)
        x, v, _ = exact_interval(x, v, force + F_OP, 0.2 * BOUND, T)
    xs, energy = np.array(xs), np.array(energy)
    peak = np.flatnonzero((xs[1:-1] > xs[:-2]) & (xs[1:-1] >= xs[2:])) + 1
    peaks = energy[peak]
    peaks = peaks[peaks > 1e-9 * energy[0]]
    assert len(peaks) >= 5
    if controller or energy_consistent:
        assert np.all(np.diff(peaks) < 0) and energy[-1] < 0.05 * energy[0]
    else:
        assert np.all(np.diff(peaks) > 0) and peaks[-1] > 5 * peaks[0]
        assert min(passivity) < -energy[0]                # the observer reports an active port

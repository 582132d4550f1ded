"""Passivity observer and controller of the haptic port (Hannaford and Ryu 2002).

Sign convention (chosen here): E is the energy that has flowed INTO the virtual environment
through the haptic port, i.e. the work done BY the device ON the environment:

    E(n) = - sum_{j=1..n} F(j-1) . (x(j) - x(j-1))

where F is the force the environment applies to the tool/device (the `tool_force` output) and x
the tool position. The force computed at sample j-1 is held over [t(j-1), t(j)] (zero-order hold),
so the displacement over that interval is the exact conjugate of the held force; with constant
velocity this is the usual sum F v T. A passive environment has E(n) >= 0 at all n (it can only
store or dissipate what the device gave it); E(n) < 0 means the environment has generated energy
(it is active, the seed of sampled-wall instability). For several tool points the port is the
set of points and the products are summed.

Passivity controller: when the observed E(n) < 0 it adds a variable damping on the tool,
F <- F - alpha v with alpha = -E(n) / (T v . v), which dissipates over the next sample exactly
the energy the environment has generated (alpha = 0 while E >= 0). The damping is held over a
sample like any rendered force, so alpha must stay below about 2 m / T for a device of mass m
(a held damper above that overshoots and is itself active: with a small |v| the unbounded gain
blows up); `max_damping` caps it (m / T dissipates the most per sample), and whatever energy the
cap leaves undissipated is taken over the following samples.
"""
import math

import numpy as np
from numba import njit


class PassivityError(ValueError):
    """Invalid input to the passivity observer/controller."""


class PassiveRenderer:
    """Observer + optional controller around a force source, one call per haptic sample.

    `render(position, velocity, force)` observes the port with the raw `force` (on the tool; arrays
    (n, 3)), and if the controller is on and the port has turned active, adds -alpha v; returns the
    force to apply (held until the next sample) and records it for the next energy increment.
    One numba kernel (hot path); tests/haptic_helpers.py holds the plain-Python observer and
    controller gain it is checked against.
    """

    def __init__(self, period: float, controller: bool = True, max_damping: float = math.inf):
        if not period > 0.0:
            raise PassivityError(f"period must be > 0 (got {period}): give the haptic sample time in s")
        if not max_damping > 0.0:
            raise PassivityError(f"max_damping must be > 0 (got {max_damping}): e.g. the device mass / period")
        self.period = float(period)
        self.max_damping = float(max_damping)
        self.controller = bool(controller)
        self.energy = 0.0
        self.min_energy = 0.0
        self.last_alpha = 0.0
        self._prev_position = None
        self._prev_force = None
        self._has_prev = False

    def render(self, position, velocity, force) -> np.ndarray:
        position = np.ascontiguousarray(position, np.float64).reshape(-1, 3)
        velocity = np.ascontiguousarray(velocity, np.float64).reshape(-1, 3)
        force = np.array(force, np.float64).reshape(-1, 3)
        self.render_in_place(position, velocity, force)
        return force

    def render_in_place(self, position, velocity, force) -> None:
        """`render` for (n,3) C-contiguous float64 arrays (the model's buffers): `force` is changed
        in place (no conversion, no copy: the 1 kHz path)."""
        if self._prev_position is None or self._prev_position.shape != position.shape:
            self._prev_position = np.zeros_like(position)
            self._prev_force = np.zeros_like(position)
            self._has_prev = False
        self.energy, self.last_alpha = passivity_step(
            position, velocity, force, self._prev_position, self._prev_force, self._has_prev, self.energy,
            self.period, self.controller, self.max_damping)
        self._has_prev = True
        self.min_energy = min(self.min_energy, self.energy)

    def observe(self, position) -> float:
        """Port energy including the work of the held force up to `position` (no sample recorded)."""
        if not self._has_prev:
            return self.energy
        position = np.asarray(position, np.float64).reshape(-1, 3)
        return self.energy - float(np.sum(self._prev_force * (position - self._prev_position)))


@njit(cache=True)
def passivity_step(position, velocity, force, prev_position, prev_force, has_prev, energy, period,
                   controller, max_damping):
    """One sample of the passivity observer/controller (see passivity.py for the convention).

    Adds the work of the held prev_force over position - prev_position to the port energy, then,
    when the controller is on and the energy is negative, adds -alpha velocity to `force` (in place)
    with alpha = min(-E / (T v.v), max_damping). Stores position and force as the new held sample.
    Returns (energy, alpha).
    """
    if has_prev:
        work = 0.0
        for i in range(position.shape[0]):
            for d in range(3):
                work += prev_force[i, d] * (position[i, d] - prev_position[i, d])
        energy -= work
    alpha = 0.0
    if controller and energy < 0.0:
        vv = 0.0
        for i in range(velocity.shape[0]):
            for d in range(3):
                vv += velocity[i, d] * velocity[i, d]
        if vv > 0.0:
            alpha = min(-energy / (period * vv), max_damping)
            for i in range(force.shape[0]):
                for d in range(3):
                    force[i, d] -= alpha * velocity[i, d]
    for i in range(position.shape[0]):
        for d in range(3):
            prev_position[i, d] = position[i, d]
            prev_force[i, d] = force[i, d]
    return energy, alpha

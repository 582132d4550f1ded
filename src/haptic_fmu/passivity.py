"""Passivity observer and controller of the haptic port (Hannaford and Ryu 2002), judged per contact
cycle, with the device's force limit.

Sign convention (chosen here): E is the energy that has flowed INTO the virtual environment
through the haptic port, i.e. the work done BY the device ON the environment:

    E(n) = - sum_{j=1..n} F(j-1) . (x(j) - x(j-1))

where F is the force the environment applies to the tool/device (the `tool_force` output) and x
the tool position. The force computed at sample j-1 is held over [t(j-1), t(j)] (zero-order hold),
so the displacement over that interval is the exact conjugate of the held force; with constant
velocity this is the usual sum F v T. A passive environment has E(n) >= 0 at all n (it can only
store or dissipate what the device gave it); E(n) < 0 means the environment has generated energy
(it is active, the seed of sampled-wall instability). For several tool points the port is the
set of points and the products are summed. F is the force the port rendered: after the passivity
controller and the device's limit (`device`), so the observer integrates what the device felt.

Passivity controller: when the observed E(n) < 0 it adds a variable damping on the tool,
F <- F - alpha v with alpha = -E(n) / (T v . v), which dissipates over the next sample exactly
the energy the environment has generated (alpha = 0 while E >= 0). The damping is held over a
sample like any rendered force, so alpha must stay below about 2 m / T for a device of mass m
(a held damper above that overshoots and is itself active: with a small |v| the unbounded gain
blows up); `max_damping` caps it (m / T dissipates the most per sample), and whatever energy the
cap leaves undissipated is taken over the following samples.

Contact cycles. The running E(n) mixes every contact of a run, so a leak of a few microjoules per
touch hides under the millijoules a long contact stores, and an absolute floor on E hides it
altogether (a 5 Hz tap on a sampled 1 kN/m wall returns 17-51 uJ more per tap than it took, up to
8 % of what was put in: the zero-order hold creates about K T / 2 v^2 per unit time). So each
contact cycle is also judged on its own, relative to the energy it exchanged:

- a cycle starts at the first sample whose contact force (the force the response computed, before
  the controller and the limit) is nonzero, and ends at the first sample where the contact force
  is zero and the force the port holds from then on is zero too: the force has been zero for one
  held interval, so the work of the last held force is in the cycle (a force the rate limit or the
  controller still holds after the contact keeps the cycle open until it is released);
- over the cycle the work of each held interval, w = -F(j-1) . (x(j) - x(j-1)), goes to the energy
  in (w > 0, device -> environment) or out (w < 0);
- at its end the cycle is active when the energy created, out - in, exceeds
  ``rel_tol * (in + out) + floor``. ``floor`` is the round-off of these sums, derived from their
  own numbers: the first-order bound of a 3n-term dot product per sample and of N samples summed
  is (3 n + N + 1) u sum|F_d dx_d| (u = 2^-53, the sum of the magnitudes of every product), and
  as much again for the rounding of the forces themselves (an energy-consistent response is
  conservative only to its own round-off): floor = 2 (3 n + N + 1) u sum|F_d dx_d|. For a
  1000-sample cycle of a probe that is 2.2e-13 of the energy exchanged; ``rel_tol`` (the Contact
  parameter ``passivity_cycle_tolerance``, default 1e-6) sits far above it and far below any leak
  worth knowing (the zero-order hold's: percents).

A cycle judged on its own assumes the environment is at rest between cycles: a wall still ringing
from a previous touch can return energy that an earlier cycle put in, and a wall driven by its own
sources (a pulsating vessel) gives energy it never took; the judgement then reports that energy too.
"""
from __future__ import annotations

import logging
import math

import numpy as np
from numba import njit

from .device import REPORT_SIZE, ForceLimiter, limit_force

logger = logging.getLogger(__name__)

#: Default relative tolerance of the per-cycle judgement (see the module documentation): the
#: energy-consistent hold (penalty.py) leaves what its prediction misses where the tool's velocity
#: changes, second order in the acceleration (2.4e-5 of a 5 Hz tap's exchange; up to a few 1e-3 at
#: a sharp reversal), while the sampled law's leak is 1-8 % of it.
DEFAULT_CYCLE_TOLERANCE = 1e-3
#: The unit round-off of float64 (2^-53).
UNIT_ROUNDOFF = 2.0 ** -53

#: Slots of the cycle array (`PassiveRenderer.cycle`): the open cycle, then the last closed one.
OPEN, ENERGY_IN, ENERGY_OUT, ABS_WORK, SAMPLES, T_START = range(6)
LAST_IN, LAST_OUT, LAST_THRESHOLD, LAST_T_START, LAST_T_END = range(6, 11)
CYCLE_SIZE = 11

#: Bits of `port_step`'s status beyond the device limiter's (device.RATE_LIMITED = 1, MAGNITUDE_LIMITED = 2).
CYCLE_CLOSED = 4
CYCLE_ACTIVE = 8
LIMITED = 3


class PassivityError(ValueError):
    """Invalid input to the passivity observer/controller."""


class PassiveRenderer:
    """Observer + optional controller + device limit around a force source, one call per haptic
    sample.

    `render(position, velocity, force)` observes the port, and if the controller is on and the
    port has turned active, adds -alpha v; then the device limit (`limiter`, a
    `device.ForceLimiter`, None for none) bounds the force; returns the force to apply (held until
    the next sample) and records it for the next energy increment and the contact cycle. One numba
    kernel (hot path); tests/haptic_helpers.py holds the plain-Python observer, controller gain,
    cycle judgement and limiter it is checked against.

    Per-cycle results: `cycles` and `active_cycles` (counts of closed cycles), `last_cycle_energy`
    (in - out of the last closed cycle, J: >= 0 passive, the sign of `energy`) and the `cycle`
    array; the first active cycle is logged with its numbers, then the count at 10, 100, ...
    active cycles. `force_limited`: the device limit engaged at the last sample (the limiter's
    counts and log line are its own, `device.ForceLimiter`).
    """

    def __init__(self, period: float, controller: bool = True, max_damping: float = math.inf,
                 limiter: ForceLimiter | None = None, cycle_tolerance: float = DEFAULT_CYCLE_TOLERANCE):
        if not period > 0.0:
            raise PassivityError(f"period must be > 0 (got {period}): give the haptic sample time in s")
        if not max_damping > 0.0:
            raise PassivityError(f"max_damping must be > 0 (got {max_damping}): e.g. the device mass / period")
        if not (cycle_tolerance >= 0.0 and math.isfinite(cycle_tolerance)):
            raise PassivityError(f"cycle_tolerance must be a finite number >= 0 (got {cycle_tolerance}): the share "
                                 "of a contact cycle's exchanged energy it may create, e.g. 1e-6")
        self.period = float(period)
        self.max_damping = float(max_damping)
        self.controller = bool(controller)
        self.limiter = limiter
        self.cycle_tolerance = float(cycle_tolerance)
        self.energy = 0.0
        self.min_energy = 0.0
        self.last_alpha = 0.0
        self.cycle = np.zeros(CYCLE_SIZE)
        self.cycles = 0                 # closed contact cycles
        self.active_cycles = 0          # closed contact cycles judged active
        self.worst_cycle = 0.0          # the largest (out - in) / (in + out) of an active cycle
        self.samples = 0                # samples rendered
        self.force_limited = False      # the device limit engaged at the last sample
        self.last_cycle_energy = 0.0    # energy into the environment over the last closed cycle, in - out (J)
        self._no_report = np.zeros(REPORT_SIZE)
        self._prev_position = None
        self._prev_force = None
        self._has_prev = False

    def render(self, position, velocity, force, t: float | None = None) -> np.ndarray:
        position = np.ascontiguousarray(position, np.float64).reshape(-1, 3)
        velocity = np.ascontiguousarray(velocity, np.float64).reshape(-1, 3)
        force = np.array(force, np.float64).reshape(-1, 3)
        self.render_in_place(position, velocity, force, t)
        return force

    def render_in_place(self, position, velocity, force, t: float | None = None) -> None:
        """`render` for (n,3) C-contiguous float64 arrays (the model's buffers): `force` is changed
        in place (no conversion, no copy: the 1 kHz path). t (s): the sample's time, for the
        cycles' and the limit's log lines (None: counted in samples of `period`)."""
        if self._prev_position is None or self._prev_position.shape != position.shape:
            self._prev_position = np.zeros_like(position)
            self._prev_force = np.zeros_like(position)
            self._has_prev = False
        self.samples += 1
        if t is None:
            t = self.samples * self.period
        limiter = self.limiter
        if limiter is None:
            max_force = max_step = math.inf
            report = self._no_report
        else:
            max_force, max_step, report = limiter.max_force, limiter.max_force_rate * self.period, limiter.report
        self.energy, self.last_alpha, status = port_step(
            position, velocity, force, self._prev_position, self._prev_force, self._has_prev, self.energy,
            self.period, self.controller, self.max_damping, max_force, max_step, report, self.cycle,
            self.cycle_tolerance, float(t))
        self._has_prev = True
        if self.energy < self.min_energy:
            self.min_energy = self.energy
        limited = status & LIMITED
        if limited or self.force_limited:
            limiter.record(limited, float(t))
            self.force_limited = limited != 0
        if status & CYCLE_CLOSED:
            self._closed(status)

    def _closed(self, status: int) -> None:
        """A contact cycle closed at this sample: count it, and log the first active one and the
        count at every power of ten."""
        self.cycles += 1
        c = self.cycle
        energy_in, energy_out = float(c[LAST_IN]), float(c[LAST_OUT])
        self.last_cycle_energy = energy_in - energy_out
        if not status & CYCLE_ACTIVE:
            return
        self.active_cycles += 1
        share = (energy_out - energy_in) / (energy_in + energy_out)
        self.worst_cycle = max(self.worst_cycle, share)
        if self.active_cycles == 1:
            logger.warning(
                "passivity observer: the contact cycle from t = %.6g s to %.6g s returned %.4g J and took %.4g J: it "
                "created %.3g J (%.3g %% of the %.3g J exchanged, above the tolerance %.3g J), an active contact; "
                "the next active cycles are counted in active_cycles (a sampled penalty wall creates about "
                "K T / 2 v^2 per unit time: a wall damping B > K T / 2 takes it out within the contact, a device "
                "damping b_dev > K T / 2 + |B| keeps the loop passive%s)",
                c[LAST_T_START], c[LAST_T_END], energy_out, energy_in, energy_out - energy_in, 100.0 * share,
                energy_in + energy_out, c[LAST_THRESHOLD],
                "; passivity_controller = true dissipates it" if not self.controller else
                "; the passivity controller dissipates it afterwards, from the run's balance")
        elif math.log10(self.active_cycles).is_integer():
            logger.warning("passivity observer: %d of %d contact cycles active so far (up to %.3g %% of the energy "
                           "they exchanged created)", self.active_cycles, self.cycles, 100.0 * self.worst_cycle)

    def observe(self, position) -> float:
        """Port energy including the work of the held force up to `position` (no sample recorded)."""
        if not self._has_prev:
            return self.energy
        position = np.asarray(position, np.float64).reshape(-1, 3)
        return self.energy - float(np.sum(self._prev_force * (position - self._prev_position)))


@njit(cache=True)
def port_step(position, velocity, force, prev_position, prev_force, has_prev, energy, period, controller,
              max_damping, max_force, max_step, report, cycle, cycle_tolerance, t):
    """One sample of the haptic port (see the module documentation): observer, contact cycle,
    controller, device limit, held sample. One kernel for all of them: the 1 kHz path pays one call.

    Adds the work of the held prev_force over position - prev_position to the port energy and to
    the open contact cycle; when the controller is on and the energy is negative, adds -alpha
    velocity to `force` (in place) with alpha = min(-E / (T v.v), max_damping); limits `force` to
    the device (`device.limit_force`: max_step = rate limit x T; inf, inf for none; `report` gets
    the requested force); opens, or closes and judges, the contact cycle (`cycle`, CYCLE_SIZE
    slots; t the sample's time). Stores position and force as the new held sample.
    Returns (energy, alpha, status bits: device.RATE_LIMITED, MAGNITUDE_LIMITED, CYCLE_CLOSED,
    CYCLE_ACTIVE).
    """
    n = position.shape[0]
    work = 0.0
    magnitude = 0.0
    if has_prev:
        for i in range(n):
            for d in range(3):
                p = prev_force[i, d] * (position[i, d] - prev_position[i, d])
                work += p
                magnitude += abs(p)
        energy -= work
    open_cycle = cycle[OPEN] != 0.0
    if open_cycle:
        if work < 0.0:
            cycle[ENERGY_IN] -= work
        else:
            cycle[ENERGY_OUT] += work
        cycle[ABS_WORK] += magnitude
        cycle[SAMPLES] += 1.0
    contact = False
    for i in range(n):
        for d in range(3):
            if force[i, d] != 0.0:
                contact = True
    alpha = 0.0
    if controller and energy < 0.0:
        vv = 0.0
        for i in range(velocity.shape[0]):
            for d in range(3):
                vv += velocity[i, d] * velocity[i, d]
        if vv > 0.0:
            alpha = min(-energy / (period * vv), max_damping)
            for i in range(n):
                for d in range(3):
                    force[i, d] -= alpha * velocity[i, d]
    status = limit_force(force, prev_force, max_force, max_step, report)
    held = False
    for i in range(n):
        for d in range(3):
            prev_position[i, d] = position[i, d]
            prev_force[i, d] = force[i, d]
            if force[i, d] != 0.0:
                held = True
    if open_cycle and not contact and not held:
        energy_in, energy_out = cycle[ENERGY_IN], cycle[ENERGY_OUT]
        floor = 2.0 * (3.0 * n + cycle[SAMPLES] + 1.0) * UNIT_ROUNDOFF * cycle[ABS_WORK]
        threshold = cycle_tolerance * (energy_in + energy_out) + floor
        cycle[LAST_IN] = energy_in
        cycle[LAST_OUT] = energy_out
        cycle[LAST_THRESHOLD] = threshold
        cycle[LAST_T_START] = cycle[T_START]
        cycle[LAST_T_END] = t
        cycle[OPEN] = 0.0
        status |= CYCLE_CLOSED
        if energy_out - energy_in > threshold:
            status |= CYCLE_ACTIVE
    elif not open_cycle and contact:
        cycle[OPEN] = 1.0
        cycle[ENERGY_IN] = 0.0
        cycle[ENERGY_OUT] = 0.0
        cycle[ABS_WORK] = 0.0
        cycle[SAMPLES] = 0.0
        cycle[T_START] = t
    return energy, alpha, status

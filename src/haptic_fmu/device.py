"""The haptic device's specification and the limiter of the force the haptic port renders.

A haptic device can exert only so much force, and a force that jumps by newtons within a
millisecond is a slam in the operator's hand whatever the virtual world says. So the force the
Contact model sends to the device is limited to a declared specification, as in CHAI3D: each
device driver declares its specification (``cHapticDeviceInfo``; ``m_maxLinearForce = 7.9`` N for
the "PHANTOM Desktop" in CHAI3D 3.2's ``CPhantomDevices.cpp``) and applications bound what they send
to the device by it (its examples read ``m_maxLinearForce`` to size their effects), while the
world's physics is left as it is.

Specification (:class:`DeviceSpec`)
- ``max_force`` (N), default 7.9 N: the nominal maximum exertable force of the PHANTOM Desktop
  (3D Systems Touch X: "maximum exertable force at nominal (orthogonal arms) position 7.9 N";
  continuous 1.75 N; CHAI3D declares the same 7.9 N). The desktop device the shipped scenes'
  stiffness is chosen for (1000 N/m, "what a PHANTOM Desktop renders").
- ``max_force_rate`` (N/s), default 10 000 N/s = 10 N per 1 ms step. The fastest change of a
  legitimate force is the stiffness times the hand's speed: 10 000 N/m (above any desktop
  device's 1-3 kN/m) x 0.5 m/s = 5 000 N/s, 5 N per step. The shipped scenes change the rendered
  force by at most 0.018 N per step (aaa_endovascular at 3000 N/m; 0.011 N at its 1000 N/m;
  catheter_tube 0.016 N; tissue_indentation 0.0008 N) and 0.74 N per step in virtual_wall (a
  probe hitting 800 N/m at 0.93 m/s). 10 N per step is twice the fastest legitimate change and
  13 times the virtual wall's, so it never engages in use; it does stop a slam: a force reversed
  from one sample to the next (up to 15.8 N per step within the 7.9 N limit: a contact normal
  flipping across a thin wall or a crease) or, on a stronger device, a force jumping from rest to
  tens of newtons (a tunnelled probe found deep in the wall) is spread over several steps. (A
  one-sided wall chattering between 0 and 7.9 N changes by less than 10 N per step: the magnitude
  limit bounds it, the rate limit does not engage.)

Limiter (:func:`limit_force`, run at every haptic step inside the passivity kernel, see
``passivity.port_step``): on the total force of the port F (the sum of the tool's node forces,
what the device renders), first the rate, then the magnitude:

    F' = F_prev + s (F - F_prev),  s = min(1, max_force_rate T / |F - F_prev|)
    F'' = c F',                     c = min(1, max_force / |F'|)

with F_prev the force rendered at the previous sample (zero before the first: a device starts at
rest). Both hold afterwards (to round-off): |F''| <= max_force, and |F'' - F_prev| <= max_force_rate T because
the scaling is the projection onto the ball |F| <= max_force, which holds F_prev (rendered, so
within it) and does not increase distances. Every node force gets the same two operations,
f_i' = c (f_i,prev + s (f_i - f_i,prev)), so the node forces still sum to the rendered force.

What is limited: the port (``tool_force``, ``node_forces``: what the device renders and what the
passivity observer integrates). What is not: ``tip_force`` (the catheter's input) and
``tissue_contact_force`` (the tissue's load) stay the physical contact force, as the world's
physics does not change with the device in CHAI3D; while the limit engages they no longer sum to
-tool_force (documented in ``ContactOutputs``).

Reporting (:class:`ForceLimiter`): the steps where a limit engaged (``force_limited``), their count,
and a log line (``logging.warning``, which the FMU layer forwards to the importer's log callback
as fmi3Warning) at the start of each limiting episode naming the time, the requested force and the
limit. An episode ends when no limit has engaged for ``EPISODE_GAP`` s, so a force riding the
limit, or chattering on it, gives one line and not one per millisecond.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from ._checks import is_finite_real

logger = logging.getLogger(__name__)

#: PHANTOM Desktop / Touch X nominal maximum exertable force (N); see the module documentation.
PHANTOM_DESKTOP_MAX_FORCE = 7.9
#: Default rate limit (N/s): twice the fastest legitimate change, 10 000 N/m x 0.5 m/s.
DEFAULT_MAX_FORCE_RATE = 10_000.0
#: Simulated seconds without a limit engaging that end a limiting episode (one log line per episode).
EPISODE_GAP = 0.1

#: Bits of the code `limit_force` returns.
RATE_LIMITED = 1
MAGNITUDE_LIMITED = 2

#: Slots of the limiter's report array (`limit_force`'s ``report``).
REQUESTED = slice(0, 3)     # the total force requested (before the limit), N
REQUESTED_TIP = slice(3, 6)  # the requested force on the last node (the catheter's physical tip force), N
SLOT_RATE_FACTOR = 6        # s (1: the rate limit did not engage)
SLOT_MAGNITUDE_FACTOR = 7   # c (1: the magnitude limit did not engage)
REPORT_SIZE = 8


class DeviceError(ValueError):
    """A device specification is out of range."""


@dataclass(frozen=True)
class DeviceSpec:
    """What the haptic device can render (SI units). Validated when made."""

    max_force: float = PHANTOM_DESKTOP_MAX_FORCE        # N
    max_force_rate: float = DEFAULT_MAX_FORCE_RATE      # N/s

    def __post_init__(self):
        for name, example in (("max_force", "7.9 N for a PHANTOM Desktop / Touch X, 3.3 N for a Touch"),
                              ("max_force_rate", "10000 N/s (10 N per 1 ms step)")):
            value = getattr(self, name)
            if not (is_finite_real(value) and value > 0):
                raise DeviceError(f"{name} must be a finite number > 0 (got {value!r}): e.g. {example}")

    def max_step(self, dt: float) -> float:
        """The largest change of the rendered force over a step of dt seconds (N)."""
        return self.max_force_rate * dt


@njit(cache=True)
def limit_force(force, prev, max_force, max_step, report):
    """Limit the port force in place: rate against the previous rendered force, then magnitude.

    force: (n, 3) node forces requested, overwritten with the rendered ones; prev: (n, 3) the node
    forces rendered at the previous sample (read only); max_force (N) and max_step (N, the rate
    limit times the step) > 0, inf for no limit. report (REPORT_SIZE,): the requested total and
    last-node force, the rate and magnitude factors s and c. Returns RATE_LIMITED | MAGNITUDE_LIMITED
    bits (0: unchanged). No allocation: the 1 kHz path.
    """
    n = force.shape[0]
    fx = fy = fz = 0.0
    px = py = pz = 0.0
    for i in range(n):
        fx += force[i, 0]
        fy += force[i, 1]
        fz += force[i, 2]
        px += prev[i, 0]
        py += prev[i, 1]
        pz += prev[i, 2]
    report[0] = fx
    report[1] = fy
    report[2] = fz
    report[3] = force[n - 1, 0]
    report[4] = force[n - 1, 1]
    report[5] = force[n - 1, 2]
    code = 0
    s = 1.0
    dx, dy, dz = fx - px, fy - py, fz - pz
    change = math.sqrt(dx * dx + dy * dy + dz * dz)
    if change > max_step:
        s = max_step / change
        code |= RATE_LIMITED
        for i in range(n):
            for d in range(3):
                force[i, d] = prev[i, d] + s * (force[i, d] - prev[i, d])
        fx, fy, fz = px + s * dx, py + s * dy, pz + s * dz
    c = 1.0
    magnitude = math.sqrt(fx * fx + fy * fy + fz * fz)
    if magnitude > max_force:
        c = max_force / magnitude
        code |= MAGNITUDE_LIMITED
        for i in range(n):
            for d in range(3):
                force[i, d] *= c
    report[6] = s
    report[7] = c
    return code


class ForceLimiter:
    """The device limit of one haptic port: its specification, the report of the last sample, and
    the bookkeeping of limiting episodes (counts, the log line at each episode's start).

    The limit itself runs in the passivity kernel (one kernel per haptic step); this object holds
    its arrays and interprets its result in `record`, which costs a comparison when nothing was
    limited. Holds numbers and numpy arrays only (FMU state: deepcopy and pickle)."""

    def __init__(self, spec: DeviceSpec | None = None):
        spec = spec or DeviceSpec()
        self.max_force = float(spec.max_force)
        self.max_force_rate = float(spec.max_force_rate)
        self.report = np.zeros(REPORT_SIZE)
        self.report[SLOT_RATE_FACTOR] = self.report[SLOT_MAGNITUDE_FACTOR] = 1.0
        self.code = 0                   # the last sample's RATE_LIMITED | MAGNITUDE_LIMITED bits
        self.limited_steps = 0          # samples whose force was limited, since the start
        self.episodes = 0               # limiting episodes, since the start
        self.largest_request = 0.0      # the largest |requested force| of a limited sample (N)
        self._last_limited_t = -math.inf

    @property
    def limited(self) -> bool:
        """Whether a limit engaged at the last sample."""
        return self.code != 0

    def record(self, code: int, t: float) -> None:
        """The limiter's result at the sample at time t (s): counts, and the episode's log line."""
        self.code = code
        if not code:
            return
        self.limited_steps += 1
        requested = float(np.linalg.norm(self.report[REQUESTED]))
        self.largest_request = max(self.largest_request, requested)
        if t - self._last_limited_t > EPISODE_GAP:
            self.episodes += 1
            logger.warning("%s", self.describe(code, t, requested))
        self._last_limited_t = t

    def describe(self, code: int, t: float, requested: float) -> str:
        """The episode's log line: time, requested force, the limit that engaged."""
        limits = []
        if code & MAGNITUDE_LIMITED:
            limits.append(f"the device's max_force {self.max_force:.3g} N")
        if code & RATE_LIMITED:
            limits.append(f"its max_force_rate {self.max_force_rate:.3g} N/s")
        return (f"haptic force limited at t = {t:.6g} s: {requested:.3g} N requested, rendered within "
                f"{' and '.join(limits)} (limiting episode {self.episodes}; tip_force and the tissue keep the "
                "physical contact force; logged once per episode, force_limited marks every limited step)")

"""Bending actuator of the active tip: first-order lag with angle and rate saturation.

``d theta / dt = (cmd - theta) * 2 pi f_b`` with the command held over the step (zero-order
hold) is integrated exactly: ``theta+ = cmd + (theta - cmd) exp(-2 pi f_b dt)``. The command is
first clipped to ``[-max_angle, max_angle]``; the change per step is then clipped to
``max_rate * dt`` (a slew limit, as a motor or a shape-memory drive has). With no saturation
active the response to a unit step is ``1 - exp(-2 pi f_b t)`` at the sample times, to
round-off.
"""

from __future__ import annotations

import logging
import math

logger = logging.getLogger(__name__)

__all__ = ["Actuator"]


class Actuator:
    """State: the bend angle ``angle`` (rad). Parameters are trusted (validated by the model)."""

    def __init__(self, bandwidth_hz: float, max_angle: float, max_rate: float, angle: float = 0.0) -> None:
        self.omega = 2.0 * math.pi * float(bandwidth_hz)
        self.max_angle = float(max_angle)
        self.max_rate = float(max_rate)
        self.angle = float(angle)
        self._dt = None
        self._decay = 1.0
        # +1 / -1 when the last step was cut by the rate limit upward / downward, else 0.
        self.rate_limited = 0

    def clip_command(self, command: float) -> float:
        return min(max(command, -self.max_angle), self.max_angle)

    def step(self, command: float, dt: float) -> float:
        """Advance by dt with the command held; return the new angle."""
        if dt != self._dt:
            self._dt = dt
            self._decay = math.exp(-self.omega * dt)
        cmd = self.clip_command(command)
        target = cmd + (self.angle - cmd) * self._decay
        max_step = self.max_rate * dt
        delta = target - self.angle
        if delta > max_step:
            delta, self.rate_limited = max_step, 1
        elif delta < -max_step:
            delta, self.rate_limited = -max_step, -1
        else:
            self.rate_limited = 0
        self.angle = min(max(self.angle + delta, -self.max_angle), self.max_angle)
        return self.angle

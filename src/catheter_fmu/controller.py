"""Tip force regulation and the effort advice reported to the surgeon.

Regulator (mode ``regulate``): PI on the force excess ``e = |F| - F_set`` with
``F_set = setpoint_fraction * force_threshold``. Its output ``u >= 0`` is how far (rad) to bend
the tip *away from the contact*, i.e. toward the force the wall exerts on the tip; with a
one-DOF bending plane (direction ``d`` set by the operator's rotation) the signed command is
``sign * u``: the side of the plane the force is on. A new contact takes its side as soon as
``|F . d|`` exceeds 1 % of ``|F|``; during a contact the side is held until the force is clearly on
the other one, ``F . d`` beyond ``DIRECTION_HYSTERESIS |F|`` (0.2: 11.5 degrees past perpendicular);
without force it is held. Taken at 1 % throughout, the tip's own motion can turn the force across the
perpendicular every step and the whole command flips with it: the actuator slews from one side to
the other every millisecond, a 500 Hz buzz of the force.

Anti-windup by conditional integration plus clamping: the integral stops growing while the
output is saturated (angle limit, or ``u = 0``) or the actuator is slew-limited, and the error
pushes further in that direction; it is kept in ``[0, max_angle]``. The rate limit matters:
a large force excess asks for a bend faster than the actuator slews, and an integral that keeps
accumulating meanwhile makes the force undershoot the setpoint afterwards. With ``anti_windup=False`` the integral is free (plain PI), which shows the
classic overshoot after a saturating phase.

Effort advice: ``effort_warning`` switches on when ``|F| >= force_threshold`` and off when
``|F| <= force_threshold - warning_hysteresis``. ``advised_insertion_scale`` is 1 for
``|F| <= a * threshold``, 0 for ``|F| >= b * threshold`` and the C1 smoothstep
``1 - (3 x^2 - 2 x^3)``, ``x = (|F| - a T) / ((b - a) T)``, in between (defaults a = 0.5, b = 2).
"""

from __future__ import annotations

import logging

logger = logging.getLogger(__name__)

__all__ = ["ForceRegulator", "EffortMonitor", "insertion_scale"]

# |F . d| / |F| beyond which a new contact's force has a side of the bending plane.
_DIRECTION_DEADBAND = 0.01
# |F . d| / |F| beyond which the force of a contact is on the other side of the bending plane (the
# sine of 11.5 degrees): the bending direction flips only then.
DIRECTION_HYSTERESIS = 0.2


class ForceRegulator:
    """PI force regulator; state: ``integral`` (rad), the held bending ``direction`` (+1/-1) and
    whether a contact has given it (``touching``)."""

    def __init__(self, kp: float, ki: float, setpoint: float, max_angle: float, anti_windup: bool = True) -> None:
        self.kp = float(kp)
        self.ki = float(ki)
        self.setpoint = float(setpoint)
        self.max_angle = float(max_angle)
        self.anti_windup = bool(anti_windup)
        self.integral = 0.0
        self.direction = 1.0
        self.touching = False
        self.saturated = False

    def reset(self) -> None:
        self.integral = 0.0
        self.direction = 1.0
        self.touching = False
        self.saturated = False

    def command(self, force_magnitude: float, force_along_bend: float, dt: float, actuator_limited: int = 0) -> float:
        """Signed bend command (rad) from |F| and F . d (N); advances the integral by dt.

        ``actuator_limited``: +1 / -1 if the actuator's last step was slew-limited upward /
        downward (in bend-angle sign), else 0.
        """
        if force_magnitude <= 0.0:
            self.touching = False
        elif not self.touching:
            if abs(force_along_bend) > _DIRECTION_DEADBAND * force_magnitude:
                self.direction = 1.0 if force_along_bend > 0.0 else -1.0
                self.touching = True
        elif force_along_bend * self.direction < -DIRECTION_HYSTERESIS * force_magnitude:
            self.direction = -self.direction
        error = force_magnitude - self.setpoint
        unsat = self.kp * error + self.integral
        u = min(max(unsat, 0.0), self.max_angle)
        self.saturated = u != unsat
        if self.anti_windup:
            # Slew limit seen in the regulator's own sign convention (u = direction * angle).
            slewing = actuator_limited * self.direction
            pushing_out = ((unsat > self.max_angle or slewing > 0) and error > 0.0) or (
                (unsat < 0.0 or slewing < 0) and error < 0.0
            )
            if not pushing_out:
                self.integral = min(max(self.integral + self.ki * error * dt, 0.0), self.max_angle)
        else:
            self.integral += self.ki * error * dt
        return self.direction * u


def insertion_scale(force_magnitude: float, threshold: float, start_fraction: float, stop_fraction: float) -> float:
    """Advised insertion speed scale in [0, 1] (see module docstring)."""
    x = (force_magnitude - start_fraction * threshold) / ((stop_fraction - start_fraction) * threshold)
    if x <= 0.0:
        return 1.0
    if x >= 1.0:
        return 0.0
    return 1.0 - x * x * (3.0 - 2.0 * x)


class EffortMonitor:
    """Hysteretic effort warning and the advised insertion scale."""

    def __init__(self, threshold: float, hysteresis: float, start_fraction: float, stop_fraction: float) -> None:
        self.threshold = float(threshold)
        self.release = float(threshold) - float(hysteresis)
        self.start_fraction = float(start_fraction)
        self.stop_fraction = float(stop_fraction)
        self.warning = False

    def update(self, force_magnitude: float) -> tuple[bool, float]:
        if force_magnitude >= self.threshold:
            self.warning = True
        elif force_magnitude <= self.release:
            self.warning = False
        scale = insertion_scale(force_magnitude, self.threshold, self.start_fraction, self.stop_fraction)
        return self.warning, scale

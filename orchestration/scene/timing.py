"""Times in scenes: exact rationals (``fractions.Fraction``) from numbers and "1/30" strings, and the
checks of steps and durations."""
from __future__ import annotations

import math
from fractions import Fraction

import numpy as np

from orchestration.scene.model import MAX_RUN_STEPS, MAX_STEP, MIN_STEP


# -- small parsers that collect problems instead of raising ------------------------------------
def parse_time(value, where: str, problems: list[str], *, allow_zero: bool = False) -> Fraction | None:
    """A time in seconds as an exact Fraction: a number (0.001 is 1/1000) or a string "1/30"."""
    try:
        if isinstance(value, bool):
            raise TypeError
        if isinstance(value, Fraction):
            result = value
        elif isinstance(value, (int, float)):
            if not np.isfinite(value):
                raise ValueError
            result = float_time(value) if isinstance(value, float) else Fraction(value)
        elif isinstance(value, str):
            result = _parse_time_text(value)
        else:
            raise TypeError
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        problems.append(f"{where}: {value!r} is not a time in seconds; write a finite number (0.001) "
                        "or a ratio (\"1/30\")")
        return None
    if result < 0 or (result == 0 and not allow_zero):
        problems.append(f"{where}: must be positive (got {value!r} s)")
        return None
    return result


def _parse_time_text(text: str) -> Fraction:
    """ "0.001", "1e-3" or "1/30" as a Fraction; ValueError otherwise. Decimals go through a float
    first: ``Fraction("1e-999999999")`` would compute 10**999999999 and never return."""
    text = text.strip()
    if "/" in text:
        numerator, denominator = text.split("/", 1)
        return Fraction(int(numerator), int(denominator))
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(text)
    return float_time(value)


def step_problem(step: Fraction) -> str | None:
    """Why ``step`` cannot be meant as a communication step (outside MIN_STEP..MAX_STEP), or None."""
    if step < MIN_STEP:
        return (f"{format_time(step).strip(chr(34))} s is shorter than {MIN_STEP} s, the shortest step a component "
                f"of this project can mean (the haptic loop runs at 1 kHz); give the step in seconds, e.g. 0.001")
    if step > MAX_STEP:
        return (f"{float(step):g} s is longer than {MAX_STEP} s, the longest step a component of this project can "
                "mean (the tissue runs at 30 Hz); give the step in seconds, e.g. \"1/30\"")
    return None


def float_time(value: float) -> Fraction:
    """The time a float means: 0.001 is 1/1000, and 0.03333333333333333 (1/30 rounded, as model
    descriptions write it) is 1/30, the simple ratio whose nearest float it is."""
    exact = Fraction(repr(value))
    if exact.denominator > 10**6:
        simple = exact.limit_denominator(10**6)
        if float(simple) == value:
            return simple
    return exact


def format_time(value: Fraction) -> str:
    """A time as a scene writes it: a decimal when exact (0.002), else a ratio in quotes ("1/30")."""
    d = value.denominator
    while d % 2 == 0:
        d //= 2
    while d % 5 == 0:
        d //= 5
    if d == 1:
        return repr(float(value)) if value.denominator != 1 else str(value.numerator)
    return f'"{value.numerator}/{value.denominator}"'


def duration_problem(components, duration: Fraction) -> str | None:
    """Why a run of ``duration`` cannot end exactly on every stepped component's grid, or None.

    A run ends where every component has made whole steps: a duration that is not a multiple of a
    step would overshoot it, so it is refused (with the nearest durations that work).
    """
    steps = [c.step for c in components if c.step is not None]
    if not steps:
        return None
    period = Fraction(0)
    for step in steps:  # the lcm of rationals: lcm of numerators over gcd of denominators
        period = step if period == 0 else Fraction(math.lcm(period.numerator, step.numerator),
                                                     math.gcd(period.denominator, step.denominator))
    if (duration / period).denominator == 1:
        return None
    below = (duration // period) * period
    options = [d for d in (below, below + period) if d > 0]
    offending = ", ".join(f"{c.name} ({c.step} s)" for c in components
                          if c.step is not None and (duration / c.step).denominator != 1)
    return (f"{float(duration):g} s is not a whole number of steps of {offending}; a run ends on every "
            f"component's grid: use a multiple of {period} s, e.g. "
            + " or ".join(f"{float(d):.6g}" for d in options))


def run_size_problem(components, duration: Fraction) -> str | None:
    """Why a run of ``duration`` is too long to be meant (more than MAX_RUN_STEPS steps), or None."""
    stepped = [c for c in components if c.step is not None]
    total = sum(duration / c.step for c in stepped)
    if total <= MAX_RUN_STEPS:
        return None
    fastest = min(stepped, key=lambda c: c.step)
    longest = MAX_RUN_STEPS / sum(1 / c.step for c in stepped)
    return (f"{float(duration):g} s means {float(total):.3g} component steps ({fastest.name} alone takes "
            f"{float(duration / fastest.step):.3g}), more than the limit of {MAX_RUN_STEPS:.0e} steps per run "
            f"(about 50 minutes of computing on a 2-core machine); give the duration in seconds, at most "
            f"{float(longest):.6g} s with these steps, or split a long session into several runs")

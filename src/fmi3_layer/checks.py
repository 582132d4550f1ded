"""What counts as a number for the models' checks of their parameters and inputs.

Each FMU package links this file as ``<package>/_checks.py``, so that the three models share one
definition while each raises its own error with its own message (the message names the value and
the fix; the checks here only answer yes or no). Plain Python, no numpy: numpy's scalars are
``numbers.Real`` (``np.bool_`` is not), so they pass as the numbers they are.

- :func:`is_real`: a real number of a numeric type, not a Boolean (Python counts ``True`` as 1,
  which would let a switch pass for a stiffness).
- :func:`is_finite_real`: the same, and neither NaN nor infinite.
- :func:`is_integer`: an integer of an integer type (int, numpy integers), not a Boolean.
- :func:`as_float`: ``float(value)`` where a value may be any number or text of one (the mesh
  generator's and the catheter's parameters), None where ``float`` refuses it.
"""
from __future__ import annotations

import math
import numbers

__all__ = ["as_float", "is_finite_real", "is_integer", "is_real"]


def is_real(value) -> bool:
    """A real number (int, float, a numpy scalar, a Fraction), not a Boolean."""
    if type(value) is float:  # the 1 kHz common case, checked cheaply
        return True
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def is_finite_real(value) -> bool:
    """A real number (:func:`is_real`) that is neither NaN nor infinite."""
    if type(value) is float:  # the 1 kHz common case, checked cheaply
        return math.isfinite(value)
    return is_real(value) and math.isfinite(value)


def is_integer(value) -> bool:
    """An integer of an integer type (int, a numpy integer), not a Boolean."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def as_float(value) -> float | None:
    """``float(value)``, or None when ``float`` refuses the value (no number, no text of one)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return None

"""The orchestrator's checks of the values a user gives (scenes, blocks, command lines): one set.

TOML integers have no size limit, so a "number" may be one no float holds (10**400); and a Boolean
is an integer to Python but never a number in a scene.
"""
from __future__ import annotations

import math
import numbers

import numpy as np


def is_real(value) -> bool:
    """A number a float can hold (not a Boolean; an integer beyond any float is not)."""
    if not isinstance(value, numbers.Real) or isinstance(value, (bool, np.bool_)):
        return False
    try:
        float(value)
    except OverflowError:
        return False
    return True


def is_int(value) -> bool:
    """An integer, not a Boolean."""
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def is_finite_number(value) -> bool:
    """A finite number; False for an integer beyond any float (TOML integers have no size limit)."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False

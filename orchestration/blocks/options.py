"""A block's options checked: each checker appends a readable problem and returns the clean value (or None)."""
from __future__ import annotations

import math

import numpy as np

from orchestration.checks import is_int, is_real


class BlockConfigError(ValueError):
    """A block's options are invalid; ``problems`` lists every problem found, each naming the key."""

    def __init__(self, problems: list[str], block: str | None = None):
        self.problems = list(problems)
        self.block = block
        where = f"block '{block}'" if block else "block"
        lines = "\n".join(f"  - {p}" for p in self.problems)
        super().__init__(f"{where}: {len(self.problems)} configuration problem(s):\n{lines}")


# ---------------------------------------------------------------------------------- value checks
# Each checker appends readable problems to `problems` and returns the clean value (or None).

def check_real(problems, key, value, fix, *, low=None, strict=True):
    if not (is_real(value) and math.isfinite(value)):
        problems.append(f"{key} must be a finite number (got {value!r}): {fix}")
        return None
    value = float(value)
    if low is not None and (value <= low if strict else value < low):
        problems.append(f"{key} must be {'>' if strict else '>='} {low:g} (got {value!r}): {fix}")
        return None
    return value


def check_int(problems, key, value, fix, *, low=1):
    if not is_int(value) or value < low:
        problems.append(f"{key} must be an integer >= {low} (got {value!r}): {fix}")
        return None
    return int(value)


def check_vector(problems, key, value, n, fix):
    try:
        arr = np.asarray(value, dtype=np.float64)
    except OverflowError:  # an integer no float holds (TOML integers have no size limit)
        problems.append(f"{key} must hold finite numbers (got {value!r}): {fix}")
        return None
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != (n,) or isinstance(value, (str, bytes)) or (
            not isinstance(value, np.ndarray) and not all(is_real(v) for v in value)):
        problems.append(f"{key} must be a list of {n} numbers (got {value!r}): {fix}")
        return None
    if not np.isfinite(arr).all():
        problems.append(f"{key} must hold finite numbers (got {value!r}): {fix}")
        return None
    return arr


def check_choice(problems, key, value, options):
    if value not in options:
        problems.append(f"{key} must be one of {list(options)} (got {value!r})")
        return None
    return value


def check_units(problems, key, value, names):
    if value is None:
        return {}
    if not isinstance(value, dict) or not all(isinstance(u, str) for u in value.values()):
        problems.append(f"{key} must be a table output name -> unit string (got {value!r}), e.g. {{ insertion = \"m\" }}")
        return {}
    unknown = sorted(set(value) - set(names))
    if unknown:
        problems.append(f"{key} names unknown outputs {unknown}: the outputs are {sorted(names)}")
    return dict(value)

"""The float64 buffers a bound FMU instance reads its inputs from and writes its observed outputs
into, and how ports are laid out in one buffer (the same in every process that shares it)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

#: The largest integer magnitude below which every integer is a float64 exactly.
EXACT_INTEGER = 2 ** 53


class PortLike:  # documentation only: what bind() reads of a port
    type: str
    value_reference: int
    size: int


def slot_layout(ports: Mapping[str, PortLike], names: Sequence[str]) -> tuple[dict[str, tuple[int, int]], int]:
    """Offsets ``name -> (start, stop)`` in one float64 buffer, grouped by type (Float64 first), and its size.

    A pure function of the port lists, so that two processes lay out the same shared buffer alike.
    """
    order = sorted(range(len(names)), key=lambda i: (ports[names[i]].type != "Float64", ports[names[i]].type, i))
    layout, offset = {}, 0
    for i in order:
        size = ports[names[i]].size
        layout[names[i]] = (offset, offset + size)
        offset += size
    return layout, offset


def exact_in_float64(values: np.ndarray) -> bool:
    """Whether every integer in ``values`` is one float64 holds exactly (|v| <= 2**53), compared as integers."""
    if not values.size:
        return True
    if int(values.max()) > EXACT_INTEGER:
        return False
    return values.dtype.kind == "u" or int(values.min()) >= -EXACT_INTEGER


@dataclass
class InputPort:
    """A writable port: its float64 slot and, for other types, the native buffer it is cast to."""

    name: str
    call: str
    size: int
    vr: object
    slot: np.ndarray
    native: np.ndarray
    pointer: object
    setter: object
    exact: bool   # integer and Boolean values must survive the cast unchanged
    cast: bool    # native is not slot


@dataclass
class OutputGroup:
    """Observed ports of one type, read with one call into ``native`` then cast into ``slot``."""

    call: str
    count: int
    size: int
    vrs: object
    slot: np.ndarray
    native: np.ndarray
    pointer: object
    getter: object
    cast: bool
    wide: bool    # 64-bit integers: checked to fit float64 exactly
    names: tuple

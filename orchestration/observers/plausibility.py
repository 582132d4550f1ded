"""Plausible ranges of outputs: the declared range of a port, or a magnitude no run of this project can
mean."""
from __future__ import annotations

import math

from orchestration.blocks.plant import PLANT_MAX_POSITION, PLANT_MAX_SPEED


# -- physical plausibility of the outputs ------------------------------------------------------------
#: The plausible magnitude of a run's outputs, by unit: every value of a Float output of a stepped
#: component (an FMU or a block such as the device plant) lies within +-bound, or the run's summary
#: warns ("warnings", "implausible_outputs"): a value beyond it is a model that diverged, a unit slip
#: or a force far beyond the scene's, not a result. An output whose FMU declares min/max in its
#: modelDescription.xml (from its limit table, FmuDeclaration.limits) is held to that range instead;
#: one without it is also held to the range of each input it feeds (the consumer's limit table is the
#: contract, e.g. Tissue's compliance to Contact's). Outputs in other units that feed no such input
#: are not checked. The one table of these bounds.
PLAUSIBLE_MAGNITUDE: dict[str, tuple[float, str]] = {
    "m": (PLANT_MAX_POSITION, "positions and lengths: the body, the vessel and a device's workspace (about 0.2 m) "
                              "lie within metres of the origin; a device plant starting beyond it is refused too"),
    "m/s": (PLANT_MAX_SPEED, "speeds: a hand, a device or a wall moves at centimetres to metres per second"),
    "N": (1e4, "forces: 10 kN is 1000 times what a catheter or a haptic device applies; the FMUs refuse a force "
               "input beyond it"),
    "J": (1e5, "energies: the work of 10 kN over 10 m"),
    "N/m": (1e9, "stiffnesses: the Catheter refuses a tip stiffness beyond it"),
    "rad": (1e6, "angles: the Catheter refuses a rotation beyond 1e6 rad (160k turns)"),
}
#: Outputs of up to this many values are checked at every step; larger ones (a tissue's surface, its
#: nodal forces: thousands of values each step) at the end of the run, where the run reads them.
PLAUSIBILITY_STEP_VALUES = 1024


def _declared(port) -> tuple[float, float] | None:
    if port.minimum is None and port.maximum is None:
        return None
    return (-math.inf if port.minimum is None else float(port.minimum),
            math.inf if port.maximum is None else float(port.maximum))


def plausible_range(port, consumers=()) -> tuple[float, float, str] | None:
    """``(low, high, why)`` bounding every value of the output ``port`` (a PortInfo), or None when
    nothing bounds it: its declared min/max, else the declared ranges of the inputs it feeds
    (``consumers``: ``(name, PortInfo)``) and PLAUSIBLE_MAGNITUDE of its unit, all of them."""
    if port.causality != "output" or port.type not in ("Float64", "Float32"):
        return None
    declared = _declared(port)
    if declared is not None:
        return (*declared, "the range its FMU declares for it (min/max in its modelDescription.xml)")
    # each bound that applies, as (low, high, why): the output must keep within all of them
    bounds = [(*_declared(target), f"the range {name} accepts (min/max in its FMU's modelDescription.xml)")
              for name, target in consumers if _declared(target) is not None]
    magnitude = PLAUSIBLE_MAGNITUDE.get(port.unit)
    if magnitude is not None:
        bounds.append((-magnitude[0], magnitude[0], magnitude[1]))
    if not bounds:
        return None
    narrowest = min(bounds, key=lambda b: b[1] - b[0])
    return max(b[0] for b in bounds), min(b[1] for b in bounds), narrowest[2]


def _excess(value: float, low: float, high: float) -> float:
    """How far ``value`` lies outside [low, high] (inf for NaN: nothing is further)."""
    if value != value:
        return math.inf
    return max(low - value, value - high)

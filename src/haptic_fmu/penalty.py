"""Contact response: penalty laws and how a contact's force reaches the tool and the tissue.

The haptic force on the tool (design eq. 5, law "linear"):

    F_c = -k dist n - b (v . n) n    if dist < 0, else 0

with n the facet's outward unit normal (triangle (a, b, c) wound so that (b-a) x (c-a) points out
of the tissue), dist = (p - q) . n the signed distance of the tool point p (q: the closest point
of the facet, so dist is the plane distance; dist < 0 is penetration) and v the velocity of the
tool relative to the surface at q. The tissue receives exactly -F_c, applied at q and split over
the facet's three vertices by the barycentric weights of q (so the nodal forces sum to -F_c and
their moment about any point equals that of -F_c applied at q).

Penalty laws (delta = -dist > 0, rate = d delta/dt = -(v.n); d0 = `penalty_length`):
- "linear":        f = k delta + b rate                            energy k delta^2 / 2
- "quadratic":     f = k delta (1 + delta/d0) + b rate             energy k delta^2/2 + k delta^3/(3 d0)
- "hunt_crossley": f = max(0, k delta (delta/d0)^0.5 + b (delta/d0) rate)   energy 0.4 k delta^2.5/d0^0.5
  (k keeps units of N/m: it is the secant stiffness at delta = d0; damping grows with depth so the
  force starts from zero at first contact and never pulls the tool in.)

Energy-consistent hold (the default, parameter `energy_consistent`): the force is computed at a
sample and held until the next one (a zero-order hold), while the depth keeps changing. Held at its
sampled value k delta_j over an interval in which the depth goes from delta_j to delta_j+1, it does
the work k delta_j (delta_j+1 - delta_j), short of the potential's change by k (delta_j+1 - delta_j)^2 / 2
in both directions of motion: a sampled penalty wall creates about K T / 2 v^2 per unit time, and
a touch-and-release (a tap) returns more energy than it took. So the elastic part is held at its mean over the depths
predicted for the hold interval, [delta, delta + rate T] (T the step, rate the measured depth rate):
the difference quotient of the potential, (E(delta + rate T) - E(delta)) / (rate T) (k (delta + rate
T / 2) for the linear law; when the predicted depth leaves the contact, the stored energy spread over
the whole interval, E(delta) / (-rate T)). For a tool moving at constant velocity against a static wall
the held force then does exactly the potential's change over every interval: the energy stored on
the way in is what comes back on the way out, to round-off, except for what the interval of first
touch stores before any force is held (at most k (v T)^2 / 2 per contact). At rest it is the law
itself. Its price is the same as any damping from a differenced velocity: K T / 2 more of it at
the Nyquist frequency (Colgate's bound for a device of damping b becomes b > K T / 2 + |B| + K T / 2),
which the device's damping or the passivity controller covers.

The rigid-wall response (local models "hold" and "extrapolate") is `penalty_kernels.penalty_forces`
then `penalty_kernels.distribute`; the compliance local model solves the same laws against a
yielding wall (`rendering_kernels.compliance_forces`) and distributes the same way.
"""
from . import penalty_kernels as kernels

PENALTY_LAWS = {"linear": kernels.LAW_LINEAR, "quadratic": kernels.LAW_QUADRATIC,
                "hunt_crossley": kernels.LAW_HUNT_CROSSLEY}


class PenaltyInputError(ValueError):
    """Invalid input to a penalty computation."""


def law_code(name: str) -> int:
    """Kernel code of a penalty law name; ValueError naming the choices otherwise."""
    try:
        return PENALTY_LAWS[name]
    except (KeyError, TypeError):
        raise PenaltyInputError(
            f"penalty_law must be one of {sorted(PENALTY_LAWS)} (got {name!r})") from None


def normal_force(depth, rate, law="linear", stiffness=500.0, damping=0.0, penalty_length=1e-3, hold=0.0) -> float:
    """Force magnitude along the outward normal for penetration `depth` (m) and rate d depth/dt;
    hold (s) > 0: the force held over the next `hold` seconds, its elastic part the law's mean over
    the predicted depths (see the module docstring)."""
    return float(kernels.penalty_magnitude(float(depth), float(rate), law_code(law), float(stiffness),
                                           float(damping), float(penalty_length), float(hold)))


def penalty_energy(depth, law="linear", stiffness=500.0, penalty_length=1e-3) -> float:
    """Elastic potential energy (J) stored by the penalty law at penetration `depth`."""
    return float(kernels.penalty_energy(float(depth), law_code(law), float(stiffness), float(penalty_length)))

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


def normal_force(depth, rate, law="linear", stiffness=500.0, damping=0.0, penalty_length=1e-3) -> float:
    """Force magnitude along the outward normal for penetration `depth` (m) and rate d depth/dt."""
    return float(kernels.penalty_magnitude(float(depth), float(rate), law_code(law), float(stiffness),
                                           float(damping), float(penalty_length)))


def penalty_energy(depth, law="linear", stiffness=500.0, penalty_length=1e-3) -> float:
    """Elastic potential energy (J) stored by the penalty law at penetration `depth`."""
    return float(kernels.penalty_energy(float(depth), law_code(law), float(stiffness), float(penalty_length)))

"""Controller-design tools for the active catheter, without the FMU.

Everything here runs the same ``CatheterModel`` the FMU wraps, closed on a rigid planar wall
(``PlaneWall``) through an explicit 1-step exchange, exactly as the co-simulation does: the
wall force computed from the tip position at the end of step k is the model's input in
step k + 1.

Linearised plant (``linearise`` / ``open_loop_frequency_response``). With the wall normal in the
bending plane, let ``beta`` be the total bend along the bending direction d, ``h = -d pen /
d beta`` the geometric lever of the bend on the wall penetration (``h = L cos(a) / 2`` for a
straight tip against a wall inclined by ``a``), ``q = n . d`` the share of the wall force across
the tip, ``g = L^2 / (2 EI)`` the passive bend per newton, ``k`` the wall stiffness. Then

    theta = w_b / (s + w_b) * theta_cmd                     (actuator, w_b = 2 pi f_b)
    tau beta_p' = g q F - beta_p                            (passive bend)
    F = k (pen_0 - h (theta + beta_p))                      (wall)

    P(s) = dF / dtheta_cmd = -k h * w_b / (s + w_b) * (1 + tau s) / (1 + G + tau s),  G = k h g q.

``P(0) = -k h / (1 + G)``: the catheter tip and the wall act as springs in series. The explicit
co-simulation exchange is stable while ``(1 - exp(-dt / tau)) (1 + G) < 2``
(``contact_loop_gain``); with the wall's stiffness passed along (``simulate(...,
tip_stiffness=True)``, the scenes' ``tip_stiffness`` connection) the passive bend is implicit and
stable at every G.

How to tune the regulator (``kp`` rad/N, ``ki`` rad/(N s)):

1. ``lin = linearise(params, wall, insertion)`` gives ``P0 = |P(0)|`` (N/rad) for the stiffest
   contact you expect (the loop gain grows with wall stiffness; a stiff wall is the worst case).
2. Integral action sets the speed. With the actuator pole dominant (the passive pole/zero
   pair sits above 1/tau) the closed loop is ``s^2 + w_b (1 + kp P0) s + w_b ki P0``:
   ``w_n = sqrt(w_b ki P0)``, damping ``zeta = 0.5 (1 + kp P0) sqrt(w_b / (ki P0))``. With
   ``kp = 0``, ``ki ~ w_b / (2 P0)`` gives zeta ~ 0.7; raise ki for speed until zeta ~ 0.7.
   Defaults (P0 ~ 1.2 N/rad on the default wall, w_b = 31.4 rad/s): ki = 8, kp = 0.3 give
   zeta ~ 1.2, a 0.25 s rise and 0.45 s settling with no overshoot (``step_response``).
3. ``kp`` adds damping and a zero at ``ki / kp``; keep ``kp P0 <~ 0.5`` so the proportional path
   does not ask the actuator for more than its bandwidth (and amplify contact-force noise).
4. Large force excesses are slew-limited: the bend needed, ``excess / P0``, takes at least
   ``excess / (P0 max_bend_rate)``; keep ``anti_windup=True`` so the saturated phases
   (angle limit reached, or no contact) do not cause overshoot afterwards.
5. Check with ``step_response`` (rise, overshoot, settling, steady-state error) and
   ``compare_gains`` (a table over candidate gains), then with the FMU in the scene.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from .model import CatheterModel, CatheterParameterError, CatheterParameters

logger = logging.getLogger(__name__)

__all__ = [
    "PlaneWall",
    "Trajectory",
    "simulate",
    "StepResponse",
    "step_response",
    "PlantLinearisation",
    "linearise",
    "FrequencyResponse",
    "open_loop_frequency_response",
    "simulated_frequency_response",
    "contact_loop_gain",
    "compare_gains",
    "format_gain_table",
]


# --------------------------------------------------------------------------------------
# Contact environment
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlaneWall:
    """Rigid planar wall with a penalty force on the tip.

    ``normal`` (unit) points from the wall into the lumen; the tip penetrates by
    ``pen = -(p - point) . normal``; the force ON the tip is ``stiffness * max(pen, 0) * normal``
    (the tip centre is the contact point: place the plane one catheter radius off the real wall).
    """

    point: tuple = (0.0, 0.0, 0.08)
    normal: tuple = (math.cos(math.radians(20.0)), 0.0, -math.sin(math.radians(20.0)))
    stiffness: float = 500.0

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64)
        p = np.asarray(self.point, dtype=np.float64)
        if n.shape != (3,) or not np.isfinite(n).all() or np.linalg.norm(n) == 0.0:
            raise CatheterParameterError(f"wall normal must be a finite non-zero 3-vector (got {self.normal!r})")
        if p.shape != (3,) or not np.isfinite(p).all():
            raise CatheterParameterError(f"wall point must be a finite 3-vector in m (got {self.point!r})")
        if not (math.isfinite(self.stiffness) and self.stiffness > 0.0):
            raise CatheterParameterError(f"wall stiffness must be > 0 (got {self.stiffness!r}): e.g. 500 (N/m)")
        object.__setattr__(self, "_n", n / np.linalg.norm(n))
        object.__setattr__(self, "_p", p)

    @classmethod
    def inclined(cls, contact_insertion: float = 0.08, incline_deg: float = 20.0, stiffness: float = 500.0):
        """Wall on the -x side, closing in on the +z axis at ``incline_deg``: a straight catheter on
        the default (z-axis) centerline first touches it when its tip reaches z = contact_insertion.
        Bending toward +x (rotation 0, positive angle) moves the tip away from it."""
        a = math.radians(incline_deg)
        return cls((0.0, 0.0, float(contact_insertion)), (math.cos(a), 0.0, -math.sin(a)), float(stiffness))

    @property
    def unit_normal(self) -> np.ndarray:
        return self._n

    def penetration(self, p) -> float:
        return -float((np.asarray(p, dtype=np.float64) - self._p) @ self._n)

    def force(self, p) -> np.ndarray:
        pen = self.penetration(p)
        return self.stiffness * pen * self._n if pen > 0.0 else np.zeros(3)

    def stiffness_matrix(self, p) -> np.ndarray:
        """(3, 3) ``-d force / d p`` at tip position p (N/m): ``k n n^T``, in contact or the stiffness
        a tip clear of the plane will meet (what the Contact FMU outputs as ``tip_stiffness``, with
        ``tip_gap``: its reach is finite, the plane's is not)."""
        return self.stiffness * np.outer(self._n, self._n)

    def gap(self, p) -> np.ndarray:
        """(3,) the clearance ``g n`` of a tip at p clear of the plane, zeros in contact (what the
        Contact FMU outputs as ``tip_gap``)."""
        return max(-self.penetration(p), 0.0) * self._n


# --------------------------------------------------------------------------------------
# Closed-loop simulation
# --------------------------------------------------------------------------------------


@dataclass
class Trajectory:
    """Samples at t_{k+1} = (k + 1) dt: the state after step k and the wall force it produces."""

    time: np.ndarray
    insertion: np.ndarray
    force: np.ndarray  # (N, 3) wall force on the tip at the end of the step
    force_magnitude: np.ndarray
    tip_position: np.ndarray  # (N, 3)
    bend_angle: np.ndarray
    actuator_command: np.ndarray
    effort_warning: np.ndarray
    advised_insertion_scale: np.ndarray


def _as_signal(value, name: str) -> Callable[[float], float]:
    if callable(value):
        return value
    x = float(value)
    if not math.isfinite(x):
        raise CatheterParameterError(f"{name} must be finite (got {value!r})")
    return lambda t: x


def simulate(
    model: CatheterModel,
    wall: PlaneWall,
    duration: float,
    insertion,
    rotation=0.0,
    external_command=0.0,
    t_start: float = 0.0,
    tip_stiffness: bool = False,
) -> Trajectory:
    """Run ``model`` (its current state, its dt) against ``wall`` for ``duration`` seconds.

    ``insertion``, ``rotation`` and ``external_command`` are constants or functions of time
    (evaluated at the start of each step, held over it). ``tip_stiffness``: pass the wall's
    stiffness and the tip's clearance at the last tip position with its force, as the scenes
    connect the Contact FMU's ``tip_stiffness`` and ``tip_gap`` (the implicit passive bend); False:
    the force only (explicit).
    """
    dt = model.dt
    n = int(round(duration / dt))
    ins, rot, ext = _as_signal(insertion, "insertion"), _as_signal(rotation, "rotation"), _as_signal(external_command, "external_command")
    time = t_start + dt * np.arange(1, n + 1)
    out = {k: np.empty(n) for k in ("insertion", "force_magnitude", "bend_angle", "actuator_command", "advised_insertion_scale")}
    warning = np.empty(n, dtype=bool)
    force_hist = np.empty((n, 3))
    tip_hist = np.empty((n, 3))
    force = wall.force(model.outputs.tip_position)
    stiffness = wall.stiffness_matrix(model.outputs.tip_position) if tip_stiffness else None
    gap = wall.gap(model.outputs.tip_position) if tip_stiffness else None
    for k in range(n):
        t = t_start + k * dt
        s = ins(t)
        o = model.step(t, dt, s, rot(t), force, ext(t), stiffness, gap)
        force = wall.force(o.tip_position)
        if tip_stiffness:
            stiffness = wall.stiffness_matrix(o.tip_position)
            gap = wall.gap(o.tip_position)
        out["insertion"][k] = s
        force_hist[k] = force
        tip_hist[k] = o.tip_position
        out["bend_angle"][k] = o.bend_angle
        out["actuator_command"][k] = o.actuator_command
        out["advised_insertion_scale"][k] = o.advised_insertion_scale
        warning[k] = o.effort_warning
    out["force_magnitude"] = np.linalg.norm(force_hist, axis=1)
    return Trajectory(time=time, force=force_hist, tip_position=tip_hist, effort_warning=warning, **out)


def _settle_passive(model: CatheterModel, wall: PlaneWall, insertion: float, seconds: float) -> None:
    """Bring the passive deflection to equilibrium against the wall with the controller off."""
    mode = model.mode
    model.set_mode("off")
    simulate(model, wall, seconds, insertion)
    model.set_mode(mode)


# --------------------------------------------------------------------------------------
# Step response
# --------------------------------------------------------------------------------------


@dataclass
class StepResponse:
    """Force regulation after switching the regulator on against a loaded wall at t = 0.

    The force starts at ``initial_force`` (passive equilibrium, controller off) and is driven to
    ``setpoint``. ``rise_time``: 10 % to 90 % of the way; ``overshoot``: largest excursion past
    the setpoint as a fraction of |initial - setpoint|; ``settling_time``: last time outside the
    band ``band * |initial - setpoint|`` (inf if still outside at the end);
    ``steady_state_error``: mean force over the last 10 % minus the setpoint.
    """

    trajectory: Trajectory
    setpoint: float
    threshold: float
    initial_force: float
    final_force: float
    rise_time: float
    overshoot: float
    settling_time: float
    steady_state_error: float
    warning_clear_time: float  # first time after which the warning stays off (inf if never)
    band: float


def _metrics(time: np.ndarray, f: np.ndarray, f0: float, f_set: float, band: float) -> tuple[float, float, float]:
    span = f_set - f0
    if span == 0.0:
        return 0.0, 0.0, 0.0
    progress = (f - f0) / span
    i10 = np.flatnonzero(progress >= 0.1)
    i90 = np.flatnonzero(progress >= 0.9)
    rise = float(time[i90[0]] - time[i10[0]]) if i10.size and i90.size else math.inf
    overshoot = max(0.0, float(np.max(progress)) - 1.0)
    outside = np.flatnonzero(np.abs(f - f_set) > band * abs(span))
    if outside.size == 0:
        settling = 0.0
    elif outside[-1] == f.size - 1:
        settling = math.inf
    else:
        settling = float(time[outside[-1] + 1])
    return rise, overshoot, settling


def _equilibrium_insertion(params: CatheterParameters, wall: PlaneWall, force: float, dt: float) -> float:
    """Insertion at which the straight, passively deflected tip pushes on the wall with ``force``."""
    model = CatheterModel(params.with_changes(controller_mode="off"), dt)

    def excess(s: float) -> float:
        return linearise(params, wall, s, model=model).force - force

    lo = params.active_length
    if excess(lo) >= 0.0:
        raise CatheterParameterError(
            f"the wall already pushes with more than {force:g} N at the smallest insertion {lo:g} m: move it further in"
        )
    hi = lo + 0.01
    while excess(hi) < 0.0:
        if hi > lo + 10.0:
            raise CatheterParameterError(f"the catheter never reaches {force:g} N against this wall: check its position")
        lo, hi = hi, lo + 2.0 * (hi - lo)
    return brentq(excess, lo, hi, xtol=1e-12)


def step_response(
    params: CatheterParameters | None = None,
    wall: PlaneWall | None = None,
    duration: float = 2.0,
    dt: float = 1e-3,
    insertion: float | None = None,
    band: float = 0.02,
    settle_time: float = 0.3,
) -> StepResponse:
    """Regulator step response against ``wall`` (default ``PlaneWall.inclined()``).

    The catheter is held at ``insertion`` (default: where the uncontrolled force is twice the
    threshold) with the controller off until the passive bend settles (``settle_time``), then
    the regulator switches on at t = 0 and runs for ``duration``.
    """
    params = CatheterParameters() if params is None else params
    wall = PlaneWall.inclined() if wall is None else wall
    if insertion is None:
        insertion = _equilibrium_insertion(params, wall, 2.0 * params.force_threshold, dt)
    model = CatheterModel(params.with_changes(controller_mode="off"), dt)
    model.reset(insertion)
    _settle_passive(model, wall, insertion, settle_time)
    f0 = float(np.linalg.norm(wall.force(model.outputs.tip_position)))
    model.set_mode("regulate")
    traj = simulate(model, wall, duration, insertion)
    f = traj.force_magnitude
    f_set = params.setpoint_fraction * params.force_threshold
    rise, overshoot, settling = _metrics(traj.time, f, f0, f_set, band)
    tail = f[int(0.9 * f.size) :]
    on = np.flatnonzero(traj.effort_warning)
    if on.size == 0:
        clear = 0.0
    elif on[-1] == f.size - 1:
        clear = math.inf
    else:
        clear = float(traj.time[on[-1] + 1])
    return StepResponse(
        trajectory=traj,
        setpoint=f_set,
        threshold=params.force_threshold,
        initial_force=f0,
        final_force=float(tail.mean()),
        rise_time=rise,
        overshoot=overshoot,
        settling_time=settling,
        steady_state_error=float(tail.mean() - f_set),
        warning_clear_time=clear,
        band=band,
    )


# --------------------------------------------------------------------------------------
# Linearised plant and frequency response
# --------------------------------------------------------------------------------------


@dataclass
class PlantLinearisation:
    """Operating point and coefficients of P(s) (see the module docstring)."""

    insertion: float
    active_angle: float
    passive_bend: float  # rad, along the bending direction
    force: float  # N, contact force magnitude at the operating point
    lever: float  # h = -d pen / d beta (m/rad)
    normal_share: float  # q = n . d
    passive_gain: float  # g = L^2 / (2 EI) (rad/N)
    wall_stiffness: float
    loop_gain: float  # G = k h g q
    actuator_omega: float  # w_b (rad/s)
    passive_time_constant: float

    @property
    def static_gain(self) -> float:
        """P(0) = dF / dtheta_cmd at zero frequency (N/rad, negative: bending away relieves)."""
        return -self.wall_stiffness * self.lever / (1.0 + self.loop_gain)

    def transfer(self, s) -> np.ndarray:
        """P(s) for complex s (array-like)."""
        s = np.asarray(s, dtype=complex)
        tau = self.passive_time_constant
        wb = self.actuator_omega
        return -self.wall_stiffness * self.lever * wb / (s + wb) * (1.0 + tau * s) / (1.0 + self.loop_gain + tau * s)


def linearise(
    params: CatheterParameters,
    wall: PlaneWall,
    insertion: float,
    active_angle: float = 0.0,
    rotation: float = 0.0,
    model: CatheterModel | None = None,
) -> PlantLinearisation:
    """Static equilibrium of the passive bend against ``wall`` and the plant coefficients there.

    Assumes the wall normal lies in the bending plane set by ``rotation`` (an out-of-plane
    component is ignored; a warning is logged).
    """
    model = CatheterModel(params.with_changes(controller_mode="off")) if model is None else model
    kin = model.kinematics
    frame = kin.base_frame(insertion)
    _, t, e1, e2 = frame
    d = math.cos(rotation) * e1 + math.sin(rotation) * e2
    n = wall.unit_normal
    q = float(n @ d)
    n_perp = n - (n @ t) * t
    if np.linalg.norm(n_perp - q * d) > 1e-6 * max(np.linalg.norm(n_perp), 1e-300):
        logger.warning("wall normal is not in the bending plane: the linearisation ignores its out-of-plane part")
    g = model.passive_gain
    k = wall.stiffness

    def pen(beta: float) -> float:
        b = (beta * math.cos(rotation), beta * math.sin(rotation))
        return wall.penetration(kin.active_chain(frame[0], t, e1, e2, b)[-1])

    def residual(bp: float) -> float:
        return bp - g * q * k * max(pen(active_angle + bp), 0.0)

    free = g * q * k * max(pen(active_angle), 0.0)
    bp = 0.0 if free == 0.0 else brentq(residual, min(0.0, free), max(0.0, free), xtol=1e-14)
    beta0 = active_angle + bp
    eps = 1e-6
    h = -(pen(beta0 + eps) - pen(beta0 - eps)) / (2.0 * eps)
    force = k * max(pen(beta0), 0.0)
    return PlantLinearisation(
        insertion=float(insertion),
        active_angle=float(active_angle),
        passive_bend=float(bp),
        force=float(force),
        lever=float(h),
        normal_share=q,
        passive_gain=g,
        wall_stiffness=k,
        loop_gain=k * h * g * q,
        actuator_omega=2.0 * math.pi * params.actuator_bandwidth,
        passive_time_constant=params.passive_time_constant,
    )


@dataclass
class FrequencyResponse:
    frequencies: np.ndarray  # Hz
    response: np.ndarray  # complex
    magnitude: np.ndarray  # |response|
    phase: np.ndarray  # rad, unwrapped from the lowest frequency


def open_loop_frequency_response(
    params: CatheterParameters | None,
    frequencies,
    wall: PlaneWall | None = None,
    insertion: float | None = None,
    active_angle: float = 0.0,
    with_controller: bool = False,
) -> FrequencyResponse:
    """Analytic frequency response of the linearised plant P(jw) = dF/dtheta_cmd (N/rad).

    The operating point is the passive equilibrium at ``insertion`` (default: where the straight
    tip pushes with the force threshold) and bend command ``active_angle``. The phase starts
    near -pi (bending away lowers the force). With ``with_controller=True`` it returns the loop
    transfer ``L(jw) = -C(jw) P(jw)``, ``C = kp + ki / s``, for negative feedback: read the
    crossover and the phase margin ``pi + angle(L)`` there.
    """
    params = CatheterParameters() if params is None else params
    wall = PlaneWall.inclined() if wall is None else wall
    if insertion is None:
        insertion = _equilibrium_insertion(params, wall, params.force_threshold, 1e-3)
    f = np.asarray(frequencies, dtype=np.float64)
    if f.ndim != 1 or not np.isfinite(f).all() or (f <= 0).any():
        raise CatheterParameterError("frequencies must be a 1-D array of positive finite values in Hz, e.g. [1, 5, 10]")
    lin = linearise(params, wall, insertion, active_angle)
    s = 2j * math.pi * f
    h = lin.transfer(s)
    if with_controller:
        h = -(params.kp + params.ki / s) * h
    phase = np.unwrap(np.angle(h))
    if phase[0] > 0.0:  # report the negative plant's phase from -pi, not +pi
        phase -= 2.0 * math.pi
    return FrequencyResponse(frequencies=f, response=h, magnitude=np.abs(h), phase=phase)


def simulated_frequency_response(
    params: CatheterParameters,
    wall: PlaneWall,
    insertion: float,
    frequency: float,
    amplitude: float = 0.02,
    active_angle: float = 0.0,
    dt: float = 1e-3,
    settle_cycles: int = 3,
    measure_cycles: int = 4,
) -> complex:
    """Measured dF/dtheta_cmd at one frequency: run the model in mode external with a sine
    command ``active_angle + amplitude sin(w t)`` against the wall and fit the force's
    fundamental by least squares over whole periods after ``settle_cycles``."""
    model = CatheterModel(params.with_changes(controller_mode="external"), dt)
    model.reset(insertion)
    _settle_passive(model, wall, insertion, 0.3)
    # Hold the mean command until the actuator and passive bend settle around it.
    simulate(model, wall, 1.0, insertion, external_command=active_angle)
    w = 2.0 * math.pi * frequency
    period = 1.0 / frequency
    duration = (settle_cycles + measure_cycles) * period
    traj = simulate(model, wall, duration, insertion, external_command=lambda t: active_angle + amplitude * math.sin(w * t))
    keep = traj.time > settle_cycles * period + 0.5 * dt
    t = traj.time[keep]
    f = traj.force_magnitude[keep]
    basis = np.stack([np.sin(w * t), np.cos(w * t), np.ones_like(t)], axis=1)
    (a, b, _), *_ = np.linalg.lstsq(basis, f, rcond=None)
    # a sin + b cos = Re[(a - i b) e^{i w t}] against the input amplitude * sin = Re[-i amplitude e^{i w t}].
    return complex(a, b) / amplitude


def contact_loop_gain(
    params: CatheterParameters, wall_stiffness: float, dt: float = 1e-3, implicit: bool = False
) -> tuple[float, bool]:
    """(G, stable) for a straight tip on a wall normal to it: ``G = k L^3 / (4 EI)``.

    Explicit exchange (the tip gets the force only): the error of the passive bend is multiplied
    by ``1 - alpha (1 + G)`` per step, ``alpha = 1 - exp(-dt / tau)``: stable iff
    ``alpha (1 + G) < 2``. Implicit (the tip also gets the contact's stiffness, ``implicit=True``):
    by ``(1 - alpha) / (1 + alpha G)``, in [0, 1) for every G >= 0: always stable."""
    L = params.active_length
    G = wall_stiffness * L**3 / (4.0 * params.bending_stiffness)
    if implicit:
        return G, True
    tau = params.passive_time_constant
    alpha = 1.0 - math.exp(-dt / tau) if tau > 0.0 else 1.0
    return G, alpha * (1.0 + G) < 2.0


# --------------------------------------------------------------------------------------
# Gain comparison
# --------------------------------------------------------------------------------------


def compare_gains(
    gains: Sequence,
    params: CatheterParameters | None = None,
    wall: PlaneWall | None = None,
    **step_kwargs,
) -> list[dict]:
    """Step-response metrics for each (kp, ki) pair (or dict with kp/ki and other parameter
    overrides, e.g. ``{"kp": 0.2, "ki": 10, "anti_windup": False}``). Returns one dict per row."""
    params = CatheterParameters() if params is None else params
    rows = []
    for g in gains:
        changes = dict(g) if isinstance(g, dict) else {"kp": g[0], "ki": g[1]}
        p = params.with_changes(**changes)
        r = step_response(p, wall, **step_kwargs)
        rows.append(
            {
                "kp": p.kp,
                "ki": p.ki,
                "rise_time": r.rise_time,
                "overshoot": r.overshoot,
                "settling_time": r.settling_time,
                "steady_state_error": r.steady_state_error,
                "final_force": r.final_force,
                "peak_command": float(np.max(np.abs(r.trajectory.actuator_command))),
                "warning_clear_time": r.warning_clear_time,
            }
        )
    return rows


def format_gain_table(rows: list[dict]) -> str:
    """Fixed-width text table of ``compare_gains`` rows."""
    cols = ["kp", "ki", "rise_time", "overshoot", "settling_time", "steady_state_error", "final_force", "peak_command"]
    head = " ".join(f"{c:>18s}" for c in cols)
    lines = [head]
    for r in rows:
        lines.append(" ".join(f"{r[c]:18.5g}" for c in cols))
    return "\n".join(lines)

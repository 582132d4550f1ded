"""Active catheter model: parameters, validation and the 1 ms ``step`` (no FMI here).

One step (inputs held over ``[t, t + dt]``, outputs at ``t + dt``):

1. base frame of the active section at the new insertion;
2. controller command from the tip force (``off``: 0, ``regulate``: PI on the force excess,
   ``external``: ``external_command``), clipped to the angle limit;
3. actuator: exact first-order lag with rate and angle saturation;
4. passive deflection: the bend vector relaxes toward ``g F_perp`` with ``g = L^2 / (2 EI)``
   (``L`` active length, ``F_perp`` the tip force across the base tangent) and time constant
   ``passive_time_constant`` (exact exponential; 0 = quasi-static), against the force
   linearised at the new bend when the contact gives its tip stiffness (see below);
5. shape: proximal chain on the centerline, active arc bent by
   ``beta = active_angle * (cos rotation, sin rotation) + passive_bend`` (see kinematics);
6. effort warning (hysteresis) and advised insertion scale.

Mechanics of the passive bend. A constant-curvature section cannot carry the cantilever's
linear moment ``M(x) = F (L - x)``; it carries the mean moment ``F L / 2``, so
``kappa = kappa_act + F L / (2 EI)`` and the passive tip rotation is ``F L^2 / (2 EI)``, equal to
the cantilever's. The tip deflection is then ``F L^3 / (4 EI)``, 3/4 of the cantilever's
``F L^3 / (3 EI)`` (a 4/3 stiffer tip). Small-deflection mechanics: the moment arm is taken
across the base tangent, not the bent shape.

The tip force is an input computed by another FMU from the tip position of the previous step,
so the passive bend closes a loop through the contact with gain ``G = k_contact L^3 / (4 EI)``
(a 500 N/m wall gives G = 3.3 with the defaults). Integrated explicitly (the bend relaxes toward
``g F`` of the last step, ``alpha = 1 - exp(-dt / tau)``) the loop is stable only while
``alpha (1 + G) < 2`` (the default 10 ms at dt = 1 ms: G < 20, a rigid contact up to ~3000 N/m;
quasi-static, tau = 0, needs G < 1, below ~150 N/m). With the input ``tip_stiffness``
``K = -dF/dx`` of the contact (the Contact FMU's output of the same name: the penalty slope, with
the wall's compliance ``k / (1 + k w)``), the bend is solved against the force linearised at its
new value, ``F_n - K J (pb' - pb + da)`` (``J`` = d tip / d bend, ``da`` the actuator's bend change
in this step): the error then shrinks by ``(1 - alpha) / (1 + alpha G)`` per step, stable and
monotone at every stiffness and for tau = 0 too, and the force the actuator's own motion adds is
met in the step it is made (the regulator's command does not return through a stiff wall one step
late). With ``tip_gap`` the bend also meets a wall the tip has not touched yet (one-sided, see
``kernels.implicit_passive_bend``). Without them (zeros) the step is the explicit one. The time constant stands for the tip's
structural and blood damping. See ``analysis.contact_loop_gain``.

Default bending stiffness: a 6 Fr (2.0 mm OD, 1.4 mm ID) Pebax 72D tube, E ~ 0.5 GPa,
``I = pi (D^4 - d^4) / 64 = 5.97e-13 m^4``, gives ``EI ~ 3.0e-4 N m^2``, inside the 1e-4..1e-3
range of braided Pebax / nitinol catheter shafts.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, fields, replace

import numpy as np

from . import kernels
from ._checks import as_float, is_integer
from ._coupling import TOOL_POINTS
from .actuator import Actuator
from .controller import EffortMonitor, ForceRegulator
from .geometry import CenterlineCurve
from .kinematics import CatheterKinematics

logger = logging.getLogger(__name__)

__all__ = ["CatheterParameterError", "CatheterParameters", "CatheterOutputs", "CatheterModel", "CONTROLLER_MODES"]

CONTROLLER_MODES = ("off", "regulate", "external")

# The drawn shape bends at most this much (rad) in total, active plus passive.
MAX_TOTAL_BEND = math.pi


class CatheterParameterError(ValueError):
    """Invalid catheter parameter or input; the message names the field and the fix."""


def _number(name: str, value, example: str) -> float:
    if type(value) is float and math.isfinite(value):  # the 1 kHz common case, checked cheaply
        return value
    x = None if isinstance(value, (bool, np.bool_)) else as_float(value)
    if x is None:
        raise CatheterParameterError(f"{name} must be a number (got {value!r}): e.g. {example}")
    if not math.isfinite(x):
        raise CatheterParameterError(f"{name} must be finite (got {value!r}): e.g. {example}")
    return x


def _positive(name: str, value, example: str) -> float:
    x = _number(name, value, example)
    if x <= 0.0:
        raise CatheterParameterError(f"{name} must be > 0 (got {value!r}): e.g. {example}")
    return x


def _non_negative(name: str, value, example: str) -> float:
    x = _number(name, value, example)
    if x < 0.0:
        raise CatheterParameterError(f"{name} must be >= 0 (got {value!r}): e.g. {example}")
    return x


@dataclass
class CatheterParameters:
    """Parameters of the active catheter (SI units). ``validate(dt)`` checks them all.

    Geometry: ``n_segments`` links of ``segment_length`` (m), ``radius`` (m, 1 mm = 6 Fr),
    the distal ``active_length`` (m, a whole number of links). ``centerline``: None for the
    built-in AAA aorta axis, a ``CenterlineCurve`` or any (k, 3) polyline (m).
    Mechanics: ``bending_stiffness`` EI (N m^2), ``passive_time_constant`` (s, 0 = quasi-static).
    Actuator: ``actuator_bandwidth`` (Hz), ``max_bend_angle`` (rad), ``max_bend_rate`` (rad/s).
    Control: ``controller_mode`` in ("off", "regulate", "external"), ``kp`` (rad/N),
    ``ki`` (rad/(N s)), ``anti_windup``, ``force_threshold`` (N), ``setpoint_fraction`` (the
    regulator targets this fraction of the threshold), ``warning_hysteresis`` (N),
    ``advice_start_fraction`` / ``advice_stop_fraction`` (insertion scale 1 below, 0 above,
    in units of the threshold).
    """

    n_segments: int = TOOL_POINTS - 1
    segment_length: float = 0.005
    radius: float = 0.001
    active_length: float = 0.02
    centerline: object = None
    bending_stiffness: float = 3.0e-4
    passive_time_constant: float = 0.01
    actuator_bandwidth: float = 5.0
    max_bend_angle: float = math.pi / 2
    max_bend_rate: float = 10.0
    controller_mode: str = "regulate"
    kp: float = 0.3
    ki: float = 8.0
    anti_windup: bool = True
    force_threshold: float = 0.5
    setpoint_fraction: float = 0.8
    warning_hysteresis: float = 0.05
    advice_start_fraction: float = 0.5
    advice_stop_fraction: float = 2.0

    def with_changes(self, **changes) -> "CatheterParameters":
        """Copy with some fields replaced (unknown names raise, naming the valid fields)."""
        names = {f.name for f in fields(self)}
        unknown = sorted(set(changes) - names)
        if unknown:
            raise CatheterParameterError(f"unknown parameter(s) {unknown}: valid names are {sorted(names)}")
        return replace(self, **changes)

    @property
    def n_active_segments(self) -> int:
        return int(round(self.active_length / self.segment_length))

    def centerline_curve(self) -> CenterlineCurve:
        if self.centerline is None:
            return CenterlineCurve.aaa_default()
        if isinstance(self.centerline, CenterlineCurve):
            return self.centerline
        try:
            return CenterlineCurve(self.centerline)
        except ValueError as exc:
            raise CatheterParameterError(f"centerline: {exc}") from None

    def validate(self, dt: float = 1e-3) -> None:
        """Raise CatheterParameterError naming the first bad field and the fix."""
        dt = _positive("dt", dt, "1e-3 (s, the communication step)")
        n = self.n_segments
        if not is_integer(n) or n < 1:
            raise CatheterParameterError(f"n_segments must be an integer >= 1 (got {n!r}): e.g. 30")
        seg = _positive("segment_length", self.segment_length, "0.005 (m)")
        _positive("radius", self.radius, "0.001 (m, 2 mm diameter = 6 Fr)")
        act = _positive("active_length", self.active_length, f"{4 * seg:g} (m, 4 links)")
        n_act = round(act / seg)
        if n_act < 1 or abs(act - n_act * seg) > 1e-9 * max(act, seg):
            raise CatheterParameterError(
                f"active_length must be a whole number of links of segment_length={seg:g} m"
                f" (got {act!r}): e.g. {max(n_act, 1) * seg:g}"
            )
        if n_act > n:
            raise CatheterParameterError(
                f"active_length ({act:g} m = {n_act} links) must not exceed the catheter"
                f" (n_segments={n} links): lower active_length or raise n_segments"
            )
        self.centerline_curve()
        _positive("bending_stiffness", self.bending_stiffness, "3e-4 (N m^2, a 2 mm Pebax/nitinol catheter)")
        _non_negative("passive_time_constant", self.passive_time_constant, "0.01 (s)")
        fb = _positive("actuator_bandwidth", self.actuator_bandwidth, "5.0 (Hz)")
        if fb >= 0.5 / dt:
            raise CatheterParameterError(
                f"actuator_bandwidth must be below the Nyquist frequency 1/(2 dt) = {0.5 / dt:g} Hz of"
                f" the communication step dt = {dt:g} s (got {fb:g} Hz): the step cannot resolve the"
                f" actuator; lower actuator_bandwidth (e.g. {0.1 / dt:g} Hz) or use a smaller step"
            )
        amax = _positive("max_bend_angle", self.max_bend_angle, "1.5708 (rad, 90 deg)")
        if amax > math.pi:
            raise CatheterParameterError(
                f"max_bend_angle must be <= pi (got {amax!r}): the active arc would fold back; e.g. 1.5708"
            )
        _positive("max_bend_rate", self.max_bend_rate, "10.0 (rad/s)")
        if self.controller_mode not in CONTROLLER_MODES:
            raise CatheterParameterError(
                f"controller_mode must be one of {CONTROLLER_MODES} (got {self.controller_mode!r})"
            )
        _non_negative("kp", self.kp, "0.3 (rad/N)")
        _non_negative("ki", self.ki, "8.0 (rad/(N s))")
        if not isinstance(self.anti_windup, (bool, np.bool_)):
            raise CatheterParameterError(f"anti_windup must be True or False (got {self.anti_windup!r})")
        thr = _positive("force_threshold", self.force_threshold, "0.5 (N)")
        frac = _positive("setpoint_fraction", self.setpoint_fraction, "0.8")
        if frac > 1.0:
            raise CatheterParameterError(
                f"setpoint_fraction must be in (0, 1] (got {frac!r}): the regulator must target a force"
                " at or below the threshold, e.g. 0.8"
            )
        hyst = _non_negative("warning_hysteresis", self.warning_hysteresis, "0.05 (N)")
        if hyst >= thr:
            raise CatheterParameterError(
                f"warning_hysteresis must be < force_threshold = {thr:g} N (got {hyst!r}): e.g. {0.1 * thr:g}"
            )
        a = _non_negative("advice_start_fraction", self.advice_start_fraction, "0.5")
        b = _positive("advice_stop_fraction", self.advice_stop_fraction, "2.0")
        if b <= a:
            raise CatheterParameterError(
                f"advice_stop_fraction must be > advice_start_fraction = {a:g} (got {b!r}): e.g. 2.0"
            )


@dataclass
class CatheterOutputs:
    """Outputs at the end of a step (port names of docs/design.md section 4)."""

    centerline_positions: np.ndarray  # (n_tool * 3,) flat, proximal end first, tip last
    tip_position: np.ndarray  # (3,)
    bend_angle: float  # actuator bend angle (rad, signed in the plane set by rotation)
    actuator_command: float  # command sent to the actuator (rad, after angle clipping)
    effort_warning: bool
    advised_insertion_scale: float
    tip_force_magnitude: float  # |tip_force| used by the controller (N)
    total_bend: float  # |active + passive bend vector| (rad)


class CatheterModel:
    """State and step of the active catheter; ``outputs`` holds the latest outputs.

    ``CatheterModel(params, dt)`` validates ``params`` against the step ``dt`` (s). ``step``
    validates its inputs (non-finite values raise CatheterParameterError naming the input).
    """

    def __init__(self, params: CatheterParameters | None = None, dt: float = 1e-3) -> None:
        params = CatheterParameters() if params is None else params
        params.validate(dt)
        self.params = params
        self.dt = float(dt)
        self.curve = params.centerline_curve()
        self.n_tool = params.n_segments + 1
        self.kinematics = CatheterKinematics(
            self.curve, params.n_segments, params.segment_length, params.n_active_segments
        )
        self.active_length = self.kinematics.active_length
        # Passive bend per unit force across the tangent: L^2 / (2 EI) (rad/N).
        self.passive_gain = self.active_length**2 / (2.0 * params.bending_stiffness)
        self._jacobian = np.zeros((3, 2))  # d tip / d bend (work array of the implicit passive bend)
        self._link_fraction = self.kinematics.link_fraction
        self.actuator = Actuator(params.actuator_bandwidth, params.max_bend_angle, params.max_bend_rate)
        self.regulator = ForceRegulator(
            params.kp,
            params.ki,
            params.setpoint_fraction * params.force_threshold,
            params.max_bend_angle,
            params.anti_windup,
        )
        self.monitor = EffortMonitor(
            params.force_threshold,
            params.warning_hysteresis,
            params.advice_start_fraction,
            params.advice_stop_fraction,
        )
        self.mode = params.controller_mode
        self._bound = None  # (centerline (n_tool, 3), the same flat, tip) arrays of write_outputs_into
        self._no_gap = np.zeros(3)
        self.reset()
        # load (or compile) the implicit passive bend's kernel now, not at the first 1 kHz step
        kernels.implicit_passive_bend(self.kinematics.frame, 0.0, 0.0, self._link_fraction, params.segment_length,
                                      np.eye(3), self._jacobian, 0.0, 0.0, 0.0, 0.0, 0.5, self.passive_gain, 0.0, 0.0,
                                      np.zeros(3))

    # ----------------------------------------------------------------------------------

    def reset(self, insertion: float = 0.0, rotation: float = 0.0) -> CatheterOutputs:
        """Straight, unloaded catheter at this insertion; controller and actuator at rest."""
        insertion = _number("insertion", insertion, "0.05 (m)")
        rotation = _number("rotation", rotation, "0.0 (rad)")
        self.actuator.angle = 0.0
        self.actuator.rate_limited = 0
        self.regulator.reset()
        self.monitor.warning = False
        self.passive_bend = np.zeros(2)
        self.time = 0.0
        self._outputs_from(insertion, rotation, 0.0, 0.0, self.kinematics.fill_base_frame(insertion))
        return self.outputs

    def set_mode(self, mode: str) -> None:
        """Switch controller mode ("off", "regulate", "external"); the regulator restarts from rest."""
        if mode not in CONTROLLER_MODES:
            raise CatheterParameterError(f"controller_mode must be one of {CONTROLLER_MODES} (got {mode!r})")
        if mode != self.mode:
            self.regulator.reset()
        self.mode = mode

    def write_outputs_into(self, centerline_positions: np.ndarray, tip_position: np.ndarray) -> None:
        """Let every step write the centerline (n_tool x 3 values) and the tip position (3) into
        these float64 arrays (writable, C-contiguous: e.g. an FMU's output buffers, which then
        need no copy) instead of new ones. They take the current outputs now; ``outputs`` refers
        to them, overwritten by the next step. A copy of the model (deepcopy, pickle) writes into
        arrays of its own again."""
        for name, array, size in (("centerline_positions", centerline_positions, 3 * self.n_tool),
                                  ("tip_position", tip_position, 3)):
            if not (isinstance(array, np.ndarray) and array.dtype == np.float64 and array.size == size
                    and array.flags.c_contiguous and array.flags.writeable):
                raise CatheterParameterError(f"{name} goes into a writable C-contiguous float64 array of {size} "
                                             f"values (got {getattr(array, 'dtype', type(array).__name__)} "
                                             f"{getattr(array, 'shape', '')})")
        flat = centerline_positions.reshape(-1)
        flat[...] = self.outputs.centerline_positions
        tip = tip_position if tip_position.ndim == 1 else tip_position.reshape(-1)  # the caller's array itself
        tip[...] = self.outputs.tip_position
        self._bound = (flat.reshape(self.n_tool, 3), flat, tip)
        self.outputs = replace(self.outputs, centerline_positions=flat, tip_position=tip)

    def __getstate__(self) -> dict:
        """A copy (deepcopy, pickle) keeps the outputs in arrays of its own (write_outputs_into)."""
        state = self.__dict__.copy()
        if state.get("_bound") is not None:
            state["_bound"] = None
            state["outputs"] = replace(self.outputs, centerline_positions=self.outputs.centerline_positions.copy(),
                                       tip_position=self.outputs.tip_position.copy())
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.__dict__.setdefault("_bound", None)

    def get_state(self) -> dict:
        """Everything ``step`` changes, for FMU get/set state (rollback)."""
        return {
            "time": self.time,
            "angle": self.actuator.angle,
            "rate_limited": self.actuator.rate_limited,
            "integral": self.regulator.integral,
            "direction": self.regulator.direction,
            "touching": self.regulator.touching,
            "warning": self.monitor.warning,
            "passive_bend": self.passive_bend.copy(),
            "mode": self.mode,
            "outputs": self.outputs if self._bound is None else self.__getstate__()["outputs"],
        }

    def set_state(self, state: dict) -> None:
        self.time = state["time"]
        self.actuator.angle = state["angle"]
        self.actuator.rate_limited = state["rate_limited"]
        self.regulator.integral = state["integral"]
        self.regulator.direction = state["direction"]
        self.regulator.touching = state["touching"]
        self.monitor.warning = state["warning"]
        self.passive_bend = state["passive_bend"].copy()
        self.mode = state["mode"]
        self.outputs = state["outputs"]
        if self._bound is not None:  # into the bound arrays, as a step would
            _, flat, tip = self._bound
            flat[...] = self.outputs.centerline_positions
            tip[...] = self.outputs.tip_position
            self.outputs = replace(self.outputs, centerline_positions=flat, tip_position=tip)

    # ----------------------------------------------------------------------------------

    def _check_step(self, dt: float) -> float:
        dt = _number("dt", dt, "1e-3 (s)")
        if dt <= 0.0:
            raise CatheterParameterError(f"dt must be > 0 (got {dt!r}): e.g. 1e-3 (s)")
        if dt != self.dt and self.params.actuator_bandwidth >= 0.5 / dt:
            raise CatheterParameterError(
                f"dt = {dt:g} s cannot resolve actuator_bandwidth = {self.params.actuator_bandwidth:g} Hz"
                f" (Nyquist 1/(2 dt) = {0.5 / dt:g} Hz): use a step below {0.5 / self.params.actuator_bandwidth:g} s"
            )
        return dt

    def step(self, t: float, dt: float, insertion: float, rotation: float, tip_force, external_command: float = 0.0,
             tip_stiffness=None, tip_gap=None):
        """Advance from t to t + dt with the inputs held; return (and store) the outputs.

        insertion (m), rotation (rad), tip_force (3,) force ON the tip from the wall (N),
        external_command (rad, used in mode "external"), tip_stiffness (3, 3) or 9 values,
        ``K = -d tip_force / d tip_position`` (N/m) where tip_force was computed, or None (zeros):
        the passive bend is integrated against the force linearised at its new value (see the
        module docstring); tip_gap (3,) m, with tip_stiffness, the clearance g n of a tip near the
        wall that carries no force, or None (zeros): the bend meets the wall in the step it reaches
        it (one-sided).
        """
        dt = self._check_step(dt)
        insertion = _number("insertion", insertion, "0.05 (m)")
        rotation = _number("rotation", rotation, "0.0 (rad)")
        external_command = _number("external_command", external_command, "0.0 (rad)")
        force = np.asarray(tip_force, dtype=np.float64)
        if force.shape != (3,):
            raise CatheterParameterError(f"tip_force must have 3 components (N) (got shape {force.shape})")
        # Plain floats from here on: numpy calls on 3-vectors cost about 1 us each.
        fx, fy, fz = force.tolist()
        if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
            raise CatheterParameterError(
                f"tip_force must be finite (got {force.tolist()}): check the contact component's output"
            )

        frame = self.kinematics.fill_base_frame(insertion)
        _, _, (e10, e11, e12), (e20, e21, e22) = frame.tolist()
        f1 = fx * e10 + fy * e11 + fz * e12
        f2 = fx * e20 + fy * e21 + fz * e22
        force_magnitude = math.sqrt(fx * fx + fy * fy + fz * fz)
        cos_r, sin_r = math.cos(rotation), math.sin(rotation)

        if self.mode == "regulate":
            command = self.regulator.command(
                force_magnitude, f1 * cos_r + f2 * sin_r, dt, self.actuator.rate_limited
            )
        elif self.mode == "external":
            command = external_command
        else:
            command = 0.0
        command = self.actuator.clip_command(command)
        # the bend the contact saw (before this step's actuator motion): where K linearises the force
        p1, p2 = self.passive_bend.tolist()
        bend1 = self.actuator.angle * cos_r + p1
        bend2 = self.actuator.angle * sin_r + p2
        angle_before = self.actuator.angle
        self.actuator.step(command, dt)
        moved = self.actuator.angle - angle_before

        g = self.passive_gain
        target1 = g * f1
        target2 = g * f2
        tau = self.params.passive_time_constant
        keep = math.exp(-dt / tau) if tau > 0.0 else 0.0
        pb = self.passive_bend
        status = 0
        if tip_stiffness is not None:
            new1, new2, status = kernels.implicit_passive_bend(
                frame, bend1, bend2, self._link_fraction, self.params.segment_length, self._stiffness(tip_stiffness),
                self._jacobian, p1, p2, target1, target2, 1.0 - keep, g, moved * cos_r, moved * sin_r,
                self._gap(tip_gap))
            if status < 0:
                raise CatheterParameterError(
                    f"tip_stiffness and tip_gap must be finite (got {np.asarray(tip_stiffness).tolist()} and "
                    f"{None if tip_gap is None else np.asarray(tip_gap).tolist()}): check the contact component's"
                    " outputs")
        if status == 1:
            pb[0] = new1
            pb[1] = new2
        else:  # explicit: no stiffness given, zeros (no contact), or not restoring where linearised
            pb[0] = target1 + (p1 - target1) * keep
            pb[1] = target2 + (p2 - target2) * keep

        self.time = float(t) + dt
        self._outputs_from(insertion, rotation, command, force_magnitude, frame, cos_r, sin_r)
        return self.outputs

    @staticmethod
    def _stiffness(tip_stiffness) -> np.ndarray:
        """The tip stiffness as a (3, 3) float64 array (the FMU's buffer as it is)."""
        k = tip_stiffness
        if type(k) is np.ndarray and k.shape == (3, 3) and k.dtype == np.float64:  # the 1 kHz common case
            return k
        k = np.asarray(k, dtype=np.float64)
        if k.size != 9:
            raise CatheterParameterError(f"tip_stiffness must have 3x3 = 9 values (N/m) (got shape {k.shape})")
        return np.ascontiguousarray(k.reshape(3, 3))

    def _gap(self, tip_gap) -> np.ndarray:
        """The tip's clearance to the wall as a (3,) float64 array (zeros when not given)."""
        if tip_gap is None:
            return self._no_gap
        g = tip_gap
        if type(g) is np.ndarray and g.shape == (3,) and g.dtype == np.float64:  # the 1 kHz common case
            return g
        g = np.asarray(g, dtype=np.float64)
        if g.size != 3:
            raise CatheterParameterError(f"tip_gap must have 3 values (m) (got shape {g.shape})")
        return np.ascontiguousarray(g.reshape(3))

    def _outputs_from(self, insertion, rotation, command, force_magnitude, frame, cos_r=None, sin_r=None) -> None:
        """Shape and outputs; ``frame`` is the (4, 3) base frame array of this insertion."""
        if cos_r is None:
            cos_r, sin_r = math.cos(rotation), math.sin(rotation)
        angle = self.actuator.angle
        p1, p2 = self.passive_bend.tolist()
        b1 = angle * cos_r + p1
        b2 = angle * sin_r + p2
        total = math.hypot(b1, b2)
        if total > MAX_TOTAL_BEND:
            # Beyond a half turn the small-deflection passive model means nothing (forces of
            # several N on the tip); fold no further than a U-turn.
            b1, b2 = b1 * MAX_TOTAL_BEND / total, b2 * MAX_TOTAL_BEND / total
        bound = self._bound
        if bound is None:
            pos = self.kinematics.fill_shape(insertion, b1, b2, frame)
            centerline, tip = pos.reshape(-1).copy(), pos[-1].copy()
        else:  # write_outputs_into
            pos, centerline, tip = bound
            self.kinematics.fill_shape(insertion, b1, b2, frame, pos)
            tip[:] = pos[-1]
        warning, scale = self.monitor.update(force_magnitude)
        self.outputs = CatheterOutputs(
            centerline_positions=centerline,
            tip_position=tip,
            bend_angle=angle,
            actuator_command=command,
            effort_warning=warning,
            advised_insertion_scale=scale,
            tip_force_magnitude=force_magnitude,
            total_bend=math.hypot(b1, b2),
        )

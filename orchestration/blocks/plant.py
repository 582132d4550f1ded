"""The haptic device as a damped mass, integrated exactly over each step with its input forces held."""
from __future__ import annotations

import math

import numpy as np

from orchestration.blocks.options import BlockConfigError, check_real, check_vector
from orchestration.checks import is_real
from orchestration.errors import FmuCallError
from orchestration.hosts.description import PortInfo


# ---------------------------------------------------------------------------------- device plant
def _series(a: float, coefficient) -> float:
    """sum_k coefficient(k) (-a)^k for small a (converged well before 30 terms for a < 0.5)."""
    total, power = 0.0, 1.0
    for k in range(30):
        total += coefficient(k) * power
        power *= -a
    return total


def exact_step_factors(a: float) -> tuple[float, float, float, float]:
    """Factors of the exact solution of m v' = F - b v over a step h, with a = b h / m >= 0.

    E1 = (1 - e^-a)/a, E2 = (a - 1 + e^-a)/a^2, E1(2a), J2 = (1 - 2 E1(a) + E1(2a))/a^2; each -> its
    limit as a -> 0 (1, 1/2, 1, 1/3), by series where the closed form cancels.
    """
    if a < 0.5:
        e1 = _series(a, lambda k: 1.0 / math.factorial(k + 1))
        e2 = _series(a, lambda k: 1.0 / math.factorial(k + 2))
        e1_2a = _series(2.0 * a, lambda k: 1.0 / math.factorial(k + 1))
        j2 = _series(a, lambda k: (2.0 ** (k + 2) - 2.0) / math.factorial(k + 3))
        return e1, e2, e1_2a, j2
    e1 = -math.expm1(-a) / a
    e1_2a = -math.expm1(-2.0 * a) / (2.0 * a)
    e2 = (a + math.expm1(-a)) / (a * a)
    j2 = (1.0 - 2.0 * e1 + e1_2a) / (a * a)
    return e1, e2, e1_2a, j2


_PLANT_PARAMETERS = ("mass", "damping", "step", "initial_position", "initial_velocity")
_PLANT_INPUTS = ("operator_force", "wall_force")
_PLANT_OUTPUTS = ("position", "velocity", "wall_energy", "operator_energy", "dissipated_energy", "kinetic_energy")


#: Plausibility limits of the device plant: values outside cannot be meant, and some overflow the
#: exact step (mass = 1e-300 kg makes F/m and the energy integrals inf, then NaN, silently).
#: mass: 1e-10 kg is 100x below the lightest device the stability study models (the passivity worst
#: case, m = 1e-3 bound T: about 1.6e-8 kg), 1000 kg far above any haptic device (0.01-1 kg).
#: damping: 1e6 N s/m is 1e5 times a desktop device's. Initial state: a desktop device's workspace
#: is about 0.2 m and its speeds below 1 m/s; 10 m and 100 m/s cannot be meant.
PLANT_LIMITS = {"mass": (1e-10, 1e3), "damping": (0.0, 1e6)}
PLANT_MAX_POSITION = 10.0       # m, |initial_position|
PLANT_MAX_SPEED = 100.0         # m/s, |initial_velocity|


def _check_plant_limits(problems, out: dict) -> None:
    for key, (low, high) in PLANT_LIMITS.items():
        value = out.get(key)
        if value is not None and not low <= value <= high:
            problems.append(f"{key} must be within {low:g} to {high:g} (got {value!r}): see orchestration.blocks.plant.PLANT_LIMITS for why")
    for key, limit, unit in (("initial_position", PLANT_MAX_POSITION, "m"),
                             ("initial_velocity", PLANT_MAX_SPEED, "m/s")):
        value = out.get(key)
        if value is not None and float(np.linalg.norm(value)) > limit:
            problems.append(f"{key} must have a magnitude of at most {limit:g} {unit} (got {value.tolist()!r}): "
                            "a desktop haptic device's workspace is about 0.2 m")


def check_plant(problems, values: dict) -> dict:
    out = {}
    checks = {
        "mass": lambda v: check_real(problems, "mass", v, "give the device's moving mass in kg, e.g. 0.1", low=0.0),
        "damping": lambda v: check_real(problems, "damping", v, "give the device's physical damping b_dev in N s/m, "
                                                            "e.g. 1.0", low=0.0, strict=False),
        "step": lambda v: check_real(problems, "step", v, "give the haptic step in s, e.g. 0.001", low=0.0),
        "initial_position": lambda v: check_vector(problems, "initial_position", v, 3, "give [x, y, z] in m"),
        "initial_velocity": lambda v: check_vector(problems, "initial_velocity", v, 3, "give [vx, vy, vz] in m/s"),
    }
    for key, value in values.items():
        if isinstance(value, np.ndarray) and value.size == 1 and key in ("mass", "damping", "step"):
            value = float(value.reshape(-1)[0])
        out[key] = checks[key](value)
    _check_plant_limits(problems, out)
    return out


class DevicePlant:
    """The haptic device: a mass with physical damping, ``m x'' = F_operator + F_wall - b_dev x'``.

    Both forces are held constant over each step (zero-order hold, as a sampled haptic loop applies
    them) and the linear ODE is integrated exactly over the step (closed form). The energy outputs
    are the exact integrals over the steps: ``operator_energy`` and ``wall_energy`` (work of each
    force, F . dx), ``dissipated_energy`` (integral of b v^2, computed from v(t) independently) and
    ``kinetic_energy``; kinetic(t) - kinetic(0) = operator + wall - dissipated to round-off.

    Host protocol (``ComponentHost``): in process and synchronous, ``step_done()`` is True.
    """

    continuous = False
    asynchronous = False

    def __init__(self, name: str, mass: float = 0.1, damping: float = 1.0, step: float = 0.001,
                 initial_position=(0.0, 0.0, 0.0), initial_velocity=(0.0, 0.0, 0.0)):
        problems: list[str] = []
        clean = check_plant(problems, {"mass": mass, "damping": damping, "step": step,
                                        "initial_position": initial_position, "initial_velocity": initial_velocity})
        if problems:
            raise BlockConfigError(problems, name)
        self.name = name
        self.messages: list[tuple[int, str]] = []
        self._params = clean
        vec = dict(shape=(3,))
        self.ports = {
            "mass": PortInfo("mass", "parameter", "Float64", "fixed", "kg", start=clean["mass"]),
            "damping": PortInfo("damping", "parameter", "Float64", "fixed", "N.s/m", start=clean["damping"]),
            "step": PortInfo("step", "parameter", "Float64", "fixed", "s", start=clean["step"]),
            "initial_position": PortInfo("initial_position", "parameter", "Float64", "fixed", "m",
                                         start=clean["initial_position"].tolist(), **vec),
            "initial_velocity": PortInfo("initial_velocity", "parameter", "Float64", "fixed", "m/s",
                                         start=clean["initial_velocity"].tolist(), **vec),
            "operator_force": PortInfo("operator_force", "input", "Float64", "continuous", "N",
                                       start=[0.0] * 3, **vec),
            "wall_force": PortInfo("wall_force", "input", "Float64", "continuous", "N", start=[0.0] * 3, **vec),
            "position": PortInfo("position", "output", "Float64", "continuous", "m", **vec),
            "velocity": PortInfo("velocity", "output", "Float64", "continuous", "m/s", **vec),
        }
        for out in _PLANT_OUTPUTS[2:]:
            self.ports[out] = PortInfo(out, "output", "Float64", "continuous", "J")
        self._inputs = {k: np.zeros(3) for k in _PLANT_INPUTS}
        self._configured_inputs = list(_PLANT_INPUTS)
        self._observed = list(_PLANT_OUTPUTS)
        self._state = "created"
        self._time = 0.0
        self._pending = None
        self._factors = None
        self._reset()

    # -- protocol -----------------------------------------------------------------------------
    @property
    def step(self) -> float:
        """The fixed step the plant expects from the master, s."""
        return self._params["step"]

    @property
    def default_step(self) -> float:
        return self._params["step"]

    def instantiate(self) -> None:
        if self._state != "created":
            raise FmuCallError(self.name, "instantiate", None, f"already instantiated (state {self._state})")
        self._state = "instantiated"

    def set_values(self, values: dict[str, object]) -> None:
        self._require(("instantiated", "initialization"), "setValues", None)
        params = {k: v for k, v in values.items() if k in _PLANT_PARAMETERS}
        inputs = {k: v for k, v in values.items() if k in _PLANT_INPUTS}
        unknown = sorted(set(values) - set(params) - set(inputs))
        if unknown:
            raise FmuCallError(self.name, f"setValues({', '.join(unknown)})", None,
                               f"no such variable(s) {unknown}: settable are "
                               f"{list(_PLANT_PARAMETERS) + list(_PLANT_INPUTS)}")
        problems: list[str] = []
        clean = check_plant(problems, params)
        if problems:
            raise FmuCallError(self.name, f"setValues({', '.join(params)})", None, "; ".join(problems))
        self._params.update(clean)
        self._set_inputs(inputs, "setValues", None)
        self._reset()

    def enter_initialization(self, start_time: float) -> None:
        self._require(("instantiated",), "enterInitializationMode", start_time)
        if not (is_real(start_time) and math.isfinite(start_time)):
            raise FmuCallError(self.name, "enterInitializationMode", None,
                               f"start_time must be a finite time in s (got {start_time!r})")
        self._start_time = float(start_time)
        self._state = "initialization"
        self._reset()

    def configure(self, inputs: list[str], observed: list[str]) -> None:
        bad_in = [n for n in inputs if n not in _PLANT_INPUTS]
        bad_obs = [n for n in observed if n not in self.ports]
        if bad_in or bad_obs:
            raise FmuCallError(self.name, "configure", None,
                               (f"not inputs: {bad_in} (inputs are {list(_PLANT_INPUTS)}); " if bad_in else "")
                               + (f"no such ports: {bad_obs} (ports are {list(self.ports)})" if bad_obs else ""))
        self._configured_inputs = list(inputs)
        self._observed = list(observed)

    def set_inputs(self, values: dict[str, np.ndarray]) -> None:
        self._require(("instantiated", "initialization", "stepping"), "setInputs", self._time)
        self._set_inputs(values, "setFloat64", self._time)

    def get_outputs(self) -> dict[str, np.ndarray]:
        self._require(("initialization", "stepping"), "getFloat64", self._time)
        return self._read(self._observed)

    def get_values(self, names: list[str]) -> dict[str, np.ndarray]:
        """Current values of any ports (parameters, inputs, outputs), fresh float64 copies."""
        self._require(("instantiated", "initialization", "stepping"), "getValues", self._time)
        unknown = [n for n in names if n not in self.ports]
        if unknown:
            raise FmuCallError(self.name, "getValues", self._time,
                               f"no such ports: {unknown} (ports are {list(self.ports)})")
        return self._read(names)

    def exit_initialization(self) -> None:
        self._require(("initialization",), "exitInitializationMode", self._time)
        self._state = "stepping"

    def start_step(self, t: float, h: float, inputs: dict[str, np.ndarray]) -> None:
        self._require(("stepping",), "doStep", t)
        step = self._params["step"]
        if not (is_real(h) and math.isclose(h, step, rel_tol=1e-9, abs_tol=0.0)):
            raise FmuCallError(self.name, "doStep", t,
                               f"communication step {h!r} s differs from the plant's step {step!r} s: "
                               f"set the plant's step to the step the scene gives it (or the other way round)")
        if not (is_real(t) and math.isclose(t, self._time, rel_tol=1e-9, abs_tol=1e-12)):
            raise FmuCallError(self.name, "doStep", t,
                               f"step starts at t = {t!r} s but the plant is at t = {self._time!r} s")
        self._set_inputs(inputs, "setFloat64", t)
        self._advance(float(h))
        self._time = float(t) + float(h)
        self._pending = self._read(self._observed)

    def finish_step(self) -> dict[str, np.ndarray]:
        if self._pending is None:
            raise FmuCallError(self.name, "doStep", self._time, "finish_step called without start_step")
        out, self._pending = self._pending, None
        return out

    def step_done(self) -> bool:
        return True  # synchronous: start_step did the step

    def terminate(self) -> None:
        self._state = "terminated"
        self._pending = None

    # -- model --------------------------------------------------------------------------------
    def _require(self, states, call, t):
        if self._state not in states:
            raise FmuCallError(self.name, call, t, f"not allowed in state '{self._state}' (allowed in {list(states)})")

    def _set_inputs(self, values, call, t):
        for key, value in values.items():
            if key not in _PLANT_INPUTS:
                raise FmuCallError(self.name, f"{call}({key})", t,
                                   f"{key!r} is not an input: the inputs are {list(_PLANT_INPUTS)}")
            arr = np.asarray(value, dtype=np.float64).reshape(-1)
            if arr.shape != (3,) or not np.isfinite(arr).all():
                raise FmuCallError(self.name, f"{call}({key})", t,
                                   f"{key} must be 3 finite numbers in N (got {value!r})")
            self._inputs[key][:] = arr

    def _reset(self):
        self._x = self._params["initial_position"].copy()
        self._v = self._params["initial_velocity"].copy()
        self._time = getattr(self, "_start_time", 0.0)
        self._energy = {"wall_energy": 0.0, "operator_energy": 0.0, "dissipated_energy": 0.0}

    def _advance(self, h: float) -> None:
        m, b = self._params["mass"], self._params["damping"]
        f_op, f_wall = self._inputs["operator_force"], self._inputs["wall_force"]
        g = (f_op + f_wall) / m
        v0 = self._v
        a = b * h / m
        if self._factors is None or self._factors[0] != a:  # constant over a run: computed once
            self._factors = (a, exact_step_factors(a), math.exp(-a))
        (e1, e2, e1_2a, j2), decay = self._factors[1], self._factors[2]
        # v(s) = v0 e^{-bs/m} + g (1 - e^{-bs/m}) m/b ; x(h) - x0 = v0 h E1 + g h^2 E2
        dx = v0 * (h * e1) + g * (h * h * e2)
        v1 = v0 * decay + g * (h * e1)
        # int_0^h |v|^2 ds = |v0|^2 h E1(2a) + 2 v0.g h^2 E1(a)^2/2 + |g|^2 h^3 J2
        int_v2 = (v0 @ v0) * h * e1_2a + (v0 @ g) * h * h * e1 * e1 + (g @ g) * h ** 3 * j2
        self._energy["operator_energy"] += float(f_op @ dx)
        self._energy["wall_energy"] += float(f_wall @ dx)
        self._energy["dissipated_energy"] += b * float(int_v2)
        self._x = self._x + dx
        self._v = v1

    def _read(self, names) -> dict[str, np.ndarray]:
        out = {}
        for n in names:
            if n == "position":
                out[n] = self._x.copy()
            elif n == "velocity":
                out[n] = self._v.copy()
            elif n == "kinetic_energy":
                out[n] = np.array([0.5 * self._params["mass"] * float(self._v @ self._v)])
            elif n in self._energy:
                out[n] = np.array([self._energy[n]])
            elif n in self._inputs:
                out[n] = self._inputs[n].copy()
            else:
                out[n] = np.atleast_1d(np.asarray(self._params[n], dtype=np.float64)).copy()
        return out

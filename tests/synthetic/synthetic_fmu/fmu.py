"""The synthetic slaves (one package, three FMUs: Signal, Echo, Faulty).

pythonfmu3 0.3.4 does not pass the start time of ``fmi3EnterInitializationMode`` to the slave,
so before the first step a slave's time is its ``time`` variable (0.0); after ``fmi3DoStep(t, h)``
it is ``t + h``, computed here exactly as the host would (one float addition).
"""
from __future__ import annotations

import os

from pythonfmu3 import Boolean, Fmi3Causality, Fmi3Slave, Fmi3Variability, Float64, Int32, String

from ._fmi_support import GuardedSlaveMixin

C, V = Fmi3Causality, Fmi3Variability

DEFAULT_STEP = 0.01


def polynomial(coefficients, t: float) -> float:
    """y = a + b t + c t^2, in this exact order of float operations (tests rely on it)."""
    a, b, c = (float(x) for x in coefficients)
    return a + b * t + c * t * t


class SignalSlave(GuardedSlaveMixin, Fmi3Slave):
    """A polynomial of time: y = a + b t + c t^2 at the instance's current time."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self._declare_basics("Polynomial of time with array, Int32 and Boolean outputs", DEFAULT_STEP)
        self._now = 0.0
        self._register_array("coefficients", (3,), C.parameter, "a, b, c of y = a + b t + c t^2",
                             variability=V.fixed)
        self.coefficients[...] = (1.0, 2.0, 3.0)
        self.y = 0.0
        self._register_scalars([("y", None, "a + b t + c t^2 at the current time")], C.output, V.continuous)
        self._register_array("y3", (3,), C.output, "(y, current time, 1.0)")
        self.count = 0
        self.register_variable(Int32("count", causality=C.output, variability=V.discrete,
                                     description="steps done"))
        self.odd = False
        self.register_variable(Boolean("odd", causality=C.output, variability=V.discrete,
                                       description="the number of steps done is odd"))

    def _initialize_model(self) -> None:
        self._now = float(self.time)
        self.count = 0

    def _step_model(self, t: float, dt: float) -> None:
        self._now = t + dt
        self.count += 1

    def _publish_outputs(self) -> None:
        self.y = polynomial(self.coefficients, self._now)
        self.y3[...] = (self.y, self._now, 1.0)
        self.odd = bool(self.count % 2)


# Start values of Echo's inputs: what last_* report before the first step.
ECHO_START = dict(u=0.0, v=(0.0, 0.0, 0.0), k=0, b=False, n_w=2)


class EchoSlave(GuardedSlaveMixin, Fmi3Slave):
    """Reports the inputs in effect during the most recent step, and the integral of u.

    Beyond the inputs it also echoes one parameter of each remaining kind (String ``label`` as
    ``label_length``, Boolean ``flag``, and the structural ``n_w`` that sizes ``w``/``last_w``),
    so a host's setters can be checked end to end.
    """

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self._declare_basics("Echoes its inputs after each step", DEFAULT_STEP)
        fixed = dict(causality=C.parameter, variability=V.fixed)
        self.label = "echo"
        self.register_variable(String("label", **fixed, description="any text; its length is echoed"))
        self.flag = False
        self.register_variable(Boolean("flag", **fixed, description="echoed as flag_echo"))
        self._register_structural("n_w", ECHO_START["n_w"], "size of w")

        self.u = ECHO_START["u"]
        self.register_variable(Float64("u", causality=C.input, variability=V.continuous, start=self.u,
                                       description="scalar input"))
        self._register_array("v", (3,), C.input, "array input")
        self.k = ECHO_START["k"]
        self.register_variable(Int32("k", causality=C.input, variability=V.discrete, start=self.k,
                                     description="integer input"))
        self.b = ECHO_START["b"]
        self.register_variable(Boolean("b", causality=C.input, variability=V.discrete, start=self.b,
                                       description="boolean input"))
        self._register_array("w", ("n_w",), C.input, "input sized by n_w")

        self.last_u = 0.0
        self.last_t = 0.0
        self.integral_u = 0.0
        self._register_scalars([("last_u", None, "u during the last step"),
                                ("last_t", "s", "start time of the last step"),
                                ("integral_u", None, "sum of u h over all steps")], C.output, V.continuous)
        self._register_array("last_v", (3,), C.output, "v during the last step")
        self._register_array("last_w", ("n_w",), C.output, "w during the last step")
        self.last_k = 0
        self.register_variable(Int32("last_k", causality=C.output, variability=V.discrete,
                                     description="k during the last step"))
        self.last_b = False
        self.register_variable(Boolean("last_b", causality=C.output, variability=V.discrete,
                                       description="b during the last step"))
        self.label_length = 0
        self.register_variable(Int32("label_length", causality=C.output, variability=V.discrete,
                                     description="number of characters of label"))
        self.flag_echo = False
        self.register_variable(Boolean("flag_echo", causality=C.output, variability=V.discrete,
                                       description="the parameter flag"))

    def _initialize_model(self) -> None:
        self.last_u = ECHO_START["u"]
        self.last_v[...] = ECHO_START["v"]
        self.last_k = ECHO_START["k"]
        self.last_b = ECHO_START["b"]
        self.last_w[...] = 0.0
        self.last_t = float(self.time)
        self.integral_u = 0.0
        self.label_length = len(str(self.label))
        self.flag_echo = bool(self.flag)

    def _step_model(self, t: float, dt: float) -> None:
        self.last_u = float(self.u)
        self.last_v[...] = self.v
        self.last_k = int(self.k)
        self.last_b = bool(self.b)
        self.last_w[...] = self.w
        self.last_t = t
        self.integral_u += self.last_u * dt

    def _publish_outputs(self) -> None:
        """The outputs are the recorded values themselves."""


class FaultySlave(GuardedSlaveMixin, Fmi3Slave):
    """Steps normally until ``error_at`` (returns fmi3Error) or ``crash_at`` (aborts the process)."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self._declare_basics("Fails on request: error status or process abort", DEFAULT_STEP)
        self.error_at = -1.0
        self.crash_at = -1.0
        self._register_scalars([("error_at", "s", "steps starting at t >= error_at fail (negative: never)"),
                                ("crash_at", "s", "steps starting at t >= crash_at abort the process (negative: never)")],
                               C.parameter, V.fixed)
        self.y = 0.0
        self._register_scalars([("y", "s", "current time")], C.output, V.continuous)

    def _initialize_model(self) -> None:
        self.y = float(self.time)

    def _step_model(self, t: float, dt: float) -> None:
        if self.crash_at >= 0.0 and t >= self.crash_at:
            os.abort()  # a segfaulting native library, as far as the host can tell
        if self.error_at >= 0.0 and t >= self.error_at:
            raise ValueError(f"requested error at t = {t!r}")
        self.y = t + dt

    def _publish_outputs(self) -> None:
        """``y`` is written by the step."""


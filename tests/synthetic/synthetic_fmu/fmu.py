"""The synthetic FMUs (one package, three declarations: Signal, Echo, Faulty).

Before the first step an FMU's time is the start time of ``fmi3EnterInitializationMode``; after
``fmi3DoStep(t, h)`` it is ``t + h``, computed here exactly as the host would (one float addition).
"""
from __future__ import annotations

import logging
import os

from ._fmi import FmuDeclaration, input_port, output, parameter, structural

DEFAULT_STEP = 0.01
logger = logging.getLogger(__name__)


def polynomial(coefficients, t: float) -> float:
    """y = a + b t + c t^2, in this exact order of float operations (tests rely on it)."""
    a, b, c = (float(x) for x in coefficients)
    return a + b * t + c * t * t


class Signal:
    """A polynomial of time: y = a + b t + c t^2 at the instance's current time."""

    def __init__(self, values):
        self.values = values
        self.now = float(values.time)
        self.count = 0
        self._publish()

    def step(self, t: float, dt: float) -> None:
        self.now = t + dt
        self.count += 1
        self._publish()

    def _publish(self) -> None:
        v = self.values
        v.y = polynomial(v.coefficients, self.now)
        v.y3 = (v.y, self.now, 1.0)
        v.count = self.count
        v.odd = bool(self.count % 2)


SIGNAL = FmuDeclaration(
    model_name="Signal", description="Polynomial of time with array, Int32 and Boolean outputs",
    internal_step=DEFAULT_STEP, adapter=Signal,
    variables=(
        parameter("coefficients", (1.0, 2.0, 3.0), "a, b, c of y = a + b t + c t^2", shape=(3,)),
        output("y", "a + b t + c t^2 at the current time"),
        output("y3", "(y, current time, 1.0)", shape=(3,)),
        output("count", "steps done", type="Int32"),
        output("odd", "the number of steps done is odd", type="Boolean"),
    ),
)

# Start values of Echo's inputs: what last_* report before the first step.
ECHO_START = dict(u=0.0, v=(0.0, 0.0, 0.0), k=0, b=False, n_w=2)


class Echo:
    """Reports the inputs in effect during the most recent step, and the integral of u.

    Beyond the inputs it also echoes one parameter of each remaining kind (String ``label`` as
    ``label_length``, Boolean ``flag``, and the structural ``n_w`` that sizes ``w``/``last_w``),
    so a host's setters can be checked end to end.
    """

    def __init__(self, values):
        self.values = v = values
        v.last_u = ECHO_START["u"]
        v.last_v = ECHO_START["v"]
        v.last_k = ECHO_START["k"]
        v.last_b = ECHO_START["b"]
        v.last_w = 0.0
        v.last_t = v.time
        v.integral_u = 0.0
        v.label_length = len(v.label)
        v.flag_echo = v.flag

    def step(self, t: float, dt: float) -> None:
        v = self.values
        if 0.0 <= v.fail_at <= t:
            raise ValueError(f"requested failure at t = {t!r}")  # a model failure on request
        v.last_u = v.u
        v.last_v = v.v
        v.last_k = v.k
        v.last_b = v.b
        v.last_w = v.w
        v.last_t = t
        v.integral_u = v.integral_u + v.last_u * dt


ECHO = FmuDeclaration(
    model_name="Echo", description="Echoes its inputs after each step", internal_step=DEFAULT_STEP, adapter=Echo,
    variables=(
        parameter("label", "echo", "any text; its length is echoed"),
        parameter("flag", False, "echoed as flag_echo"),
        parameter("fail_at", -1.0, "steps starting at t >= fail_at fail (negative: never)", "s"),
        structural("n_w", ECHO_START["n_w"], "size of w"),
        input_port("u", "scalar input", start=ECHO_START["u"]),
        input_port("v", "array input", shape=(3,)),
        input_port("k", "integer input", type="Int32", start=ECHO_START["k"]),
        input_port("b", "boolean input", type="Boolean", start=ECHO_START["b"]),
        input_port("w", "input sized by n_w", shape=("n_w",)),
        output("last_u", "u during the last step"),
        output("last_t", "start time of the last step", "s"),
        output("integral_u", "sum of u h over all steps"),
        output("last_v", "v during the last step", shape=(3,)),
        output("last_w", "w during the last step", shape=("n_w",)),
        output("last_k", "k during the last step", type="Int32"),
        output("last_b", "b during the last step", type="Boolean"),
        output("label_length", "number of characters of label", type="Int32"),
        output("flag_echo", "the parameter flag", type="Boolean"),
    ),
)


#: What Faulty writes into ``ys[bad_index]`` from ``bad_at`` on, by ``bad_kind``.
BAD_VALUES = (float("nan"), float("inf"), float("-inf"), 1.7976931348623157e308)  # the last one is finite
N_YS = 19  # more than a multiple of the layer's 8-value blocks: the scan's tail is tested too


class Faulty:
    """Steps normally until ``error_at`` (returns fmi3Error) or ``crash_at`` (aborts the process),
    or writes a non-finite value into an output from ``bad_at`` on (the layer must refuse it)."""

    def __init__(self, values):
        self.values = values
        values.y = values.time
        values.ys = values.time

    def step(self, t: float, dt: float) -> None:
        v = self.values
        if v.crash_at >= 0.0 and t >= v.crash_at:
            os.abort()  # a segfaulting native library, as far as the host can tell
        if v.error_at >= 0.0 and t >= v.error_at:
            raise ValueError(f"requested error at t = {t!r}")
        if v.interrupt_at >= 0.0 and t >= v.interrupt_at:
            raise KeyboardInterrupt  # as a Ctrl-C arriving while the FMU computes
        if v.warn_at >= 0.0 and abs(t - v.warn_at) < 0.5 * dt:
            logger.warning("requested warning at t = %r", t)  # the step returns fmi3Warning
        v.y = t + dt
        ys = v.ys
        ys[...] = t + dt
        if v.bad_at >= 0.0 and t >= v.bad_at:
            ys[v.bad_index] = BAD_VALUES[v.bad_kind]


FAULTY = FmuDeclaration(
    model_name="Faulty", description="Fails on request: error status or process abort", internal_step=DEFAULT_STEP,
    adapter=Faulty,
    variables=(
        parameter("error_at", -1.0, "steps starting at t >= error_at fail (negative: never)", "s"),
        parameter("crash_at", -1.0, "steps starting at t >= crash_at abort the process (negative: never)", "s"),
        parameter("interrupt_at", -1.0, "steps starting at t >= interrupt_at raise KeyboardInterrupt (negative: never)",
                  "s"),
        parameter("warn_at", -1.0, "the step starting at t = warn_at logs a warning (negative: never)", "s"),
        parameter("bad_at", -1.0, "steps starting at t >= bad_at write BAD_VALUES[bad_kind] into ys[bad_index] "
                  "(negative: never)", "s"),
        parameter("bad_index", 0, "which value of ys goes bad"),
        parameter("bad_kind", 0, "0 NaN, 1 +infinity, 2 -infinity, 3 the largest finite number"),
        output("y", "current time", "s"),
        output("ys", "current time, N_YS times", "s", shape=(N_YS,)),
    ),
)

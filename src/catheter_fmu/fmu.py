"""The Catheter FMU: a thin FMI 3.0 Co-Simulation slave over :class:`catheter_fmu.model.CatheterModel`.

Ports follow DESIGN.md section 4. The number of centerline points (``n_tool_points`` =
segments + 1) and of vessel-centerline vertices are structural parameters: they size the arrays.
"""
from __future__ import annotations

import numpy as np
from pythonfmu3 import (
    Boolean,
    Fmi3Causality,
    Fmi3Slave,
    Fmi3Variability,
    Float64,
    String,
)

from ._fmi_support import GuardedSlaveMixin
from .geometry import CenterlineCurve
from .model import CatheterModel, CatheterParameters

C, V = Fmi3Causality, Fmi3Variability

#: Float64 parameters passed to CatheterParameters unchanged: (name, unit, description).
FLOAT_PARAMETERS = [
    ("segment_length", "m", "length of one catheter segment"),
    ("radius", "m", "catheter radius (1 mm: 6 Fr)"),
    ("active_length", "m", "length of the distal active (bending) section"),
    ("bending_stiffness", "N.m2", "bending stiffness EI of the active section"),
    ("passive_time_constant", "s", "relaxation time of the passive tip deflection (0: quasi-static)"),
    ("actuator_bandwidth", "Hz", "first-order actuator bandwidth"),
    ("max_bend_angle", "rad", "actuator angle saturation"),
    ("max_bend_rate", "rad/s", "actuator rate saturation"),
    ("kp", None, "proportional gain of the force regulator (rad/N)"),
    ("ki", None, "integral gain of the force regulator (rad/(N s))"),
    ("force_threshold", "N", "tip force above which the operator is told to ease off"),
    ("setpoint_fraction", None, "regulated force as a fraction of the threshold"),
    ("warning_hysteresis", "N", "hysteresis of the effort warning"),
]


class CatheterSlave(GuardedSlaveMixin, Fmi3Slave):
    """Active catheter with an effort-regulating tip controller (Catheter FMU)."""

    forwarded_loggers = (__name__.rsplit(".", 1)[0],)  # this package, under whatever name it was imported

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self._declare_basics("Active catheter: kinematics on the vessel centerline, actuated tip, effort controller",
                             0.001)
        self.model: CatheterModel | None = None
        defaults = CatheterParameters()
        fixed = dict(causality=C.parameter, variability=V.fixed)
        for name, _, _ in FLOAT_PARAMETERS:
            setattr(self, name, float(getattr(defaults, name)))
        self._register_scalars(FLOAT_PARAMETERS, C.parameter, V.fixed)
        self.controller_mode = defaults.controller_mode
        self.anti_windup = bool(defaults.anti_windup)
        self.register_variable(String("controller_mode", **fixed, description="off, regulate or external"))
        self.register_variable(Boolean("anti_windup", **fixed, description="stop integrating while the actuator saturates"))

        default_centerline = np.array(CenterlineCurve.aaa_default().vertices, dtype=float)
        self._register_structural("n_tool_points", defaults.n_segments + 1,
                                  "catheter centerline points (segments + 1)")
        self._register_structural("n_centerline_points", len(default_centerline),
                                  "vertices of the vessel centerline polyline")
        self._register_array("centerline_points", ("n_centerline_points", 3), C.parameter,
                             "vessel centerline polyline the catheter follows (entry first)", "m",
                             variability=V.fixed)
        self.centerline_points[...] = default_centerline

        self.insertion = 0.0
        self.rotation = 0.0
        self.external_command = 0.0
        self.register_variable(Float64("insertion", causality=C.input, variability=V.continuous, unit="m",
                                       start=0.0, description="inserted length from the operator/device"))
        self.register_variable(Float64("rotation", causality=C.input, variability=V.continuous, unit="rad",
                                       start=0.0, description="catheter rotation from the operator/device"))
        self.register_variable(Float64("external_command", causality=C.input, variability=V.continuous,
                                       unit="rad", start=0.0, description="actuator command in mode external"))
        self._register_array("tip_force", (3,), C.input, "contact force on the tip (from Contact)", "N")
        self._register_array("centerline_positions", ("n_tool_points", 3), C.output,
                             "catheter centerline points, proximal first, tip last", "m")
        self._register_array("tip_position", (3,), C.output, "tip position", "m")
        self.bend_angle = 0.0
        self.actuator_command = 0.0
        self.advised_insertion_scale = 1.0
        self.tip_force_magnitude = 0.0
        self.total_bend = 0.0
        self.effort_warning = False
        self._register_scalars([
            ("bend_angle", "rad", "actuator bend angle"),
            ("actuator_command", "rad", "command sent to the actuator"),
            ("advised_insertion_scale", None, "1 when all is well, lower as the effort grows"),
            ("tip_force_magnitude", "N", "magnitude of the tip force seen by the controller"),
            ("total_bend", "rad", "active plus passive bend"),
        ], C.output, V.continuous)
        self.register_variable(Boolean("effort_warning", causality=C.output, variability=V.discrete,
                                       description="the order to the operator to reduce the effort"))

    # -- model delegation -----------------------------------------------------------------------
    def _initialize_model(self) -> None:
        params = CatheterParameters(
            n_segments=int(self.n_tool_points) - 1,
            centerline=np.array(self.centerline_points, dtype=float),
            controller_mode=str(self.controller_mode),
            anti_windup=bool(self.anti_windup),
            **{name: float(getattr(self, name)) for name, _, _ in FLOAT_PARAMETERS},
        )
        params.validate(float(self.communication_step))
        self.model = CatheterModel(params, dt=float(self.communication_step))
        self.model.reset(float(self.insertion), float(self.rotation))

    def _step_model(self, t: float, dt: float) -> None:
        self.model.step(t, dt, float(self.insertion), float(self.rotation), self.tip_force,
                        float(self.external_command))

    def _publish_outputs(self) -> None:
        out = self.model.outputs
        self.centerline_positions[...] = out.centerline_positions.reshape(self.centerline_positions.shape)
        self.tip_position[...] = out.tip_position
        self.bend_angle = float(out.bend_angle)
        self.actuator_command = float(out.actuator_command)
        self.effort_warning = bool(out.effort_warning)
        self.advised_insertion_scale = float(out.advised_insertion_scale)
        self.tip_force_magnitude = float(out.tip_force_magnitude)
        self.total_bend = float(out.total_bend)

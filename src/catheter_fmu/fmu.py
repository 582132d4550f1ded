"""The Catheter FMU: its interface, declared once, and the glue to :class:`catheter_fmu.model.CatheterModel`.

Ports follow docs/design.md section 4. The number of centerline points (``n_tool_points`` =
segments + 1) and of vessel-centerline vertices are structural parameters: they size the arrays.
"""
from __future__ import annotations

import numpy as np

from ._coupling import TOOL_POINTS, size_rules
from ._fmi import FmuDeclaration, Limit, input_port, output, output_publisher, parameter, structural
from .geometry import CenterlineCurve
from .model import CatheterModel, CatheterOutputs, CatheterParameterError, CatheterParameters

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


#: The plausible range of every number an importer gives this FMU, and why (a 6 Fr catheter in an
#: aorta, docs/design.md section 7). Values outside are refused (fmi3Error naming the variable, the value
#: and this range); the model checks the relations between them (CatheterParameters.validate).
LIMITS = {
    "segment_length": Limit(1e-4, 0.1, "a catheter link is millimetres long (5 mm by default)"),
    "radius": Limit(1e-4, 0.01, "catheters are 0.3-4 mm in radius (6 Fr: 1 mm)"),
    "active_length": Limit(1e-4, 1.0, "the bending section is a few centimetres of the catheter"),
    "bending_stiffness": Limit(1e-9, 1.0, "EI of a catheter is about 1e-5 to 1e-3 N m2; 1 N m2 is a steel rod"),
    "passive_time_constant": Limit(0.0, 100.0, "the passive tip relaxes in milliseconds to seconds"),
    "actuator_bandwidth": Limit(1e-3, 1e4, "actuators have millihertz to kilohertz bandwidths (and below the step's "
                                           "Nyquist frequency, checked with the step)"),
    "max_bend_angle": Limit(1e-6, 3.141592653589793, "beyond pi the active arc folds back on itself"),
    "max_bend_rate": Limit(1e-6, 1e3, "an actuator bends at most a few radians per second"),
    "kp": Limit(0.0, 1e3, "the regulator's gain is about 0.3 rad/N; 1000 rad/N saturates at any force"),
    "ki": Limit(0.0, 1e5, "the regulator's integral gain is about 8 rad/(N s)"),
    "force_threshold": Limit(1e-6, 1e3, "tip forces that matter are 0.1-10 N"),
    "setpoint_fraction": Limit(1e-6, 1.0, "the regulated force is a fraction of the threshold"),
    "warning_hysteresis": Limit(0.0, 1e3, "a fraction of force_threshold (checked against it)"),
    "n_tool_points": Limit(2, 10_001, f"catheter centerline points (segments + 1): {TOOL_POINTS} by default"),
    "n_centerline_points": Limit(2, 1_000_000, "vertices of the vessel centerline polyline"),
    "centerline_points": Limit(-100.0, 100.0, "the vessel lies within 100 m of the origin"),
    "insertion": Limit(-100.0, 100.0, "an inserted length of metres; 100 m is no catheter"),
    "rotation": Limit(-1e6, 1e6, "an accumulated rotation of up to 1e6 rad (160k turns)"),
    "external_command": Limit(-1e3, 1e3, "an actuator command in radians (saturated at max_bend_angle)"),
    "tip_force": Limit(-1e4, 1e4, "a contact force beyond 10 kN is 1000 times what the tip meets: a broken "
                                  "connection or unit"),
    "tip_stiffness": Limit(-1e9, 1e9, "the contact's stiffness is at most about 1e6 N/m (Contact's limit) times a "
                                      "few facets"),
    "tip_gap": Limit(-1.0, 1.0, "the tip's clearance to the wall is at most the contact's reach (millimetres)"),
}

_defaults = CatheterParameters()
_default_centerline = np.array(CenterlineCurve.aaa_default().vertices, dtype=float)

VARIABLES = (
    *(parameter(name, float(getattr(_defaults, name)), text, unit) for name, unit, text in FLOAT_PARAMETERS),
    parameter("controller_mode", str(_defaults.controller_mode), "off, regulate or external"),
    parameter("anti_windup", bool(_defaults.anti_windup), "stop integrating while the actuator saturates"),
    structural("n_tool_points", _defaults.n_segments + 1, "catheter centerline points (segments + 1)"),
    structural("n_centerline_points", len(_default_centerline), "vertices of the vessel centerline polyline"),
    parameter("centerline_points", _default_centerline, "vessel centerline polyline the catheter follows (entry first)",
              "m", shape=("n_centerline_points", 3)),
    input_port("insertion", "inserted length from the operator/device", "m"),
    input_port("rotation", "catheter rotation from the operator/device", "rad"),
    input_port("external_command", "actuator command in mode external", "rad"),
    input_port("tip_force", "contact force on the tip (from Contact)", "N", shape=(3,)),
    input_port("tip_stiffness", "stiffness of tip_force against the tip's motion, -d tip_force / d tip (from "
               "Contact; zeros: the passive bend is integrated explicitly)", "N/m", shape=(3, 3)),
    input_port("tip_gap", "clearance of the tip to the wall along the normal it will meet, when near it without "
               "force (from Contact, with tip_stiffness; zeros: in contact or far)", "m", shape=(3,)),
    output("centerline_positions", "catheter centerline points, proximal first, tip last", "m",
           shape=("n_tool_points", 3)),
    output("tip_position", "tip position", "m", shape=(3,)),
    output("bend_angle", "actuator bend angle", "rad"),
    output("actuator_command", "command sent to the actuator", "rad"),
    output("advised_insertion_scale", "1 when all is well, lower as the effort grows"),
    output("tip_force_magnitude", "magnitude of the tip force seen by the controller", "N"),
    output("total_bend", "active plus passive bend", "rad"),
    output("effort_warning", "the order to the operator to reduce the effort", type="Boolean"),
)


#: The model's names of the parameters the FMU exposes under other names (its messages name the
#: FMU's variable, the one the user sets).
MODEL_NAMES = {"centerline": "centerline_points", "n_segments": "n_tool_points - 1 (n_segments)"}


def _in_fmu_names(message: str) -> str:
    head, separator, rest = message.partition(": ")
    for model_name, fmu_name in MODEL_NAMES.items():
        if head == model_name:
            return f"{fmu_name}{separator}{rest}"
        if message.startswith(model_name + " "):
            return fmu_name + message[len(model_name):]
    return message


#: The outputs copied from the model's record after each step (the arrays it writes in place).
publish_outputs = output_publisher(VARIABLES, CatheterOutputs,
                                   written_in_place=("centerline_positions", "tip_position"))


class CatheterFmu:
    """Builds the catheter model from the parameters and steps it with the operator's inputs."""

    def __init__(self, values):
        self.values = v = values
        params = CatheterParameters(
            n_segments=v.n_tool_points - 1,
            centerline=np.array(v.centerline_points, dtype=float),
            controller_mode=v.controller_mode,
            anti_windup=v.anti_windup,
            **{name: float(getattr(v, name)) for name, _, _ in FLOAT_PARAMETERS},
        )
        try:
            params.validate(v.internal_step)
        except CatheterParameterError as exc:
            raise CatheterParameterError(_in_fmu_names(str(exc))) from None
        self.model = CatheterModel(params, dt=v.internal_step)
        self.model.reset(v.insertion, v.rotation)
        self.model.write_outputs_into(v.centerline_positions, v.tip_position)
        self._publish(self.model.outputs)

    def step(self, t: float, dt: float) -> None:
        v = self.values
        out = self.model.step(t, dt, v.insertion, v.rotation, v.tip_force, v.external_command,
                              v.tip_stiffness, v.tip_gap)
        # the model writes the arrays into the FMU's buffers; a model restored from an FMU state (a
        # copy) wrote this step into its own: bind it to the buffers again (they take this step's values)
        if out.tip_position is not v.tip_position:
            self.model.write_outputs_into(v.centerline_positions, v.tip_position)
        self._publish(out)

    def _publish(self, out) -> None:
        publish_outputs(self.values, out)


DECLARATION = FmuDeclaration(
    model_name="Catheter",
    description="Active catheter: kinematics on the vessel centerline, actuated tip, effort controller",
    internal_step=0.001,
    variables=VARIABLES,
    adapter=CatheterFmu,
    limits=LIMITS,
    size_rules=size_rules("Catheter"),
)

"""Active catheter: kinematics, tip actuator, force regulation and effort advice (no FMI here).

An active compliant micro-mechanism at the catheter tip senses the contact effort, bends the
tip away from the vessel wall to keep that effort under a threshold, and reports an order to
the surgeon (``effort_warning``, ``advised_insertion_scale``). The FMU wrapper (written on top
of this package) maps docs/design.md section 4 ports one to one onto ``CatheterModel.step``.

Modules:
    geometry    ``CenterlineCurve``: arc-length polyline of the vessel (default: AAA aorta axis,
                +z from (0,0,0) to (0,0,0.13) m), smoothed tangent, parallel-transported frames.
    kinematics  ``CatheterKinematics``: chain of equal links on the centerline; distal active
                section bent as a discrete constant-curvature arc (segment lengths exact).
    actuator    ``Actuator``: exact first-order lag, angle and rate saturation.
    controller  ``ForceRegulator`` (PI on the force excess, anti-windup), ``EffortMonitor``.
    model       ``CatheterParameters`` (validate), ``CatheterModel`` (reset, step, get/set_state).
    analysis    ``PlaneWall`` contact, ``simulate``, ``step_response``, ``linearise``,
                ``open_loop_frequency_response``, ``simulated_frequency_response``,
                ``compare_gains``; module docstring explains how to tune the gains.

Ports of ``CatheterModel.step(t, dt, insertion, rotation, tip_force, external_command=0.0)``:
    inputs   insertion (m, inserted length along the centerline), rotation (rad, turns the
             bending plane about the tangent; 0 = plane of the frame's e1, +x on the default
             centerline), tip_force (3,) N ON the tip from the wall, external_command (rad).
    outputs  (``CatheterOutputs``) centerline_positions (n_tool*3, proximal end first, tip
             last; n_tool = n_segments + 1), tip_position (3,), bend_angle (rad, actuator angle,
             signed in the bending plane), actuator_command (rad), effort_warning (bool),
             advised_insertion_scale (1 below 0.5x threshold, 0 above 2x, smoothstep between),
             plus tip_force_magnitude and total_bend (active + passive) for inspection.

Example::

    import numpy as np
    from catheter_fmu import CatheterModel, CatheterParameters, PlaneWall

    params = CatheterParameters(controller_mode="regulate", force_threshold=0.5, kp=0.3, ki=8.0)
    model = CatheterModel(params, dt=1e-3)          # validates; raises CatheterParameterError
    wall = PlaneWall.inclined(contact_insertion=0.08, incline_deg=20.0, stiffness=500.0)
    force = np.zeros(3)
    for k in range(2000):                           # push 4 cm in 1 s, then hold
        t = k * 1e-3
        out = model.step(t, 1e-3, insertion=min(0.07 + 0.04 * t, 0.11), rotation=0.0, tip_force=force)
        force = wall.force(out.tip_position)        # the Contact FMU's job in the scene
    print(np.linalg.norm(force), out.effort_warning, out.bend_angle)   # 0.40 N, False, 0.72 rad

    from catheter_fmu.analysis import step_response, compare_gains, format_gain_table
    print(step_response(params).settling_time)
    print(format_gain_table(compare_gains([(0.1, 4.0), (0.3, 8.0), (0.3, 16.0)])))
"""

from .actuator import Actuator
from .analysis import (
    FrequencyResponse,
    PlaneWall,
    StepResponse,
    compare_gains,
    contact_loop_gain,
    format_gain_table,
    linearise,
    open_loop_frequency_response,
    simulate,
    simulated_frequency_response,
    step_response,
)
from .controller import EffortMonitor, ForceRegulator, insertion_scale
from .geometry import CenterlineCurve, CenterlineError
from .kinematics import CatheterKinematics
from .model import CONTROLLER_MODES, CatheterModel, CatheterOutputs, CatheterParameterError, CatheterParameters

__all__ = [
    "Actuator",
    "CatheterKinematics",
    "CatheterModel",
    "CatheterOutputs",
    "CatheterParameterError",
    "CatheterParameters",
    "CenterlineCurve",
    "CenterlineError",
    "CONTROLLER_MODES",
    "EffortMonitor",
    "ForceRegulator",
    "FrequencyResponse",
    "PlaneWall",
    "StepResponse",
    "compare_gains",
    "contact_loop_gain",
    "format_gain_table",
    "insertion_scale",
    "linearise",
    "open_loop_frequency_response",
    "simulate",
    "simulated_frequency_response",
    "step_response",
]

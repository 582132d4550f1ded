"""FMU state of the Catheter model: copy.deepcopy and pickle of a CatheterModel that has stepped give
models that continue bit-identically (actuator, controller integrator and direction, warning
hysteresis, passive bend, outputs)."""
import copy
import math
import pickle

import numpy as np
import pytest

from catheter_fmu.model import CatheterModel, CatheterParameters


def _run(model, k0, k1):
    outs = []
    for k in range(k0, k1):
        t = k * 1e-3
        force = [0.3 + 0.4 * math.sin(7 * t), 0.2 * math.cos(5 * t), 0.1]   # crosses the 0.5 N threshold
        out = model.step(t, 1e-3, 0.05 + 0.02 * t, 0.3 * math.sin(2 * t), force, external_command=0.1)
        outs.append((out.centerline_positions.copy(), out.tip_position.copy(), out.bend_angle, out.actuator_command,
                     out.effort_warning, out.advised_insertion_scale, out.tip_force_magnitude, out.total_bend,
                     model.regulator.integral, model.regulator.direction, model.actuator.angle,
                     model.actuator.rate_limited, model.monitor.warning, model.passive_bend.copy(), model.time))
    return outs


@pytest.mark.parametrize("mode", ["regulate", "external", "off"])
@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
def test_catheter_model_copies_continue_bit_identically(mode, how):
    model = CatheterModel(CatheterParameters(controller_mode=mode))
    before = _run(model, 0, 300)
    assert mode != "regulate" or any(o[8] != 0.0 for o in before)         # the integrator has state
    clone = copy.deepcopy(model) if how == "deepcopy" else pickle.loads(pickle.dumps(model))
    first, again = _run(model, 300, 900), _run(clone, 300, 900)
    assert any(o[4] for o in first) and not all(o[4] for o in first)      # the warning toggles
    for a, b in zip(first, again):
        for x, y in zip(a, b):
            if isinstance(x, np.ndarray):
                np.testing.assert_array_equal(x, y)
            else:
                assert x == y


def test_outputs_written_into_bound_arrays_are_the_same_bits():
    """write_outputs_into (an FMU's buffers): the same outputs in the caller's arrays; a deepcopy
    and get_state keep arrays of their own."""
    model, bound = CatheterModel(), CatheterModel()
    _run(model, 0, 200)
    _run(bound, 0, 200)
    centerline, tip = np.full((bound.n_tool, 3), np.nan), np.full(3, np.nan)
    bound.write_outputs_into(centerline, tip)
    np.testing.assert_array_equal(centerline.ravel(), model.outputs.centerline_positions)
    np.testing.assert_array_equal(tip, model.outputs.tip_position)
    state, clone = bound.get_state(), copy.deepcopy(bound)
    first, again, copied = _run(model, 200, 500), _run(bound, 200, 500), _run(clone, 200, 500)
    for a, b, c in zip(first, again, copied):
        for x, y, z in zip(a, b, c):
            np.testing.assert_array_equal(x, y)
            np.testing.assert_array_equal(x, z)
    assert bound.outputs.tip_position is tip and clone.outputs.tip_position is not tip
    np.testing.assert_array_equal(centerline.ravel(), bound.outputs.centerline_positions)
    assert state["outputs"].tip_position is not tip                       # a snapshot, not the live array
    bound.set_state(state)                                                # back into the bound arrays
    assert bound.outputs.tip_position is tip
    np.testing.assert_array_equal(tip, state["outputs"].tip_position)
    np.testing.assert_array_equal(_run(bound, 200, 300)[-1][0], first[99][0])

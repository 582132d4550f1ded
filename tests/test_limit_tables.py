"""The limit tables of connected FMUs agree: what one FMU within its own limits sends, the FMU it
is connected to accepts (issue 33: a Tissue with young_modulus 100 Pa, inside its range, sent a
compliance of 7.7 m/N that Contact refused, ending the run halfway)."""
from __future__ import annotations

import numpy as np
import pytest
from fmpy import read_model_description

from fmu_harness import fmu_instance


def _range(fmu_path, name):
    variable = {v.name: v for v in read_model_description(str(fmu_path)).modelVariables}[name]
    return float(variable.min), float(variable.max)


@pytest.mark.parametrize("viscosity", [0.0, 50.0])
def test_the_softest_tissue_sends_a_compliance_contact_accepts(tissue_fmu, contact_fmu, viscosity):
    low_e, _ = _range(tissue_fmu, "young_modulus")
    low_w, high_w = _range(contact_fmu, "compliance")
    with fmu_instance(tissue_fmu) as fmu:
        fmu.set("young_modulus", low_e)
        fmu.set("viscosity", viscosity)
        fmu.initialize()
        n = fmu.size("patch_nodes")
        fmu.set("patch_nodes", np.arange(n) * 97 % fmu.size("surface_positions") // 3)
        fmu.slave.doStep(0.0, float(fmu.md.coSimulation.fixedInternalStepSize))
        w = fmu.get("compliance")
    assert np.abs(w).max() > 1.0  # soft enough to have crossed the former 1 m/N limit
    assert low_w <= w.min() and w.max() <= high_w, (w.min(), w.max(), low_w, high_w)


def test_an_output_without_a_range_is_held_to_the_range_of_the_inputs_it_feeds():
    """The run's plausibility check takes the consumer's limit table as the contract: one place for
    each limit (Tissue declares no range for its compliance; Contact's input does)."""
    from types import SimpleNamespace

    from orchestration.observers.plausibility import plausible_range

    def port(minimum=None, maximum=None, unit="m/N"):
        return SimpleNamespace(causality="output", type="Float64", minimum=minimum, maximum=maximum, unit=unit)

    compliance = port()
    assert plausible_range(compliance) is None  # no unit bound of its own
    low, high, why = plausible_range(compliance, [("contact.compliance", port(-1e4, 1e4)),
                                                  ("other.compliance", port(-5.0, 100.0))])
    assert (low, high) == (-5.0, 100.0) and "other.compliance" in why
    assert plausible_range(port(0.0, 1.0), [("contact.compliance", port(-1e4, 1e4))])[:2] == (0.0, 1.0)


@pytest.mark.parametrize("name, default, inside", [
    ("max_force", 7.9, (3.3, 22.0, 1000.0)),        # Touch, PHANTOM Premium 3.0, unlimited for contact studies
    ("max_force_rate", 1e4, (5e3, 1e7)),            # the fastest legitimate change (10 kN/m x 0.5 m/s), unlimited
    ("passivity_cycle_tolerance", 1e-3, (0.0, 1.0)),
])
def test_the_device_and_cycle_limits_hold_their_defaults_and_the_devices(contact_fmu, name, default, inside):
    """Contact's device limit (max_force, max_force_rate) and the per-cycle passivity tolerance have
    ranges in the limit table holding the default and the settings the documentation names."""
    low, high = _range(contact_fmu, name)
    variable = {v.name: v for v in read_model_description(str(contact_fmu)).modelVariables}[name]
    assert float(variable.start) == default
    assert all(low <= x <= high for x in (default, *inside)), (low, high)


def test_the_rendered_force_limit_lies_within_what_the_run_calls_plausible():
    """The largest max_force Contact accepts (1 kN) is within the orchestrator's plausible force
    (1e4 N): an unlimited study's force is not reported as implausible for the limit alone."""
    from haptic_fmu.fmu import LIMITS

    from orchestration.observers.plausibility import PLAUSIBLE_MAGNITUDE

    assert LIMITS["max_force"].maximum < PLAUSIBLE_MAGNITUDE["N"][0]

"""Regression tests of the haptic findings: one real scene run per finding, judged by
tests/operator_motion.py.

These fail on the contact model as it was when they were written (each docstring gives the
numbers measured then) and pass once the narrow phase rewrite delivers what the findings ask:
no force without overlap, a wall that stays finite, no force steps beyond what the tool's motion
explains, no period-2 alternation, a held probe that is still, and no energy handed back by a
tap. Every test collects all its violations before failing, so one run says everything.

Runs are shared through a module-scoped cache (each scene/motion/stiffness runs once); all are
marked slow (whole 2-4 s scene runs with the 30 Hz tissue: 13 runs, about 40 s for the file here).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

import operator_motion as om

pytestmark = pytest.mark.slow

#: tolerances: tests/operator_motion.py says how each was measured
STEP_TOL, FRAME_SLACK, PHANTOM_TOL = om.STEP_TOL, om.FRAME_SLACK, om.PHANTOM_TOL


@pytest.fixture(scope="module")
def built(tissue_fmu, contact_fmu, catheter_fmu):
    """The scenes use fmus/: build them from this checkout first (as tests/test_runs.py does)."""
    from orchestration.app.warmup import ensure_fmus_built

    ensure_fmus_built(quiet=True)


@pytest.fixture(scope="module")
def run(built, tmp_path_factory):
    """run(scene, motion, stiffness, duration) -> Trace, each distinct run made once per module."""
    cache: dict = {}

    def get(scene: str, motion: om.Motion, stiffness: float, duration: float) -> om.Trace:
        key = (scene, motion.describe(), float(stiffness), float(duration))
        if key not in cache:
            out = tmp_path_factory.mktemp(f"{scene}_{int(stiffness)}")
            cache[key] = om.run_motion(scene, motion, stiffness, duration, out)
        return cache[key]

    return get


def _report(trace: om.Trace, problems: list[str]) -> str:
    return f"{trace.label()}:\n  " + "\n  ".join(problems)


# -- 1. twice as fast into the sac: phantom force and a diverging wall -----------------------------
def fast_insertion() -> om.Motion:
    """aaa_endovascular's insertion with the same start and end but half the ramp time (the
    ramp from 0.2 s to 1.35 s instead of 2.5 s): 12 mm/s instead of 6."""
    scripted = om.scripted_motion("aaa_endovascular")
    t = scripted.times
    return om.Motion((t[0], t[1], t[1] + (t[2] - t[1]) / 2, t[3]), scripted.outputs)


#: N: a plausible peak of the catheter tip against the sac. The regulator holds 0.4 N and warns at
#: 0.5 N; the scripted push peaks at 0.57-0.61 N at every stiffness (400-10000 N/m) and the fast
#: push at 0.76 N at 1000 N/m (measured). 2 N is 2.5x the largest of them and 4x the warning, while
#: the phantom reaches 27-89 N.
PLAUSIBLE_PEAK = 2.0


@pytest.mark.parametrize("stiffness", [3000.0, 5000.0, 8000.0, 10000.0])
def test_fast_insertion_gives_no_phantom_force_and_keeps_the_wall_finite(run, stiffness):
    """Finding: at 3000-10000 N/m the twice-as-fast insertion meets a 27-89 N force at ~1.07 s
    (penetration_depth jumps from 0.2 to 9 mm at a new tissue frame, the tool overlapping the wall
    by 0.15-0.3 mm) and the tissue diverges at 1.1 s (the run fails). Measured then: 26.6 / 44.6 /
    71.5 / 89.4 N at 1.068 s, run failed at t = 1.1 s (tetrahedra inverted)."""
    trace = run("aaa_endovascular", fast_insertion(), stiffness, 2.0)
    problems = (om.finite_tissue(trace) + om.phantom_force(trace, PHANTOM_TOL)
                + om.peak_force(trace, PLAUSIBLE_PEAK))
    assert not problems, _report(trace, problems)


# -- 2. the default scene: period-2 alternation ---------------------------------------------------
#: s: after this the default scene's force is settled (tests/test_runs.py: t > 3.0 s)
SETTLED_AFTER = 3.0
#: N: the regulator's setpoint, setpoint_fraction 0.8 x force_threshold 0.5 N
SETPOINT = 0.400


@pytest.mark.parametrize("stiffness, settled_after", [(1000.0, SETTLED_AFTER), (400.0, 3.3)])
def test_default_scene_force_neither_alternates_nor_steps_and_settles(run, stiffness, settled_after):
    """Finding: aaa_endovascular as shipped alternates 0.55 <-> 0.61 N every millisecond at 2.211 s
    and 2.263 s (1000 N/m); at 400 N/m 19 alternating samples in 3 bursts of up to 149 mN and
    single 150 mN spikes after the force first settled. Measured then: at 1000 N/m bursts of 4 and 6
    reversals from 2.210 and 2.262 s (steps of 39-67 mN where 18-24 mN were allowed); at 400 N/m
    bursts of 8, 8 and 2 reversals at 1.784, 1.825 and 1.937 s and 30 steps up to 154 mN (2.881 s).
    The settled force (t > 3 s, as tests/test_runs.py) stays at the setpoint: 0.4000-0.4003 N then,
    asserted within 1 mN. At 400 N/m the regulator now approaches it a little more slowly (the
    energy-consistent hold: 1.06 mN above it at 3.0 s, 0.15 mN at 3.2 s, 0.06 mN at 3.3 s, decaying
    without a reversal), so there it is judged from 3.3 s."""
    trace = run("aaa_endovascular", om.scripted_motion("aaa_endovascular"), stiffness, 4.0)
    problems = om.completed(trace) + om.alternation(trace) + om.force_steps(trace, STEP_TOL, FRAME_SLACK)
    settled = om.settled(trace, settled_after)
    if settled.size == 0 or np.abs(settled - SETPOINT).max() > 0.001:
        worst = float(settled[np.argmax(np.abs(settled - SETPOINT))]) if settled.size else float("nan")
        problems.append(f"settled force (t > {settled_after} s) leaves {SETPOINT} N +- 1 mN: {worst:.5f} N "
                        f"(range {settled.min() if settled.size else np.nan:.5f}-"
                        f"{settled.max() if settled.size else np.nan:.5f} N)")
    assert not problems, _report(trace, problems)


# -- 3. the catheter in the rigid tube: radius crossing, limit cycle, energy -------------------------
@pytest.mark.parametrize("stiffness", [1000.0, 5000.0, 10000.0])
def test_catheter_tube_force_is_continuous_and_creates_no_energy(run, stiffness):
    """Finding: the force jumps by 1.4 / 9.4 / 18.4 N (1000 / 5000 / 10000 N/m) when the penetration
    crosses the catheter radius; at 10000 N/m the tip regulator limit-cycles for 76 ms and the port
    creates 0.0102 J. Measured then: steps of 1.425 / 9.471 / 18.45 N at 2.111 / 2.131 / 2.142 s;
    alternation bursts at all three (76 reversals in a row from 1.952 s at 10000 N/m); the contact
    cycle from 1.403 s ends with -9.16 mJ at 10000 N/m (passivity_energy down to -24 mJ)."""
    trace = run("catheter_tube", om.scripted_motion("catheter_tube"), stiffness, 3.0)
    problems = (om.completed(trace) + om.force_steps(trace, STEP_TOL, FRAME_SLACK) + om.alternation(trace)
                + om.cycle_energy(trace, om.ENERGY_REL_TOL, om.ENERGY_ABS_TOL))
    assert not problems, _report(trace, problems)


# -- 4. a probe held on the sac: permanent 500 Hz vibration ----------------------------------------
#: N: peak-to-peak of the held probe's force over the last 0.3 s. The probe stands still from 1.1 s
#: and the wall settles (viscosity 50 Pa s): at 1000 N/m the force is constant to 7e-12 N over that
#: window (measured), so anything above round-off is the contact's own motion. 0.1 mN is 0.02 % of
#: the 0.42-0.44 N held force and 1/30 of the 3-4 mN vibration.
STILL_PTP = 1e-4


@pytest.mark.parametrize("stiffness", [5000.0, 10000.0])
def test_held_probe_force_is_still(run, stiffness):
    """Finding: tissue_indentation at 5000 and 10000 N/m vibrates at 500 Hz after settling, 3-4 mN
    peak to peak, the probe resting on a mesh vertex (its force direction flips between the facets
    meeting there). Measured then: |F| peak-to-peak 4.11 / 3.22 mN over the last 0.3 s, a component
    of F moving by 22.8 / 25.4 mN (steps of up to 35 mN). Asserted on |F| and on every component."""
    trace = run("tissue_indentation", om.scripted_motion("tissue_indentation"), stiffness, 2.0)
    problems = om.completed(trace)
    window = trace.t > trace.t[-1] - 0.3
    ptp = float(np.ptp(trace.magnitude[window])) if window.any() else np.inf
    spread = float(np.ptp(trace.force[window], axis=0).max()) if window.any() else np.inf
    if ptp >= STILL_PTP:
        problems.append(f"|F| over the last 0.3 s: peak-to-peak {ptp * 1e3:.4f} mN >= {STILL_PTP * 1e3:g} mN "
                        f"(mean {trace.magnitude[window].mean():.5f} N)")
    if spread >= STILL_PTP:
        problems.append(f"F over the last 0.3 s: a component moves by {spread * 1e3:.4f} mN >= {STILL_PTP * 1e3:g} mN")
    assert not problems, _report(trace, problems)


# -- 5. taps return more energy than they took ----------------------------------------------------
#: Per-cycle energy: E >= -(1e-3 x exchanged + 1 nJ + what the wall held when the tap began)
#: (operator_motion.ENERGY_REL_TOL: "within round-off" is ~1e-15 of the exchange; a passive
#: rendering keeps E >= 0, measured on virtual_wall with damping above K T / 2; 1e-3 is 20-65x below
#: today's 2-6.6 % per tap).
TAP_REL_TOL, TAP_ABS_TOL = om.ENERGY_REL_TOL, om.ENERGY_ABS_TOL
TAP_HZ = 5.0


def probe_tap() -> om.Motion:
    """The probe of tissue_indentation tapping the sac at 5 Hz between its scripted extremes: 1 mm
    outside the outer wall and 1.5 mm past it (25 mm/s), for 2 s."""
    return om.tap_motion("tissue_indentation", TAP_HZ, outside=-0.001, inside=0.0015, start=-0.001, end=2.0)


def catheter_tap() -> om.Motion:
    """The catheter of aaa_endovascular tapping the sac at 5 Hz: insertion between 1 mm short of
    where the tip meets the wall (0.0782 m) and 2 mm past it (30 mm/s), for 2 s."""
    return om.tap_motion("aaa_endovascular", TAP_HZ, outside=0.0772, inside=0.0802, start=0.074, end=2.0)


#: What the energy-consistent hold leaves on the tissue scenes (issue 28 stays open on it): the
#: probe's tap creates 2.8-3.8 uJ of 526 uJ (from 11.2 uJ), the catheter's 30-37 uJ of 690 uJ (from
#: 39-42 uJ; the same with its controller off): the 30 Hz wall's frames and its compliance under a
#: force applied two frames late give back what the hold no longer creates.
MULTIRATE_TAP = pytest.mark.xfail(strict=True, reason="issue 28: energy from the 30 Hz tissue coupling")


@pytest.mark.parametrize("scene", [pytest.param("tissue_indentation", marks=MULTIRATE_TAP),
                                   pytest.param("aaa_endovascular", marks=MULTIRATE_TAP)])
def test_a_tap_returns_no_more_energy_than_it_took(run, scene):
    """Finding: a 5 Hz tap on the sac wall at 1000 N/m returns 17-51 uJ more than it took, every
    tap. Measured then with these taps: the probe creates 11.2 uJ of 526 uJ exchanged per tap
    (12.2 uJ the first), the catheter 39-42 uJ of 610-630 uJ (its wall holding at most 5.5 uJ when
    a tap begins), 9 taps each (the energy a zero-order-hold penalty creates per tap grows as
    k x depth x speed x T: other tap depths and speeds give other amounts, all of one sign). For
    the probe the energy is summed here from the recorded force and position and checked against
    the FMU's passivity_energy (port_energy_agrees)."""
    motion = probe_tap() if scene == "tissue_indentation" else catheter_tap()
    trace = run(scene, motion, 1000.0, 2.0)
    cycles = om.contact_cycles(trace)
    problems = om.completed(trace) + om.port_energy_agrees(trace)
    if len(cycles) < 8:
        problems.append(f"only {len(cycles)} contact cycles in 2 s of 5 Hz taps (expected 8 or more): the tap "
                        "no longer leaves the wall, the test does not measure what it should")
    problems += om.cycle_energy(trace, TAP_REL_TOL, TAP_ABS_TOL)
    assert not problems, _report(trace, problems)


# -- 6. the catheter's tip loop under other hands (found by the operator-motion fuzzer) -------------
def _tube(times, insertion, rotation=None) -> om.Motion:
    rotation = rotation if rotation is not None else [0.0] * len(times)
    return om.Motion(tuple(times), {"insertion": tuple(insertion), "rotation": tuple(rotation)})


#: catheter_tube motions the fuzzer found alternating, each with its stiffness and what was measured:
TIP_LOOP_CASES = {
    # pushed at 50 mm/s to 0.09 m: the tip's stiffness counted the last segment's overlap as if the
    # tip's own sphere did not carry it (80 % too stiff, jumping every step): up to 5 N at 500 Hz
    "fast push": (10000.0, _tube([0.0, 0.1, 0.42, 1.0], [0.074, 0.074, 0.09, 0.09]), 1.0),
    # in and out at 0.1 m/s: the regulator's own motion came back through the wall one step late,
    # and the released tip sprang back into the wall each other step (0.217 -> 0 -> 0.168 -> 0 N)
    "fast retraction": (3000.0, _tube([0.0, 0.1, 0.348, 0.372, 0.431, 0.6],
                                      [0.077, 0.077, 0.08, 0.0776837, 0.0795, 0.0795]), 0.6),
    # in and out at 87-137 mm/s: a first touch counted twice (the tip and its segment), and the
    # predicted depth change carrying a jump into two holds (0 -> 0.533 -> 0.493 -> 0.511 N)
    "taps": (10000.0, _tube([0.0, 0.1, 0.221, 0.338, 0.455, 0.572, 0.7],
                            [0.0753, 0.0753, 0.0855, 0.0753, 0.0855, 0.0753, 0.0753]), 0.7),
    # taps at 150 mm/s: at each turn the tip jumped out of the wall while its segment still touched
    # it, and the wall it was about to meet again was known only without that segment's force:
    # 3.36 -> 1.33 -> 3.11 -> 1.00 -> 2.69 -> 0.68 N
    "tap turns": (5000.0, _tube([0.0, 0.1, 0.38, 0.993, 1.07, 1.147, 1.224, 1.301, 1.4],
                                [0.077, 0.077, 0.0790968, 0.0745046, 0.0860393, 0.0745046, 0.0860393, 0.0745046,
                                 0.0745046]), 1.4),
    # rolled through a quarter turn while pressed: the bending plane crossed the force's
    # perpendicular and the regulator's hard sign flipped its command every step (70 mN at 500 Hz)
    "roll": (5000.0, _tube([0.0, 0.1, 0.659, 0.681, 2.108], [0.077, 0.077, 0.0853711, 0.0853711, 0.0853711],
                           [0.0, 0.0, 0.0, 0.0, -math.pi]), 2.2),
}


@pytest.mark.parametrize("case", list(TIP_LOOP_CASES))
def test_catheter_tip_loop_does_not_alternate_under_other_hands(run, case):
    """Findings of the operator-motion fuzzer on catheter_tube (see TIP_LOOP_CASES): the force must
    neither alternate nor step beyond what the tool's motion explains."""
    stiffness, motion, duration = TIP_LOOP_CASES[case]
    trace = run("catheter_tube", motion, stiffness, duration)
    problems = om.completed(trace) + om.alternation(trace) + om.force_steps(trace, STEP_TOL, FRAME_SLACK)
    assert not problems, _report(trace, problems)


#: aaa_endovascular: the tip pressed 2 N deep into the sac at 10 kN/m, then rolled a quarter turn:
#: bursts of 35-250 mN alternation where a new tissue frame moves the wall under it (open)
SAC_ROLL_MOTION = _tube([0.0, 0.1, 0.166, 0.298, 0.475, 0.708, 1.0],
                        [0.0772, 0.0772, 0.08, 0.0849194, 0.0849194, 0.0849194, 0.0849194],
                        [0.0, 0.0, 0.0, 0.0, 0.0, 1.5, 1.5])


@pytest.mark.xfail(strict=True, reason="issue 28: the 30 Hz sac's frames move the wall under a deeply pressed, "
                                       "rolling tip at 10 kN/m")
def test_a_tip_rolled_on_the_sac_does_not_alternate(run):
    """Found by the operator-motion fuzzer: measured 7 alternation bursts (2-6 reversals, up to 246
    mN) between 0.64 and 0.75 s, most at a sample that took a new tissue frame."""
    trace = run("aaa_endovascular", SAC_ROLL_MOTION, 10000.0, 1.0)
    problems = om.completed(trace) + om.alternation(trace)
    assert not problems, _report(trace, problems)

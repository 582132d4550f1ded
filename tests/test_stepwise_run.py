"""A run advanced call by call (``MultirateAlgorithm.advance``, what the scene exported as one FMU
does each fmi3DoStep) makes the steps of a whole run with the same values, bit for bit, also when
the operator's values come from outside (``ExternalSource``) instead of the scene's script."""
from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from orchestration.blocks.sources import ExternalSource
from orchestration.hosts.in_process import InProcessFmu
from orchestration.observers.base import Observer
from orchestration.run.algorithm import MultirateAlgorithm
from orchestration.scene.loading import load_scene

PORTS = {"contact": ["tool_force", "tip_force", "penetration_depth"], "catheter": ["tip_position", "bend_angle"],
         "tissue": ["max_strain", "frame"]}
DURATION = Fraction(17, 10)  # past the first touch of the sac wall (about 1.5 s)


class Samples(Observer):
    def __init__(self):
        self.rows: dict[str, list] = {name: [] for name in PORTS}

    def ports(self, component: str) -> list[str]:
        return PORTS.get(component, [])

    def stepped(self, component, tick, outputs):
        self.rows[component.name].append((tick, np.concatenate([np.ravel(outputs[p]) for p in PORTS[component.name]])))


def _algorithm(scene, samples, sources=None):
    def host(spec):
        return InProcessFmu(spec.name, spec.description) if spec.is_fmu else spec.new_block()

    algorithm = MultirateAlgorithm(scene, DURATION, host, [samples], compiled_loop=False, sources=sources)
    algorithm.setup()
    algorithm.initialize()
    return algorithm


@pytest.fixture(scope="module")
def whole_run(fmus_in_repo):
    scene = load_scene("aaa_endovascular")
    samples = Samples()
    algorithm = _algorithm(scene, samples)
    try:
        algorithm.run(lambda: 0.0)
    finally:
        algorithm.teardown()
    return scene, samples.rows


def _same(rows, reference):
    assert [t for t, _ in rows] == [t for t, _ in reference]
    for (_, a), (_, b) in zip(rows, reference):
        assert a.tobytes() == b.tobytes()


def test_advancing_millisecond_by_millisecond_makes_the_same_steps(whole_run):
    scene, reference = whole_run
    samples = Samples()
    algorithm = _algorithm(scene, samples)
    try:
        ms = algorithm.base // 1000
        for k in range(1, int(DURATION * 1000) + 1):
            algorithm.advance(k * ms)
            # no step ends beyond the tick asked for, and the 1 kHz components reached it
            assert all(c.time <= k * ms for c in algorithm.ordered)
            assert algorithm.components["contact"].time == algorithm.components["catheter"].time == k * ms
    finally:
        algorithm.teardown()
    for name in PORTS:
        _same(samples.rows[name], reference[name])
    assert max(row[1][0] ** 2 + row[1][1] ** 2 + row[1][2] ** 2 for row in reference["contact"]) > 0.01  # touched


def test_the_operator_from_outside_gives_the_same_steps(whole_run):
    """The values a master sets before advancing over (t, t + h] are those of the scene's script at
    t + h (the catheter's connection from the operator is gauss-seidel: it reads them at its step's end)."""
    scene, reference = whole_run
    script = scene.components["operator"].new_block()
    external = ExternalSource("operator", script.ports)
    samples = Samples()
    algorithm = _algorithm(scene, samples, sources={"operator": external})
    try:
        ms = algorithm.base // 1000
        for k in range(1, int(DURATION * 1000) + 1):
            for name, value in script.evaluate(k / 1000).items():
                external.values[name][:] = value
            algorithm.advance(k * ms)
    finally:
        algorithm.teardown()
    for name in PORTS:
        _same(samples.rows[name], reference[name])


def test_advancing_by_uneven_amounts_makes_the_same_steps(whole_run):
    scene, reference = whole_run
    samples = Samples()
    algorithm = _algorithm(scene, samples)
    try:
        tick, end = 0, int(DURATION * algorithm.base)
        rng = np.random.default_rng(7)
        while tick < end:
            tick = min(end, tick + int(rng.integers(1, 400)))  # not on any grid: a step ends at or before it
            algorithm.advance(tick)
    finally:
        algorithm.teardown()
    for name in PORTS:
        _same(samples.rows[name], reference[name])

"""docs/extending.md, done as it says: a new transition and a fourth FMU with a port of its own,
coupled in a scene and run (with the compiled loop and without), so that the page cannot go stale."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

from fmu_build.package import build_fmu_from_spec
from fmu_build.specs import FmuSpec
from orchestration.observers.recorder import read_stream
from orchestration.plan import transitions as tr
from orchestration.run.simulation import run_scene
from orchestration.scene.loading import scene_from_dict
from orchestration.scene.model import SceneError

ROOT = Path(__file__).resolve().parent.parent
PAGE = (ROOT / "docs" / "extending.md").read_text()
GAIN = 2.5
A, B, C = 1.0, 2.0, 3.0  # the signal y = A + B t + C t^2

FMU_PY = '''"""Gain: y = k u (the fourth FMU of docs/extending.md)."""
from ._fmi import FmuDeclaration, input_port, output, parameter


class Gain:
    def __init__(self, values):
        self.values = values
        values.y = values.k * values.u

    def step(self, t, dt):
        self.values.y = self.values.k * self.values.u


DECLARATION = FmuDeclaration(
    model_name="Gain", description="y = k u", internal_step=0.01, adapter=Gain,
    variables=(
        parameter("k", 1.0, "the gain"),
        input_port("u", "the input"),
        output("y", "k u, the gained input"),
    ),
)
'''


def _python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, re.DOTALL)


@pytest.fixture
def previous_transition():
    """The page's transition, registered by running the page's own code."""
    namespace: dict = {}
    exec(_python_blocks(PAGE)[0], namespace)
    cls = namespace["Previous"]
    yield cls
    del tr.REGISTRY[cls.name]


@pytest.fixture(scope="module")
def gain_fmu(tmp_path_factory) -> Path:
    """The page's fourth FMU: a package with fmu.py and the _fmi.py link, built from its FmuSpec."""
    root = tmp_path_factory.mktemp("packages")
    package = root / "gain_fmu"
    package.mkdir()
    (package / "__init__.py").write_text("")
    os.symlink(ROOT / "src" / "fmi3_layer" / "declare.py", package / "_fmi.py")
    (package / "fmu.py").write_text(FMU_PY)
    assert 'output("y", "k u, the gained input")' in PAGE and 'FmuSpec("Gain", "gain_fmu")' in PAGE
    return build_fmu_from_spec(FmuSpec("Gain", "gain_fmu", source_root=root), tmp_path_factory.mktemp("fmus"))


def _scene(synthetic_fmus, gain_fmu, transition: str) -> dict:
    return {
        "scene": {"name": "extending", "duration": 0.2, "hosting": "in-process"},
        "fmu": {
            "signal": {"path": str(synthetic_fmus["Signal"]), "step": 0.01, "parameters": {"coefficients": [A, B, C]}},
            "gain": {"path": str(gain_fmu), "step": 0.01, "parameters": {"k": GAIN}},
        },
        "connection": [{"from": "signal.y", "to": "gain.u", "transition": transition, "ordering": "jacobi"}],
        "record": {"gain": ["y"], "signal": ["y"]},
    }


def test_the_pages_transition_is_one_class_and_stays_out_of_the_compiled_loop(previous_transition):
    assert tr.REGISTRY["previous"] is previous_transition
    assert previous_transition.compiled is None            # declared nowhere in its body
    assert tr.Hold.compiled is tr.Compiled.LATEST

    class LateHold(tr.Hold):                               # a subclass of Hold that does not say
        name = "late_hold"

    assert LateHold.compiled is None


def test_a_fourth_fmu_and_a_new_transition_run_in_a_scene(synthetic_fmus, gain_fmu, previous_transition, tmp_path):
    data = _scene(synthetic_fmus, gain_fmu, "previous")
    columns = {}
    for loop in (True, False):
        out = tmp_path / f"compiled_{loop}"
        summary, _ = run_scene(scene_from_dict(data, tmp_path), out, progress=False, plots=False,
                               compiled_loop=loop)
        assert summary["status"] == "completed", summary["error"]
        columns[loop] = {name: (out / f"{name}.csv").read_bytes() for name in ("gain", "signal")}
        t, gain = read_stream(out / "gain.csv")
        _, signal = read_stream(out / "signal.csv")
        y = signal["y"]
        # jacobi: the step from t reads the samples up to t; "previous" passes the one before the latest
        for i in range(2, len(t)):
            assert gain["y"][i] == pytest.approx(GAIN * y[i - 2], rel=1e-15), (i, t[i])
    assert columns[True] == columns[False]                 # the compiled loop stepped it as Python does


def test_an_unregistered_transition_is_refused_with_the_names_there_are(synthetic_fmus, gain_fmu, tmp_path):
    with pytest.raises(SceneError, match="is not one of hold, interpolate, extrapolate, average"):
        scene_from_dict(_scene(synthetic_fmus, gain_fmu, "previous"), tmp_path)

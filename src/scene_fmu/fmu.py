"""The scene FMU: its interface, declared from ``scene_fmu.json``, and the glue to the orchestrator.

Each fmi3DoStep of ``h`` runs ``h / step`` internal steps; an internal step ``[t, t + step]`` sets
the scene's sources from the inputs and advances the scene's run to ``t + step``
(``MultirateAlgorithm.advance``): every component makes the steps that end by then, with the same
values as a whole run. An input set before the step ``[t, t + step]`` is the source's value at
``t + step`` (the operator's hand where the step ends, as the scene's own script gives it to a
gauss-seidel connection); outputs are those of the components at ``t + step``, and a slower
component's (the 30 Hz tissue) those of its latest step.
"""
from __future__ import annotations

import json
import logging
import math
import sys
from fractions import Fraction
from pathlib import Path

from ._fmi import SI_UNITS, FmuDeclaration, Variable, input_port, output

HERE = Path(__file__).resolve().parent
SPEC_FILE = HERE / "scene_fmu.json"

logger = logging.getLogger(__name__)


def _read_spec() -> dict:
    if not SPEC_FILE.exists():
        raise ImportError(f"{SPEC_FILE} is missing: a scene FMU is made by `python -m orchestration export SCENE "
                          "--fmu OUT.fmu`, which writes it")
    return json.loads(SPEC_FILE.read_text())


SPEC = _read_spec()


def _variable(port: dict) -> Variable:
    unit = port.get("unit") if port.get("unit") in SI_UNITS else None
    if port["causality"] == "input":
        return input_port(port["name"], port["description"], unit, start=float(port["start"]))
    return output(port["name"], port["description"], unit, type=port["type"])


#: an output's type -> the Python value it is written as (the layer's buffers take exactly these)
_CASTS = {"Float64": float, "Int32": int, "Boolean": bool}

VARIABLES = tuple(_variable(port) for port in SPEC["inputs"] + SPEC["outputs"])


class SceneFmu:
    """Runs the scene's orchestrator inside the FMU; its sources from the inputs, its ports as outputs."""

    def __init__(self, values):
        # this instance's files: the module may have been imported from another instance's extraction
        here = Path(values.resource_folder()) / HERE.name
        if str(here / "vendor") not in sys.path:
            sys.path.append(str(here / "vendor"))  # an importer's own orchestrator (the same checkout) goes first
        from orchestration.blocks.sources import ExternalSource
        from orchestration.errors import OrchestrationError
        from orchestration.hosts.in_process import InProcessFmu
        from orchestration.run.algorithm import MultirateAlgorithm
        from orchestration.scene.loading import scene_from_dict

        self.values = values
        data = json.loads((here / "scene.json").read_text(encoding="utf-8"))
        for name, table in data.get("fmu", {}).items():  # the FMUs this FMU carries, each in this process
            table["path"] = str(here / "fmus" / SPEC["fmus"][name])
            table.pop("hosting", None)
        data.setdefault("scene", {}).update(hosting="in-process", realtime=False)
        data.pop("record", None)  # the importer records the outputs
        data.pop("summary", None)
        overrides = {**SPEC["overrides"], "duration": SPEC["horizon"]}
        scene = scene_from_dict(data, here, here / "scene.json", overrides)
        self.sources = {name: ExternalSource(name, scene.components[name].new_block().ports)
                        for name in {port["source"] for port in SPEC["inputs"]}}
        self.inputs = [(port["name"], self.sources[port["source"]].values[port["port"]], port["index"])
                       for port in SPEC["inputs"]]
        self.outputs = [(port["name"], port["component"], port["port"], port["index"], _CASTS[port["type"]])
                        for port in SPEC["outputs"]]
        observed = {}
        for _, component, port, _, _ in self.outputs:
            observed.setdefault(component, [])
            if port not in observed[component]:
                observed[component].append(port)

        def host(spec):
            return InProcessFmu(spec.name, spec.description) if spec.is_fmu else spec.new_block()

        self.algorithm = MultirateAlgorithm(scene, Fraction(SPEC["horizon"]), host, extra_observed=observed,
                                            compiled_loop=False, sources=self.sources)
        self.base = self.algorithm.base
        self._read_inputs()
        #: what a scene's component refusing a call raises: the importer hears its reason (a refusal, not a defect)
        self.refusal = OrchestrationError
        try:
            self.algorithm.setup()
            self.algorithm.initialize()
        except self.refusal as exc:
            self.algorithm.teardown()
            raise ValueError(str(exc)) from None
        except BaseException:
            self.algorithm.teardown()
            raise
        self._publish()

    def _read_inputs(self) -> None:
        v = self.values
        for name, target, index in self.inputs:
            target[index] = getattr(v, name)

    def _publish(self) -> None:
        v, components = self.values, self.algorithm.components
        for name, component, port, index, cast in self.outputs:
            setattr(v, name, cast(components[component].outputs[port].flat[index]))

    def step(self, t: float, dt: float) -> None:
        self._read_inputs()
        ticks = (t + dt) * self.base
        tick = round(ticks)
        if not math.isclose(ticks, tick, rel_tol=0, abs_tol=1e-3):  # a master summing its steps drifts
            raise ValueError(f"t + h = {t + dt!r} s is not on the scene's time grid (1/{self.base} s)")
        if tick > self.algorithm.end:
            raise ValueError(f"t + h = {t + dt!r} s is beyond the {SPEC['horizon']} s this FMU was exported to run; "
                             "export the scene again with a longer --horizon")
        try:
            self.algorithm.advance(tick)
        except self.refusal as exc:  # e.g. "catheter: fmi3SetFloat64 ... failed (fmi3Error): insertion = ..."
            raise ValueError(str(exc)) from None
        self._publish()

    def terminate(self) -> None:
        for component, status, text in self.algorithm.teardown():
            if status >= 3:  # the inner FMUs' errors, for the importer's log
                logger.error("%s: %s", component, text)

    def __deepcopy__(self, memo):
        raise ValueError("the scene FMU cannot save its state: it holds the instances of the FMUs it carries")


DECLARATION = FmuDeclaration(
    model_name=SPEC["model_name"],
    description=SPEC["description"],
    internal_step=float(Fraction(SPEC["step"])),
    variables=VARIABLES,
    adapter=SceneFmu,
    stop_time=float(SPEC["stop_time"]),
    max_steps_per_call=int(Fraction(SPEC["horizon"]) / Fraction(SPEC["step"])) + 1,
    saves_state=False,
)

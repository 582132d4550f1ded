"""The coupling contract travels with the FMUs (src/fmi3_layer/coupling.py): the default scene wires
them as it says, each FMU carries it (documentation/coupling.json, index.html), a master written
from it alone reproduces the orchestrator's run, and the FMUs refuse a broken rule quoting it."""
from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from fractions import Fraction

import pytest
from fmpy.fmi1 import FMICallException

from fmu_harness import fmu_instance
from haptic_fmu._coupling import AGREEMENTS, LINKS, PATCH_NODES, RULES, STEPS, TOOL_POINTS, contract_of
from orchestration.hosts.description import read_fmu
from project import REPO, scene_path

DEFAULT_SCENE = "aaa_endovascular"


def _scene_links(scene) -> set[tuple]:
    """The default scene's connections as (source, target, transition, ordering), by FMU model name."""
    def name(component: str, port: str) -> str:
        spec = scene.components[component]
        return f"{spec.description.model_identifier if spec.is_fmu else component}.{port}"

    links = set()
    for c in scene.connections:
        parameter = scene.components[c.target].ports[c.target_port].causality != "input"
        links.add((name(c.source, c.source_port), name(c.target, c.target_port),
                   "parameter" if parameter else (c.transition or "hold"), "" if parameter else str(c.ordering)))
    return links


def test_the_default_scene_wires_the_fmus_as_the_contract_says(fmus_in_repo):
    from orchestration.scene.loading import load_scene

    scene = load_scene(DEFAULT_SCENE)
    assert _scene_links(scene) == {(x.source, x.target, x.transition, x.ordering) for x in LINKS}
    steps = {spec.description.model_identifier: spec.step for spec in scene.components.values() if spec.is_fmu}
    assert steps == {name: Fraction(step) for name, step in STEPS.items()}


def test_the_sizes_the_contract_pairs_start_equal(fmus):
    ports = {name: read_fmu(fmus[name]).ports for name in ("Tissue", "Contact", "Catheter")}
    assert len(AGREEMENTS) == 4
    for agreement in AGREEMENTS:
        starts = {ports[fmu][parameter].start for fmu, parameter in (p.split(".") for p in agreement.parameters)}
        assert len(starts) == 1, agreement
        assert agreement.default is None or starts == {agreement.default}
    assert ports["Contact"]["tool_positions"].size == ports["Catheter"]["centerline_positions"].size == TOOL_POINTS * 3
    assert ports["Contact"]["patch_nodes"].size == ports["Tissue"]["patch_nodes"].size == PATCH_NODES


@pytest.mark.parametrize("name", ["Tissue", "Contact", "Catheter"])
def test_each_fmu_carries_its_part_of_the_contract(fmus, name):
    with zipfile.ZipFile(fmus[name]) as archive:
        carried = json.loads(archive.read("documentation/coupling.json"))
        html = archive.read("documentation/index.html").decode()
    assert carried == contract_of(name)
    mine = [x for x in LINKS if name in (x.source.split(".")[0], x.target.split(".")[0])]
    assert len(carried["inputs"]) + len(carried["outputs"]) == len(mine) > 0
    assert "<h2>Coupling</h2>" in html
    for link in carried["inputs"]:
        assert f"<code>{link['source']}</code>" in html  # every producer named on the FMU's own page
    assert all(f"<dt>{rule}</dt>" in html for rule in RULES)


def test_a_master_written_from_the_contract_reproduces_the_orchestrator(fmus_in_repo, tmp_path):
    """examples/fmpy_master.py, plain FMPy, wired from the FMUs' coupling.json: the orchestrator's
    contact and catheter CSVs byte for byte over the first touch of the sac wall (about 1.5 s)."""
    duration = "1.7"
    example = subprocess.run([sys.executable, str(REPO / "examples" / "fmpy_master.py"), "--duration", duration,
                              "--out", str(tmp_path / "example")], capture_output=True, text=True, timeout=600)
    assert example.returncode == 0, example.stderr[-3000:]
    orchestrator = subprocess.run([sys.executable, "-m", "orchestration", "run", str(scene_path(DEFAULT_SCENE)),
                                   "--duration", duration, "--out", str(tmp_path / "orchestrator")],
                                  capture_output=True, text=True, timeout=600, cwd=REPO)
    assert orchestrator.returncode == 0, orchestrator.stderr[-3000:]
    for stream in ("contact", "catheter"):
        ours = (tmp_path / "example" / f"{stream}.csv").read_text()
        theirs = (tmp_path / "orchestrator" / f"{stream}.csv").read_text()
        assert len(ours.splitlines()) == 1702
        assert ours == theirs, stream
    # and the run is not trivial: the wall was touched
    contact = (tmp_path / "orchestrator" / "contact.csv").read_text().splitlines()[1:]
    assert max(float(row.split(",")[7]) for row in contact) > 1e-5  # penetration_depth, m


# -- the FMUs refuse a broken rule, quoting it -------------------------------------------------------
def _refusal(fmu, call) -> str:
    with pytest.raises(FMICallException):
        call()
    return " ".join(message for _, message in fmu.messages)


def test_contact_refuses_a_frame_handed_before_its_first_step(contact_fmu):
    with fmu_instance(contact_fmu) as fmu:
        fmu.slave.enterInitializationMode()
        fmu.slave.exitInitializationMode()
        fmu.set("tissue_frame", 1)  # Tissue's first step cannot have ended at t = 0
        text = _refusal(fmu, lambda: fmu.slave.doStep(0.0, 0.001))
    assert "tissue_frame changed from 0 to 1 at t = 0.0 s" in text
    assert f"coupling rule 'frame': {RULES['frame']}" in text


def test_contact_takes_a_frame_after_its_first_step(contact_fmu):
    with fmu_instance(contact_fmu) as fmu:
        fmu.slave.enterInitializationMode()
        fmu.slave.exitInitializationMode()
        fmu.slave.doStep(0.0, 0.001)
        fmu.set("tissue_frame", 1)
        fmu.slave.doStep(0.001, 0.001)  # accepted: Contact stepped past frame 0
        assert not [m for status, m in fmu.messages if status >= 3], fmu.messages  # no error logged


@pytest.mark.parametrize("name, port, values, rule", [
    ("Contact", "compliance_nodes", [-1] * 8, "Tissue.n_patch_nodes = Contact.max_patch_nodes"),
    ("Contact", "tool_positions", [0.0] * 21 * 3, "Catheter.n_tool_points = Contact.n_tool_points"),
    ("Tissue", "patch_nodes", [-1] * 8, "Tissue.n_patch_nodes = Contact.max_patch_nodes"),
    ("Catheter", "tip_force", [0.0] * 2, None),  # a fixed size: the count alone
])
def test_an_array_of_another_fmus_size_is_refused_with_the_rule(fmus, name, port, values, rule):
    with fmu_instance(fmus[name]) as fmu:
        fmu.slave.enterInitializationMode()
        setter = fmu.slave.setInt32 if isinstance(values[0], int) else fmu.slave.setFloat64
        text = _refusal(fmu, lambda: setter(fmu.vr(port), values))
    assert f"but nValues = {len(values)}" in text
    if rule is None:
        assert "coupling rule" not in text and "is sized by" not in text
    else:
        assert f"'{port}' is sized by " in text and f"coupling rule 'sizes': {rule}" in text


def test_contact_refuses_another_mesh_without_its_triangles(contact_fmu):
    with fmu_instance(contact_fmu) as fmu:
        fmu.slave.enterConfigurationMode()
        fmu.slave.setUInt64(fmu.vr("n_surface_nodes"), [100])
        fmu.slave.setUInt64(fmu.vr("n_surface_triangles"), [196])
        fmu.slave.exitConfigurationMode()
        fmu.slave.enterInitializationMode()
        text = _refusal(fmu, fmu.slave.exitInitializationMode)
    assert "surface_triangles was never set" in text and "100 nodes, 196 triangles" in text
    assert f"coupling rule 'triangles': {RULES['triangles']}" in text

"""SSP packages (orchestration/scene/ssp/, docs/ssp.md): a scene exported as an SSP 1.0 package and
read back as a scene.

- The exported default scene is valid SSP: its SystemStructure.ssd validates against the official
  SSP 1.0 schemas (those of pyssp-standard, identical to modelica/ssp-standard v1.0.1; the XSD 1.1
  variant also validates the inline ssv:ParameterSets), and an independent SSP reader (pyssp-standard)
  sees its components, connectors and connections with no connection the standard disallows.
- Round trip: every shipped scene -> .ssp -> scene gives the same components (steps, parameters bit
  for bit, arrays included), connections, sources, record and summary; running the .ssp writes the
  TOML's CSVs byte for byte.
- Untrusted archives are refused with a message naming the problem, never a traceback.
"""
from __future__ import annotations

import hashlib
import importlib.util
import stat
import struct
import subprocess
import sys
import zipfile
from pathlib import Path
from xml.etree import ElementTree as ET

import pytest
import xmlschema
from project import scene_path, shipped_scenes

from orchestration.app import cli
from orchestration.hosts.description import PortInfo
from orchestration.scene import ssp
from orchestration.scene.loading import load_scene
from orchestration.scene.model import SceneError
from orchestration.scene.ssp import archive as ssp_archive
from orchestration.scene.ssp import ssd_reader, writing

REPO = Path(__file__).resolve().parent.parent
SCHEMAS = Path(importlib.util.find_spec("pyssp_standard").submodule_search_locations[0]) / "resources"
SSV = f"{{{ssp.SSV_NS}}}"


@pytest.fixture(scope="module")
def package(fmus_in_repo, tmp_path_factory):
    """``package(scene)`` -> the .ssp of a shipped scene, exported once per module (the default scene
    through the command line)."""
    folder = tmp_path_factory.mktemp("ssp")
    made: dict[str, Path] = {}

    def make(name: str) -> Path:
        if name not in made:
            out = folder / f"{name}.ssp"
            if name == "aaa_endovascular":
                assert cli.main(["export", name, "--ssp", str(out)]) == cli.EXIT_OK
            else:
                ssp.export_ssp(load_scene(name), out)
            made[name] = out
        return made[name]

    return make


def _ssd(package: Path) -> bytes:
    with zipfile.ZipFile(package) as archive:
        return archive.read(ssp.SSD_NAME)


def _sha256(data: bytes | Path) -> str:
    return hashlib.sha256(data if isinstance(data, bytes) else data.read_bytes()).hexdigest()


# -- the package is standard SSP -----------------------------------------------------------------------
def test_the_default_scene_exports_as_a_package_the_ssp_schemas_accept(package):
    path = package("aaa_endovascular")
    scene = load_scene("aaa_endovascular")
    with zipfile.ZipFile(path) as archive:
        assert archive.namelist() == [ssp.SSD_NAME, "resources/Catheter.fmu", "resources/Contact.fmu",
                                      "resources/Tissue.fmu"]
        for name in ("tissue", "catheter", "contact"):   # the very FMU files the scene's paths resolve to
            fmu = scene.components[name].path
            assert _sha256(archive.read(f"resources/{fmu.name}")) == _sha256(fmu)
    document = _ssd(path).decode()
    xmlschema.XMLSchema10(str(SCHEMAS / "SystemStructureDescription.xsd")).validate(document)
    # The 1.0 schema leaves the inline ssv:ParameterSet to a lax wildcard; its XSD 1.1 variant checks it.
    schema11 = xmlschema.XMLSchema11(str(SCHEMAS / "SystemStructureDescription11.xsd"))
    schema11.validate(document)
    assert not schema11.is_valid(document.replace('<ssv:Real value="50.0" />', '<ssv:Real value="fifty" />'))


def test_an_ssp_tool_without_our_annotation_sees_the_structure(package, tmp_path):
    from pyssp_standard.ssd import SSD

    scene = load_scene("aaa_endovascular")
    file = tmp_path / ssp.SSD_NAME
    file.write_bytes(_ssd(package("aaa_endovascular")))
    with SSD(file) as ssd:
        components = {c.name: c for c in ssd.system.elements}
        assert list(components) == ["tissue", "catheter", "contact"]
        assert components["tissue"].source == "resources/Tissue.fmu"
        assert components["tissue"].component_type == "application/x-fmu-sharedlibrary"
        kinds = {c.name: c.kind for c in components["contact"].connectors}
        assert kinds["tool_positions"] == "input" and kinds["tool_force"] == "output"
        assert kinds["surface_triangles"] == "parameter" and kinds["stiffness"] == "parameter"
        assert {c.name: c.kind for c in ssd.system.connectors} == {"operator.insertion": "input",
                                                                  "operator.rotation": "input"}
        ends = [(c.start_element, c.start_connector, c.end_element, c.end_connector) for c in ssd.connections()]
        assert ends[:2] == [(None, "operator.insertion", "catheter", "insertion"),
                            (None, "operator.rotation", "catheter", "rotation")]
        assert ends[2:] == [(c.source, c.source_port, c.target, c.target_port) for c in scene.connections[2:]]
        assert ssd.check_connections() == []              # no connection SSP disallows (output -> output, ...)
        assert ssd.default_experiment.start_time == 0.0 and ssd.default_experiment.stop_time == 4.0
    # scalar parameters as a standard parameter set, arrays in the annotation
    root = ET.fromstring(_ssd(package("aaa_endovascular")))
    tissue = root.find(f".//{{{ssp.SSD_NS}}}Component[@name='tissue']")
    values = {p.get("name"): (p[0].tag.removeprefix(SSV), p[0].get("value")) for p in tissue.iter(f"{SSV}Parameter")}
    assert values == {"law": ("String", "etmm"), "integrator": ("String", "implicit"), "viscosity": ("Real", "50.0"),
                      "active_radius": ("Real", "0.03"), "implicit_step": ("String", "budgeted"),
                      "budget_iterations": ("Integer", "4")}
    arrays = {v.get("name"): v.text for v in tissue.iter(f"{{{ssp.SCENE_NS}}}Value")}
    assert arrays == {"active_center": "[0.022, 0.0, 0.065]"}


# -- round trip --------------------------------------------------------------------------------------
def _same(a, b) -> bool:
    """Equal values of the same types, floats bit for bit (-0.0 is not 0.0), lists element by element."""
    if isinstance(a, float) or isinstance(b, float):
        return type(a) is type(b) and struct.pack("<d", a) == struct.pack("<d", b)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return type(b) is dict and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return type(a) is type(b) and a == b


def _assert_same_scene(original, read) -> None:
    assert (read.name, read.description, read.duration) == (original.name, original.description, original.duration)
    assert (read.hosting, read.realtime, read.worker_timeout) == (original.hosting, original.realtime,
                                                                  original.worker_timeout)
    assert list(read.components) == list(original.components)
    for name, spec in original.components.items():
        copy = read.components[name]
        assert (copy.kind, copy.step, copy.hosting) == (spec.kind, spec.step, spec.hosting), name
        assert _same(copy.parameters, spec.parameters), name
        assert _same(copy.table, spec.table), name
        assert copy.ports == spec.ports, name
        if spec.is_fmu:  # the FMU inside the package, extracted
            assert _sha256(copy.path) == _sha256(spec.path)
    assert read.connections == original.connections       # ends, transition, ordering and order
    assert _same(read.record, original.record) and read.surfaces == original.surfaces
    assert _same(read.plots, original.plots) and _same(read.summary, original.summary)


@pytest.mark.parametrize("name", shipped_scenes())
def test_a_shipped_scene_reads_back_from_its_package_unchanged(package, name):
    original = load_scene(name)
    read = load_scene(package(name))
    assert read.path == package(name)
    _assert_same_scene(original, read)


def test_overrides_apply_to_a_package_as_to_a_toml_scene(package):
    overrides = {"contact.stiffness": 800.0, "tissue.step": "1/15", "duration": 0.4}
    _assert_same_scene(load_scene("aaa_endovascular", overrides), load_scene(package("aaa_endovascular"), overrides))


def test_a_package_is_extracted_once_and_kept_while_the_process_runs(package):
    first, second = load_scene(package("virtual_wall")), load_scene(package("virtual_wall"))
    fmu = first.components["contact"].path
    assert fmu == second.components["contact"].path and fmu.is_file()
    assert fmu.parent.name == "resources" and fmu.parent.parent.name.startswith("aaa-cosim-ssp-")


def test_a_csv_source_travels_in_the_package(fmus_in_repo, tmp_path):
    """The recorded signal a csv source plays goes into resources/ and plays the same."""
    text = scene_path("virtual_wall").read_text()
    start, end = text.index("[source.operator]"), text.index("[fmu.contact]")
    csv_source = ('[source.operator]\nkind = "csv"\npath = "push.csv"\ncolumns = { force = ["fx", "fy", "fz"] }\n'
                  'units = { force = "N" }\n\n')
    (tmp_path / "scene.toml").write_text(text[:start] + csv_source + text[end:])
    (tmp_path / "push.csv").write_text("time,fx,fy,fz\n0.0,0.0,0.0,0.0\n0.5,2.0,0.0,0.0\n1.0,0.0,0.0,0.0\n")
    original = load_scene(tmp_path / "scene.toml", {"duration": 0.2})
    out = ssp.export_ssp(original, tmp_path / "scene.ssp")
    with zipfile.ZipFile(out) as archive:
        assert archive.read("resources/operator.csv") == (tmp_path / "push.csv").read_bytes()
    read = load_scene(out)
    played, source = read.components["operator"].new_block(), original.components["operator"].new_block()
    for t in (0.0, 0.25, 0.5, 0.75, 1.0):
        assert played.evaluate(t)["force"].tolist() == source.evaluate(t)["force"].tolist()
    assert Path(read.components["operator"].table["path"]).read_bytes() == (tmp_path / "push.csv").read_bytes()


def test_running_the_package_writes_the_csvs_of_the_toml_scene(package, tmp_path, capsys):
    path = package("aaa_endovascular")
    assert cli.main(["validate", str(path)]) == cli.EXIT_OK
    assert f"{path}: OK" in capsys.readouterr().out
    for label, scene in (("toml", str(scene_path("aaa_endovascular"))), ("ssp", str(path))):
        proc = subprocess.run([sys.executable, "-m", "orchestration", "run", scene, "--duration", "0.3", "--quiet",
                               "--no-vtu", "--out", str(tmp_path / label)], capture_output=True, text=True, cwd=REPO,
                              timeout=600)
        assert proc.returncode == 0, proc.stderr
    csvs = sorted(p.name for p in (tmp_path / "toml").glob("*.csv"))
    assert csvs == ["catheter.csv", "contact.csv", "tissue.csv"]
    assert sorted(p.name for p in (tmp_path / "ssp").glob("*.csv")) == csvs
    for name in csvs:
        assert (tmp_path / "ssp" / name).read_bytes() == (tmp_path / "toml" / name).read_bytes(), name


# -- the export command ----------------------------------------------------------------------------------
def test_export_needs_a_format_and_replaces_a_file_only_when_forced(fmus_in_repo, tmp_path, capsys):
    out = tmp_path / "wall.ssp"
    assert cli.main(["export", "virtual_wall"]) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "say which format to write: `export SCENE --ssp out.ssp`" in err and "`export SCENE --fmu out.fmu`" in err
    out.write_bytes(b"keep")
    assert cli.main(["export", "virtual_wall", "--ssp", str(out)]) == cli.EXIT_USAGE
    assert "exists; give --force to replace it" in capsys.readouterr().err and out.read_bytes() == b"keep"
    assert cli.main(["export", "virtual_wall", "--ssp", str(out), "--force", "--duration", "0.5"]) == cli.EXIT_OK
    assert f"wrote {out}" in capsys.readouterr().out
    assert load_scene(out).duration == 0.5
    assert [p.name for p in tmp_path.iterdir()] == ["wall.ssp"]          # no temporary file left beside it
    assert stat.S_IMODE(out.stat().st_mode) & 0o044                      # an ordinary file, not a private temporary
    assert cli.main(["export", "virtual_wall", "--ssp", str(tmp_path / "wall.zip")]) == cli.EXIT_USAGE
    assert "ends in .ssp" in capsys.readouterr().err
    assert cli.main(["export", "virtual_wall", "--ssp", str(tmp_path / "no" / "wall.ssp")]) == cli.EXIT_USAGE
    assert "does not exist; create it" in capsys.readouterr().err


def test_a_value_ssv_cannot_hold_goes_into_the_annotation():
    """An ssv:Integer is 32-bit, an ssv:Enumeration an item name: else the value stays exact in the
    component's annotation; a Real keeps the TOML's integer or float."""
    assert writing._ssv_value(PortInfo("n", "parameter", "Int64"), 2**40) is None
    assert writing._ssv_value(PortInfo("n", "parameter", "Int64"), 7) == ("Integer", "7")
    assert writing._ssv_value(PortInfo("mode", "parameter", "Enumeration"), 2) is None
    assert writing._ssv_value(PortInfo("mode", "parameter", "Enumeration"), "fast") == ("Enumeration", "fast")
    assert writing._ssv_value(PortInfo("k", "parameter", "Float64"), 1000) == ("Real", "1000")
    assert writing._ssv_value(PortInfo("k", "parameter", "Float64"), 0.1 + 0.2) == ("Real", "0.30000000000000004")
    assert writing._ssv_value(PortInfo("x", "parameter", "Float64", shape=(3,)), [1.0, 2.0, 3.0]) is None
    assert ssd_reader._number("1000") == 1000 and type(ssd_reader._number("1000.0")) is float and ssd_reader._number("1e999") is None


# -- untrusted archives --------------------------------------------------------------------------------
def _archive(path: Path, members: dict[str, bytes], infos: dict[str, zipfile.ZipInfo] | None = None) -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            archive.writestr((infos or {}).get(name) or name, data)
    return path


@pytest.fixture(scope="module")
def template(package) -> str:
    """The default scene's SSD, to break in one place; its FMUs stand in as a few bytes (every problem
    below is found before an FMU is read)."""
    return _ssd(package("aaa_endovascular")).decode()


FAKE_FMUS = {f"resources/{name}.fmu": b"an FMU" for name in ("Tissue", "Catheter", "Contact")}


def _break(template: str, old: str, new: str) -> bytes:
    assert old in template, old
    return template.replace(old, new, 1).encode()


BROKEN_SSDS = {
    "unknown component": ('startElement="catheter"', 'startElement="cathetre"',
                          "startElement='cathetre' is not a component of the system (components: catheter, contact, "
                          "tissue)"),
    "undeclared connector": ('endConnector="tool_positions"', 'endConnector="tool_positionz"',
                             "contact has no connector 'tool_positionz'; declare it in the component's ssd:Connectors"),
    "undeclared system connector": ('startConnector="operator.insertion"', 'startConnector="operator.pull"',
                                    "startConnector='operator.pull' is not a connector of the system"),
    "annotation not JSON": ("[0.022, 0.0, 0.065]", "[0.022, 0.0,",
                            "Value 'active_center': not a JSON value"),
    "annotation attribute": ('<scene:Connection ordering="jacobi" transition="average" />',
                             '<scene:Connection ordering="jacobi" transition="average" speed="fast" />',
                             "unknown attribute 'speed'; valid: ordering, transition"),
    "annotation version": ('<scene:Scene version="1"', '<scene:Scene version="9"',
                           "version '9'; this reader reads version 1"),
    "annotation content": ('<scene:Connection ordering="gauss-seidel" />',
                           '<scene:Component ordering="gauss-seidel" />',
                           "annotation holds scene:Component; it holds one scene:Connection"),
    "source outside": ('source="resources/Tissue.fmu"', 'source="/etc/passwd"',
                       "source='/etc/passwd' is not a file inside the package"),
    "source escaping": ('source="resources/Tissue.fmu"', 'source="resources/../../Tissue.fmu"',
                        "is not a file inside the package"),
    "source missing": ('source="resources/Tissue.fmu"', 'source="resources/Wall.fmu"',
                       "source='resources/Wall.fmu' is not in the archive"),
    "ssv value": ('<ssv:Real value="50.0" />', '<ssv:Real value="fifty" />',
                  "ssv:Real value='fifty' is not a finite decimal number"),
    "transformation": ('endConnector="tissue_frame">', 'endConnector="tissue_frame"><ssc:LinearTransformation '
                                                       'factor="2" />', "LinearTransformation, which the master does "
                                                                        "not apply"),
    "entities": ("<ssd:SystemStructureDescription", '<!DOCTYPE x [<!ENTITY a "aaaa">]><ssd:SystemStructureDescription',
                 "has a DOCTYPE or ENTITY declaration"),
    "not XML": ("</ssd:System>", "</ssd:Sistem>", "SystemStructure.ssd: not well-formed XML at line"),
    "SSP 2": ('version="1.0" name="aaa_endovascular"', 'version="2.0" name="aaa_endovascular"',
              "this reader reads SSP 1.0"),
    "stop time": ('stopTime="4.0"', 'stopTime="soon"', "stopTime='soon' is not a finite number of seconds"),
}


@pytest.mark.parametrize("case", BROKEN_SSDS)
def test_a_broken_ssd_is_refused_naming_the_problem(template, tmp_path, case):
    old, new, message = BROKEN_SSDS[case]
    path = _archive(tmp_path / "broken.ssp", {ssp.SSD_NAME: _break(template, old, new), **FAKE_FMUS})
    with pytest.raises(SceneError) as error:
        load_scene(path)
    assert message in str(error.value)
    assert str(error.value).startswith(f"{path}: ")


def _link(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.create_system = 3
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    return info


BROKEN_ARCHIVES = {
    "not a zip": (None, "not an SSP package: not a zip archive"),
    "no SSD": ({"resources/Tissue.fmu": b"x"}, "no SystemStructure.ssd at the root of the archive"),
    "parent member": ({"../evil.sh": b"x"}, "archive member '../evil.sh' has a '..'"),
    "absolute member": ({"/tmp/evil.sh": b"x"}, "archive member '/tmp/evil.sh' has an absolute path"),
    "link member": ({"resources/link": b"/etc/passwd"}, "archive member 'resources/link' is a symbolic link"),
    "huge member": ({"resources/big.bin": b"x" * 5000}, "archive member 'resources/big.bin' unpacks to 5000 bytes"),
}


@pytest.mark.parametrize("case", BROKEN_ARCHIVES)
def test_an_unsafe_or_broken_archive_is_refused(template, tmp_path, monkeypatch, case):
    members, message = BROKEN_ARCHIVES[case]
    monkeypatch.setattr(ssp_archive, "MAX_MEMBER_BYTES", 4096)
    path = tmp_path / "broken.ssp"
    if members is None:
        path.write_text("[scene]\nname = 'not a zip'\n")
    else:
        with_ssd = {} if case == "no SSD" else {ssp.SSD_NAME: template.encode(), **FAKE_FMUS}
        _archive(path, {**with_ssd, **members}, {"resources/link": _link("resources/link")})
    with pytest.raises(SceneError) as error:
        load_scene(path)
    assert message in str(error.value)


def test_validate_refuses_a_broken_package_with_a_message_not_a_traceback(template, tmp_path, capsys):
    path = _archive(tmp_path / "broken.ssp", {ssp.SSD_NAME: _break(template, 'startElement="catheter"',
                                                                   'startElement="nobody"'), **FAKE_FMUS})
    assert cli.main(["validate", str(path)]) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert err.startswith(f"error: {path}: ") and "'nobody' is not a component" in err and "Traceback" not in err


def test_a_connector_that_contradicts_its_fmu_is_refused(package, tmp_path):
    """What the SSD declares is checked against the FMU once loaded: kind, type, unit and shape."""
    source = package("virtual_wall")
    document = _ssd(source).decode()
    for connector, old, new in (("tool_force", 'kind="output"', 'kind="input"'),
                                ("tissue_positions", '<scene:Array shape="4 3" />', '<scene:Array shape="5 3" />'),
                                ("stiffness", '<ssc:Real unit="N/m" />', '<ssc:Real unit="N.m" />')):
        at = document.index(f'<ssd:Connector name="{connector}"')   # the change in that connector only
        assert old in document[at:at + 600], (connector, old)
        document = document[:at] + document[at:].replace(old, new, 1)
    path = tmp_path / "contradicting.ssp"
    with zipfile.ZipFile(source) as original, zipfile.ZipFile(path, "w") as archive:
        archive.writestr(ssp.SSD_NAME, document)
        with original.open("resources/Contact.fmu") as src, archive.open("resources/Contact.fmu", "w") as dst:
            dst.write(src.read())
    with pytest.raises(SceneError) as error:
        load_scene(path)
    message = str(error.value)
    assert "Component 'contact' Connector 'tool_force': declared kind='input', but the port is output" in message
    assert "Connector 'tissue_positions': the annotation gives the shape 5x3, but the port has 4x3" in message
    assert "Connector 'stiffness': declared in 'N.m', but the port is in 'N/m'" in message


# -- FMUs from elsewhere: every FMI type ---------------------------------------------------------------
@pytest.fixture(scope="module")
def conformance_fmus(tmp_path_factory) -> dict[str, Path]:
    from conformance_fmus import build_all

    return build_all(tmp_path_factory.mktemp("conformance_fmus"))


def test_every_fmi_type_survives_the_package(conformance_fmus, tmp_path):
    """tests/conformance's Types FMU: a String, a Binary, enumerations by item name (ssv:Enumeration)
    and by value, an Int64 beyond 32 bits (both in the annotation), enumeration connectors (with the
    ssd:Enumerations they name); the same scene back, the same rows when run."""
    from orchestration.run.simulation import run_scene
    from orchestration.scene.loading import scene_from_dict

    types = str(conformance_fmus["Types"])
    data = {"scene": {"name": "types", "duration": 0.05, "hosting": "in-process"},
            "fmu": {"a": {"path": types, "step": 0.01, "parameters": {"label": "résumé", "blob": "00ff10",
                                                                      "mode": "Fast", "big_offset": 2**40}},
                    "b": {"path": types, "step": "1/100", "parameters": {"mode": 2, "big_offset": -7}}},
            "connection": [{"from": "a.mode_out", "to": "b.mode"}, {"from": "a.count", "to": "b.x"}],
            "record": {"a": ["count", "big", "flag", "mode_out", "label_length", "blob_sum"],
                       "b": ["x_echo", "mode_out"]}}
    original = scene_from_dict(data, tmp_path)
    out = ssp.export_ssp(original, tmp_path / "types.ssp")
    document = _ssd(out).decode()
    xmlschema.XMLSchema11(str(SCHEMAS / "SystemStructureDescription11.xsd")).validate(document)
    assert '<ssc:Enumeration name="Mode">' in document and '<ssv:Enumeration value="Fast" />' in document
    assert '<ssv:Binary value="00ff10" />' in document and '<ssv:String value="résumé" />' in document
    assert '<scene:Value name="big_offset">1099511627776</scene:Value>' in document
    assert '<scene:Value name="mode">2</scene:Value>' in document
    with zipfile.ZipFile(out) as archive:
        assert archive.namelist() == [ssp.SSD_NAME, "resources/Types.fmu"]   # one file for both instances
    read = load_scene(out)
    _assert_same_scene(original, read)
    for label, loaded in (("toml", original), ("ssp", read)):
        summary, _ = run_scene(loaded, tmp_path / label, progress=False, plots=False)
        assert summary["status"] == "completed", summary["error"]
    for name in ("a.csv", "b.csv"):
        assert (tmp_path / "ssp" / name).read_bytes() == (tmp_path / "toml" / name).read_bytes()

"""SSP packages: a scene written as, and read from, an SSP 1.0 package (System Structure and
Parameterization, Modelica Association), for system engineers who compose simulators in their own tools.

An ``.ssp`` file is a zip archive with ``SystemStructure.ssd`` at its root and the files the SSD refers
to under ``resources/``. :func:`export_ssp` writes a loaded scene as one. :func:`read_package` reads
one back into the scene *dict* the TOML parser gives (``load_scene`` hands it to ``scene_from_dict``,
so every check of a TOML scene applies), and :meth:`SspPackage.check` then compares what the SSD
declares (connector kinds, types, units, array shapes) with what the loaded components have.

What goes where. In standard SSP 1.0, what any SSP tool reads:

    the scene                   ssd:SystemStructureDescription and its ssd:System: name, description
    [scene] duration            ssd:DefaultExperiment startTime="0.0" stopTime (a whole number of every
                                step: its float reads back exactly, see timing.float_time)
    [fmu.X]                     ssd:Component name="X" type="application/x-fmu-sharedlibrary"
                                source="resources/<file>.fmu", the FMU file inside the package
    the ports a scene uses      the component's ssd:Connectors (parameters, connections, record,
                                summary): kind and type, ssc:Real with its unit, ssc:Integer, ...
    scalar parameter values     the component's ssd:ParameterBindings: one inline ssv:ParameterSet
    [[connection]]              ssd:Connection startElement.startConnector -> endElement.endConnector
    a csv source's file         resources/<source>.csv
    sources' and blocks' ports  connectors of the system itself, named "operator.insertion": what an SSP
                                tool without our annotation must drive from outside (a source's output
                                is a system input, a block's input a system output)
    units                       ssd:Units, as the FMUs define them

In ``ssc:Annotation type="org.aaa-cosim.scene"`` elements (XML namespace ``urn:org.aaa-cosim.scene``),
what SSP 1.0 cannot say (an SSP tool skips annotations of a type it does not know):

    on the ssd:System           <scene:Scene version="1" hosting realtime [worker_timeout]>, holding a
                                <scene:Source name kind> or <scene:Block name kind [step]> per source
                                and block with their options, <scene:Record> and <scene:Summary>
    on an ssd:Component         <scene:Component step="1/30" [hosting]>: the exact communication step,
                                the hosting, and the parameters an ssv:ParameterSet cannot hold (arrays,
                                integers beyond 32 bits, an enumeration given by its value)
    on an ssd:Connector         <scene:Array shape="2688 3">: an array port's shape
    on an ssd:Connection        <scene:Connection ordering [transition]>

A value is ``<scene:Value name="key">JSON</scene:Value>``: a parameter of a component, an option of a
source or block, a key of [record] or of [summary], as the TOML file has it (JSON keeps integers and
floats apart, and floats bit for bit).

Reading an archive is reading untrusted data: members with absolute or ``..`` paths, links, more than
MAX_MEMBERS members or members beyond MAX_MEMBER_BYTES refuse the archive; the SSD is parsed with the
standard library's XML parser with no DOCTYPE (so no entities), and every attribute and value read is
checked. Problems raise ``SceneError`` naming the element and the fix. The FMUs (and CSV files) the
SSD uses are extracted into a temporary folder kept for the life of the process (one per archive
content, by SHA-256) and removed at exit.
"""
from __future__ import annotations

import atexit
import hashlib
import json
import logging
import math
import os
import re
import secrets
import shutil
import stat
import tempfile
import threading
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from urllib.parse import quote, unquote, urlsplit
from xml.etree import ElementTree as ET

from orchestration.hosts.description import INTEGER_RANGES, PortInfo
from orchestration.scene.model import HOSTINGS, Scene, SceneError
from orchestration.scene.timing import format_time, parse_time

logger = logging.getLogger(__name__)

SSD_NS = "http://ssp-standard.org/SSP1/SystemStructureDescription"
SSC_NS = "http://ssp-standard.org/SSP1/SystemStructureCommon"
SSV_NS = "http://ssp-standard.org/SSP1/SystemStructureParameterValues"
SCENE_NS = "urn:org.aaa-cosim.scene"
#: the vendor annotation type (SSP names annotation types by reverse domain names)
ANNOTATION_TYPE = "org.aaa-cosim.scene"
#: the version of what is inside our annotation; a reader refuses another
SCENE_ANNOTATION_VERSION = "1"
SSD_NAME = "SystemStructure.ssd"
FMU_TYPE = "application/x-fmu-sharedlibrary"
PARAMETER_SET_TYPE = "application/x-ssp-parameter-set"

# -- limits of an archive read (an .ssp is untrusted data) ------------------------------------------
#: The most members an archive may have: a package holds an SSD and a few FMUs and files.
MAX_MEMBERS = 10_000
#: The largest member, bytes. The project's FMUs are about 150 MB (each carries a Python runtime);
#: a member of more than 2 GiB is no FMU of this kind, and would fill the temporary folder.
MAX_MEMBER_BYTES = 2 << 30
#: The most bytes all members may unpack to.
MAX_TOTAL_BYTES = 8 << 30
#: The largest SSD, bytes: it is parsed in memory. The default scene's is about 20 kB; a scene that
#: sets a million-value array parameter (MAX_PORT_VALUES) writes about 20 MB.
MAX_SSD_BYTES = 64 << 20

_ET_NAMESPACES = {"ssd": SSD_NS, "ssc": SSC_NS, "ssv": SSV_NS, "scene": SCENE_NS}
#: xs:int, the range of ssv:Integer and of enumeration item values
_INT32 = (-2**31, 2**31 - 1)
#: xs:double without INF and NaN (a scene's numbers are finite); xs:hexBinary
_DECIMAL = re.compile(r"[+-]?([0-9]+(\.[0-9]*)?|\.[0-9]+)([eE][+-]?[0-9]+)?")
_INTEGER = re.compile(r"[+-]?[0-9]+")
_HEX = re.compile(r"([0-9a-fA-F]{2})*")
_VERSION_1 = re.compile(r"1[.][0-9]+(-.*)?")
#: an array's sizes, space-separated ("2688 3")
_SHAPE = re.compile(r"[0-9]{1,10}( [0-9]{1,10}){0,31}")


class SspExportError(ValueError):
    """A scene cannot be written as an SSP package (the output is in the way, a file is missing)."""


def _q(namespace: str, tag: str) -> str:
    return f"{{{namespace}}}{tag}"


# -- the mapping both ways: which ports, and how SSP declares them ----------------------------------
#: a FMI causality as the kind of an FMU component's connector
_FMU_KINDS = {"input": "input", "output": "output", "parameter": "parameter", "structuralParameter": "parameter",
              "calculatedParameter": "calculatedParameter"}
#: a block port's causality as the kind of the system connector standing for it: seen from the
#: system, a source's output comes in from outside, a block's input goes out
_MIRRORED_KINDS = {"output": "input", "input": "output", "parameter": "calculatedParameter",
                   "calculatedParameter": "parameter"}


def connector_kind(port: PortInfo, on_system: bool) -> str:
    """The SSP connector kind of ``port``: of an FMU component's connector, or (``on_system``) of the
    system connector that stands for a source's or block's port."""
    if not on_system:
        return _FMU_KINDS.get(port.causality, "output")  # a recorded local variable is read like an output
    if port.causality == "output" and port.variability in ("constant", "fixed"):
        return "parameter"  # a rigid surface: set once, and SSP lets a system parameter feed parameters
    return _MIRRORED_KINDS.get(port.causality, "input")


def connector_type(port: PortInfo) -> tuple[str, dict] | None:
    """The ssc type element (tag, attributes) of ``port``; None for a type SSP 1.0 has not (Clock)."""
    if port.type.startswith("Float"):
        return "Real", ({"unit": port.unit} if port.unit else {})
    if port.type == "Enumeration":
        if port.declared_type and _enumeration_fits(port):
            return "Enumeration", {"name": port.declared_type}
        return "Integer", {}
    if port.type in INTEGER_RANGES:
        return "Integer", {}
    if port.type in ("Boolean", "String", "Binary"):
        return port.type, {}
    return None


def _enumeration_fits(port: PortInfo) -> bool:
    return bool(port.items) and all(_INT32[0] <= value <= _INT32[1] for _, value in port.items)


def _exported_parameters(spec) -> dict:
    """An FMU's parameters as the scene gives them: without ``internal_step``, which the loader sets
    from the step (docs/scenes.md)."""
    return {k: v for k, v in spec.parameters.items() if not (k == "internal_step" and "internal_step" in spec.ports)}


def used_ports(scene: Scene) -> dict[str, list[str]]:
    """The ports of each component the scene uses (parameters, connections, record, surfaces,
    summary), in the component's port order: the connectors of its SSP element."""
    used: dict[str, set[str]] = {name: set() for name in scene.components}
    for name, spec in scene.components.items():
        used[name].update(_exported_parameters(spec) if spec.is_fmu else ())
    for c in scene.connections:
        used[c.source].add(c.source_port)
        used[c.target].add(c.target_port)
    for name, ports in scene.record.items():
        used[name].update(ports)
    for surface in scene.surfaces:
        used[surface.component].update((surface.positions, surface.triangles, *surface.point_data))
    for key in ("peaks", "energy", "warnings"):
        for item in scene.summary.get(key, []):
            name, port = item.split(".")
            used[name].add(port)
    return {name: [p for p in scene.components[name].ports if p in used[name]] for name in scene.components}


def _ssv_value(port: PortInfo, value) -> tuple[str, str] | None:
    """A scalar parameter value as an ssv value element (tag, value text); None when ssv cannot hold
    it exactly (an array, an integer beyond 32 bits, an enumeration given by its value): then it goes
    into the annotation. A Real is written as the TOML number was: ``1000`` for an integer, ``1000.0``
    (repr, bit for bit) for a float, and read back as such."""
    if port.is_array or isinstance(value, (list, dict)):
        return None
    if isinstance(value, bool):
        return ("Boolean", "true" if value else "false") if port.type == "Boolean" else None
    if port.type.startswith("Float") and isinstance(value, (int, float)):
        return "Real", repr(value) if isinstance(value, float) else str(value)
    if port.type in INTEGER_RANGES and port.type != "Enumeration" and isinstance(value, int):
        return ("Integer", str(value)) if _INT32[0] <= value <= _INT32[1] else None
    if port.type == "Enumeration" and isinstance(value, str):
        return "Enumeration", value
    if port.type == "String" and isinstance(value, str):
        return "String", value
    if port.type == "Binary" and isinstance(value, str) and _HEX.fullmatch(value):
        return "Binary", value
    return None


# -- export ------------------------------------------------------------------------------------------
def export_ssp(scene: Scene, out: Path | str, *, force: bool = False) -> Path:
    """Write ``scene`` as the SSP package ``out`` (an ``.ssp`` file) and return its path.

    Written to a temporary file beside ``out`` and renamed into place, so ``out`` is either the old
    file or the whole new one. An existing ``out`` is replaced only with ``force``. Deterministic:
    the same scene and FMUs give the same bytes.
    """
    out = Path(out)
    _check_output(out, force)
    files = _package_files(scene)
    document = _ssd_bytes(scene, files)
    # not mkstemp: its file is private (0600), the package is an ordinary file (the umask's mode)
    temporary = out.parent / f".{out.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"
    try:
        with temporary.open("xb") as fh:
            _write_zip(fh, document, files)
            fh.flush()
            os.fsync(fh.fileno())
        _move_into_place(temporary, out, force)
    except OSError as exc:
        raise SspExportError(f"{out}: cannot write the package ({exc.strerror or exc}); check the folder is "
                             "writable and has room") from None
    finally:
        temporary.unlink(missing_ok=True)
    logger.info("wrote %s: %s and %d file(s)", out, SSD_NAME, len(files))
    return out


def _check_output(out: Path, force: bool) -> None:
    if out.suffix.lower() != ".ssp":
        raise SspExportError(f"{out}: an SSP package's file name ends in .ssp (run and validate know it by that); "
                             f"give e.g. {out.with_suffix('.ssp').name}")
    if not out.parent.is_dir():
        raise SspExportError(f"{out}: the folder {out.parent} does not exist; create it or write elsewhere")
    if out.is_dir():
        raise SspExportError(f"{out}: is a folder; give the name of the .ssp file to write")
    if out.exists() and not force:
        raise SspExportError(f"{out}: exists; give --force to replace it, or another file name")


def _move_into_place(temporary: Path, out: Path, force: bool) -> None:
    if force:
        os.replace(temporary, out)
        return
    try:  # a link fails if `out` appeared meanwhile: never replace a file that was not asked for
        os.link(temporary, out)
    except FileExistsError:
        raise SspExportError(f"{out}: exists; give --force to replace it, or another file name") from None
    except OSError:  # a file system without hard links
        if out.exists():
            raise SspExportError(f"{out}: exists; give --force to replace it, or another file name") from None
        os.replace(temporary, out)


@dataclass
class _PackageFiles:
    """The files a package carries: member name -> file on disk, and which member each FMU and
    CSV source uses."""

    members: dict[str, Path] = field(default_factory=dict)
    by_component: dict[str, str] = field(default_factory=dict)

    def add(self, component: str, path: Path, preferred: str) -> None:
        path = path.resolve()
        same = next((m for m, p in self.members.items() if p == path), None)
        member = same or (preferred if preferred not in self.members else
                          str(PurePosixPath(preferred).with_name(f"{component}_{PurePosixPath(preferred).name}")))
        self.members[member] = path
        self.by_component[component] = member

    def __len__(self) -> int:
        return len(self.members)


def _package_files(scene: Scene) -> _PackageFiles:
    files = _PackageFiles()
    for name, spec in scene.components.items():
        if spec.is_fmu:
            files.add(name, Path(spec.path), f"resources/{Path(spec.path).name}")
        elif spec.kind == "csv":
            source = Path(spec.table["path"])
            source = source if source.is_absolute() else Path(spec.base_dir or ".") / source
            files.add(name, source, f"resources/{name}.csv")
    for member, path in files.members.items():
        if not path.is_file():
            raise SspExportError(f"{path}: not found, so it cannot go into the package as {member}; build the FMUs "
                                 "(`python -m orchestration build`) or restore the file")
    return files


def _write_zip(fh, document: bytes, files: _PackageFiles) -> None:
    with zipfile.ZipFile(fh, "w") as archive:
        archive.writestr(_zip_info(SSD_NAME, zipfile.ZIP_DEFLATED, len(document)), document)
        for member, path in sorted(files.members.items()):
            # an FMU is a zip already: stored as it is, the package is written at disk speed
            compression = zipfile.ZIP_STORED if member.endswith(".fmu") else zipfile.ZIP_DEFLATED
            info = _zip_info(member, compression, path.stat().st_size)
            with path.open("rb") as src, archive.open(info, "w") as dst:
                shutil.copyfileobj(src, dst, 1 << 20)


def _zip_info(name: str, compression: int, size: int) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))  # no clock in the bytes: reproducible
    info.compress_type = compression
    info.create_system = 3  # Unix, so that the mode below is read as one
    info.external_attr = (stat.S_IFREG | 0o644) << 16
    info.file_size = size   # > 2 GiB would need ZIP64, which zipfile decides from it
    return info


def _sub(parent: ET.Element, namespace: str, tag: str, **attributes) -> ET.Element:
    return ET.SubElement(parent, _q(namespace, tag), {k: str(v) for k, v in attributes.items() if v is not None})


def _json(value, what: str) -> str:
    try:
        return json.dumps(value, ensure_ascii=False, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise SspExportError(f"{what}: {exc}; a scene's values are numbers, strings, Booleans, lists and "
                             "tables") from None


def _annotation(parent: ET.Element, tag: str, **attributes) -> ET.Element:
    """``<ssd:Annotations><ssc:Annotation type=...><scene:{tag}/>``: the element to fill (the SSD
    schema declares the Annotations of its elements in its own namespace, of the type ssc:TAnnotations)."""
    annotations = _sub(parent, SSD_NS, "Annotations")
    annotation = _sub(annotations, SSC_NS, "Annotation", type=ANNOTATION_TYPE)
    return _sub(annotation, SCENE_NS, tag, **attributes)


def _values(parent: ET.Element, values: dict, what: str) -> None:
    for name, value in values.items():
        _sub(parent, SCENE_NS, "Value", name=name).text = _json(value, f"{what} {name}")


def _ssd_bytes(scene: Scene, files: _PackageFiles) -> bytes:
    for prefix, namespace in _ET_NAMESPACES.items():
        ET.register_namespace(prefix, namespace)
    used = used_ports(scene)
    root = ET.Element(_q(SSD_NS, "SystemStructureDescription"),
                      {"version": "1.0", "name": scene.name, "generationTool": "aaa-cosim (python -m orchestration "
                                                                                "export)"})
    system = _sub(root, SSD_NS, "System", name=scene.name, description=scene.description or None)
    blocks = [spec for spec in scene.components.values() if not spec.is_fmu]
    system_ports = [(spec, spec.ports[p]) for spec in blocks for p in used[spec.name]]
    if system_ports:
        connectors = _sub(system, SSD_NS, "Connectors")
        for spec, port in system_ports:
            _connector(connectors, f"{spec.name}.{port.name}", port, on_system=True)
    fmus = [spec for spec in scene.components.values() if spec.is_fmu]
    if fmus:
        elements = _sub(system, SSD_NS, "Elements")
        for spec in fmus:
            _component(elements, spec, used[spec.name], files.by_component[spec.name])
    if scene.connections:
        connections = _sub(system, SSD_NS, "Connections")
        for c in scene.connections:
            _connection(connections, scene, c)
    _scene_annotation(system, scene, blocks, files)
    _enumerations(root, scene, used)  # the schema's order: Enumerations, Units, DefaultExperiment
    _units(root, scene, used)
    _sub(root, SSD_NS, "DefaultExperiment", startTime="0.0", stopTime=repr(float(scene.duration)))
    ET.indent(root)
    return ET.tostring(root, encoding="utf-8", xml_declaration=True) + b"\n"


def _connector(parent: ET.Element, name: str, port: PortInfo, on_system: bool) -> None:
    connector = _sub(parent, SSD_NS, "Connector", name=name, kind=connector_kind(port, on_system),
                     description=port.description or None)
    kind = connector_type(port)
    if kind is not None:
        _sub(connector, SSC_NS, kind[0], **kind[1])
    if port.is_array:
        _annotation(connector, "Array", shape=" ".join(map(str, port.shape)))


def _component(elements: ET.Element, spec, ports: list[str], member: str) -> None:
    component = _sub(elements, SSD_NS, "Component", name=spec.name, type=FMU_TYPE, source=quote(member))
    if ports:
        connectors = _sub(component, SSD_NS, "Connectors")
        for name in ports:
            _connector(connectors, name, spec.ports[name], on_system=False)
    standard, extra = {}, {}
    for name, value in _exported_parameters(spec).items():
        written = _ssv_value(spec.ports[name], value)
        (standard if written else extra)[name] = written or value
    if standard:
        binding = _sub(_sub(component, SSD_NS, "ParameterBindings"), SSD_NS, "ParameterBinding")
        parameter_set = _sub(_sub(binding, SSD_NS, "ParameterValues"), SSV_NS, "ParameterSet", version="1.0",
                             name=spec.name)
        parameters = _sub(parameter_set, SSV_NS, "Parameters")
        for name, (tag, text) in standard.items():
            _sub(_sub(parameters, SSV_NS, "Parameter", name=name), SSV_NS, tag, value=text)
    annotation = _annotation(component, "Component", step=format_time(spec.step).strip('"'), hosting=spec.hosting)
    _values(annotation, extra, f"[fmu.{spec.name}] parameter")


def _endpoint(scene: Scene, component: str, port: str) -> tuple[str | None, str]:
    """(element, connector) of a connection end: a source's or block's port is a system connector."""
    return (component, port) if scene.components[component].is_fmu else (None, f"{component}.{port}")


def _connection(parent: ET.Element, scene: Scene, c) -> None:
    start, end = _endpoint(scene, c.source, c.source_port), _endpoint(scene, c.target, c.target_port)
    connection = _sub(parent, SSD_NS, "Connection", startElement=start[0], startConnector=start[1],
                      endElement=end[0], endConnector=end[1])
    _annotation(connection, "Connection", ordering=str(c.ordering), transition=c.transition)


def _scene_annotation(system: ET.Element, scene: Scene, blocks: list, files: _PackageFiles) -> None:
    head = _annotation(system, "Scene", version=SCENE_ANNOTATION_VERSION, hosting=str(scene.hosting),
                       realtime="true" if scene.realtime else "false",
                       worker_timeout=None if scene.worker_timeout is None else repr(scene.worker_timeout))
    for spec in blocks:
        options = {k: v for k, v in spec.table.items() if k not in ("kind", "step")}
        if spec.kind == "csv":
            options["path"] = files.by_component[spec.name]
        step = format_time(spec.step).strip('"') if "step" in spec.table else None
        element = _sub(head, SCENE_NS, "Source" if spec.is_continuous else "Block", name=spec.name, kind=spec.kind,
                       step=step)
        _values(element, options, f"[{'source' if spec.is_continuous else 'block'}.{spec.name}]")
    record = dict(scene.record)
    if scene.surfaces:
        record["surfaces"] = [{"component": s.component, "positions": s.positions, "triangles": s.triangles,
                               "every": s.every, "name": s.name, **({"point_data": list(s.point_data)}
                                                                    if s.point_data else {})}
                              for s in scene.surfaces]
    if scene.plots:
        record["plots"] = scene.plots
    _values(_sub(head, SCENE_NS, "Record"), record, "[record]")
    _values(_sub(head, SCENE_NS, "Summary"), scene.summary, "[summary]")


def _enumerations(root: ET.Element, scene: Scene, used: dict) -> None:
    """ssd:Enumerations: the enumeration types the connectors name (ssc:Enumeration name=...)."""
    types = {}
    for spec in scene.components.values():
        for port in (spec.ports[p] for p in used[spec.name]):
            if (connector_type(port) or ("",))[0] == "Enumeration":
                types.setdefault(port.declared_type, port.items)
    if types:
        enumerations = _sub(root, SSD_NS, "Enumerations")
        for name, items in types.items():
            enumeration = _sub(enumerations, SSC_NS, "Enumeration", name=name)
            for item, value in items:
                _sub(enumeration, SSC_NS, "Item", name=item, value=value)


def _units(root: ET.Element, scene: Scene, used: dict) -> None:
    """ssd:Units: the units the connectors name, as the FMUs define them (a unit only a source
    names and no FMU defines is named on its connector and not defined here)."""
    definitions = {}
    for spec in scene.components.values():
        md = spec.description.model_description if spec.is_fmu and spec.description else None
        for unit in getattr(md, "unitDefinitions", None) or []:
            definitions.setdefault(unit.name, unit.baseUnit)
    names = [spec.ports[p].unit for spec in scene.components.values() for p in used[spec.name]
             if spec.ports[p].type.startswith("Float") and spec.ports[p].unit]
    names = [n for n in dict.fromkeys(names) if n in definitions]
    if not names:
        return
    units = _sub(root, SSD_NS, "Units")
    for name in names:
        base = definitions[name]
        exponents = {k: getattr(base, k, 0) for k in ("kg", "m", "s", "A", "K", "mol", "cd", "rad")} if base else {}
        attributes = {k: v for k, v in exponents.items() if v}
        if base and getattr(base, "factor", 1.0) != 1.0:
            attributes["factor"] = repr(float(base.factor))
        if base and getattr(base, "offset", 0.0) != 0.0:
            attributes["offset"] = repr(float(base.offset))
        _sub(_sub(units, SSC_NS, "Unit", name=name), SSC_NS, "BaseUnit", **attributes)


# -- import --------------------------------------------------------------------------------------------
@dataclass
class _Connector:
    kind: str
    type: str | None
    unit: str | None
    shape: tuple[int, ...] | None
    where: str


@dataclass
class SspPackage:
    """An SSP package read: the scene dict for ``scene_from_dict``, the folder its relative paths
    start from, and the connectors the SSD declares (checked against the scene once loaded)."""

    path: Path
    data: dict
    base_dir: Path
    connectors: dict[tuple[str | None, str], _Connector] = field(default_factory=dict)

    def check(self, scene: Scene) -> None:
        """Raise ``SceneError`` if a connector the SSD declares is not what its component has: a
        port it lacks, another kind, type, unit or array shape."""
        problems = []
        for (element, name), declared in self.connectors.items():
            component, port_name = (element, name) if element is not None else name.split(".", 1)
            spec = scene.components.get(component)
            if element is None and (spec is None or spec.is_fmu):
                problems.append(f"{declared.where}: names no source or block of the {ANNOTATION_TYPE} annotation; "
                                "a system connector stands for one's port: remove it or add the source")
                continue
            port = spec.ports.get(port_name) if spec else None
            if port is None:
                owner = spec.path.name if spec is not None and spec.is_fmu else f"the {component} component"
                problems.append(f"{declared.where}: {owner} has no port {port_name!r}; remove the connector")
                continue
            problem = _connector_problem(declared, port, element is None)
            if problem:
                problems.append(f"{declared.where}: {problem}; correct the connector (or export the scene again)")
        if problems:
            raise SceneError(self.path, problems)


def _connector_problem(declared: _Connector, port: PortInfo, on_system: bool) -> str | None:
    kind, ssc = connector_kind(port, on_system), connector_type(port)
    unit = ssc[1].get("unit") if ssc else None
    if declared.kind != kind:
        return f"declared kind={declared.kind!r}, but the port is {port.describe()} (kind {kind!r})"
    if declared.type is not None and (ssc is None or declared.type != ssc[0]):
        return f"declared as ssc:{declared.type}, but the port is {port.describe()}"
    if declared.unit is not None and unit is not None and declared.unit != unit:
        return f"declared in {declared.unit!r}, but the port is in {unit!r}"
    if declared.shape is not None and declared.shape != port.shape:
        return (f"the annotation gives the shape {'x'.join(map(str, declared.shape)) or 'scalar'}, but the port has "
                f"{'x'.join(map(str, port.shape)) or 'scalar'}")
    return None


def read_package(path: Path | str) -> SspPackage:
    """Read the SSP package ``path``: check the archive, parse its SSD, extract the files it uses;
    raise ``SceneError`` naming every problem and its fix."""
    path = Path(path)
    try:
        fh = path.open("rb")
    except OSError as exc:
        raise SceneError(path, [f"cannot read the file: {exc.strerror or exc}"]) from None
    with fh:
        digest = hashlib.file_digest(fh, "sha256").hexdigest()
        fh.seek(0)
        try:
            archive = zipfile.ZipFile(fh)
        except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
            raise SceneError(path, [f"not an SSP package: not a zip archive ({exc}); an .ssp file is the zip "
                                    "`python -m orchestration export --ssp` or an SSP tool writes"]) from None
        with archive:
            members = _checked_members(path, archive)
            root = _parse_ssd(path, archive, members)
            reader = _SsdReader(members, lambda member: _parse_xml(
                path, member, _read_member(path, archive, members[member], MAX_SSD_BYTES)))
            data = reader.scene_dict(root)
            if reader.problems:
                raise SceneError(path, reader.problems)
            base_dir = _extract(path, archive, digest, sorted(reader.files_used))
    _make_paths_absolute(data, base_dir)
    return SspPackage(path=path, data=data, base_dir=base_dir, connectors=reader.connectors)


def _checked_members(path: Path, archive: zipfile.ZipFile) -> dict[str, zipfile.ZipInfo]:
    """The archive's files by name; ``SceneError`` if any member could escape the folder it is
    extracted into, is a link, is encrypted or too large, or the archive is too large."""
    infos = archive.infolist()
    if len(infos) > MAX_MEMBERS:
        raise SceneError(path, [f"the archive has {len(infos)} members, more than {MAX_MEMBERS}: no SSP package of "
                                "scenes has that many; give the .ssp that `export --ssp` wrote"])
    problems, members, total = [], {}, 0
    for info in infos:
        problem = _member_name_problem(info.filename)
        if problem is None and stat.S_ISLNK(info.external_attr >> 16):
            problem = "is a symbolic link; a package holds plain files"
        if problem is None and info.flag_bits & 0x1:
            problem = "is encrypted; a package's members are not"
        if problem is None and info.file_size > MAX_MEMBER_BYTES:
            problem = f"unpacks to {info.file_size} bytes, more than {MAX_MEMBER_BYTES} (2 GiB)"
        if problem is None and info.filename in members:
            problem = "is in the archive twice"
        if problem:
            problems.append(f"archive member {info.filename!r} {problem}: the archive is refused; write it again with "
                            "`export --ssp` or an SSP tool")
            continue
        total += info.file_size
        if not info.is_dir():
            members[info.filename] = info
    if total > MAX_TOTAL_BYTES:
        problems.append(f"the archive unpacks to {total} bytes, more than {MAX_TOTAL_BYTES} (8 GiB); a package holds "
                        "an SSD and its FMUs")
    if problems:
        raise SceneError(path, problems)
    return members


def _member_name_problem(name: str) -> str | None:
    """Why an archive member name is not a plain relative path inside the archive, or None."""
    if not name or any(ord(c) < 32 or c == "\x7f" for c in name):
        return "has an empty name or a control character in its name"
    if "\\" in name or name.startswith("/") or re.match(r"[A-Za-z]:", name):
        return "has an absolute path or a backslash; members are relative paths with '/'"
    parts = name.rstrip("/").split("/")
    if any(part in ("", ".", "..") for part in parts):
        return "has a '..', '.' or empty part in its path, which could point outside the package"
    return None


def _parse_ssd(path: Path, archive: zipfile.ZipFile, members: dict) -> ET.Element:
    info = members.get(SSD_NAME)
    if info is None:
        raise SceneError(path, [f"not an SSP package: no {SSD_NAME} at the root of the archive (it holds "
                                f"{_some(members)}); an SSP package has its system structure there"])
    if info.file_size > MAX_SSD_BYTES:
        raise SceneError(path, [f"{SSD_NAME} is {info.file_size} bytes, more than {MAX_SSD_BYTES}: no scene's SSD is "
                                "that large"])
    root = _parse_xml(path, SSD_NAME, _read_member(path, archive, info, MAX_SSD_BYTES))
    if root.tag != _q(SSD_NS, "SystemStructureDescription"):
        raise SceneError(path, [f"{SSD_NAME}: the root element is {_tag_name(root.tag)}, not "
                                f"ssd:SystemStructureDescription (namespace {SSD_NS})"])
    version = root.get("version", "")
    if not _VERSION_1.fullmatch(version):
        raise SceneError(path, [f"{SSD_NAME}: version {version!r}; this reader reads SSP 1.0 (version=\"1.0\"): "
                                "save the system as SSP 1.0"])
    return root


def _parse_xml(path: Path, member: str, raw: bytes) -> ET.Element:
    """An XML member of the archive parsed by the standard library, with no DOCTYPE."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SceneError(path, [f"{member}: not UTF-8 (byte {raw[exc.start]:#04x} at offset {exc.start}); SSP "
                                "files are UTF-8 XML"]) from None
    if "<!DOCTYPE" in text or "<!ENTITY" in text:
        # entities expand (a few bytes to gigabytes) and may name outside files: SSP needs neither
        raise SceneError(path, [f"{member}: has a DOCTYPE or ENTITY declaration, which SSP files do not use; "
                                "remove it"])
    try:
        return ET.fromstring(text)
    except ET.ParseError as exc:
        line, column = exc.position
        reason = str(exc).split(": line ")[0]  # ("mismatched tag"), without the parser's 0-based column
        raise SceneError(path, [f"{member}: not well-formed XML at line {line}, column {column + 1} ({reason}); "
                                "correct the file or export the scene again"]) from None


def _some(members: dict) -> str:
    names = sorted(members)
    return ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "") if names else "nothing"


def _read_member(path: Path, archive: zipfile.ZipFile, info: zipfile.ZipInfo, limit: int) -> bytes:
    try:
        with archive.open(info) as fh:
            data = fh.read(limit + 1)
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, NotImplementedError, RuntimeError) as exc:
        raise SceneError(path, [f"archive member {info.filename!r} cannot be read ({exc}): the archive is damaged; "
                                "write it again"]) from None
    if len(data) > limit:
        raise SceneError(path, [f"archive member {info.filename!r} is larger than {limit} bytes"])
    return data


def _tag_name(tag: str) -> str:
    namespace, _, local = tag[1:].partition("}") if tag.startswith("{") else ("", "", tag)
    prefix = next((p for p, ns in _ET_NAMESPACES.items() if ns == namespace), None)
    return f"{prefix}:{local}" if prefix else (f"{local} (namespace {namespace})" if namespace else local)


def _make_paths_absolute(data: dict, base_dir: Path) -> None:
    """The FMU and CSV files as paths into the extraction folder: absolute, so that no other folder
    (fmus/ is searched for relative FMU paths) can stand in for a member."""
    for table in data.get("fmu", {}).values():
        table["path"] = str(base_dir / table["path"])
    for table in data.get("source", {}).values():
        if table.get("kind") == "csv":
            table["path"] = str(base_dir / table["path"])


# -- the SSD, element by element ---------------------------------------------------------------------
class _SsdReader:
    """Reads the SSD into the scene dict, collecting every problem ("where: what; the fix")."""

    def __init__(self, members: dict, read_xml):
        self.members = members
        self.read_xml = read_xml  # member name -> its parsed root (an .ssv a ParameterBinding names)
        self.problems: list[str] = []
        self.files_used: set[str] = set()
        self.connectors: dict[tuple[str | None, str], _Connector] = {}

    def scene_dict(self, root: ET.Element) -> dict:
        systems = root.findall(_q(SSD_NS, "System"))
        if len(systems) != 1:
            self.problems.append(f"{SSD_NAME}: has {len(systems)} ssd:System elements; an SSD has exactly one")
            return {}
        system = systems[0]
        where = f"{SSD_NAME}: System {system.get('name')!r}"
        for tag in ("SignalDictionaries", "ParameterBindings"):
            if system.find(_q(SSD_NS, tag)) is not None:
                self.problems.append(f"{where}: has ssd:{tag}, which this reader does not apply; set parameters on "
                                     "each component")
        head = self._scene_annotation(system, where)
        data: dict = {"scene": self._scene_table(root, system, head, where)}
        self._system_connectors(system, where)
        fmus = self._components(system, where)
        blocks = self._blocks(head, where)
        if fmus:
            data["fmu"] = fmus
        for section in ("source", "block"):
            if blocks[section]:
                data[section] = blocks[section]
        connections = self._connections(system, where, set(fmus), {n for s in blocks.values() for n in s})
        if connections:
            data["connection"] = connections
        for tag, key in (("Record", "record"), ("Summary", "summary")):
            element = head.find(_q(SCENE_NS, tag)) if head is not None else None
            if element is not None:
                self._unknown(element, set(), {"scene:Value"}, f"{where}: annotation scene:{tag}")
                data[key] = self._values(element, f"{where}: annotation scene:{tag}")
        return data

    # -- helpers: children, attributes, values ------------------------------------------------------
    def _attribute(self, element: ET.Element, name: str, where: str, pattern=None, fix: str = "") -> str | None:
        value = element.get(name)
        if value is None:
            self.problems.append(f"{where}: no {name} attribute; {fix or f'add {name}=...'}")
        elif pattern is not None and not pattern.fullmatch(value):
            self.problems.append(f"{where}: {name}={value!r} {fix}")
            value = None
        return value

    def _unknown(self, element: ET.Element, attributes: set, children: set, where: str) -> None:
        """Our own annotation's elements are strict: an unknown attribute or child is a typo."""
        for name in element.attrib:
            if name not in attributes:
                self.problems.append(f"{where}: unknown attribute {name!r}; valid: {', '.join(sorted(attributes))}")
        for child in element:
            if _tag_name(child.tag) not in children:
                self.problems.append(f"{where}: unknown element {_tag_name(child.tag)}; valid: "
                                     f"{', '.join(sorted(children)) or 'none'}")

    def _annotation(self, element: ET.Element, tag: str, where: str) -> ET.Element | None:
        """The content of the element's annotation of our type (at most one), which must be
        ``scene:{tag}``; None without one (annotations of other types are another tool's)."""
        found = [a for a in element.findall(f"{_q(SSD_NS, 'Annotations')}/{_q(SSC_NS, 'Annotation')}")
                 if a.get("type") == ANNOTATION_TYPE]
        if not found:
            return None
        if len(found) > 1:
            self.problems.append(f"{where}: has {len(found)} annotations of type {ANNOTATION_TYPE}; give one")
        content = list(found[0])
        if len(content) != 1 or content[0].tag != _q(SCENE_NS, tag):
            got = ", ".join(_tag_name(c.tag) for c in content) or "nothing"
            self.problems.append(f"{where}: the {ANNOTATION_TYPE} annotation holds {got}; it holds one scene:{tag} "
                                 f"(namespace {SCENE_NS})")
            return None
        return content[0]

    def _values(self, element: ET.Element, where: str) -> dict:
        """``<scene:Value name="key">JSON</scene:Value>`` children as a dict (the caller checks the
        element's attributes and that it holds nothing else)."""
        values = {}
        for child in element.findall(_q(SCENE_NS, "Value")):
            name = child.get("name")
            at = f"{where} Value {name!r}"
            self._unknown(child, {"name"}, set(), at)
            if not name:
                self.problems.append(f"{where}: a scene:Value without a name; give name=\"key\"")
                continue
            if name in values:
                self.problems.append(f"{at}: given twice; give each once")
                continue
            try:
                values[name] = json.loads(child.text or "", parse_constant=_refuse_constant)
            except (ValueError, RecursionError) as exc:
                self.problems.append(f"{at}: not a JSON value ({exc}); write the value as JSON, e.g. [0.0, 1.0] or "
                                     "{\"insertion\": \"m\"}")
        return values

    # -- the scene ------------------------------------------------------------------------------------
    def _scene_annotation(self, system: ET.Element, where: str) -> ET.Element | None:
        head = self._annotation(system, "Scene", f"{where} annotation")
        if head is None:
            return None
        at = f"{where}: annotation scene:Scene"
        self._unknown(head, {"version", "hosting", "realtime", "worker_timeout"},
                      {"scene:Source", "scene:Block", "scene:Record", "scene:Summary"}, at)
        version = head.get("version")
        if version != SCENE_ANNOTATION_VERSION:
            self.problems.append(f"{at}: version {version!r}; this reader reads version {SCENE_ANNOTATION_VERSION}: "
                                 "export the scene again with this version of the project")
            return None
        for tag in ("Record", "Summary"):
            if len(head.findall(_q(SCENE_NS, tag))) > 1:
                self.problems.append(f"{at}: more than one scene:{tag}; merge them into one")
        return head

    def _scene_table(self, root: ET.Element, system: ET.Element, head: ET.Element | None, where: str) -> dict:
        table: dict = {}
        name = self._attribute(system, "name", where)
        if name is not None:
            table["name"] = name
        if system.get("description") is not None:
            table["description"] = system.get("description")
        experiments = root.findall(_q(SSD_NS, "DefaultExperiment"))
        if experiments:
            at = f"{SSD_NAME}: DefaultExperiment"
            start, stop = experiments[0].get("startTime"), experiments[0].get("stopTime")
            if start is not None and _number(start) != 0:
                self.problems.append(f"{at}: startTime={start!r}; a scene starts at 0 (shift the sources instead)")
            if stop is not None:
                if _number(stop) is not None:
                    table["duration"] = float(stop)  # as a TOML duration = 4.0: exact (timing.float_time)
                else:
                    self.problems.append(f"{at}: stopTime={stop!r} is not a finite number of seconds; give the "
                                         "duration, e.g. stopTime=\"4.0\"")
        if head is not None:
            at = f"{where}: annotation scene:Scene"
            hosting = head.get("hosting")
            if hosting is not None:
                if hosting not in HOSTINGS:
                    self.problems.append(f"{at}: hosting={hosting!r} is not one of {', '.join(HOSTINGS)}")
                table["hosting"] = hosting
            realtime = head.get("realtime")
            if realtime is not None:
                table["realtime"] = self._boolean(realtime, f"{at}: realtime")
            timeout = head.get("worker_timeout")
            if timeout is not None:
                if _number(timeout) is not None:
                    table["worker_timeout"] = float(timeout)
                else:
                    self.problems.append(f"{at}: worker_timeout={timeout!r} is not a number of seconds")
        return table

    def _boolean(self, text: str, where: str) -> bool | None:
        if text in ("true", "1"):
            return True
        if text in ("false", "0"):
            return False
        self.problems.append(f"{where}: {text!r} is not true or false")
        return None

    # -- connectors --------------------------------------------------------------------------------
    def _connector_list(self, parent: ET.Element, element_name: str | None, where: str) -> set[str]:
        names: set[str] = set()
        for group in parent.findall(_q(SSD_NS, "Connectors")):
            for connector in group.findall(_q(SSD_NS, "Connector")):
                name = connector.get("name")
                at = f"{where} Connector {name!r}"
                if not name:
                    self.problems.append(f"{where}: a Connector without a name; give name=\"port\"")
                    continue
                if name in names:
                    self.problems.append(f"{at}: declared twice; declare each connector once")
                    continue
                names.add(name)
                kind = connector.get("kind")
                if kind not in ("input", "output", "parameter", "calculatedParameter", "inout"):
                    self.problems.append(f"{at}: kind={kind!r} is not input, output, parameter or calculatedParameter")
                    continue
                self.connectors[(element_name, name)] = self._connector(connector, kind, at)
        return names

    def _connector(self, connector: ET.Element, kind: str, where: str) -> _Connector:
        types = [c for c in connector if c.tag.startswith(f"{{{SSC_NS}}}")]
        tag = types[0].tag.partition("}")[2] if types else None
        if tag is not None and tag not in ("Real", "Integer", "Boolean", "String", "Enumeration", "Binary"):
            self.problems.append(f"{where}: ssc:{tag} is not an SSP connector type")
        unit = types[0].get("unit") if types else None
        shape = None
        array = self._annotation(connector, "Array", where)
        if array is not None:
            self._unknown(array, {"shape"}, set(), f"{where}: annotation scene:Array")
            text = self._attribute(array, "shape", f"{where}: annotation scene:Array", _SHAPE,
                                   "is not the array's sizes, e.g. shape=\"2688 3\"")
            shape = tuple(int(n) for n in text.split()) if text else None
        return _Connector(kind, tag, unit, shape, where)

    def _system_connectors(self, system: ET.Element, where: str) -> None:
        for name in self._connector_list(system, None, where):
            if name.count(".") != 1 or not all(name.split(".")):
                self.problems.append(f"{where} Connector {name!r}: a system connector stands for a source's or block's "
                                     "port and is named \"component.port\"")
                self.connectors.pop((None, name), None)

    # -- components ----------------------------------------------------------------------------------
    def _components(self, system: ET.Element, where: str) -> dict:
        fmus: dict = {}
        for elements in system.findall(_q(SSD_NS, "Elements")):
            for element in elements:
                if element.tag != _q(SSD_NS, "Component"):
                    self.problems.append(f"{where}: has an {_tag_name(element.tag)} element; this reader takes FMU "
                                         "components only (no sub-systems or signal dictionaries): flatten the system")
                    continue
                name = element.get("name")
                if not name:
                    self.problems.append(f"{where}: a Component without a name; give name=\"tissue\"")
                    continue
                if name in fmus:
                    self.problems.append(f"{where}: two components are named {name!r}; give each its own name")
                    continue
                table = self._component(element, f"{SSD_NAME}: Component {name!r}", name)
                if table is not None:
                    fmus[name] = table
        return fmus

    def _component(self, element: ET.Element, where: str, name: str) -> dict | None:
        kind = element.get("type", FMU_TYPE)
        if kind != FMU_TYPE:
            self.problems.append(f"{where}: type={kind!r}; a scene's components are FMUs ({FMU_TYPE})")
            return None
        if element.get("implementation", "any") not in ("any", "CoSimulation"):
            self.problems.append(f"{where}: implementation={element.get('implementation')!r}; the master runs FMUs "
                                 "as Co-Simulation (implementation=\"CoSimulation\" or \"any\")")
        member = self._source(element, where, "the FMU file in the package, e.g. source=\"resources/Tissue.fmu\"")
        if member:
            self.files_used.add(member)
        self._connector_list(element, name, where)
        table: dict = {"path": member} if member else {}
        parameters = self._parameter_bindings(element, where)
        annotation = self._annotation(element, "Component", where)
        if annotation is not None:
            at = f"{where}: annotation scene:Component"
            self._unknown(annotation, {"step", "hosting"}, {"scene:Value"}, at)
            step = annotation.get("step")
            if step is not None and self._time(step, f"{at} step"):
                table["step"] = step
            if annotation.get("hosting") is not None:
                table["hosting"] = annotation.get("hosting")
            for key, value in self._values(annotation, at).items():
                if key in parameters:
                    self.problems.append(f"{at} Value {key!r}: also set in the component's ssv:ParameterSet; "
                                         "set each parameter once")
                elif isinstance(value, dict):
                    self.problems.append(f"{at} Value {key!r}: a parameter is a number, string, Boolean or a list "
                                         "of them, not a table")
                else:
                    parameters[key] = value
        if parameters:
            table["parameters"] = parameters
        return table if member else None

    def _time(self, text: str, where: str) -> bool:
        problems: list[str] = []
        parse_time(text, where, problems)
        self.problems += problems
        return not problems

    def _source(self, element: ET.Element, where: str, fix: str) -> str | None:
        """The archive member a ``source`` attribute names (a relative URI inside the package)."""
        uri = self._attribute(element, "source", where, fix=f"give {fix}")
        if uri is None:
            return None
        parts = urlsplit(uri)
        member = unquote(parts.path)
        if parts.scheme or parts.netloc or parts.query or parts.fragment or _member_name_problem(member):
            self.problems.append(f"{where}: source={uri!r} is not a file inside the package; give {fix}")
            return None
        if member not in self.members:
            self.problems.append(f"{where}: source={uri!r} is not in the archive (it holds {_some(self.members)}); "
                                 f"give {fix}")
            return None
        return member

    def _parameter_bindings(self, element: ET.Element, where: str) -> dict:
        parameters: dict = {}
        for bindings in element.findall(_q(SSD_NS, "ParameterBindings")):
            for binding in bindings.findall(_q(SSD_NS, "ParameterBinding")):
                at = f"{where}: ParameterBinding"
                unsupported = [f"{k}={binding.get(k)!r}" for k, ok in (("type", PARAMETER_SET_TYPE), ("prefix", ""),
                                                                        ("sourceBase", "SSD"))
                               if binding.get(k, ok) != ok]
                if binding.find(_q(SSD_NS, "ParameterMapping")) is not None:
                    unsupported.append("a ParameterMapping")
                if unsupported:
                    self.problems.append(f"{at}: {', '.join(unsupported)}, which this reader does not apply; give "
                                         "an ssv:ParameterSet with the FMU's variable names")
                    continue
                parameter_set = self._parameter_set(binding, at)
                if parameter_set is not None:
                    # SSP: a later binding's value wins over an earlier one's
                    parameters.update(self._parameters(parameter_set, f"{where}: ssv:ParameterSet"))
        return parameters

    def _parameter_set(self, binding: ET.Element, where: str) -> ET.Element | None:
        inline = binding.find(_q(SSD_NS, "ParameterValues"))
        if (inline is None) == (binding.get("source") is None):
            self.problems.append(f"{where}: give either inline ssd:ParameterValues or a source=\"resources/x.ssv\"")
            return None
        if inline is not None:
            content = list(inline)
            if len(content) != 1 or content[0].tag != _q(SSV_NS, "ParameterSet"):
                self.problems.append(f"{where}: ssd:ParameterValues holds one ssv:ParameterSet (namespace {SSV_NS})")
                return None
            return content[0]
        member = self._source(binding, where, "an .ssv file in the package, e.g. source=\"resources/tissue.ssv\"")
        if member is None:
            return None
        if self.members[member].file_size > MAX_SSD_BYTES:
            self.problems.append(f"{where}: {member} is larger than {MAX_SSD_BYTES} bytes, which no parameter set is")
            return None
        root = self.read_xml(member)
        if root.tag != _q(SSV_NS, "ParameterSet"):
            self.problems.append(f"{where}: {member} holds {_tag_name(root.tag)}, not an ssv:ParameterSet")
            return None
        return root

    def _parameters(self, parameter_set: ET.Element, where: str) -> dict:
        if not _VERSION_1.fullmatch(parameter_set.get("version", "")):
            self.problems.append(f"{where}: version {parameter_set.get('version')!r}; give version=\"1.0\"")
        values: dict = {}
        for group in parameter_set.findall(_q(SSV_NS, "Parameters")):
            for parameter in group.findall(_q(SSV_NS, "Parameter")):
                name = parameter.get("name")
                at = f"{where} Parameter {name!r}"
                if not name:
                    self.problems.append(f"{where}: a Parameter without a name; give the FMU variable's name")
                    continue
                if name in values:
                    self.problems.append(f"{at}: given twice; give each parameter once")
                    continue
                value = self._ssv_parameter(parameter, at)
                if value is not None:
                    values[name] = value
        return values

    def _ssv_parameter(self, parameter: ET.Element, where: str):
        content = [c for c in parameter if c.tag.startswith(f"{{{SSV_NS}}}")]
        if len(content) != 1:
            self.problems.append(f"{where}: holds {len(content)} value elements; give one (ssv:Real, ssv:Integer, "
                                 "ssv:Boolean, ssv:String, ssv:Enumeration or ssv:Binary)")
            return None
        tag, text = content[0].tag.partition("}")[2], content[0].get("value")
        if text is None:
            self.problems.append(f"{where}: ssv:{tag} has no value attribute")
            return None
        if tag == "Real":
            value = _number(text)
            if value is None:
                self.problems.append(f"{where}: ssv:Real value={text!r} is not a finite decimal number")
            return value
        if tag == "Integer":
            if len(text) > 12 or not _INTEGER.fullmatch(text) or not _INT32[0] <= int(text) <= _INT32[1]:
                self.problems.append(f"{where}: ssv:Integer value={text!r} is not a 32-bit integer (xs:int); a "
                                     "larger value goes into the component's annotation")
                return None
            return int(text)
        if tag == "Boolean":
            return self._boolean(text, f"{where}: ssv:Boolean value")
        if tag in ("String", "Enumeration"):
            return text
        if tag == "Binary":
            if not _HEX.fullmatch(text):
                self.problems.append(f"{where}: ssv:Binary value={text!r} is not hexadecimal bytes (e.g. \"0a1bff\")")
                return None
            return text
        self.problems.append(f"{where}: ssv:{tag} is not an SSP parameter type")
        return None

    # -- sources and blocks --------------------------------------------------------------------------
    def _blocks(self, head: ET.Element | None, where: str) -> dict[str, dict]:
        found: dict[str, dict] = {"source": {}, "block": {}}
        if head is None:
            return found
        for tag, section in (("Source", "source"), ("Block", "block")):
            for element in head.findall(_q(SCENE_NS, tag)):
                name, kind = element.get("name"), element.get("kind")
                at = f"{where}: annotation scene:{tag} {name!r}"
                if not name or not kind:
                    self.problems.append(f"{at}: give name=\"...\" and kind=\"...\" (e.g. kind=\"piecewise_linear\")")
                    continue
                if name in found["source"] or name in found["block"]:
                    self.problems.append(f"{at}: the name {name!r} is used twice; give each source and block its own")
                    continue
                self._unknown(element, {"name", "kind", "step"}, {"scene:Value"}, at)
                table = {"kind": kind}
                step = element.get("step")
                if step is not None and self._time(step, f"{at} step"):
                    table["step"] = step
                options = self._values(element, at)
                if kind == "csv" and isinstance(options.get("path"), str):
                    options["path"] = self._csv_member(options["path"], f"{at} Value 'path'")
                table.update({k: v for k, v in options.items() if k not in ("kind", "step")})
                for key in set(options) & {"kind", "step"}:
                    self.problems.append(f"{at} Value {key!r}: give the {key} as the attribute {key}=\"...\"")
                found[section][name] = table
        return found

    def _csv_member(self, text: str, where: str) -> str | None:
        if _member_name_problem(text) or text not in self.members:
            self.problems.append(f"{where}: {text!r} is not a file in the package; a CSV source plays a file the "
                                 "package carries, e.g. \"resources/operator.csv\"")
            return None
        self.files_used.add(text)
        return text

    # -- connections ------------------------------------------------------------------------------------
    def _connections(self, system: ET.Element, where: str, fmus: set, blocks: set) -> list[dict]:
        connections = []
        for group in system.findall(_q(SSD_NS, "Connections")):
            for index, element in enumerate(group.findall(_q(SSD_NS, "Connection")), start=len(connections) + 1):
                at = f"{SSD_NAME}: Connection {index}"
                start = self._end(element, "start", at, fmus, blocks)
                end = self._end(element, "end", at, fmus, blocks)
                at = f"{at} ({start or '?'} -> {end or '?'})"
                transforms = [c for c in element if c.tag.endswith("Transformation")]
                if transforms:
                    self.problems.append(f"{at}: has an ssc:{transforms[0].tag.partition('}')[2]}, which the master "
                                         "does not apply (it moves values unchanged); remove it")
                item = {"from": start, "to": end}
                annotation = self._annotation(element, "Connection", at)
                if annotation is not None:
                    self._unknown(annotation, {"ordering", "transition"}, set(), f"{at}: annotation scene:Connection")
                    item.update({k: annotation.get(k) for k in ("transition", "ordering") if annotation.get(k)})
                if start and end:
                    connections.append(item)
        return connections

    def _end(self, element: ET.Element, side: str, where: str, fmus: set, blocks: set) -> str | None:
        """"component.port" of one end of a connection, or None with the problem reported."""
        component, connector = element.get(f"{side}Element"), element.get(f"{side}Connector")
        if connector is None:
            self.problems.append(f"{where}: no {side}Connector")
            return None
        if component is None:  # a connector of the system: a source's or block's port
            if (None, connector) not in self.connectors:
                self.problems.append(f"{where}: {side}Connector={connector!r} is not a connector of the system; "
                                     "declare it in the system's ssd:Connectors or name the component (startElement)")
                return None
            if connector.split(".")[0] not in blocks:
                self.problems.append(f"{where}: the system connector {connector!r} names no source or block of the "
                                     f"{ANNOTATION_TYPE} annotation; add the source that drives it")
                return None
            return connector
        if component not in fmus:
            known = ", ".join(sorted(fmus)) or "none"
            self.problems.append(f"{where}: {side}Element={component!r} is not a component of the system (components: "
                                 f"{known}); name one of them")
            return None
        if (component, connector) not in self.connectors:
            self.problems.append(f"{where}: {component} has no connector {connector!r}; declare it in the component's "
                                 "ssd:Connectors")
            return None
        return f"{component}.{connector}"


def _number(text: str) -> int | float | None:
    """A finite xs:double as the TOML number it was written from: "1000" the integer, "1000.0" the
    float (bit for bit, as repr wrote it); None if it is not one (or too long to be meant: Python
    refuses integers of more than 4300 digits)."""
    if len(text) > 100 or not _DECIMAL.fullmatch(text):
        return None
    value = int(text) if _INTEGER.fullmatch(text) else float(text)
    return value if math.isfinite(value) else None


def _refuse_constant(name: str):
    raise ValueError(f"{name} is not a finite number")


# -- extraction ----------------------------------------------------------------------------------------
_extractions: dict[str, Path] = {}
_extractions_lock = threading.Lock()


def _extract(path: Path, archive: zipfile.ZipFile, digest: str, members: list[str]) -> Path:
    """The folder holding ``members`` of the archive whose content has SHA-256 ``digest``: extracted
    once per process, into a temporary folder removed at exit."""
    with _extractions_lock:
        folder = _extractions.get(digest)
        if folder is None or not folder.is_dir():
            if not _extractions:
                atexit.register(_remove_extractions, os.getpid())
            folder = Path(tempfile.mkdtemp(prefix="aaa-cosim-ssp-"))
            _extractions[digest] = folder
        for member in members:
            target = folder / member
            if not target.is_file():
                _extract_member(path, archive, member, target)
        logger.debug("%s: %d file(s) in %s", path, len(members), folder)
        return folder


def _extract_member(path: Path, archive: zipfile.ZipFile, member: str, target: Path) -> None:
    info = archive.getinfo(member)
    partial = target.with_name(f".{target.name}.partial")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        with archive.open(info) as src, partial.open("wb") as dst:
            copied = 0
            while chunk := src.read(1 << 20):
                copied += len(chunk)
                if copied > info.file_size:  # zipfile stops at the declared size; a second guard
                    raise zipfile.BadZipFile("more data than its declared size")
                dst.write(chunk)
        partial.replace(target)  # whole or absent: a failed extraction is not taken for a file
    except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, RuntimeError) as exc:
        partial.unlink(missing_ok=True)
        raise SceneError(path, [f"archive member {member!r} cannot be read ({exc}): the archive is damaged; write it "
                                "again"]) from None
    except OSError as exc:
        partial.unlink(missing_ok=True)
        raise SceneError(path, [f"cannot extract {member!r} into {target.parent} ({exc.strerror or exc}): the "
                                "temporary folder must be writable and have room (set TMPDIR to another)"]) from None


def _remove_extractions(pid: int) -> None:
    if os.getpid() != pid:  # a forked child leaving: the folders are its parent's
        return
    for folder in _extractions.values():
        shutil.rmtree(folder, ignore_errors=True)
    _extractions.clear()

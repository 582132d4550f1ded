"""SSP package export: :func:`export_ssp` writes a scene as an ``.ssp`` archive, and the SSD writer
(connectors, parameter values, connections, the scene annotation, enumerations and units)."""
from __future__ import annotations

import json
import logging
import os
import secrets
import shutil
import stat
import zipfile
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from urllib.parse import quote
from xml.etree import ElementTree as ET

from orchestration.hosts.description import INTEGER_RANGES, PortInfo
from orchestration.scene.model import Scene
from orchestration.scene.ssp.common import (ANNOTATION_TYPE, ET_NAMESPACES, FMU_TYPE, HEX, INT32,
                                            SCENE_ANNOTATION_VERSION, SCENE_NS, SSC_NS, SSD_NAME, SSD_NS, SSV_NS,
                                            connector_kind, connector_type, q)
from orchestration.scene.timing import format_time

logger = logging.getLogger(__name__)


class SspExportError(ValueError):
    """A scene cannot be written as an SSP package (the output is in the way, a file is missing)."""


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
        return ("Integer", str(value)) if INT32[0] <= value <= INT32[1] else None
    if port.type == "Enumeration" and isinstance(value, str):
        return "Enumeration", value
    if port.type == "String" and isinstance(value, str):
        return "String", value
    if port.type == "Binary" and isinstance(value, str) and HEX.fullmatch(value):
        return "Binary", value
    return None


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
    return ET.SubElement(parent, q(namespace, tag), {k: str(v) for k, v in attributes.items() if v is not None})


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
    for prefix, namespace in ET_NAMESPACES.items():
        ET.register_namespace(prefix, namespace)
    used = used_ports(scene)
    root = ET.Element(q(SSD_NS, "SystemStructureDescription"),
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

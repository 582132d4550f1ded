"""The SSD of an SSP package read element by element into the scene dict a TOML file gives, every
problem collected, and the connectors it declares."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from urllib.parse import unquote, urlsplit
from xml.etree import ElementTree as ET

from orchestration.scene.model import HOSTINGS
from orchestration.scene.ssp.archive import member_name_problem, some, tag_name
from orchestration.scene.ssp.common import (ANNOTATION_TYPE, DECIMAL, FMU_TYPE, HEX, INT32, INTEGER, MAX_SSD_BYTES,
                                            PARAMETER_SET_TYPE, SCENE_ANNOTATION_VERSION, SCENE_NS, SHAPE, SSC_NS,
                                            SSD_NAME, SSD_NS, SSV_NS, VERSION_1, q)
from orchestration.scene.timing import parse_time


@dataclass
class Connector:
    kind: str
    type: str | None
    unit: str | None
    shape: tuple[int, ...] | None
    where: str


class SsdReader:
    """Reads the SSD into the scene dict, collecting every problem ("where: what; the fix")."""

    def __init__(self, members: dict, read_xml):
        self.members = members
        self.read_xml = read_xml  # member name -> its parsed root (an .ssv a ParameterBinding names)
        self.problems: list[str] = []
        self.files_used: set[str] = set()
        self.connectors: dict[tuple[str | None, str], Connector] = {}

    def scene_dict(self, root: ET.Element) -> dict:
        systems = root.findall(q(SSD_NS, "System"))
        if len(systems) != 1:
            self.problems.append(f"{SSD_NAME}: has {len(systems)} ssd:System elements; an SSD has exactly one")
            return {}
        system = systems[0]
        where = f"{SSD_NAME}: System {system.get('name')!r}"
        for tag in ("SignalDictionaries", "ParameterBindings"):
            if system.find(q(SSD_NS, tag)) is not None:
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
            element = head.find(q(SCENE_NS, tag)) if head is not None else None
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
            if tag_name(child.tag) not in children:
                self.problems.append(f"{where}: unknown element {tag_name(child.tag)}; valid: "
                                     f"{', '.join(sorted(children)) or 'none'}")

    def _annotation(self, element: ET.Element, tag: str, where: str) -> ET.Element | None:
        """The content of the element's annotation of our type (at most one), which must be
        ``scene:{tag}``; None without one (annotations of other types are another tool's)."""
        found = [a for a in element.findall(f"{q(SSD_NS, 'Annotations')}/{q(SSC_NS, 'Annotation')}")
                 if a.get("type") == ANNOTATION_TYPE]
        if not found:
            return None
        if len(found) > 1:
            self.problems.append(f"{where}: has {len(found)} annotations of type {ANNOTATION_TYPE}; give one")
        content = list(found[0])
        if len(content) != 1 or content[0].tag != q(SCENE_NS, tag):
            got = ", ".join(tag_name(c.tag) for c in content) or "nothing"
            self.problems.append(f"{where}: the {ANNOTATION_TYPE} annotation holds {got}; it holds one scene:{tag} "
                                 f"(namespace {SCENE_NS})")
            return None
        return content[0]

    def _values(self, element: ET.Element, where: str) -> dict:
        """``<scene:Value name="key">JSON</scene:Value>`` children as a dict (the caller checks the
        element's attributes and that it holds nothing else)."""
        values = {}
        for child in element.findall(q(SCENE_NS, "Value")):
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
            if len(head.findall(q(SCENE_NS, tag))) > 1:
                self.problems.append(f"{at}: more than one scene:{tag}; merge them into one")
        return head

    def _scene_table(self, root: ET.Element, system: ET.Element, head: ET.Element | None, where: str) -> dict:
        table: dict = {}
        name = self._attribute(system, "name", where)
        if name is not None:
            table["name"] = name
        if system.get("description") is not None:
            table["description"] = system.get("description")
        experiments = root.findall(q(SSD_NS, "DefaultExperiment"))
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
    def _named_items(self, parent: ET.Element, group: str, item: str, where: str, name_fix: str, twice: str):
        """``(name, element, where)`` of each ``item`` in the ``group`` elements of ``parent``, in order;
        an item without a name or with the name of one before it is a problem (``name_fix``, ``twice``)."""
        namespace = SSD_NS if group == "Connectors" else SSV_NS
        seen: set[str] = set()
        for elements in parent.findall(q(namespace, group)):
            for element in elements.findall(q(namespace, item)):
                name = element.get("name")
                at = f"{where} {item} {name!r}"
                if not name:
                    self.problems.append(f"{where}: a {item} without a name; {name_fix}")
                elif name in seen:
                    self.problems.append(f"{at}: {twice}")
                else:
                    seen.add(name)
                    yield name, element, at

    def _connector_list(self, parent: ET.Element, element_name: str | None, where: str) -> set[str]:
        names: set[str] = set()
        for name, connector, at in self._named_items(parent, "Connectors", "Connector", where, 'give name="port"',
                                                     "declared twice; declare each connector once"):
            names.add(name)
            kind = connector.get("kind")
            if kind not in ("input", "output", "parameter", "calculatedParameter", "inout"):
                self.problems.append(f"{at}: kind={kind!r} is not input, output, parameter or calculatedParameter")
                continue
            self.connectors[(element_name, name)] = self._connector(connector, kind, at)
        return names

    def _connector(self, connector: ET.Element, kind: str, where: str) -> Connector:
        types = [c for c in connector if c.tag.startswith(f"{{{SSC_NS}}}")]
        tag = types[0].tag.partition("}")[2] if types else None
        if tag is not None and tag not in ("Real", "Integer", "Boolean", "String", "Enumeration", "Binary"):
            self.problems.append(f"{where}: ssc:{tag} is not an SSP connector type")
        unit = types[0].get("unit") if types else None
        shape = None
        array = self._annotation(connector, "Array", where)
        if array is not None:
            self._unknown(array, {"shape"}, set(), f"{where}: annotation scene:Array")
            text = self._attribute(array, "shape", f"{where}: annotation scene:Array", SHAPE,
                                   "is not the array's sizes, e.g. shape=\"2688 3\"")
            shape = tuple(int(n) for n in text.split()) if text else None
        return Connector(kind, tag, unit, shape, where)

    def _system_connectors(self, system: ET.Element, where: str) -> None:
        for name in self._connector_list(system, None, where):
            if name.count(".") != 1 or not all(name.split(".")):
                self.problems.append(f"{where} Connector {name!r}: a system connector stands for a source's or block's "
                                     "port and is named \"component.port\"")
                self.connectors.pop((None, name), None)

    # -- components ----------------------------------------------------------------------------------
    def _components(self, system: ET.Element, where: str) -> dict:
        fmus: dict = {}
        for elements in system.findall(q(SSD_NS, "Elements")):
            for element in elements:
                if element.tag != q(SSD_NS, "Component"):
                    self.problems.append(f"{where}: has an {tag_name(element.tag)} element; this reader takes FMU "
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
        if parts.scheme or parts.netloc or parts.query or parts.fragment or member_name_problem(member):
            self.problems.append(f"{where}: source={uri!r} is not a file inside the package; give {fix}")
            return None
        if member not in self.members:
            self.problems.append(f"{where}: source={uri!r} is not in the archive (it holds {some(self.members)}); "
                                 f"give {fix}")
            return None
        return member

    def _parameter_bindings(self, element: ET.Element, where: str) -> dict:
        parameters: dict = {}
        for bindings in element.findall(q(SSD_NS, "ParameterBindings")):
            for binding in bindings.findall(q(SSD_NS, "ParameterBinding")):
                at = f"{where}: ParameterBinding"
                unsupported = [f"{k}={binding.get(k)!r}" for k, ok in (("type", PARAMETER_SET_TYPE), ("prefix", ""),
                                                                        ("sourceBase", "SSD"))
                               if binding.get(k, ok) != ok]
                if binding.find(q(SSD_NS, "ParameterMapping")) is not None:
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
        inline = binding.find(q(SSD_NS, "ParameterValues"))
        if (inline is None) == (binding.get("source") is None):
            self.problems.append(f"{where}: give either inline ssd:ParameterValues or a source=\"resources/x.ssv\"")
            return None
        if inline is not None:
            content = list(inline)
            if len(content) != 1 or content[0].tag != q(SSV_NS, "ParameterSet"):
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
        if root.tag != q(SSV_NS, "ParameterSet"):
            self.problems.append(f"{where}: {member} holds {tag_name(root.tag)}, not an ssv:ParameterSet")
            return None
        return root

    def _parameters(self, parameter_set: ET.Element, where: str) -> dict:
        if not VERSION_1.fullmatch(parameter_set.get("version", "")):
            self.problems.append(f"{where}: version {parameter_set.get('version')!r}; give version=\"1.0\"")
        values: dict = {}
        for name, parameter, at in self._named_items(parameter_set, "Parameters", "Parameter", where,
                                                     "give the FMU variable's name",
                                                     "given twice; give each parameter once"):
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
            if len(text) > 12 or not INTEGER.fullmatch(text) or not INT32[0] <= int(text) <= INT32[1]:
                self.problems.append(f"{where}: ssv:Integer value={text!r} is not a 32-bit integer (xs:int); a "
                                     "larger value goes into the component's annotation")
                return None
            return int(text)
        if tag == "Boolean":
            return self._boolean(text, f"{where}: ssv:Boolean value")
        if tag in ("String", "Enumeration"):
            return text
        if tag == "Binary":
            if not HEX.fullmatch(text):
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
            for element in head.findall(q(SCENE_NS, tag)):
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
        if member_name_problem(text) or text not in self.members:
            self.problems.append(f"{where}: {text!r} is not a file in the package; a CSV source plays a file the "
                                 "package carries, e.g. \"resources/operator.csv\"")
            return None
        self.files_used.add(text)
        return text

    # -- connections ------------------------------------------------------------------------------------
    def _connections(self, system: ET.Element, where: str, fmus: set, blocks: set) -> list[dict]:
        connections = []
        for group in system.findall(q(SSD_NS, "Connections")):
            for index, element in enumerate(group.findall(q(SSD_NS, "Connection")), start=len(connections) + 1):
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
    if len(text) > 100 or not DECIMAL.fullmatch(text):
        return None
    value = int(text) if INTEGER.fullmatch(text) else float(text)
    return value if math.isfinite(value) else None


def _refuse_constant(name: str):
    raise ValueError(f"{name} is not a finite number")

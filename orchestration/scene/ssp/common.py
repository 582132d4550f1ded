"""SSP packages, what export and import share: the format's namespaces and names, the limits of an
archive read, the XSD lexical forms, and how a port maps to an SSP connector (kind and type)."""
from __future__ import annotations

import re

from orchestration.hosts.description import INTEGER_RANGES, PortInfo

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

ET_NAMESPACES = {"ssd": SSD_NS, "ssc": SSC_NS, "ssv": SSV_NS, "scene": SCENE_NS}
#: xs:int, the range of ssv:Integer and of enumeration item values
INT32 = (-2**31, 2**31 - 1)
#: xs:double without INF and NaN (a scene's numbers are finite); xs:hexBinary
DECIMAL = re.compile(r"[+-]?([0-9]+(\.[0-9]*)?|\.[0-9]+)([eE][+-]?[0-9]+)?")
INTEGER = re.compile(r"[+-]?[0-9]+")
HEX = re.compile(r"([0-9a-fA-F]{2})*")
VERSION_1 = re.compile(r"1[.][0-9]+(-.*)?")
#: an array's sizes, space-separated ("2688 3")
SHAPE = re.compile(r"[0-9]{1,10}( [0-9]{1,10}){0,31}")


def q(namespace: str, tag: str) -> str:
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
    return bool(port.items) and all(INT32[0] <= value <= INT32[1] for _, value in port.items)

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

from orchestration.scene.ssp.common import (ANNOTATION_TYPE, FMU_TYPE, MAX_MEMBER_BYTES, MAX_MEMBERS, MAX_SSD_BYTES,
                                            MAX_TOTAL_BYTES, PARAMETER_SET_TYPE, SCENE_ANNOTATION_VERSION, SCENE_NS,
                                            SSC_NS, SSD_NAME, SSD_NS, SSV_NS, connector_kind, connector_type)
from orchestration.scene.ssp.reading import SspPackage, read_package
from orchestration.scene.ssp.writing import SspExportError, export_ssp, used_ports

__all__ = ["ANNOTATION_TYPE", "FMU_TYPE", "MAX_MEMBER_BYTES", "MAX_MEMBERS", "MAX_SSD_BYTES", "MAX_TOTAL_BYTES",
           "PARAMETER_SET_TYPE", "SCENE_ANNOTATION_VERSION", "SCENE_NS", "SSC_NS", "SSD_NAME", "SSD_NS", "SSV_NS",
           "SspExportError", "SspPackage", "connector_kind", "connector_type", "export_ssp", "read_package",
           "used_ports"]

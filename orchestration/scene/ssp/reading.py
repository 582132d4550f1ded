"""Reading an SSP package: :func:`read_package` gives the scene dict of its SSD, and
:class:`SspPackage` checks the connectors the SSD declares against the scene once loaded."""
from __future__ import annotations

import hashlib
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

from orchestration.hosts.description import PortInfo
from orchestration.scene.model import Scene, SceneError
from orchestration.scene.ssp.archive import checked_members, parse_ssd, parse_xml, read_member
from orchestration.scene.ssp.common import ANNOTATION_TYPE, MAX_SSD_BYTES, connector_kind, connector_type
from orchestration.scene.ssp.extraction import extract
from orchestration.scene.ssp.ssd_reader import Connector, SsdReader


@dataclass
class SspPackage:
    """An SSP package read: the scene dict for ``scene_from_dict``, the folder its relative paths
    start from, and the connectors the SSD declares (checked against the scene once loaded)."""

    path: Path
    data: dict
    base_dir: Path
    connectors: dict[tuple[str | None, str], Connector] = field(default_factory=dict)

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


def _connector_problem(declared: Connector, port: PortInfo, on_system: bool) -> str | None:
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
            members = checked_members(path, archive)
            root = parse_ssd(path, archive, members)
            reader = SsdReader(members, lambda member: parse_xml(
                path, member, read_member(path, archive, members[member], MAX_SSD_BYTES)))
            data = reader.scene_dict(root)
            if reader.problems:
                raise SceneError(path, reader.problems)
            base_dir = extract(path, archive, digest, sorted(reader.files_used))
    _make_paths_absolute(data, base_dir)
    return SspPackage(path=path, data=data, base_dir=base_dir, connectors=reader.connectors)


def _make_paths_absolute(data: dict, base_dir: Path) -> None:
    """The FMU and CSV files as paths into the extraction folder: absolute, so that no other folder
    (fmus/ is searched for relative FMU paths) can stand in for a member."""
    for table in data.get("fmu", {}).values():
        table["path"] = str(base_dir / table["path"])
    for table in data.get("source", {}).values():
        if table.get("kind") == "csv":
            table["path"] = str(base_dir / table["path"])

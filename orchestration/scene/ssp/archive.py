"""Reading an ``.ssp`` archive as untrusted data: its members checked (names, links, sizes), the SSD
and other XML members read and parsed with no DOCTYPE."""
from __future__ import annotations

import re
import stat
import zipfile
import zlib
from pathlib import Path
from xml.etree import ElementTree as ET

from orchestration.scene.model import SceneError
from orchestration.scene.ssp.common import (ET_NAMESPACES, MAX_MEMBER_BYTES, MAX_MEMBERS, MAX_SSD_BYTES,
                                            MAX_TOTAL_BYTES, SSD_NAME, SSD_NS, VERSION_1, q)


def checked_members(path: Path, archive: zipfile.ZipFile) -> dict[str, zipfile.ZipInfo]:
    """The archive's files by name; ``SceneError`` if any member could escape the folder it is
    extracted into, is a link, is encrypted or too large, or the archive is too large."""
    infos = archive.infolist()
    if len(infos) > MAX_MEMBERS:
        raise SceneError(path, [f"the archive has {len(infos)} members, more than {MAX_MEMBERS}: no SSP package of "
                                "scenes has that many; give the .ssp that `export --ssp` wrote"])
    problems, members, total = [], {}, 0
    for info in infos:
        problem = member_name_problem(info.filename)
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


def member_name_problem(name: str) -> str | None:
    """Why an archive member name is not a plain relative path inside the archive, or None."""
    if not name or any(ord(c) < 32 or c == "\x7f" for c in name):
        return "has an empty name or a control character in its name"
    if "\\" in name or name.startswith("/") or re.match(r"[A-Za-z]:", name):
        return "has an absolute path or a backslash; members are relative paths with '/'"
    parts = name.rstrip("/").split("/")
    if any(part in ("", ".", "..") for part in parts):
        return "has a '..', '.' or empty part in its path, which could point outside the package"
    return None


def parse_ssd(path: Path, archive: zipfile.ZipFile, members: dict) -> ET.Element:
    info = members.get(SSD_NAME)
    if info is None:
        raise SceneError(path, [f"not an SSP package: no {SSD_NAME} at the root of the archive (it holds "
                                f"{some(members)}); an SSP package has its system structure there"])
    if info.file_size > MAX_SSD_BYTES:
        raise SceneError(path, [f"{SSD_NAME} is {info.file_size} bytes, more than {MAX_SSD_BYTES}: no scene's SSD is "
                                "that large"])
    root = parse_xml(path, SSD_NAME, read_member(path, archive, info, MAX_SSD_BYTES))
    if root.tag != q(SSD_NS, "SystemStructureDescription"):
        raise SceneError(path, [f"{SSD_NAME}: the root element is {tag_name(root.tag)}, not "
                                f"ssd:SystemStructureDescription (namespace {SSD_NS})"])
    version = root.get("version", "")
    if not VERSION_1.fullmatch(version):
        raise SceneError(path, [f"{SSD_NAME}: version {version!r}; this reader reads SSP 1.0 (version=\"1.0\"): "
                                "save the system as SSP 1.0"])
    return root


def parse_xml(path: Path, member: str, raw: bytes) -> ET.Element:
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


def some(members: dict) -> str:
    names = sorted(members)
    return ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "") if names else "nothing"


def read_member(path: Path, archive: zipfile.ZipFile, info: zipfile.ZipInfo, limit: int) -> bytes:
    try:
        with archive.open(info) as fh:
            data = fh.read(limit + 1)
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, NotImplementedError, RuntimeError) as exc:
        raise SceneError(path, [f"archive member {info.filename!r} cannot be read ({exc}): the archive is damaged; "
                                "write it again"]) from None
    if len(data) > limit:
        raise SceneError(path, [f"archive member {info.filename!r} is larger than {limit} bytes"])
    return data


def tag_name(tag: str) -> str:
    namespace, _, local = tag[1:].partition("}") if tag.startswith("{") else ("", "", tag)
    prefix = next((p for p, ns in ET_NAMESPACES.items() if ns == namespace), None)
    return f"{prefix}:{local}" if prefix else (f"{local} (namespace {namespace})" if namespace else local)

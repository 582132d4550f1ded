"""The extraction folder: the files an SSP package's SSD uses, extracted once per archive content
(by SHA-256) into a temporary folder kept for the life of the process and removed at exit."""
from __future__ import annotations

import atexit
import logging
import os
import shutil
import tempfile
import threading
import zipfile
import zlib
from pathlib import Path

from orchestration.scene.model import SceneError

logger = logging.getLogger(__name__)

_extractions: dict[str, Path] = {}
_extractions_lock = threading.Lock()


def extract(path: Path, archive: zipfile.ZipFile, digest: str, members: list[str]) -> Path:
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

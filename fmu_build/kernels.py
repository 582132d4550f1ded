"""The numba kernels: those an FMU carries (compiled for any x86-64 CPU) and the health of the
numba cache runs compile into."""
from __future__ import annotations

import hashlib
import importlib.util
import io
import logging
import os
import pickletools
import zipfile
from pathlib import Path

from .paths import BUILD_DIR, LAYER
from .specs import FMU_SPECS, FmuSpec

logger = logging.getLogger(__name__)

#: Where the build compiles the kernels the FMUs carry (a numba cache for numba_cache.CARRIED_CPU).
CARRIED_KERNELS = BUILD_DIR / "numba-carried"


def _numba_cache_module():
    """src/fmi3_layer/numba_cache.py (a resource of the FMUs, not a package of the project)."""
    spec = importlib.util.spec_from_file_location("_aaa_cosim_build_numba_cache", LAYER / "numba_cache.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def kernel_cache_folders(spec: FmuSpec) -> list[str]:
    """The names of the numba cache folders the kernels of ``spec``'s FMU load from (numba_cache:
    one per source file and version of the package, under the name the FMU imports it by)."""
    cache = _numba_cache_module()
    package_dir = Path(spec.source_root) / spec.package
    digest = cache.package_digest(package_dir)
    return sorted(cache.cache_folder_name(f"{spec.model_identifier}_{spec.package}", digest, path)
                  for path in package_dir.rglob("*.py"))


def carried_kernel_folders(spec: FmuSpec, root: Path) -> list[Path]:
    """The folders of the carried-kernel cache ``root`` that ``spec``'s FMU loads."""
    return [root / name for name in kernel_cache_folders(spec) if (root / name).is_dir()]


def write_carried_kernels(archive: zipfile.ZipFile, spec: FmuSpec) -> bool:
    """Add to the FMU being written the carried kernels of its package compiled before; False when
    there are none for this version of its sources (orchestration.app.warmup compiles them)."""
    folders = carried_kernel_folders(spec, CARRIED_KERNELS) if CARRIED_KERNELS.is_dir() else []
    for folder in folders:
        for file in sorted(folder.iterdir()):
            archive.write(file, f"resources/numba_cache/{folder.name}/{file.name}")
    return bool(folders)


def _numba_cache_root() -> Path:
    """The folder the FMUs cache their compiled kernels in (as src/fmi3_layer/numba_cache.py finds it);
    RuntimeError when there is no home folder to find it in."""
    return Path(os.environ.get("AAA_COSIM_NUMBA_CACHE", Path.home() / ".cache" / "aaa-cosim" / "numba"))


#: What to do when the numba cache folder cannot be used (said with the reason).
_CACHE_FIX = ("the FMUs then compile their kernels in every run (tens of seconds). Set AAA_COSIM_NUMBA_CACHE to a "
              "folder this user can write, or run with this user's own HOME (`sudo -H`, not plain `sudo`)")


def usable_cache_root() -> Path | None:
    """The numba cache folder, or None (with a warning saying why and the fix) when this user cannot
    look into it: a HOME of another user (sudo without -H), no home folder at all."""
    try:
        root = _numba_cache_root()
        root.exists()  # EACCES is an exception here, not False
    except RuntimeError as exc:  # Path.home(): no HOME and no entry in the user database
        logger.warning("no numba cache folder (%s): %s", exc, _CACHE_FIX)
        return None
    except OSError as exc:
        logger.warning("the numba cache folder %s cannot be used (%s): %s", root, exc.strerror or exc, _CACHE_FIX)
        return None
    return root


def _current_cache_folders(root: Path) -> list[Path]:
    """The folders of the numba cache that the current sources' kernels load from. numba_cache
    names each after a source file's content (the name ends in "-" and the first 24 hex digits of
    its SHA-256), so a folder of an older source is never read again, and is not looked at here."""
    names = {name for spec in FMU_SPECS.values() for name in kernel_cache_folders(spec)}
    return sorted(folder for folder in root.iterdir() if folder.is_dir() and folder.name in names)


def _pickle_problem(data: bytes, count: int) -> str | None:
    """Why ``data`` is not ``count`` complete pickles one after the other, or None. Read with
    pickletools, which follows the opcodes without making any object (nothing in it runs)."""
    stream = io.BytesIO(data)
    try:
        for _ in range(count):
            for _ in pickletools.genops(stream):
                pass
    except Exception as exc:  # genops: ValueError for a truncated stream or an unknown opcode
        return f"not complete ({exc})"
    if stream.tell() != len(data):
        return f"followed by {len(data) - stream.tell()} bytes of something else"
    return None


def numba_cache_damage(root: Path) -> str | None:
    """What is damaged in the numba cache ``root`` that the current kernels load from, naming the
    folders to delete, or None. numba writes each file whole (a temporary file, then a rename), so a
    damaged one is a disk's or a copy's doing; the FMUs would fail to load it ("UnpicklingError:
    pickle data was truncated"), and only deleting it makes numba compile it again."""
    damaged: dict[Path, str] = {}  # folder -> what is wrong with its first damaged file
    try:
        for folder in _current_cache_folders(root) if root.is_dir() else []:
            for file in sorted(folder.iterdir()):
                count = {".nbi": 2, ".nbc": 1}.get(file.suffix)  # numba: an index is its version, then its data
                problem = _pickle_problem(file.read_bytes(), count) if count else None
                if problem:
                    damaged[folder] = f"{file.name} is {problem}"
                    break
    except OSError as exc:
        where = exc.filename if exc.filename is not None else root
        return (f"the numba cache cannot be read: {where} ({exc.strerror or exc}). Delete the folder {root} "
                f"(`rm -rf '{root}'`) if it is yours, or set AAA_COSIM_NUMBA_CACHE to a folder of your own")
    if not damaged:
        return None
    listing = "; ".join(f"{folder}: {problem}" for folder, problem in list(damaged.items())[:3])
    if len(damaged) > 3:  # many: the whole cache is the simpler thing to delete
        listing += f"; and {len(damaged) - 3} more folders"
        what, command = f"the whole cache folder {root}", f"'{root}'"
    else:
        what = "that folder" if len(damaged) == 1 else "those folders"
        command = " ".join(f"'{folder}'" for folder in damaged)
    return (f"the numba cache is damaged, and the FMUs would fail to load their kernels from it ({listing}). "
            f"Delete {what} (`rm -rf {command}`) and run again: the kernels compile again, once")


def fmu_set_digest(fmus: list[Path]) -> str:
    """What the FMUs' kernels depend on: every entry's name, size and CRC (from the archives'
    directories, nothing inflated) but the kernels the FMUs carry for other machines."""
    digest = hashlib.sha256()
    for fmu in fmus:
        with zipfile.ZipFile(fmu) as archive:
            for entry in archive.infolist():
                if not entry.filename.startswith("resources/numba_cache/"):
                    digest.update(f"{fmu.name}:{entry.filename}:{entry.file_size}:{entry.CRC}\n".encode())
    return digest.hexdigest()[:16]

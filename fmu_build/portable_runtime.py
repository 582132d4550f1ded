"""The Python runtime an FMU carries, so that it runs where nothing is installed.

The FMUs' models are the project's Python/numba code. A C importer (fmusim, the tests' C host,
a C++ master) has no Python, and a machine that never saw the project has neither the
interpreter nor the packages. Each FMU therefore carries, under ``resources/runtime/``:

```
lib/libpython3.X.so.1.0          the build's CPython, loaded by the FMI layer (python_embed.c)
lib/python3.X/                   its standard library, pruned (tests, GUI, build tools)
lib/python3.X/lib-dynload/       its extension modules, pruned (no TLS, no GUI, no terminal)
lib/python3.X/site-packages/     the packages the model imports, and only those
deps/                            the shared libraries those need that glibc does not provide
manifest.txt                     what the FMI layer loads, in order (read by python_embed.c)
runtime.json                     its Python, the oldest glibc it runs on, the package versions
```

What the model imports is measured, not listed by hand: a fresh interpreter imports every module
of every FMU package (and the modules they import inside functions) and reports the packages
they came from. Byte code is compiled with unchecked hashes, because importers extract an FMU
without keeping file times and a checked ``.pyc`` would be compiled again on every load.

The runtime is built once per Python, package set and version (``build/runtime-<digest>``) and
copied into each FMU by ``package.py``.
"""
from __future__ import annotations

import compileall
import hashlib
import importlib.metadata
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from dataclasses import dataclass
from pathlib import Path

from .errors import unwritable
from .paths import BUILD_DIR, SRC

logger = logging.getLogger(__name__)

#: The packages of the FMUs (imported whole by the probe) and what they import only inside functions.
PROBED_PACKAGES = ("tissue_fmu", "haptic_fmu", "catheter_fmu")
LAZY_IMPORTS = ("scipy.sparse.linalg", "cholespy", "meshio", "sksparse.cholmod", "threadpoolctl")

#: Not carried: the build environment's own machinery. (scikit-sparse is carried where the build
#: has it, with the system SuiteSparse and BLAS it links: the tissue then factorises as in the
#: build's own process, to the bit.)
EXCLUDED_TOP_LEVEL = {"_distutils_hack"}

#: Standard library folders and extension modules no model uses: tests, GUI, terminal, packaging
#: tools and the modules that link libraries absent from a minimal system (TLS, Tk, curses, gdbm).
STDLIB_EXCLUDED = {"test", "idlelib", "tkinter", "turtledemo", "lib2to3", "ensurepip", "site-packages",
                   "pydoc_data", "venv", "curses", "dbm", "sqlite3"}
DYNLOAD_EXCLUDED = re.compile(r"^(_tkinter|_curses.*|readline|_dbm|_gdbm|nis|_sqlite3|_ssl|_hashlib|_uuid|"
                              r"_ctypes_test|_testcapi|_testbuffer|_testinternalcapi|_testmultiphase|"
                              r"_testimportmultiple|_xxtestfuzz|xxlimited.*|_test.*)\.")

#: Libraries every glibc system has (never carried: a second libc in a process is fatal).
GLIBC = re.compile(r"^(libc|libm|libdl|libpthread|librt|libutil|libresolv|libanl|ld-linux-x86-64|"
                   r"linux-vdso|libmvec|libnsl|libcrypt)\.so")

_PROBE = r"""
import importlib, json, os, pkgutil, sys, sysconfig
sys.path[:0] = sys.argv[3:]
for package in sys.argv[1].split(","):
    module = importlib.import_module(package)
    for info in pkgutil.walk_packages(module.__path__, package + "."):
        importlib.import_module(info.name)
for name in sys.argv[2].split(","):
    try:
        importlib.import_module(name)
    except ImportError:
        pass
site = os.path.realpath(sysconfig.get_paths()["purelib"])
found = {}
for name, module in list(sys.modules.items()):
    path = os.path.realpath(getattr(module, "__file__", None) or "")
    if path.startswith(site + os.sep):
        parts = os.path.relpath(path, site).split(os.sep)
        found.setdefault(parts[0], set())
        if len(parts) > 2:
            found[parts[0]].add(parts[1])
print(json.dumps({k: sorted(v) for k, v in found.items()}))
"""


class RuntimeUnavailable(RuntimeError):
    """This Python cannot be carried (no shared libpython); the message says why and the fix."""


def python_library() -> Path:
    """This interpreter's shared libpython, or RuntimeUnavailable."""
    libdir = sysconfig.get_config_var("LIBDIR") or ""
    name = sysconfig.get_config_var("INSTSONAME") or sysconfig.get_config_var("LDLIBRARY") or ""
    library = Path(libdir) / name
    if not sysconfig.get_config_var("Py_ENABLE_SHARED") or not library.exists():
        raise RuntimeUnavailable(
            f"this Python ({sys.executable}) has no shared libpython, so the FMUs cannot carry it: build them "
            "with a Python configured with --enable-shared (pyenv: PYTHON_CONFIGURE_OPTS=--enable-shared "
            "pyenv install 3.11), or Debian's python3 with the libpython3.11 package")
    return library.resolve()


def _environment_versions() -> list[str]:
    return sorted(f"{d.metadata['Name']}=={d.version}" for d in importlib.metadata.distributions())


def probe_imports(source_root: Path, build_dir: Path, extra_imports: tuple[str, ...] = ()) -> dict[str, list[str]]:
    """The site-packages entries the FMU packages import (and the modules ``extra_imports``): {top-level
    entry: [sub-entries used]}; probed once per version of their sources and of this environment
    (cached in ``build_dir``)."""
    sources = hashlib.sha256(sys.version.encode() + "\n".join(_environment_versions()).encode()
                             + "\n".join(extra_imports).encode())
    for package in PROBED_PACKAGES + ("fmi3_layer",):
        for path in sorted((Path(source_root) / package).rglob("*.py")):
            sources.update(path.name.encode() + path.read_bytes())
    cached = Path(build_dir) / f"runtime-probe-{sources.hexdigest()[:16]}.json"
    if cached.exists():
        return json.loads(cached.read_text())
    found = _probe(source_root, extra_imports)
    Path(build_dir).mkdir(parents=True, exist_ok=True)
    partial = cached.with_name(cached.name + f".{os.getpid()}.partial")
    partial.write_text(json.dumps(found))
    partial.replace(cached)
    return found


def _probe(source_root: Path, extra_imports: tuple[str, ...] = ()) -> dict[str, list[str]]:
    layer = Path(source_root) / "fmi3_layer"
    proc = subprocess.run([sys.executable, "-c", _PROBE, ",".join(PROBED_PACKAGES),
                           ",".join(LAZY_IMPORTS + tuple(extra_imports)), str(source_root), str(layer)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"probing what the FMU packages import failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _site_packages() -> Path:
    return Path(sysconfig.get_paths()["purelib"]).resolve()


def _carried_entries(probe: dict[str, list[str]]) -> dict[str, list[str] | None]:
    """site-packages entries to copy: {name: None (whole, less tests) or [subfolders kept]}.

    A package's vendored libraries (``numpy.libs``) travel with it. scipy is kept to the
    subpackages imported (and its private ``_lib``): it is the largest package and the models use a
    few of its parts.
    """
    site = _site_packages()
    entries: dict[str, list[str] | None] = {}
    for name, used in probe.items():
        top = name
        if top in EXCLUDED_TOP_LEVEL or top.startswith("__editable__") or not (site / top).exists():
            continue
        if top == "scipy":
            keep = {u for u in used if (site / "scipy" / u).is_dir()} | {"_lib"}
            entries[top] = sorted(keep)
        else:
            entries[top] = None
        libs = site / f"{top}.libs"
        if libs.is_dir():
            entries[libs.name] = None
    return entries


def requirements(entries: dict) -> dict[str, str]:
    """{distribution: version} of the packages carried: what an importer's own Python must have, at
    those versions, to run the model in its own process (the FMI layer asks it, remote.h)."""
    owners = importlib.metadata.packages_distributions()
    found = {}
    for name in entries:
        for distribution in owners.get(name.removesuffix(".py"), []):
            found[distribution] = importlib.metadata.version(distribution)
    return dict(sorted(found.items()))


def glibc_required(folder: Path) -> str:
    """The newest glibc symbol version any carried shared object needs (the oldest glibc it runs on),
    read from the version strings in the files."""
    newest = (2, 0)
    for so in Path(folder).rglob("*.so*"):
        if so.is_file():
            for match in re.finditer(rb"GLIBC_(\d+)\.(\d+)", so.read_bytes()):
                newest = max(newest, (int(match.group(1)), int(match.group(2))))
    return "%d.%d" % newest


def runtime_digest(entries: dict) -> str:
    """What a runtime is made of: the interpreter, the entries carried and their distributions' versions."""
    versions = _environment_versions()
    library = python_library()
    text = json.dumps([sys.version, str(library), library.stat().st_size, entries, versions,
                       Path(__file__).read_bytes().decode()], sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _ignore_tests(folder, names):
    return [n for n in names if n in ("tests", "__pycache__") or n.endswith((".pyc", ".a", ".pxd", ".pyi"))]


def _copy_stdlib(stdlib: Path, dest: Path) -> None:
    dest.mkdir(parents=True)
    for item in sorted(stdlib.iterdir()):
        if item.name in STDLIB_EXCLUDED or item.name.startswith("config-") or item.name == "__pycache__":
            continue
        if item.name == "lib-dynload":
            (dest / item.name).mkdir(parents=True)
            for module in sorted(item.iterdir()):
                if not DYNLOAD_EXCLUDED.match(module.name):
                    shutil.copy2(module, dest / item.name / module.name)
        elif item.is_dir():
            shutil.copytree(item, dest / item.name, ignore=_ignore_tests)
        elif item.suffix == ".py":
            shutil.copy2(item, dest / item.name)


def _copy_site_packages(entries: dict, dest: Path) -> None:
    site = _site_packages()
    dest.mkdir(parents=True)
    for name, keep in sorted(entries.items()):
        source = site / name
        if source.is_file():
            shutil.copy2(source, dest / name)
        elif keep is None:
            shutil.copytree(source, dest / name, ignore=_ignore_tests)
        else:  # the package's own files, and only the subpackages kept
            (dest / name).mkdir()
            for item in sorted(source.iterdir()):
                if item.is_dir() and item.name not in keep:
                    continue
                if item.is_dir():
                    shutil.copytree(item, dest / name / item.name, ignore=_ignore_tests)
                elif not item.name.endswith(".pyc"):
                    shutil.copy2(item, dest / name / item.name)


def _needed_libraries(root: Path) -> dict[str, Path]:
    """{soname: resolved path} of every library the carried shared objects link that is neither
    carried nor glibc's, as ldd resolves them on the build machine."""
    carried = {p.name for p in root.rglob("*.so*") if p.is_file()}
    needed: dict[str, Path] = {}
    for so in sorted(p for p in root.rglob("*.so*") if p.is_file()):
        proc = subprocess.run(["ldd", str(so)], capture_output=True, text=True)
        for line in proc.stdout.splitlines():
            match = re.match(r"\s*(\S+) => (/\S+)", line)
            if match and match.group(1) not in carried and not GLIBC.match(match.group(1)):
                needed[match.group(1)] = Path(match.group(2)).resolve()
    return needed


def _dependency_order(libraries: dict[str, Path]) -> list[str]:
    """The sonames ordered so that each comes after the carried ones it links (loaded in that order)."""
    links = {}
    for soname, path in libraries.items():
        proc = subprocess.run(["ldd", str(path)], capture_output=True, text=True)
        links[soname] = {m.group(1) for m in re.finditer(r"^\s*(\S+) => ", proc.stdout, re.M)} & set(libraries)
    order: list[str] = []
    while len(order) < len(links):
        ready = sorted(s for s in links if s not in order and links[s] <= set(order))
        order.extend(ready or sorted(s for s in links if s not in order))  # a cycle: any order
    return order


def runtime_folder(build_dir: Path, source_root: Path, extra_imports: tuple[str, ...] = ()) -> Path:
    """Where the runtime for this Python and these packages is (or will be) built."""
    entries = _carried_entries(probe_imports(source_root, build_dir, extra_imports))
    return Path(build_dir) / f"runtime-{runtime_digest(entries)}"


#: in the folder of a runtime that carries more than the project's FMUs need (the scene FMU's)
EXTRA_MARKER = "extra_imports.txt"


def _is_extra(path: Path) -> bool:
    """Whether ``path`` (a runtime folder or its .zip) is a runtime made with extra imports."""
    folder = path if path.is_dir() else path.with_suffix("")
    return (folder / EXTRA_MARKER).exists()


def build_runtime(build_dir: Path, source_root: Path, extra_imports: tuple[str, ...] = ()) -> Path:
    """The runtime folder for this Python and these packages, and the modules ``extra_imports`` with
    what they import (built once, then reused)."""
    entries = _carried_entries(probe_imports(source_root, build_dir, extra_imports))
    library = python_library()
    folder = runtime_folder(build_dir, source_root, extra_imports)
    if (folder / "manifest.txt").exists():
        return folder
    version = "%d.%d" % sys.version_info[:2]
    partial = folder.with_name(folder.name + f".{os.getpid()}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    lib = partial / "lib"
    stdlib = lib / f"python{version}"
    _copy_stdlib(Path(sysconfig.get_paths()["stdlib"]), stdlib)
    _copy_site_packages(entries, stdlib / "site-packages")
    shutil.copy2(library, lib / library.name)
    needed = _needed_libraries(partial)
    (partial / "deps").mkdir()
    for soname, path in needed.items():
        shutil.copy2(path, partial / "deps" / soname)
    # unchecked hashes: the .pyc is used whatever the file times an importer's extraction leaves
    compileall.compile_dir(str(stdlib), quiet=2, workers=0,
                           invalidation_mode=compileall.py_compile.PycInvalidationMode.UNCHECKED_HASH)
    lines = ["# read by the FMI layer (python_embed.c): what it loads, in order, relative to this folder",
             f"python {version}"]
    lines += [f"preload deps/{soname} {soname}" for soname in _dependency_order(needed)]
    lines += [f"libpython lib/{library.name}"]
    (partial / "manifest.txt").write_text("\n".join(lines) + "\n")
    description = {"python": version, "glibc": glibc_required(partial), "requirements": requirements(entries)}
    (partial / "runtime.json").write_text(json.dumps(description, indent=2))
    if extra_imports:
        (partial / EXTRA_MARKER).write_text("\n".join(extra_imports) + "\n")
    try:  # another process of this checkout may have finished the same runtime first: its stays
        partial.rename(folder)
    except OSError:
        shutil.rmtree(partial, ignore_errors=True)
        if not (folder / "manifest.txt").exists():
            raise
    for older in Path(build_dir).glob("runtime-*"):  # of other environments or versions: never read again
        if older.name not in (folder.name, folder.name + ".zip") and not older.name.endswith(".partial") \
                and not older.name.startswith("runtime-probe-") and _is_extra(older) == bool(extra_imports):
            shutil.rmtree(older, ignore_errors=True) if older.is_dir() else older.unlink(missing_ok=True)
    logger.info("built the FMUs' Python runtime %s (%.0f MB)", folder, folder_size(folder) / 1e6)
    return folder


def folder_size(folder: Path) -> int:
    return sum(p.stat().st_size for p in Path(folder).rglob("*") if p.is_file() and not p.is_symlink())


@dataclass(frozen=True)
class CarriedRuntime:
    """The Python runtime every FMU carries (portable_runtime.py): its archive and its digest."""

    archive: Path
    digest: str
    #: {"python": "3.11", "glibc": "2.36", "requirements": {distribution: version}}
    description: dict

    @property
    def requirements(self) -> dict:
        return self.description["requirements"]


def prepare_carried_runtime(quiet: bool = False) -> None:
    """Build the runtime the FMUs carry now (once per environment), saying so when it takes time."""
    try:
        folder = runtime_folder(BUILD_DIR, SRC)
    except RuntimeUnavailable:
        folder = None
    if not quiet and folder is not None and not folder.with_suffix(".zip").exists():
        print("packing the Python runtime the FMUs carry (once per environment, about a minute) ...", flush=True)
    carried_runtime()


def carried_runtime(build_dir: Path = BUILD_DIR, extra_imports: tuple[str, ...] = ()) -> CarriedRuntime | None:
    """The runtime the FMUs carry, built and archived once per environment; None (with a warning
    saying why) when this Python cannot be carried: the FMUs then need the build's Python. With
    ``extra_imports`` (modules beyond the project's FMU packages, e.g. the orchestrator's), a runtime
    that carries them too."""
    try:
        folder = build_runtime(build_dir, SRC, tuple(extra_imports))
    except RuntimeUnavailable as exc:
        logger.warning("the FMUs will carry no Python runtime and run only where this environment is: %s", exc)
        return None
    except OSError as exc:
        raise unwritable("building the FMUs' Python runtime", exc, build_dir) from None
    archive = folder.with_suffix(".zip")
    if not archive.exists():
        partial = archive.with_name(archive.name + f".{os.getpid()}.partial")
        try:
            with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as out:
                for path in sorted(folder.rglob("*")):
                    if path.is_file():
                        out.write(path, path.relative_to(folder).as_posix())
            partial.replace(archive)
        except OSError as exc:
            partial.unlink(missing_ok=True)
            raise unwritable("archiving the FMUs' Python runtime", exc, build_dir) from None
    return CarriedRuntime(archive, folder.name.partition("-")[2], json.loads((folder / "runtime.json").read_text()))

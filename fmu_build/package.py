"""Assembling an FMU: the package copy, its generated modelDescription.xml, the layer, the runtime."""
from __future__ import annotations

import datetime
import hashlib
import json
import logging
import shutil
import site
import subprocess
import sys
import sysconfig
import tempfile
import zipfile
from pathlib import Path

from .compiler import HELPER_EXECUTABLE, LAYER_SOURCES, helper_executable, layer_library, source_digest
from .documentation import coupling_contract, documentation
from .errors import BuildError, unwritable
from .kernels import write_carried_kernels
from .paths import DEFAULT_FMU_DIR, LAYER, PLATFORM, SRC
from .portable_runtime import CarriedRuntime, carried_runtime
from .specs import FMU_SPECS, FmuSpec, available_fmus

logger = logging.getLogger(__name__)

RUNTIME_FILES = ("fmi3_runtime.py", "numba_cache.py", "state_format.py")


def python_environment() -> dict:
    """What a non-Python importer needs to run the FMU's Python: this interpreter's library and packages."""
    libdir = sysconfig.get_config_var("LIBDIR") or ""
    ldlibrary = sysconfig.get_config_var("LDLIBRARY") or ""
    library = Path(libdir) / ldlibrary
    shared = bool(sysconfig.get_config_var("Py_ENABLE_SHARED")) and library.exists()
    return {
        "libpython": str(library.resolve()) if shared else "",
        "python_version": "%d.%d" % sys.version_info[:2],
        "base_prefix": sys.base_prefix,
        "site_packages": [p for p in site.getsitepackages() if Path(p).is_dir()],
    }


_DESCRIBE_SCRIPT = r"""
import importlib, json, sys
resources, package, declaration, runtime_dir, identifier, digest, date, out, needs_tool = sys.argv[1:10]
sys.path.insert(0, resources)
sys.path.insert(0, runtime_dir)
import fmi3_runtime
module_name, _, attribute = declaration.partition(":")
decl = getattr(importlib.import_module(package + "." + module_name), attribute)
token = fmi3_runtime.instantiation_token(decl, digest)
xml = fmi3_runtime.model_description(decl, identifier, token, date, needs_tool == "1")
open(out, "w", encoding="utf-8").write(xml)
print(json.dumps({"token": token, "model_name": decl.model_name, "description": decl.description,
                  "saves_state": decl.saves_state}))
"""


def _describe(spec: FmuSpec, resources: Path, digest: str, out: Path, needs_tool: bool) -> dict:
    """Write modelDescription.xml from the declaration in a fresh interpreter; return its token."""
    date = datetime.datetime.now(datetime.timezone.utc).replace(microsecond=0).isoformat().replace("+00:00", "Z")
    proc = subprocess.run([sys.executable, "-c", _DESCRIBE_SCRIPT, str(resources), spec.package, spec.declaration,
                           str(LAYER), spec.model_identifier, digest, date, str(out), "1" if needs_tool else "0"],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise BuildError(f"{spec.model_identifier}: reading the declaration {spec.package}.{spec.declaration} "
                         f"failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def build_fmu(name: str, dest: Path = DEFAULT_FMU_DIR) -> Path:
    """Build one FMU by name (``Tissue``, ``Contact``, ``Catheter``) into ``dest``."""
    if name not in FMU_SPECS:
        raise BuildError(f"unknown FMU {name!r}: choose from {', '.join(FMU_SPECS)}")
    return build_fmu_from_spec(FMU_SPECS[name], dest)


def build_fmu_from_spec(spec: FmuSpec, dest: Path = DEFAULT_FMU_DIR) -> Path:
    """Build the FMU described by ``spec`` into ``dest``; return the path of the .fmu."""
    name = spec.model_identifier
    package_dir = Path(spec.source_root) / spec.package
    if not (package_dir / "__init__.py").exists():
        raise BuildError(f"{name}: {package_dir} is not a package in this checkout")
    library = layer_library()
    environment = python_environment()
    runtime = carried_runtime(extra_imports=spec.runtime_imports)
    dest = Path(dest)
    try:
        return _assemble(spec, package_dir, library, environment, runtime, dest)
    except OSError as exc:
        raise unwritable(f"building {name}.fmu", exc, dest) from None


def _assemble(spec: FmuSpec, package_dir: Path, library: Path, environment: dict,
              runtime: CarriedRuntime | None, dest: Path) -> Path:
    """Put the FMU together in a temporary folder and move its archive into ``dest``."""
    name = spec.model_identifier
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f"build_{name}_") as tmp:
        root = Path(tmp) / "fmu"
        resources = root / "resources"
        package_copy = resources / spec.package
        # symlinks (the shared _fmi.py) become files: an FMU carries everything it imports
        shutil.copytree(package_dir, package_copy, symlinks=False,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc"))
        add_build_data(spec, package_copy)
        for file in RUNTIME_FILES:
            shutil.copyfile(LAYER / file, resources / file)
        # the package's code and the data it declares itself from (the scene FMU's ports): another
        # declaration is another instantiation token, so a process never reuses one build's module for another
        digest = source_digest(sorted(p for p in package_copy.rglob("*") if p.suffix in (".py", ".json"))
                               + [LAYER / f for f in RUNTIME_FILES + LAYER_SOURCES])
        description = _describe(spec, resources, digest, root / "modelDescription.xml", needs_tool=runtime is None)
        meta = {
            "model_identifier": name,
            "package": spec.package,
            "declaration": spec.declaration,
            "instantiation_token": description["token"],
            # checked at instantiation: a modelDescription.xml changed after the build is refused
            "model_description_sha256": hashlib.sha256((root / "modelDescription.xml").read_bytes()).hexdigest(),
            **environment,
            # what an importer's own Python needs to run the model in its process (else: a helper process)
            "requirements": runtime.requirements if runtime is not None else {},
        }
        (resources / "fmu.json").write_text(json.dumps(meta, indent=2))
        if runtime is None:  # the build machine's Python, by path (python_embed.c)
            (resources / "libpython.txt").write_text(f"{environment['libpython']}\n{environment['base_prefix']}\n")
        else:
            (resources / "runtime.id").write_text(runtime.digest + "\n")
        binaries = root / "binaries" / PLATFORM
        binaries.mkdir(parents=True)
        shutil.copyfile(library, binaries / f"{name}.so")
        if runtime is not None:  # importers extract without file modes: the layer sets the x bit itself
            shutil.copy(helper_executable(), binaries / HELPER_EXECUTABLE)
        (root / "documentation").mkdir()
        contract = coupling_contract(package_copy, name)
        (root / "documentation" / "index.html").write_text(documentation(description, environment, runtime, contract))
        if contract is not None:
            (root / "documentation" / "coupling.json").write_text(json.dumps(contract, indent=2) + "\n")
        partial = dest / f".{name}.fmu.partial"
        with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as archive:
            for path in sorted(root.rglob("*")):
                if path.is_file():
                    archive.write(path, path.relative_to(root).as_posix())
            if runtime is not None:  # compressed already: stored as it is
                archive.write(runtime.archive, "resources/runtime.zip", zipfile.ZIP_STORED)
                write_carried_kernels(archive, spec)
        final = dest / f"{name}.fmu"
        partial.replace(final)  # an FMU in use by a running importer is never half-written
    logger.info("built %s", final)
    return final


def add_build_data(spec: FmuSpec, package_copy: Path) -> None:
    """Data an FMU needs from another component, written at build time (never a code import).

    Contact's start values (array sizes, surface triangles and rest positions) are those of the
    Tissue FMU's default AAA mesh, so the two connect without changes and Contact simulates
    standalone.
    """
    if spec.package == "haptic_fmu":
        import numpy as np

        from tissue_fmu.mesh import aaa_mesh

        mesh = aaa_mesh()
        nodes, triangles = mesh.surface()
        np.savez(package_copy / "default_tissue_surface.npz", triangles=triangles.astype(np.int32),
                 positions=mesh.points[nodes])


def build_all(names: list[str] | None = None, dest: Path = DEFAULT_FMU_DIR) -> list[Path]:
    """Build the named FMUs (default: every FMU whose package exists) and return their paths."""
    names = names or available_fmus()
    return [build_fmu(name, dest) for name in names]


def has_entries(fmu: Path, prefix: str) -> bool:
    """Whether the archive ``fmu`` holds an entry whose name starts with ``prefix``."""
    with zipfile.ZipFile(fmu) as archive:
        return any(name.startswith(prefix) for name in archive.namelist())


def fmu_is_stale(name: str, dest: Path = DEFAULT_FMU_DIR) -> bool:
    """True when the FMU is missing or older than any source file of its package or of the FMI layer."""
    spec = FMU_SPECS[name]
    fmu = Path(dest) / f"{spec.model_identifier}.fmu"
    if not fmu.exists():
        return True
    sources = list((SRC / spec.package).rglob("*.py")) + [p for p in LAYER.rglob("*") if p.is_file()]
    newest = max(p.stat().st_mtime for p in sources)
    return newest > fmu.stat().st_mtime

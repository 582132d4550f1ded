"""Build the project's FMUs (``python -m orchestration build``).

An FMU here is the project's own FMI 3.0 Co-Simulation layer (``src/fmi3_layer``: C source
compiled by the system C compiler, and its Python runtime) plus one package of the project
carried as resources, whose ``fmu.py`` declares the FMU once (``FmuDeclaration``). The archive:

```
modelDescription.xml                     generated from the declaration
binaries/x86_64-linux/<id>.so            the FMI layer (links to no libpython; see python_embed.h)
resources/fmi3_runtime.py                the layer's Python side
resources/numba_cache.py                 content-keyed numba cache (loads do not recompile)
resources/state_format.py                the serialized FMU state (data only, checked before use)
resources/fmu.json                       package, declaration, token, the build's Python environment
resources/libpython.txt                  the libpython a non-Python importer loads
resources/<package>/                     the model's package (its own copy, imported under a unique name)
documentation/index.html                 ports and how to run the FMU outside Python
```

The declaration is read in a fresh interpreter from the package copy that goes into the FMU, so
the start values in the XML are exactly those the FMU starts with, and the build never imports a
package into a process that may have loaded an FMU of it.
"""
from __future__ import annotations

import datetime
import hashlib
import importlib.util
import io
import json
import logging
import os
import pickletools
import shutil
import site
import subprocess
import sys
import sysconfig
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

from . import portable_runtime

logger = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parent.parent
SRC = REPO_ROOT / "src"
LAYER = SRC / "fmi3_layer"
DEFAULT_FMU_DIR = REPO_ROOT / "fmus"
BUILD_DIR = REPO_ROOT / "build"
PLATFORM = "x86_64-linux"
LAYER_SOURCES = ("fmi3Functions.c", "python_embed.c", "python_embed.h", "runtime_unpack.c", "runtime_unpack.h",
                 "remote.c", "remote.h", "variables.h", "helper_main.c")
#: The helper process an FMU starts where its importer's Python cannot run the model (remote.h).
HELPER_EXECUTABLE = "aaa_cosim_helper"
RUNTIME_FILES = ("fmi3_runtime.py", "numba_cache.py", "state_format.py")


class BuildError(RuntimeError):
    """A build step failed; the message names the step and the fix."""


def unwritable(step: str, exc: OSError, folder: Path) -> BuildError:
    """The BuildError of a build step that could not write (or read) a file in ``folder``: a
    read-only checkout, one owned by another user, a full disk. Names the file and the fix."""
    where = exc.filename if exc.filename is not None else folder
    return BuildError(f"{step}: cannot write {where} ({exc.strerror or exc}). The build writes into {folder}: run "
                      f"`python -m orchestration build` once as a user who may write there (the owner of the "
                      f"checkout), or use a checkout of your own")


@dataclass(frozen=True)
class FmuSpec:
    """One FMU: its model identifier, the package it carries and the declaration in that package."""

    model_identifier: str
    package: str
    #: ``module:attribute`` of the FmuDeclaration inside the package
    declaration: str = "fmu:DECLARATION"
    #: folder that holds the package (default: ``src/``); test FMUs live elsewhere
    source_root: Path = SRC


FMU_SPECS: dict[str, FmuSpec] = {
    "Tissue": FmuSpec("Tissue", "tissue_fmu"),
    "Contact": FmuSpec("Contact", "haptic_fmu"),
    "Catheter": FmuSpec("Catheter", "catheter_fmu"),
}


def available_fmus() -> list[str]:
    """FMUs whose package has an FMU declaration in this checkout."""
    return [name for name, spec in FMU_SPECS.items() if (SRC / spec.package / "fmu.py").exists()]


def _digest(paths) -> str:
    sha = hashlib.sha256()
    for path in paths:
        sha.update(path.name.encode())
        sha.update(path.read_bytes())
    return sha.hexdigest()


def find_compiler() -> str | None:
    """The C compiler the build uses: $CC, else cc, gcc or clang on the PATH."""
    return os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")


def _shared_library(name: str, what: str, sources: list[Path], arguments, build_dir: Path) -> Path:
    """``build_dir/<name>-<digest of sources and flags>/<name>.so``, compiled once per version of the
    sources and of the compiler's ``arguments(output)``; ``what`` names it in errors."""
    flags = " ".join(arguments(Path(name))).encode()
    work = Path(build_dir) / f"{name}-{hashlib.sha256(_digest(sources).encode() + flags).hexdigest()[:16]}"
    library = work / f"{name}.so"
    if library.exists():
        return library
    compiler = find_compiler()
    if compiler is None:
        raise BuildError(f"no C compiler found (cc, gcc or clang) to compile {what}. Install one (Debian: "
                         "`apt-get install -y gcc`) or set CC, and build again.")
    partial = work / f"{name}.so.{os.getpid()}.partial"  # two processes may compile at once
    command = [compiler, *arguments(partial)]
    try:
        work.mkdir(parents=True, exist_ok=True)
        proc = subprocess.run(command, capture_output=True, text=True)
        if proc.returncode != 0:
            partial.unlink(missing_ok=True)
            raise BuildError(f"compiling {what} failed (exit {proc.returncode}):\n{' '.join(command)}\n"
                             f"{proc.stderr[-3000:]}")
        partial.replace(library)
    except OSError as exc:
        raise unwritable(f"compiling {what}", exc, build_dir) from None
    return library


def layer_library(build_dir: Path = BUILD_DIR) -> Path:
    """Compile (once per source version) the FMI layer's shared library; return its path."""
    sources = [LAYER / name for name in LAYER_SOURCES] + sorted((LAYER / "include").glob("*.h"))
    return _shared_library("fmi3_layer", "the FMUs' FMI layer", sources, lambda output: [
        "-std=gnu11", "-O3", "-g", "-Wall", "-Wextra", "-Wno-unused-parameter", "-fPIC", "-shared",
        "-fvisibility=hidden", f"-I{LAYER / 'include'}", str(LAYER / "fmi3Functions.c"), str(LAYER / "python_embed.c"),
        str(LAYER / "runtime_unpack.c"), str(LAYER / "remote.c"),
        # -z nodelete: the embedded interpreter keeps pointers into the library (its callbacks) for the
        # life of the process, so an importer's dlclose must not unmap it (a second instantiation
        # through the same handle, e.g. FMPy after freeInstance, would jump into unmapped code)
        "-Wl,-z,nodelete",
        # the debug information stays, compressed (the binary is written on every extraction)
        "-Wl,--compress-debug-sections=zlib", "-o", str(output), "-ldl", "-lpthread", "-lm"], build_dir)


def helper_executable(build_dir: Path = BUILD_DIR) -> Path:
    """Compile (once per source version) the helper process's executable (helper_main.c)."""
    sources = [LAYER / name for name in LAYER_SOURCES] + sorted((LAYER / "include").glob("*.h"))
    return _shared_library(HELPER_EXECUTABLE, "the FMUs' helper process", sources, lambda output: [
        "-std=gnu11", "-O2", "-g", "-Wall", "-Wextra", f"-I{LAYER / 'include'}", str(LAYER / "helper_main.c"),
        "-Wl,--compress-debug-sections=zlib", "-o", str(output), "-ldl"], build_dir)


COMPILED_LOOP_SOURCE = REPO_ROOT / "orchestration" / "compiled_loop.c"


def compiled_loop_library(build_dir: Path = BUILD_DIR) -> Path:
    """Compile (once per source version) the master's compiled loop (orchestration/compiled_loop.c)."""
    return _shared_library("compiled_loop", "the master's compiled loop", [COMPILED_LOOP_SOURCE], lambda output: [
        # -O3 vectorises the window sums (elementwise: the same sums): 3.4 ms against 10.1 ms at -O2
        # for the default scene's 4000 contact-force samples of 8064 values
        "-std=gnu11", "-O3", "-g", "-Wall", "-Wextra", "-fPIC", "-shared", str(COMPILED_LOOP_SOURCE),
        "-o", str(output)], build_dir)


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
print(json.dumps({"token": token, "model_name": decl.model_name, "description": decl.description}))
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
    runtime = carried_runtime()
    dest = Path(dest)
    try:
        return _assemble(spec, package_dir, library, environment, runtime, dest)
    except OSError as exc:
        raise unwritable(f"building {name}.fmu", exc, dest) from None


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
        folder = portable_runtime.runtime_folder(BUILD_DIR, SRC)
    except portable_runtime.RuntimeUnavailable:
        folder = None
    if not quiet and folder is not None and not folder.with_suffix(".zip").exists():
        print("packing the Python runtime the FMUs carry (once per environment, about a minute) ...", flush=True)
    carried_runtime()


def carried_runtime(build_dir: Path = BUILD_DIR) -> CarriedRuntime | None:
    """The runtime the FMUs carry, built and archived once per environment; None (with a warning
    saying why) when this Python cannot be carried: the FMUs then need the build's Python."""
    try:
        folder = portable_runtime.build_runtime(build_dir, SRC)
    except portable_runtime.RuntimeUnavailable as exc:
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
        _add_build_data(spec, package_copy)
        for file in RUNTIME_FILES:
            shutil.copyfile(LAYER / file, resources / file)
        digest = _digest(sorted(package_copy.rglob("*.py")) + [LAYER / f for f in RUNTIME_FILES + LAYER_SOURCES])
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
        (root / "documentation" / "index.html").write_text(_documentation(description, environment, runtime))
        partial = dest / f".{name}.fmu.partial"
        with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as archive:
            for path in sorted(root.rglob("*")):
                if path.is_file():
                    archive.write(path, path.relative_to(root).as_posix())
            if runtime is not None:  # compressed already: stored as it is
                archive.write(runtime.archive, "resources/runtime.zip", zipfile.ZIP_STORED)
                _write_carried_kernels(archive, spec)
        final = dest / f"{name}.fmu"
        partial.replace(final)  # an FMU in use by a running importer is never half-written
    logger.info("built %s", final)
    return final


def _running_with_runtime(runtime: CarriedRuntime) -> str:
    """How an FMU that carries its runtime runs: what an importer must provide (next to nothing)."""
    packages = ", ".join(f"{name} {version}" for name, version in runtime.requirements.items())
    return f"""<h2>Running it</h2>
<p>The model is Python code (in <code>resources/</code>). The FMU carries what runs it: CPython
{runtime.description['python']} and the packages the model imports ({packages}), with the system
libraries they link, in <code>resources/runtime.zip</code>, and its kernels compiled for any x86-64
CPU (<code>resources/numba_cache</code>). An importer provides nothing but Linux on x86-64 with glibc
{runtime.description['glibc']} or newer (Debian 12, Ubuntu 22.10, RHEL 10) and zlib
(<code>libz.so.1</code>, on every distribution), with which the FMU unpacks its runtime once per
machine into <code>$AAA_COSIM_RUNTIME_CACHE</code>, else <code>$XDG_CACHE_HOME/aaa-cosim/runtime</code>,
else <code>~/.cache/aaa-cosim/runtime</code> (about 460 MB; where none can be written, beside the
extracted resources).</p>
<p>Where the model runs: in an importer without Python (C, C++, Rust, fmusim, ...) in the importer's
process, on the carried interpreter (its home set, the importer's <code>PYTHON*</code> variables
ignored). In a Python importer (FMPy, ...) in the importer's process when its Python is
{runtime.description['python']} and has exactly those package versions; otherwise in a helper process
the FMU starts (<code>binaries/x86_64-linux/aaa_cosim_helper</code>) and ends, its calls forwarded
over shared memory (microseconds per call). <code>AAA_COSIM_MODEL_PROCESS=importer</code> or
<code>helper</code> chooses. The interpreter is never finalized: the process exit reclaims it.</p>
<p>Threads: with scikit-sparse carried, the tissue's CHOLMOD runs its BLAS calls on one thread, but
its factorisations ask OpenMP for 4 threads, which only <code>OMP_THREAD_LIMIT=1</code> in the
importer's environment caps (a helper process inherits it).</p>
"""


def _documentation(description: dict, environment: dict, runtime: CarriedRuntime | None) -> str:
    library = environment["libpython"] or "(none: this Python was built without a shared library)"
    running = _running_with_runtime(runtime) if runtime is not None else f"""<h2>Running it</h2>
<p>This build carries no Python runtime (its Python had no shared library). The model is Python code
(in <code>resources/</code>) run by an embedded CPython {environment['python_version']}.
In a Python importer (FMPy, ...) the importer's interpreter is used: run the importer with an
environment that has numpy, scipy, numba, cholespy, meshio and trimesh. In any other importer
the FMU loads the Python library recorded at build time:</p>
<pre>{library}</pre>
<p>and the packages of <code>{', '.join(environment['site_packages'])}</code>. To use another installation set
<code>AAA_COSIM_LIBPYTHON</code> to its <code>libpython3.x.so</code>, <code>AAA_COSIM_PYTHONHOME</code> to
its prefix and <code>PYTHONPATH</code> to a site-packages folder with those packages.</p>
"""
    return f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{description['model_name']}</title></head><body>
<h1>{description['model_name']}</h1>
<p>{description['description']}</p>
<p>Variables, units and start values: <code>modelDescription.xml</code>. FMI 3.0 Co-Simulation; the
communication step must be a whole multiple of <code>fixedInternalStepSize</code> (parameter
<code>internal_step</code>). FMU state can be saved, restored and serialized.</p>
{running}</body></html>
"""


def _add_build_data(spec: FmuSpec, package_copy: Path) -> None:
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
    built = [build_fmu(name, dest) for name in names]
    add_carried_kernels(built)
    return built


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


def _carried_kernel_folders(spec: FmuSpec, root: Path) -> list[Path]:
    """The folders of the carried-kernel cache ``root`` that ``spec``'s FMU loads."""
    return [root / name for name in kernel_cache_folders(spec) if (root / name).is_dir()]


def _write_carried_kernels(archive: zipfile.ZipFile, spec: FmuSpec) -> bool:
    """Add to the FMU being written the carried kernels of its package compiled before; False when
    there are none for this version of its sources (add_carried_kernels compiles them)."""
    folders = _carried_kernel_folders(spec, CARRIED_KERNELS) if CARRIED_KERNELS.is_dir() else []
    for folder in folders:
        for file in sorted(folder.iterdir()):
            archive.write(file, f"resources/numba_cache/{folder.name}/{file.name}")
    return bool(folders)


def add_carried_kernels(fmus: list[Path], quiet: bool = False) -> None:
    """Put into each of the project's FMUs that carries a runtime the kernels compiled for any
    x86-64 CPU (resources/numba_cache): a first load on another machine then loads them instead
    of compiling (Contact: ~30 s). They are compiled by running the default scene once with those
    FMUs, once per version of the sources (the cache is content-addressed, build/numba-carried);
    an FMU built after that has them already (_write_carried_kernels)."""
    finish_carried_kernels(start_carried_kernels(fmus, quiet))


@dataclass
class _CarriedKernelJob:
    fmus: list[Path]
    compiling: subprocess.Popen | None  # the default scene run that compiles them, when needed


def start_carried_kernels(fmus: list[Path], quiet: bool = False) -> _CarriedKernelJob | None:
    """add_carried_kernels in two halves, so that other work can run while the kernels compile:
    this starts the compiling run (when needed); finish_carried_kernels waits and adds them."""
    specs = {spec.model_identifier: spec for spec in FMU_SPECS.values()}
    fmus = [f for f in fmus if f.stem in specs and _entries(f, "resources/runtime.id")
            and not _entries(f, "resources/numba_cache/")]
    if not fmus:
        return None
    compiling = None
    if any(not _carried_kernel_folders(specs[f.stem], CARRIED_KERNELS) for f in fmus):
        if not quiet:
            print("compiling the kernels the FMUs carry (once per source version) ...", flush=True)
        code = "import sys; from orchestration.build import _warm_run; sys.exit(_warm_run(sys.argv[1]))"
        env = {**os.environ, "NUMBA_CPU_NAME": "generic", "AAA_COSIM_NUMBA_CACHE": str(CARRIED_KERNELS)}
        env.pop("NUMBA_CPU_FEATURES", None)
        compiling = subprocess.Popen([sys.executable, "-c", code, str(fmus[0].parent)], cwd=str(REPO_ROOT), env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return _CarriedKernelJob(fmus, compiling)


def finish_carried_kernels(job: _CarriedKernelJob | None) -> None:
    """The second half of add_carried_kernels (see start_carried_kernels)."""
    if job is None:
        return
    if job.compiling is not None:
        out, err = job.compiling.communicate()
        if job.compiling.returncode != 0:
            logger.warning("compiling the kernels the FMUs carry failed (their first load elsewhere compiles them): %s",
                           (err or out).strip()[-2000:])
            return
    specs = {spec.model_identifier: spec for spec in FMU_SPECS.values()}
    for fmu in job.fmus:
        partial = fmu.with_name(f".{fmu.name}.kernels.partial")
        shutil.copyfile(fmu, partial)
        with zipfile.ZipFile(partial, "a", zipfile.ZIP_DEFLATED) as archive:
            added = _write_carried_kernels(archive, specs[fmu.stem])
        if added:
            partial.replace(fmu)
        else:
            partial.unlink()


def fmu_contents(fmu: Path) -> str:
    """What an FMU holds, in megabytes (as stored in the archive): its runtime and the rest."""
    with zipfile.ZipFile(fmu) as archive:
        entries = archive.infolist()
    parts = {"runtime": "resources/runtime.zip", "kernels": "resources/numba_cache/", "binaries": "binaries/"}
    sizes = {name: sum(e.compress_size for e in entries if e.filename.startswith(prefix))
             for name, prefix in parts.items()}
    sizes["model"] = sum(e.compress_size for e in entries) - sum(sizes.values())
    return ", ".join(f"{name} {size / 1e6:.1f} MB" for name, size in sizes.items() if size)


_FIRST_LOAD = r"""
import sys, tempfile, time
from fmpy import extract, read_model_description
from fmpy.fmi3 import FMU3Slave
fmu = sys.argv[1]
md = read_model_description(fmu)
slave = FMU3Slave(guid=md.guid, unzipDirectory=extract(fmu, tempfile.mkdtemp()),
                  modelIdentifier=md.coSimulation.modelIdentifier, instanceName="first_load")
start = time.perf_counter()
slave.instantiate(loggingOn=False)
slave.enterInitializationMode()
slave.exitInitializationMode()
slave.doStep(0.0, float(md.coSimulation.fixedInternalStepSize or md.defaultExperiment.stepSize))
print(time.perf_counter() - start)
slave.terminate()
slave.freeInstance()
"""


def first_load_seconds(fmu: Path) -> float | None:
    """Seconds from fmi3InstantiateCoSimulation to the return of the first fmi3DoStep as on a machine
    that never ran the FMU: its model in a helper process on the runtime it carries, unpacked into
    an empty cache, no numba cache but the kernels it carries. None when it carries no runtime."""
    if not _entries(fmu, "resources/runtime.id"):
        return None
    with tempfile.TemporaryDirectory(prefix="aaa_cosim_first_load_") as clean:
        env = {k: v for k, v in os.environ.items() if not k.startswith(("AAA_COSIM_", "NUMBA_"))}
        env.update(AAA_COSIM_MODEL_PROCESS="helper", AAA_COSIM_RUNTIME_CACHE=str(Path(clean) / "runtime"),
                   HOME=clean, TMPDIR=clean)
        proc = subprocess.run([sys.executable, "-c", _FIRST_LOAD, str(fmu)], capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise BuildError(f"{fmu.name} does not load as on a clean machine:\n{proc.stderr[-3000:]}")
    return float(proc.stdout.strip().splitlines()[-1])


def _entries(fmu: Path, prefix: str) -> bool:
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


def ensure_fmus_built(quiet: bool = False) -> None:
    """Build the project's FMUs into fmus/ when missing or older than their sources, then warm the
    numba cache their kernels compile into, so that a run compiles nothing while it is timed."""
    if any(fmu_is_stale(name) for name in available_fmus()):
        prepare_carried_runtime(quiet)
    for name in available_fmus():
        if fmu_is_stale(name):
            if not quiet:
                print(f"building fmus/{name}.fmu ...", flush=True)
            try:
                build_fmu(name)
            except BuildError as exc:
                raise BuildError(f"fmus/{name}.fmu is missing or older than its sources and cannot be built: "
                                 f"{exc}") from None
    # the kernels the FMUs carry compile in another process while this CPU's are warmed (2 cores)
    carried = start_carried_kernels(sorted(DEFAULT_FMU_DIR.glob("*.fmu")), quiet=quiet)
    try:
        try:  # the master's compiled loop, so that the first run does not compile it while it is timed
            compiled_loop_library()
        except BuildError as exc:
            logger.warning("%s; runs make every step from Python", exc)
        warm_numba_cache(quiet)
    finally:
        finish_carried_kernels(carried)


def _numba_cache_root() -> Path:
    """The folder the FMUs cache their compiled kernels in (as src/fmi3_layer/numba_cache.py finds it);
    RuntimeError when there is no home folder to find it in."""
    return Path(os.environ.get("AAA_COSIM_NUMBA_CACHE", Path.home() / ".cache" / "aaa-cosim" / "numba"))


#: What to do when the numba cache folder cannot be used (said with the reason).
_CACHE_FIX = ("the FMUs then compile their kernels in every run (tens of seconds). Set AAA_COSIM_NUMBA_CACHE to a "
              "folder this user can write, or run with this user's own HOME (`sudo -H`, not plain `sudo`)")


def _usable_cache_root() -> Path | None:
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


def _fmu_set_digest(fmus: list[Path]) -> str:
    """What the FMUs' kernels depend on: every entry's name, size and CRC (from the archives'
    directories, nothing inflated) but the kernels the FMUs carry for other machines."""
    digest = hashlib.sha256()
    for fmu in fmus:
        with zipfile.ZipFile(fmu) as archive:
            for entry in archive.infolist():
                if not entry.filename.startswith("resources/numba_cache/"):
                    digest.update(f"{fmu.name}:{entry.filename}:{entry.file_size}:{entry.CRC}\n".encode())
    return digest.hexdigest()[:16]


def warm_numba_cache(quiet: bool = False, dest: Path = DEFAULT_FMU_DIR) -> bool:
    """Compile the FMUs' kernels into the numba cache by running the default scene once.

    The FMUs import their packages under names of their own and cache compiled kernels by file
    content (``numba_cache``), so a run in a fresh interpreter compiles exactly what later runs
    load. Done once per set of FMUs (a stamp in the cache folder); returns True if it ran.
    """
    fmus = sorted(Path(dest).glob("*.fmu"))
    if not fmus:
        return False
    root = _usable_cache_root()
    if root is None:
        return False
    damage = numba_cache_damage(root)
    if damage:
        raise BuildError(damage)
    try:
        digest = _fmu_set_digest(fmus)
    except OSError as exc:
        raise BuildError(f"cannot read the FMU {exc.filename} ({exc.strerror or exc}): rebuild the FMUs with "
                         "`python -m orchestration build`, as a user who may write and read them") from None
    except zipfile.BadZipFile as exc:
        raise BuildError(f"an FMU in {dest} is not a complete archive ({exc}): rebuild the FMUs with "
                         "`python -m orchestration build`") from None
    stamp = root / f"warmed-{digest}"
    if stamp.exists():
        return False
    if not quiet:
        print("compiling the FMUs' numba kernels (once per build) ...", flush=True)
    code = "import sys; from orchestration.build import _warm_run; sys.exit(_warm_run())"
    result = subprocess.run([sys.executable, "-c", code], cwd=str(REPO_ROOT), capture_output=True, text=True)
    if result.returncode != 0:  # a warm-up failure only costs time later: say so, do not stop
        logger.warning("warming the numba cache failed (runs will compile their kernels): %s",
                       (result.stderr or result.stdout).strip()[-2000:])
        return False
    try:
        root.mkdir(parents=True, exist_ok=True)
        stamp.write_text(datetime.datetime.now().isoformat())
    except OSError as exc:
        logger.warning("cannot write %s: %s", stamp, exc)
    return True


def _warm_run(fmu_dir: str | None = None) -> int:
    """The warm-up itself (in a fresh interpreter): the whole default scene, every FMU in this process
    (those of ``fmu_dir`` when given, else the scene's).

    Some kernels first run late (the non-linear ETMM tensors once the wall strains past their
    threshold, about 0.7 s after the first contact), so a shorter run leaves them to the user's.
    """
    from .master import run_scene
    from .scene import load_scene

    scene_file = REPO_ROOT / "scenes" / "aaa_endovascular.toml"
    with tempfile.TemporaryDirectory(prefix="aaa_cosim_warm_") as tmp:
        if fmu_dir is not None:  # FMU paths resolve next to the scene file first: a copy beside those FMUs
            scene_file = Path(shutil.copy(scene_file, Path(fmu_dir) / f".warm-{os.getpid()}.toml"))
        try:
            scene = load_scene(scene_file)
        finally:
            if fmu_dir is not None:
                scene_file.unlink()
        summary, _ = run_scene(scene, tmp, hosting="in-process", progress=False, plots=False, vtu=False)
    if summary["status"] != "completed":
        print(summary["error"], file=sys.stderr)
        return 1
    return 0

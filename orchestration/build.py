"""Build the project's FMUs (``python -m orchestration build``).

Each FMU is a pythonfmu3 FMI 3.0 Co-Simulation FMU that carries its own package source as
resources (DESIGN.md section 2): ``Tissue.fmu`` carries ``tissue_fmu``, and so on. No FMU carries
another FMU's package.

Two toolchain defects are handled here rather than hidden:

* pythonfmu3 0.3.4's shared library has a use-after-free at process exit: the namespace-scope
  ``std::shared_ptr<PyState> pyState`` is destroyed by its static destructor (run from
  ``__run_exit_handlers``), and then the library's ``__attribute__((destructor))``
  ``finalizePythonInterpreter`` assigns ``nullptr`` to the destroyed object, releasing the same
  control block a second time. valgrind shows the invalid read in ``finalizePythonInterpreter``
  of a block freed in ``__run_exit_handlers``. Whether the process then aborts ("corrupted
  double-linked list", reported by the next ``free`` at exit, often libgfortran's exit handler)
  depends on the heap layout, which is why numba compilation inside an FMU made it likely and
  a host that compiled numba first made it rare. We build the export library from pythonfmu3's
  own sources with one change: ``pyState`` becomes a reference to a heap object that is never
  destroyed, so only ``finalizePythonInterpreter`` releases it, once.
* Python FMUs in one process share one interpreter, so the builder runs in a fresh interpreter
  (its import of the package must not replace the copy loaded FMUs use), the entry script of
  each FMU gets a unique module name (``<model>_<package>_entry``) and imports the package it carries under a unique
  name (``<model identifier>_<package>``), never a copy the host imported already.
"""
from __future__ import annotations

import hashlib
import logging
import shutil
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

logger = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parent.parent
SRC = REPO_ROOT / "src"
DEFAULT_FMU_DIR = REPO_ROOT / "fmus"
BUILD_DIR = REPO_ROOT / "build"

# The line in pythonfmu3 0.3.4's PySlaveInstance.cpp that holds the PyState with static storage
# duration, and its replacement (a reference to a never-destroyed heap object).
_PYSTATE_DECLARATION = "    std::shared_ptr<pythonfmu::PyState> pyState{};"
_PYSTATE_PATCHED = (
    "    // Patched by orchestration/build.py: never destroyed by a static destructor, so that\n"
    "    // finalizePythonInterpreter() is the only owner that releases it (no use-after-free).\n"
    "    std::shared_ptr<pythonfmu::PyState>& pyState = *new std::shared_ptr<pythonfmu::PyState>();"
)

# fmi3GetFloat64 in pythonfmu3 0.3.4 reads the values from a Python list, one PyFloat each: an
# 8064-value array (the tissue surface) costs about 160 us in float boxing alone, too much for the
# 1 kHz loop. The patched getter also accepts the values packed as native doubles in a bytes
# object (the slaves' ``get_float64`` returns ``ndarray.tobytes()``) and copies them in one memcpy,
# checking the length. Bytes, not the buffer protocol: the library is built against the limited
# API of Python 3.2, which has no buffer protocol.
_GET_FLOAT64_LOOP = """        for (int i = 0; i < nValues; i++) {
            PyObject* value = PyList_GetItem(refs, i);
            values[i] = PyFloat_AsDouble(value);
        }
        Py_DECREF(refs);
        clearLogBuffer();
    });
}

void PySlaveInstance::GetInt32("""
_GET_FLOAT64_PATCHED = """        if (PyBytes_Check(refs)) {
            // Patched by orchestration/build.py: the values as packed doubles, copied at once.
            char* data = nullptr;
            Py_ssize_t length = 0;
            if (PyBytes_AsStringAndSize(refs, &data, &length) != 0 ||
                static_cast<std::size_t>(length) != nValues * sizeof(cppfmu::FMIFloat64)) {
                Py_DECREF(refs);
                if (!PyErr_Occurred()) {
                    PyErr_SetString(PyExc_ValueError, "get_float64 returned bytes of the wrong length");
                }
                handle_py_exception("[getFloat64] packed values", gilState);
            }
            std::memcpy(values, data, static_cast<std::size_t>(length));
        } else {
            for (int i = 0; i < nValues; i++) {
                PyObject* value = PyList_GetItem(refs, i);
                values[i] = PyFloat_AsDouble(value);
            }
        }
        Py_DECREF(refs);
        clearLogBuffer();
    });
}

void PySlaveInstance::GetInt32("""


class BuildError(RuntimeError):
    """A build step failed; the message names the step and the fix."""


@dataclass(frozen=True)
class FmuSpec:
    """One FMU of the project: its model identifier, the package it carries and its slave class."""

    model_identifier: str
    package: str
    slave_module: str
    slave_class: str
    #: folder that holds the package (default: ``src/``); test FMUs live elsewhere
    source_root: Path = SRC

    @property
    def entry_module(self) -> str:
        # named after the model too: pythonfmu3 reuses an entry module already imported under
        # the same name, so two FMUs built from one package need two names
        return f"{self.model_identifier.lower()}_{self.package}_entry"


FMU_SPECS: dict[str, FmuSpec] = {
    "Tissue": FmuSpec("Tissue", "tissue_fmu", "tissue_fmu.fmu", "TissueSlave"),
    "Contact": FmuSpec("Contact", "haptic_fmu", "haptic_fmu.fmu", "ContactSlave"),
    "Catheter": FmuSpec("Catheter", "catheter_fmu", "catheter_fmu.fmu", "CatheterSlave"),
}


def available_fmus() -> list[str]:
    """FMUs whose package has an FMU layer in this checkout."""
    return [name for name, spec in FMU_SPECS.items() if (SRC / spec.package / "fmu.py").exists()]


def _pythonfmu3_dir() -> Path:
    import pythonfmu3

    return Path(pythonfmu3.__file__).resolve().parent


def _platform_folder() -> str:
    from pythonfmu3.osutil import get_platform

    return get_platform()


def export_library(build_dir: Path = BUILD_DIR) -> Path:
    """Build (once, cached by source hash) the patched pythonfmu3 export library; return its path."""
    source = _pythonfmu3_dir() / "pythonfmu-export"
    instance_cpp = source / "src" / "pythonfmu" / "PySlaveInstance.cpp"
    text = instance_cpp.read_text()
    if _PYSTATE_DECLARATION not in text or _GET_FLOAT64_LOOP not in text:
        raise BuildError(
            f"cannot apply the patches (exit-time use-after-free, fast array getter): {instance_cpp} does not contain the expected "
            f"declaration {_PYSTATE_DECLARATION.strip()!r} and GetFloat64 loop. This build supports pythonfmu3 0.3.4 (pinned in "
            "pyproject.toml); reinstall it with `pip install -e .`."
        )
    digest = hashlib.sha256((text + _PYSTATE_PATCHED + _GET_FLOAT64_PATCHED + sys.version).encode()).hexdigest()[:16]
    work = build_dir / f"pythonfmu-export-{digest}"
    lib_name = "libpythonfmu-export.so"
    built = work / "resources" / "binaries" / _platform_folder() / lib_name
    if built.exists():
        return built

    for tool in ("cmake", "c++"):
        if shutil.which(tool) is None:
            raise BuildError(
                f"`{tool}` was not found on PATH: building the FMUs compiles pythonfmu3's export library "
                "with a fix for its exit-time crash. Install a C++ compiler and CMake "
                "(Debian: `apt-get install -y g++ cmake`) and run the build again."
            )
    if work.exists():
        shutil.rmtree(work)
    shutil.copytree(source, work / "export", ignore=shutil.ignore_patterns("build", "__pycache__"))
    patched = work / "export" / "src" / "pythonfmu" / "PySlaveInstance.cpp"
    patched_text = text.replace(_PYSTATE_DECLARATION, _PYSTATE_PATCHED).replace(_GET_FLOAT64_LOOP, _GET_FLOAT64_PATCHED)
    if "#include <cstring>" not in patched_text:
        patched_text = "#include <cstring>\n" + patched_text
    patched.write_text(patched_text)
    # pythonfmu3's CMakeLists writes the library to <source>/../resources/binaries/<platform>.
    cmake_build = work / "export" / "build"
    cmake_build.mkdir()
    logger.info("compiling the patched pythonfmu3 export library in %s", work)
    steps = [
        ["cmake", "..", "-DCMAKE_BUILD_TYPE=Release", f"-DPython3_EXECUTABLE={sys.executable}"],
        ["cmake", "--build", ".", "-j2"],
    ]
    for cmd in steps:
        proc = subprocess.run(cmd, cwd=cmake_build, capture_output=True, text=True)
        if proc.returncode != 0:
            raise BuildError(
                f"`{' '.join(cmd)}` failed (exit {proc.returncode}) while building pythonfmu3's export library:\n"
                f"{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
            )
    if not built.exists():
        raise BuildError(f"the export library build finished but {built} is missing")
    return built


_ENTRY_TEMPLATE = '''"""FMU entry point of {model_identifier} (generated by orchestration/build.py).

Python FMUs in one process share one interpreter. So that this FMU always runs the package it
carries (not a copy the host or another FMU imported under the same name), the package is
imported under the unique name ``{model_identifier}_{package}``. Before it (and its numba kernels)
is imported, a content-keyed numba cache is enabled so that a new extraction of the FMU does not
compile the kernels again. The class statement below is what pythonfmu3's loader looks for.
"""
import importlib
import importlib.util
import pathlib
import sys

from pythonfmu3 import Fmi3Slave

_package_dir = pathlib.Path(__file__).resolve().parent / "{package}"
_spec = importlib.util.spec_from_file_location("{model_identifier}_fmi_cache", _package_dir / "_fmi_support.py")
_support = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_support)
_support.enable_stable_numba_cache(_package_dir)

_name = "{model_identifier}_{package}"
if _name not in sys.modules:
    _spec = importlib.util.spec_from_file_location(_name, _package_dir / "__init__.py",
                                                   submodule_search_locations=[str(_package_dir)])
    sys.modules[_name] = importlib.util.module_from_spec(_spec)
    _spec.loader.exec_module(sys.modules[_name])
    # pythonfmu3 imports this entry module once per process and reuses it for every later
    # instance, even after the importer deleted this extraction folder: import every module of
    # the package now, so that nothing is looked up in a deleted folder later.
    for _module in sorted(_package_dir.glob("*.py")):
        if _module.stem != "__init__":
            importlib.import_module(_name + "." + _module.stem)
_Implementation = importlib.import_module(_name + ".fmu").{slave_class}


class {model_identifier}(_Implementation, Fmi3Slave):
    """{model_identifier}: see the package documentation of {package}."""
'''



def build_fmu(name: str, dest: Path = DEFAULT_FMU_DIR) -> Path:
    """Build one FMU by name (``Tissue``, ``Contact``, ``Catheter``) into ``dest``."""
    if name not in FMU_SPECS:
        raise BuildError(f"unknown FMU {name!r}: choose from {', '.join(FMU_SPECS)}")
    return build_fmu_from_spec(FMU_SPECS[name], dest)


def build_fmu_from_spec(spec: FmuSpec, dest: Path = DEFAULT_FMU_DIR) -> Path:
    """Build the FMU described by ``spec`` (its package must hold ``_fmi_support.py``) into ``dest``."""
    name = spec.model_identifier
    package_dir = Path(spec.source_root) / spec.package
    if not (package_dir / "fmu.py").exists():
        raise BuildError(f"{name}: {package_dir / 'fmu.py'} does not exist in this checkout")
    library = export_library()
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f"build_{name}_") as tmp:
        tmp = Path(tmp)
        entry = tmp / f"{spec.entry_module}.py"
        entry.write_text(_ENTRY_TEMPLATE.format(model_identifier=spec.model_identifier, package=spec.package,
                                                slave_class=spec.slave_class))
        package_copy = tmp / spec.package
        shutil.copytree(package_dir, package_copy, ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc"))
        _add_build_data(spec, package_copy)
        fmu_path = _run_builder(entry, tmp / "out", package_copy)
        final = dest / fmu_path.name
        _replace_binary(fmu_path, final, library, spec.model_identifier)
    logger.info("built %s", final)
    return final


_BUILDER_SCRIPT = """
import sys
from pythonfmu3.builder import FmuBuilder
entry, out, package = sys.argv[1:4]
sys.path.insert(0, str(__import__("pathlib").Path(entry).parent))
path = FmuBuilder.build_FMU(entry, dest=out, project_files=[package], canHandleVariableCommunicationStepSize=False)
print(path)
"""


def _run_builder(entry: Path, out: Path, package_copy: Path) -> Path:
    """Run pythonfmu3's builder on ``entry`` in a fresh interpreter; return the FMU it wrote.

    The builder imports the entry script (to write modelDescription.xml). In this process that
    import would replace, under the package's unique name, a copy that FMUs loaded here already
    use (pythonfmu3 reuses entry modules per process): a build inside a process that had loaded
    Contact.fmu broke the next Contact instance with "No module named 'Contact_haptic_fmu'".
    """
    proc = subprocess.run([sys.executable, "-c", _BUILDER_SCRIPT, str(entry), str(out), str(package_copy)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise BuildError(f"pythonfmu3's builder failed on {entry.name} (exit {proc.returncode}):\n"
                         f"{proc.stderr[-3000:]}")
    lines = [line for line in proc.stdout.splitlines() if line.strip()]
    if not lines or not Path(lines[-1]).is_file():
        raise BuildError(f"pythonfmu3's builder did not report an FMU for {entry.name}:\n{proc.stdout[-2000:]}")
    return Path(lines[-1])


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


def _replace_binary(src_fmu: Path, dst_fmu: Path, library: Path, model_identifier: str) -> None:
    """Copy the FMU archive, swapping the platform binary for the patched export library."""
    target = f"binaries/{_platform_folder()}/{model_identifier}.so"
    with zipfile.ZipFile(src_fmu) as zin, zipfile.ZipFile(dst_fmu, "w", zipfile.ZIP_DEFLATED) as zout:
        names = zin.namelist()
        if target not in names:
            raise BuildError(f"{src_fmu.name} has no {target}: pythonfmu3 has no binary for this platform")
        for item in zin.infolist():
            if item.filename == target:
                zout.write(library, arcname=target)
            else:
                zout.writestr(item, zin.read(item.filename))


def build_all(names: list[str] | None = None, dest: Path = DEFAULT_FMU_DIR) -> list[Path]:
    """Build the named FMUs (default: every FMU whose package exists) and return their paths."""
    names = names or available_fmus()
    return [build_fmu(name, dest) for name in names]


def fmu_is_stale(name: str, dest: Path = DEFAULT_FMU_DIR) -> bool:
    """True when the FMU is missing or older than any source file of its package."""
    spec = FMU_SPECS[name]
    fmu = Path(dest) / f"{spec.model_identifier}.fmu"
    if not fmu.exists():
        return True
    newest = max(p.stat().st_mtime for p in (SRC / spec.package).rglob("*.py"))
    return newest > fmu.stat().st_mtime

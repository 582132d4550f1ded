"""The C parts: the FMI layer's shared library, the helper process, any small library, compiled
once per version of their sources and flags by the system C compiler."""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
from pathlib import Path

from .errors import BuildError, unwritable
from .paths import BUILD_DIR, LAYER

LAYER_SOURCES = ("fmi3Functions.c", "python_embed.c", "python_embed.h", "runtime_unpack.c", "runtime_unpack.h",
                 "remote.c", "remote.h", "variables.h", "helper_main.c")
#: The helper process an FMU starts where its importer's Python cannot run the model (remote.h).
HELPER_EXECUTABLE = "aaa_cosim_helper"


def source_digest(paths) -> str:
    sha = hashlib.sha256()
    for path in paths:
        sha.update(path.name.encode())
        sha.update(path.read_bytes())
    return sha.hexdigest()


def find_compiler() -> str | None:
    """The C compiler the build uses: $CC, else cc, gcc or clang on the PATH."""
    return os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")


def shared_library(name: str, what: str, sources: list[Path], arguments, build_dir: Path) -> Path:
    """``build_dir/<name>-<digest of sources and flags>/<name>.so``, compiled once per version of the
    sources and of the compiler's ``arguments(output)``; ``what`` names it in errors."""
    flags = " ".join(arguments(Path(name))).encode()
    work = Path(build_dir) / f"{name}-{hashlib.sha256(source_digest(sources).encode() + flags).hexdigest()[:16]}"
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
    return shared_library("fmi3_layer", "the FMUs' FMI layer", sources, lambda output: [
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
    return shared_library(HELPER_EXECUTABLE, "the FMUs' helper process", sources, lambda output: [
        "-std=gnu11", "-O2", "-g", "-Wall", "-Wextra", f"-I{LAYER / 'include'}", str(LAYER / "helper_main.c"),
        "-Wl,--compress-debug-sections=zlib", "-o", str(output), "-ldl"], build_dir)

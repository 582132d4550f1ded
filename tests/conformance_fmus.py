"""Small third-party-style FMI 3.0 Co-Simulation FMUs written in C (tests/conformance/), built at test time.

Each model is one C file (on the runtime in ``tests/conformance/fmu_common.h``) and a hand-written
``modelDescription.xml``; :func:`build` compiles it with the system C compiler into
``binaries/<platform>/<Model>.so`` and zips both into ``<Model>.fmu``. No Python and nothing of
the project's own FMI layer is inside them: they stand for FMUs other people wrote.

| model | source | what it exercises |
|---|---|---|
| Types | types.c | Int8/Int32/Int64/Boolean/Enumeration/String/Binary variables, units from TypeDefinitions |
| FixedStep | fixed_step.c | fixedInternalStepSize = 2 ms: communication steps must be whole multiples |
| Ramp | ramp.c | canHandleVariableCommunicationStepSize, any step (default 10 ms is only a suggestion) |
| Terminator | terminator.c | terminateSimulation at a given time (fmi3OK, or fmi3Discard with lastSuccessfulTime) |
| Structural | structural.c | a structural parameter sizing an array, accepted only in Configuration Mode |
"""
from __future__ import annotations

import shutil
import subprocess
import tempfile
import zipfile
from pathlib import Path

from orchestration.hosts.fmi3 import platform_tuple

SOURCES = Path(__file__).resolve().parent / "conformance"
INCLUDE = Path(__file__).resolve().parent.parent / "src" / "fmi3_layer" / "include"
MODELS = {"Types": "types", "FixedStep": "fixed_step", "Ramp": "ramp", "Terminator": "terminator",
          "Structural": "structural"}


def compiler() -> str:
    found = shutil.which("cc") or shutil.which("gcc")
    if found is None:
        raise RuntimeError("no C compiler on PATH: the conformance FMUs are compiled at test time (apt-get install gcc)")
    return found


def build(model: str, dest: Path) -> Path:
    """Compile and zip ``model`` into ``dest/<model>.fmu``; return its path."""
    stem = MODELS[model]
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f"build_{model}_") as tmp:
        binary = Path(tmp) / "binaries" / platform_tuple() / f"{model}.so"
        binary.parent.mkdir(parents=True)
        result = subprocess.run([compiler(), "-shared", "-fPIC", "-O1", "-std=c99", "-Wall", "-Wextra", "-Werror",
                                 "-fvisibility=hidden", f"-I{INCLUDE}", f"-I{SOURCES}", str(SOURCES / f"{stem}.c"),
                                 "-o", str(binary), "-lm"], capture_output=True, text=True)
        if result.returncode != 0:
            raise RuntimeError(f"compiling {stem}.c failed:\n{result.stderr}")
        fmu = dest / f"{model}.fmu"
        with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as archive:
            archive.write(SOURCES / f"{stem}.xml", "modelDescription.xml")
            archive.write(binary, f"binaries/{platform_tuple()}/{model}.so")
            archive.writestr("resources/", "")
    return fmu


def build_all(dest: Path) -> dict[str, Path]:
    return {model: build(model, dest) for model in MODELS}

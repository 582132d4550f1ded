"""What a built FMU holds and what its first load costs (printed by ``python -m orchestration build``)."""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from .errors import BuildError
from .package import has_entries


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
    if not has_entries(fmu, "resources/runtime.id"):
        return None
    with tempfile.TemporaryDirectory(prefix="aaa_cosim_first_load_") as clean:
        env = {k: v for k, v in os.environ.items() if not k.startswith(("AAA_COSIM_", "NUMBA_"))}
        env.update(AAA_COSIM_MODEL_PROCESS="helper", AAA_COSIM_RUNTIME_CACHE=str(Path(clean) / "runtime"),
                   HOME=clean, TMPDIR=clean)
        proc = subprocess.run([sys.executable, "-c", _FIRST_LOAD, str(fmu)], capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise BuildError(f"{fmu.name} does not load as on a clean machine:\n{proc.stderr[-3000:]}")
    return float(proc.stdout.strip().splitlines()[-1])

"""The FMUs in Python importers whose environments are not the project's.

A system engineer runs FMPy from an environment of their own: FMPy and whatever numpy it brought,
no scipy, no numba, perhaps numpy of another major version. The FMU then cannot run its model in
the importer's process and starts its helper process on the runtime it carries
(src/fmi3_layer/remote.h). Each FMU is simulated with FMPy's ``simulate_fmu`` and its defaults (and start values for inputs
that make it do something) in

- a virtual environment holding only ``fmpy`` (and what it installs: numpy 2.x),
- a virtual environment with numpy 1.x (and FMPy 0.3.22, the last that allows it),

and the results must equal, to the bit, those of the same call in the project's environment (the
model in FMPy's own process). The environments are made once with pip and cached
(``$AAA_COSIM_VENVS`` or ``~/.cache/aaa-cosim/venvs``); the test is skipped with the reason when
pip cannot install them (no package index).
"""
from __future__ import annotations

import fcntl
import json
import os
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import numpy as np
import pytest

from project import FMU_NAMES, entry

pytestmark = pytest.mark.slow

#: name -> what pip installs into the environment (FMPy pinned as the project pins it)
ENVIRONMENTS = {
    "fmpy-only": ["fmpy==0.3.32"],
    "numpy-1": ["fmpy==0.3.22", "numpy<2"],  # FMPy 0.3.23 and later need numpy 2
}

SIMULATE = r"""
import json, sys, time
import numpy as np
from fmpy import simulate_fmu
fmu, out, start_values = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
messages = []
start = time.perf_counter()
result = simulate_fmu(fmu, start_values=start_values, debug_logging=True, logger=lambda *args: messages.append(args[-1].decode() if isinstance(args[-1], bytes) else str(args[-1])))
seconds = time.perf_counter() - start
np.save(out, result, allow_pickle=False)
print(json.dumps({"numpy": np.__version__, "seconds": seconds, "messages": messages}))
"""


def _root() -> Path:
    return Path(os.environ.get("AAA_COSIM_VENVS", Path.home() / ".cache" / "aaa-cosim" / "venvs"))


def foreign_python(name: str) -> Path:
    """The Python of the cached environment ``name`` (made now when missing; skipped when pip fails)."""
    root = _root()
    root.mkdir(parents=True, exist_ok=True)
    folder = root / name
    python = folder / "bin" / "python"
    with open(root / f".{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if (folder / ".complete").exists():
            return python
        shutil.rmtree(folder, ignore_errors=True)
        venv.EnvBuilder(with_pip=True, clear=True).create(folder)
        proc = subprocess.run([str(python), "-m", "pip", "install", "-q", *ENVIRONMENTS[name]], capture_output=True,
                              text=True, timeout=900)
        if proc.returncode != 0:
            shutil.rmtree(folder, ignore_errors=True)
            pytest.skip(f"pip cannot make the environment {name} ({' '.join(ENVIRONMENTS[name])}): "
                        f"{proc.stderr.strip()[-500:]}")
        (folder / ".complete").write_text("")
    return python


#: start values that make each FMU's default run do something (else the defaults: the Tissue
#: settles under its pressure; an FMU of the build's table not listed runs with its defaults, and the
#: test checks that its run changes an output): a catheter pushed in against a tip force, tool points
#: in the wall
START_VALUES = {
    "Tissue": {},
    "Contact": {"tool_positions": [0.0072] * 93},
    "Catheter": {"insertion": 0.05, "tip_force": [0.3, 0.3, 0.3]},
}


def _simulate(python: Path, fmu: Path, out: Path, env: dict) -> tuple[np.ndarray, dict]:
    """simulate_fmu(fmu) with its defaults and START_VALUES in the environment of ``python``."""
    start_values = json.dumps(entry(START_VALUES, fmu.stem, "START_VALUES of tests/test_foreign_python.py", {}))
    proc = subprocess.run([str(python), "-c", SIMULATE, str(fmu), str(out), start_values], capture_output=True,
                          text=True, timeout=900, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return np.load(out, allow_pickle=False), json.loads(proc.stdout.strip().splitlines()[-1])


def _clean_environment() -> dict:
    """This process's environment without the project's venv and without a choice of model process."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME", "AAA_COSIM_MODEL_PROCESS")}
    return env


@pytest.fixture(scope="module")
def project_results(fmus, tmp_path_factory):
    """simulate_fmu of each FMU in the project's environment (the model in FMPy's process)."""
    folder = tmp_path_factory.mktemp("project_fmpy")
    results = {}
    for name, fmu in fmus.items():
        results[name] = _simulate(Path(sys.executable), fmu, folder / f"{name}.npy", _clean_environment())
    return results


@pytest.mark.parametrize("environment", list(ENVIRONMENTS))
@pytest.mark.parametrize("name", FMU_NAMES)
def test_simulate_fmu_in_a_foreign_environment_gives_the_projects_numbers(environment, name, fmus, project_results,
                                                                          tmp_path):
    python = foreign_python(environment)
    result, report = _simulate(python, fmus[name], tmp_path / "result.npy", _clean_environment())
    expected, project = project_results[name]
    assert not any("helper process" in m for m in project["messages"])  # the project's Python hosts it
    assert any("runs in a helper process" in m for m in report["messages"]), report["messages"][:5]
    if environment == "numpy-1":
        assert report["numpy"].startswith("1."), report["numpy"]
    assert result.dtype.names == expected.dtype.names
    for field in expected.dtype.names:
        np.testing.assert_array_equal(result[field], expected[field], err_msg=f"{name}.{field}")
    moving = [f for f in expected.dtype.names if f != "time" and np.any(expected[f] != expected[f][:1])]
    assert moving, "the default run changes no output: the comparison would prove little"

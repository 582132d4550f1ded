"""Fresh processes that load, run and unload each FMU through FMPy all exit normally.

The FMUs' first FMI layer (pythonfmu3) aborted at interpreter exit in about half of such runs
(a use-after-free in its exit handler). Each run here is a new interpreter calling
``fmpy.simulate_fmu`` with its defaults, as a user would; some runs start with an empty numba
cache so the kernels compile inside the FMU, the condition that made the abort likely.
"""
from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import pytest

from project import FMU_NAMES, entry

PROBE = """
import sys, fmpy
result = fmpy.simulate_fmu(sys.argv[1], stop_time=float(sys.argv[2]))
print('rows', len(result), 'time', repr(float(result['time'][-1])))
"""

RUNS = 30
COMPILING_RUNS = 4
#: FMU -> (stop time, rows FMPy records, last time): FMPy's default step (fixedInternalStepSize,
#: doubled until at most 1000 steps), any stop time; every FMU of the build's table (tests/project.py)
CASES = {
    "Tissue": (3 / 30, 4, "0.1"),
    "Catheter": (2.0, 1001, "2.0"),  # FMPy steps 2 ms: two internal steps per call
    "Contact": (0.0125, 13, "0.012"),  # not a multiple of the step: FMPy stops at the last whole step
}


def _run(fmu, stop_time, cache_dir=None):
    env = dict(os.environ)
    if cache_dir is not None:
        env["AAA_COSIM_NUMBA_CACHE"] = str(cache_dir)
    return subprocess.run([sys.executable, "-c", PROBE, str(fmu), repr(stop_time)], capture_output=True, text=True,
                          timeout=300, env=env)


@pytest.mark.slow
@pytest.mark.parametrize("name", FMU_NAMES)
def test_thirty_fresh_processes_exit_normally(name, built_fmu, tmp_path):
    fmu = built_fmu(name)
    stop_time, rows, last = entry(CASES, name, "CASES of tests/test_fmu_process_safety.py")
    caches = [tmp_path / f"cache{k}" for k in range(COMPILING_RUNS)]
    jobs = caches + [None] * (RUNS - COMPILING_RUNS)
    with ThreadPoolExecutor(max_workers=2) as pool:
        results = list(pool.map(lambda cache: _run(fmu, stop_time, cache), jobs))
    failures = [(k, r.returncode, r.stderr[-500:]) for k, r in enumerate(results) if r.returncode != 0]
    assert failures == []
    for r in results:
        assert f"rows {rows} time {last}" in r.stdout, r.stdout + r.stderr[-500:]
        assert "corrupted" not in r.stderr and "Fatal" not in r.stderr

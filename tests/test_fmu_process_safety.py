"""Fresh processes that load, run and unload Tissue.fmu all exit normally.

With pythonfmu3's stock export library a numba FMU aborted at interpreter exit in about half of
such runs ("corrupted double-linked list"): a use-after-free in the library's exit handler (see
orchestration/build.py). Each run here is a new interpreter calling ``fmpy.simulate_fmu`` as a
user would; some runs start with an empty numba cache so the kernels compile inside the FMU,
the condition that made the abort likely.
"""
from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

PROBE = """
import sys, fmpy
result = fmpy.simulate_fmu(sys.argv[1], stop_time=3 / 30, output=['strain_energy', 'solver_iterations'])
print('rows', len(result), 'time', repr(float(result['time'][-1])))
"""

RUNS = 30
COMPILING_RUNS = 4


def _run(fmu, cache_dir=None):
    env = dict(os.environ)
    if cache_dir is not None:
        env["AAA_COSIM_NUMBA_CACHE"] = str(cache_dir)
    return subprocess.run([sys.executable, "-c", PROBE, str(fmu)], capture_output=True, text=True,
                          timeout=300, env=env)


def test_thirty_fresh_processes_exit_normally(tissue_fmu, tmp_path):
    caches = [tmp_path / f"cache{k}" for k in range(COMPILING_RUNS)]
    jobs = caches + [None] * (RUNS - COMPILING_RUNS)
    with ThreadPoolExecutor(max_workers=2) as pool:
        results = list(pool.map(lambda cache: _run(tissue_fmu, cache), jobs))
    failures = [(k, r.returncode, r.stderr[-500:]) for k, r in enumerate(results) if r.returncode != 0]
    assert failures == []
    for r in results:
        assert "rows 4 time 0.1" in r.stdout, r.stdout
        assert "corrupted" not in r.stderr and "Fatal" not in r.stderr

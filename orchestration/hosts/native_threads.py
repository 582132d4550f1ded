"""One thread for the native libraries the FMUs load into the orchestrator's own processes.

The 1 kHz haptic loop needs a CPU of its own, and on a 2-core machine the tissue's worker has the
other one. The tissue's CHOLMOD (the ``cholmod`` extra) runs parts of a factorisation on 4 OpenMP
threads whatever ``OMP_NUM_THREADS`` says: one thread factorises faster (docs/performance.md),
and the others would take the loop's CPU. (Its BLAS calls run on one thread anyway, set by the
tissue for the same bits in every process; the system's OpenBLAS would still start a pool of
threads that nothing uses.) libgomp and OpenBLAS read their limits from the environment once,
when they are loaded, for the whole process; so the limits are set in the processes the
orchestrator owns (the command line's, and every worker process, before any FMU is loaded
there), never by an FMU, which also runs inside other people's importers. A limit already in the
environment is the user's choice and is kept.
"""

from __future__ import annotations

import os

#: Environment variables that cap native thread pools, and the cap set where none is set.
NATIVE_THREAD_LIMITS = {
    "OMP_THREAD_LIMIT": "1",       # libgomp: every OpenMP region, num_threads clauses included
    "OPENBLAS_NUM_THREADS": "1",   # OpenBLAS loaded after this (the system's, under CHOLMOD): no idle pool
}


def limit_native_threads() -> None:
    """Set :data:`NATIVE_THREAD_LIMITS` in this process's environment where they are not set.
    Effective for libraries loaded afterwards (and for child processes)."""
    for name, value in NATIVE_THREAD_LIMITS.items():
        os.environ.setdefault(name, value)

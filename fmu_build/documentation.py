"""Each FMU's documentation/index.html: what it is and what an importer must provide to run it."""
from __future__ import annotations

from .portable_runtime import CarriedRuntime


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


def documentation(description: dict, environment: dict, runtime: CarriedRuntime | None) -> str:
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

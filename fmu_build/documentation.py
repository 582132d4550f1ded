"""Each FMU's documentation/index.html: what it is and what an importer must provide to run it."""
from __future__ import annotations

import importlib.util
import sys
from html import escape
from pathlib import Path

from .portable_runtime import CarriedRuntime

#: the contract's file in an FMU's package (``src/fmi3_layer/coupling.py``, linked into each package)
CONTRACT_FILE = "_coupling.py"


def coupling_contract(package_copy: Path, model_name: str) -> dict | None:
    """The coupling contract of ``model_name`` from the contract the FMU's package carries (None for an
    FMU without one, such as the test suite's FMUs): ``documentation/coupling.json`` and the HTML section."""
    path = package_copy / CONTRACT_FILE
    if not path.is_file():
        return None
    name = f"_aaa_cosim_contract_{model_name}"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while the class is made
    try:
        spec.loader.exec_module(module)
        return module.contract_of(model_name)
    finally:
        del sys.modules[name]


def _coupling_section(contract: dict) -> str:
    """The contract as HTML: how a master composes this FMU with the other two."""
    def rows(links, own_side: str, other_side: str) -> str:
        return "".join(f"<tr><td><code>{escape(link[own_side].split('.', 1)[1])}</code></td>"
                       f"<td><code>{escape(link[other_side])}</code></td><td>{escape(link['transition'])}</td>"
                       f"<td>{escape(link['ordering'] or '-')}</td><td>{escape(link['sees'])}</td></tr>\n"
                       for link in links)
    head = ("<tr><th>{}</th><th>{}</th><th>transition</th><th>ordering</th>"
            "<th>the consumer stepping [t, t + h] sees</th></tr>\n")
    steps = ", ".join(f"{escape(fmu)} {escape(step)} s" for fmu, step in contract["steps"].items())
    agreements = "".join(f"<li><code>{escape(' = '.join(a['parameters']))}</code>: {escape(a['why'])}</li>\n"
                         for a in contract["agreements"])
    rules = "".join(f"<dt>{escape(name)}</dt><dd>{escape(text)}</dd>\n" for name, text in contract["rules"].items())
    return f"""<h2>Coupling</h2>
<p>How a master composes this FMU with the project's others into the scene it was made for (what the
project's orchestrator does; <code>documentation/coupling.json</code> holds the same contract for
programs). Steps: {steps}, each the FMU's <code>fixedInternalStepSize</code>. <em>hold</em>: the
producer's latest sample; <em>average</em>: the mean of its samples in the consumer's window;
<em>gauss-seidel</em>: the producer steps to the end of the consumer's step first; <em>jacobi</em>: the
consumer sees the producer's samples up to the start of its step. Where this FMU can tell a rule is
broken it refuses the call and quotes the rule.</p>
<h3>Inputs</h3>
<table>
{head.format("input", "from")}{rows(contract["inputs"], "target", "source")}</table>
<h3>Outputs to the other FMUs</h3>
<table>
{head.format("output", "to")}{rows(contract["outputs"], "source", "target")}</table>
<h3>Sizes that must agree</h3>
<ul>
{agreements}</ul>
<h3>Rules</h3>
<dl>
{rules}</dl>
"""


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


def documentation(description: dict, environment: dict, runtime: CarriedRuntime | None,
                  contract: dict | None = None) -> str:
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
    state = ("FMU state can be saved, restored and serialized." if description.get("saves_state", True) else
             "FMU state cannot be saved (canGetAndSetFMUState is false): the model holds other FMUs' instances.")
    return f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{description['model_name']}</title></head><body>
<h1>{description['model_name']}</h1>
<p>{description['description']}</p>
<p>Variables, units and start values: <code>modelDescription.xml</code>. FMI 3.0 Co-Simulation; the
communication step must be a whole multiple of <code>fixedInternalStepSize</code> (parameter
<code>internal_step</code>). {state}</p>
{running}{_coupling_section(contract) if contract else ""}</body></html>
"""

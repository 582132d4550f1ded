"""Build the project's FMUs (``python -m orchestration build``), apart from the orchestrator that runs them.

An FMU here is the project's own FMI 3.0 Co-Simulation layer (``src/fmi3_layer``: C source
compiled by the system C compiler, and its Python runtime) plus one package of the project
carried as resources, whose ``fmu.py`` declares the FMU once (``FmuDeclaration``). The archive:

```
modelDescription.xml                     generated from the declaration
binaries/x86_64-linux/<id>.so            the FMI layer (links to no libpython; see python_embed.h)
binaries/x86_64-linux/aaa_cosim_helper   the helper process (remote.h), with a carried runtime
resources/fmi3_runtime.py                the layer's Python side
resources/numba_cache.py                 content-keyed numba cache (loads do not recompile)
resources/numba_cache/                   the kernels compiled for any x86-64 CPU (kernels.py)
resources/state_format.py                the serialized FMU state (data only, checked before use)
resources/fmu.json                       package, declaration, token, the build's Python environment
resources/runtime.zip, runtime.id        the Python runtime the FMU carries (portable_runtime.py)
resources/libpython.txt                  without a carried runtime: the libpython a non-Python importer loads
resources/<package>/                     the model's package (its own copy, imported under a unique name)
documentation/index.html                 ports and how to run the FMU outside Python
```

Modules: ``paths`` (where things are), ``errors``, ``specs`` (the table of FMUs), ``compiler``
(the C layer and helper), ``portable_runtime`` (the carried runtime), ``package`` (assembling an
FMU), ``documentation``, ``kernels`` (carried kernels and the numba cache's health), ``report``
(what an FMU holds and costs). Nothing here imports the orchestrator.
"""

"""A numba cache that survives a new extraction of an FMU (carried in each FMU's resources).

Importers extract an FMU to a new temporary folder on every load, and numba's own cache is keyed
by the source file's path, so every load would compile the kernels again (seconds per instance).
The FMI runtime enables this before it imports the FMU's package.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path


#: The CPU the kernels an FMU carries are compiled for: any x86-64, so that they load on every
#: machine (numba keys its cache by CPU) and give the same bits everywhere.
CARRIED_CPU = "generic"


def use_carried_kernels(resources) -> None:
    """In the runtime an FMU carries: compile for CARRIED_CPU, and use the kernels the build
    compiled (``resources/numba_cache``) unless ``$AAA_COSIM_NUMBA_CACHE`` names another cache.
    Must run before numba is imported; the interpreter is the FMU's own (a non-Python importer)."""
    os.environ["NUMBA_CPU_NAME"] = CARRIED_CPU
    carried = Path(resources) / "numba_cache"
    if not os.environ.get("AAA_COSIM_NUMBA_CACHE") and carried.is_dir():
        os.environ["AAA_COSIM_NUMBA_CACHE"] = str(carried)


def package_digest(package_dir) -> str:
    """The digest of every source file of a package.

    A kernel's compiled code holds the kernels it calls from other modules of the package, and
    numba checks only the caller's own file: keyed by one file, a changed callee in another file
    would run stale. The package's digest covers every file a kernel can call.
    """
    package = hashlib.sha256()
    for source in sorted(Path(package_dir).rglob("*.py")):
        package.update(source.relative_to(package_dir).as_posix().encode() + b"\0" + source.read_bytes())
    return package.hexdigest()


def cache_folder_name(module_name: str, digest_of_package: str, py_file) -> str:
    """The cache folder of the kernels of ``py_file`` (one folder per file and package version)."""
    digest = hashlib.sha256(digest_of_package.encode() + Path(py_file).read_bytes()).hexdigest()[:24]
    return f"{module_name}-{Path(py_file).stem}-{digest}"


def enable_stable_numba_cache(package_dir, module_name: str) -> None:
    """Let numba cache the kernels of an extracted FMU across loads.

    Importers extract an FMU to a new temporary folder on every load, and numba's own cache is
    keyed by the source file's path, so every load would compile the kernels again (seconds per
    instance). This adds a cache locator, for source files inside ``package_dir`` only, keyed by
    the content of the whole package and by ``module_name``, the name the package is imported under
    (numba's cached code refers to its module by name): ``$AAA_COSIM_NUMBA_CACHE`` or
    ``~/.cache/aaa-cosim/numba``. Where that
    folder cannot be written, numba falls back to its usual locators. Must run before the
    package's kernels are imported (the FMI runtime does that).
    """
    try:
        from numba.core import caching
    except ImportError:  # numba missing: the model import will report it
        return
    package_dir = os.path.abspath(str(package_dir))
    root = Path(os.environ.get("AAA_COSIM_NUMBA_CACHE", Path.home() / ".cache" / "aaa-cosim" / "numba"))
    marker = f"_aaa_cosim_locator_{hashlib.sha1(package_dir.encode()).hexdigest()[:12]}"
    if getattr(caching, marker, False):
        return

    digest_of_package = package_digest(package_dir)

    class ContentAddressedLocator(caching._CacheLocator):
        def __init__(self, py_func, py_file):
            self._path = root / cache_folder_name(module_name, digest_of_package, py_file)
            self._digest = self._path.name.rpartition("-")[2]
            self._lineno = py_func.__code__.co_firstlineno

        def get_cache_path(self):
            return str(self._path)

        def get_source_stamp(self):
            return self._digest

        def get_disambiguator(self):
            return str(self._lineno)

        @classmethod
        def from_function(cls, py_func, py_file):
            if not os.path.abspath(py_file).startswith(package_dir + os.sep):
                return None
            try:
                locator = cls(py_func, py_file)
                locator.ensure_cache_path()
            except OSError:
                return None
            return locator

    caching.CacheImpl._locator_classes.insert(0, ContentAddressedLocator)
    setattr(caching, marker, True)


def load_cached_kernels(module_prefix: str) -> int:
    """Load now every kernel overload the cache holds for the modules named ``module_prefix`` or
    ``module_prefix.*``; returns how many were loaded.

    numba loads a cached overload at the kernel's first call: 5-50 ms each, which lands inside a
    step (the first contact of a run loads the tangent kernels) and stalls a 1 kHz loop waiting for
    it. Called at instantiation, that cost moves to the setup. Only overloads cached for this very
    code and machine are loaded (nothing is compiled here); anything unexpected in numba's
    internals leaves the lazy loading as it was.
    """
    import logging
    import sys

    log = logging.getLogger(__name__)
    try:
        from numba.core.caching import FunctionCache
        from numba.core.registry import CPUDispatcher
    except ImportError:
        return 0
    loaded = 0
    modules = [m for name, m in list(sys.modules.items())
               if m is not None and (name == module_prefix or name.startswith(module_prefix + "."))]
    for module in modules:
        for dispatcher in list(vars(module).values()):
            if not isinstance(dispatcher, CPUDispatcher) or not isinstance(dispatcher._cache, FunctionCache):
                continue
            try:
                cache = dispatcher._cache
                codegen = dispatcher.targetctx.codegen()
                for key in cache._cache_file._load_index():
                    signature = key[0]
                    if key != cache._index_key(signature, codegen) or signature in dispatcher.overloads:
                        continue  # another machine's or another version's code; or loaded already
                    dispatcher.compile(signature)
                    loaded += 1
            except Exception as exc:  # numba internals changed: the kernels load at first call instead
                log.debug("preloading %s failed: %s", getattr(dispatcher, "__name__", dispatcher), exc)
                break
    return loaded

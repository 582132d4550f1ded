"""FMI plumbing shared by the project's FMU slaves (one source, vendored into each package).

Each FMU package links this file as ``<package>/_fmi_support.py`` so that every FMU carries its
own copy under its own module name (two Python FMUs in one process share one interpreter).

Why it exists: pythonfmu3 turns any Python exception raised from an FMI callback into
``fmi3Fatal`` and releases the slave's Python objects, after which further calls on that
instance are unsafe. So a slave here never lets an exception escape: bad input is recorded and
logged with ``fmi3Error``, and the next ``fmi3DoStep`` returns ``fmi3Error`` with the reason,
leaving the host process running. It also provides array setters that do not use
``np.reshape(..., newshape=...)`` (removed in NumPy 2.4, which pythonfmu3 0.3.4's default
setter calls), and enforces the fixed communication step.
"""
from __future__ import annotations

import hashlib
import logging
import math
import os
from pathlib import Path
from typing import Callable

import numpy as np
from pythonfmu3 import (
    DefaultExperiment,
    Dimension,
    Fmi3Causality,
    Fmi3Status,
    Fmi3StepResult,
    Fmi3Variability,
    Float64,
    Int32,
    UInt64,
)
from pythonfmu3.unit import Unit

#: Units used across the project's ports (SI; DESIGN.md section 4).
SI_UNITS = {
    "m": dict(m=1),
    "s": dict(s=1),
    "N": dict(kg=1, m=1, s=-2),
    "Pa": dict(kg=1, m=-1, s=-2),
    "J": dict(kg=1, m=2, s=-2),
    "kg/m3": dict(kg=1, m=-3),
    "Pa.s": dict(kg=1, m=-1, s=-1),
    "m/s": dict(m=1, s=-1),
    "N/m": dict(kg=1, s=-2),
    "N.s/m": dict(kg=1, s=-1),
    "rad": dict(rad=1),
    "rad/s": dict(rad=1, s=-1),
    "Hz": dict(s=-1),
    "N.m2": dict(kg=1, m=3, s=-2),
}

_STEP_RELATIVE_TOLERANCE = 1e-9


def enable_stable_numba_cache(package_dir) -> None:
    """Let numba cache the kernels of an extracted FMU across loads.

    Importers extract an FMU to a new temporary folder on every load, and numba's own cache is
    keyed by the source file's path, so every load would compile the kernels again (seconds per
    instance). This adds a cache locator, for source files inside ``package_dir`` only, keyed by
    the file's content: ``$AAA_COSIM_NUMBA_CACHE`` or ``~/.cache/aaa-cosim/numba``. Where that
    folder cannot be written, numba falls back to its usual locators. Must run before the
    package's kernels are imported (the entry script of the FMU does that).
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

    class ContentAddressedLocator(caching._CacheLocator):
        def __init__(self, py_func, py_file):
            digest = hashlib.sha256(Path(py_file).read_bytes()).hexdigest()[:24]
            self._digest = digest
            self._lineno = py_func.__code__.co_firstlineno
            self._path = root / f"{Path(package_dir).name}-{Path(py_file).stem}-{digest}"

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


def _reason(exc: Exception) -> str:
    """A user's mistake (ValueError) reads as its message; anything else also names its type."""
    return str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"


class _FmuLogHandler(logging.Handler):
    """Forwards library log records (warnings and above) to the FMU's logger callback."""

    def __init__(self, slave: "GuardedSlaveMixin"):
        super().__init__(level=logging.WARNING)
        self._slave = slave

    def emit(self, record: logging.LogRecord) -> None:
        status = Fmi3Status.error if record.levelno >= logging.ERROR else Fmi3Status.warning
        try:
            self._slave.log(f"{record.name}: {record.getMessage()}", status)
        except Exception:  # a logging failure must never reach the host
            pass


class GuardedSlaveMixin:
    """Error handling, array ports and step enforcement for a pythonfmu3 ``Fmi3Slave``.

    Subclasses implement ``_initialize_model()`` (build the model from the parameters; raise
    ``ValueError`` with a clear message on bad parameters), ``_step_model(t, dt)`` and
    ``_publish_outputs()``; they declare ``communication_step``.
    """

    communication_step: float
    #: Python loggers whose warnings are forwarded to the FMU log.
    forwarded_loggers: tuple[str, ...] = ()

    def _declare_basics(self, description: str, communication_step: float) -> None:
        """Model attributes, units, the independent ``time`` and the ``communication_step`` parameter."""
        self.description = description
        self.author = "aaa-cosim"
        self.version = "0.1.0"
        self.default_experiment = DefaultExperiment(start_time=0.0, stop_time=1.0, step_size=communication_step)
        self._setup_guard()
        self._register_units()
        self.time = 0.0
        self.register_variable(Float64("time", causality=Fmi3Causality.independent,
                                       variability=Fmi3Variability.continuous, unit="s",
                                       description="simulation time"))
        self.communication_step = communication_step
        self.register_variable(Float64("communication_step", causality=Fmi3Causality.parameter,
                                       variability=Fmi3Variability.fixed, unit="s",
                                       description="fixed communication step size (enforced)"))

    def _register_scalars(self, entries, causality: Fmi3Causality, variability: Fmi3Variability) -> None:
        """Declare Float64 scalars ``(name, unit or None, description)`` backed by attributes set before."""
        for name, unit, text in entries:
            kwargs = dict(causality=causality, variability=variability, description=text)
            if unit:
                kwargs["unit"] = unit
            self.register_variable(Float64(name, **kwargs))

    def _setup_guard(self) -> None:
        self._failure: str | None = None
        self._initialized = False
        handler = _FmuLogHandler(self)
        for name in self.forwarded_loggers:
            package_logger = logging.getLogger(name)
            package_logger.addHandler(handler)
            # The messages reach the importer through the FMI log callback; a Python importer in
            # the same interpreter would otherwise print them a second time from its root logger.
            package_logger.propagate = False
        self._log_handler = handler

    # -- error bookkeeping -------------------------------------------------------------------
    def _fail(self, call: str, reason: str) -> None:
        message = f"{self.modelName} instance '{self.instance_name}': {call} failed: {reason}"
        if self._failure is None:
            self._failure = message
        self.log(message, Fmi3Status.error)

    def _guard(self, call: str, action: Callable[[], None]) -> bool:
        try:
            action()
            return True
        except Exception as exc:  # every exception becomes a logged error status, never fatal
            self._fail(call, _reason(exc))
            return False

    # -- FMI callbacks ---------------------------------------------------------------------------
    def exit_initialization_mode(self):
        def build():
            step = float(self.communication_step)
            if not (math.isfinite(step) and step > 0):
                raise ValueError(f"communication_step must be a positive number of seconds (got {step})")
            self._initialize_model()
            self._publish_outputs()
            self._initialized = True

        if self._failure is None:
            self._guard("fmi3ExitInitializationMode", build)

    def do_step(self, current_time: float, step_size: float):
        # The 1 kHz path: the call's name is formatted only when something fails.
        def call() -> str:
            return f"fmi3DoStep(t={current_time:.9g}, h={step_size:.9g})"

        if self._failure is not None:
            self.log(f"{call()} refused: {self._failure}", Fmi3Status.error)
            return Fmi3StepResult(status=Fmi3Status.error)
        if not self._initialized:
            self._fail(call(), "the instance was not initialized (call fmi3ExitInitializationMode first)")
            return Fmi3StepResult(status=Fmi3Status.error)
        step = float(self.communication_step)
        if abs(step_size - step) > _STEP_RELATIVE_TOLERANCE * step:
            self._fail(
                call(),
                f"the communication step is fixed at {step:.9g} s (parameter communication_step); "
                f"got {step_size:.9g} s. Step with {step:.9g} s or set communication_step before initialization.",
            )
            return Fmi3StepResult(status=Fmi3Status.error)
        try:
            self._step_model(current_time, step_size)
            self._publish_outputs()
        except Exception as exc:  # every exception becomes a logged error status, never fatal
            self._fail(call(), _reason(exc))
            return Fmi3StepResult(status=Fmi3Status.error)
        self.time = current_time + step_size
        return Fmi3StepResult(status=Fmi3Status.ok)

    def terminate(self):
        for name in self.forwarded_loggers:
            logging.getLogger(name).removeHandler(self._log_handler)

    def to_xml(self, *args, **kwargs):
        # pythonfmu3's builder reads the start values through get_float64: give it the list form.
        self._writing_xml = True
        try:
            return super().to_xml(*args, **kwargs)
        finally:
            self._writing_xml = False

    def get_float64(self, vrs):
        """Values of Float64 variables packed as native doubles (``bytes``).

        The export library the build ships (orchestration/build.py) copies them with one memcpy
        instead of unboxing one Python float per value: reading the 8064-value tissue surface
        drops from about 180 us to a few us, which the 1 kHz loop needs. While the builder
        writes modelDescription.xml (start values) the base class's list is returned.
        """
        if getattr(self, "_writing_xml", False):
            return super().get_float64(vrs)
        arrays = getattr(self, "_float64_arrays", {})
        parts = []
        for vr in vrs:
            name = arrays.get(vr)
            if name is not None:
                parts.append(getattr(self, name).ravel())
                continue
            variable = self.vars[vr]
            if not isinstance(variable, Float64):
                raise TypeError(f"Variable with valueReference={vr} is not of type Float64!")
            parts.append(np.array([float(variable.getter())]))
        if len(parts) == 1:
            return np.ascontiguousarray(parts[0], dtype=np.float64).tobytes()
        return np.concatenate(parts).astype(np.float64, copy=False).tobytes()

    # -- declarations --------------------------------------------------------------------------
    def _register_units(self) -> None:
        self.register_units([Unit(name, **dims) for name, dims in SI_UNITS.items()])

    def _register_structural(self, name: str, value: int, description: str) -> None:
        """Declare a UInt64 structural parameter that sizes arrays; setting it resizes them."""
        setattr(self, name, int(value))

        def setter(new_value):
            try:
                new_value = int(new_value.value if hasattr(new_value, "value") else new_value)
                if new_value < 1:
                    raise ValueError(f"{name} must be >= 1 (got {new_value})")
                setattr(self, name, new_value)
                for array_name, (shape, dtype) in self._sized_arrays.items():
                    if name in shape:
                        setattr(self, array_name, np.zeros(self._resolve(shape), dtype=dtype))
            except Exception as exc:
                self._fail(f"fmi3SetUInt64({name})", str(exc))

        self.register_variable(UInt64(name, causality=Fmi3Causality.structuralParameter,
                                      variability=Fmi3Variability.fixed, start=int(value),
                                      description=description, getter=lambda: getattr(self, name),
                                      setter=setter))

    def _resolve(self, shape: tuple) -> tuple:
        return tuple(int(getattr(self, d)) if isinstance(d, str) else int(d) for d in shape)

    def _register_array(self, name: str, shape: tuple, causality: Fmi3Causality, description: str,
                        unit: str | None = None, variability=Fmi3Variability.continuous,
                        dtype=np.float64, on_set: Callable[[], None] | None = None) -> None:
        """Declare an array port backed by ``self.<name>`` (an ndarray).

        ``shape`` holds ints and names of structural parameters (declared before), e.g.
        ``("n_surface_nodes", 3)``; setting such a parameter reallocates the array. Float64 arrays
        must be finite. The setter checks size and values and records a logged error instead of
        raising; ``on_set`` is called after each accepted value (e.g. to mark a new tissue frame).
        """
        if not hasattr(self, "_sized_arrays"):
            self._sized_arrays = {}
        self._sized_arrays[name] = (tuple(shape), dtype)
        setattr(self, name, np.zeros(self._resolve(shape), dtype=dtype))
        references = {v.name: v.value_reference for v in self.vars.values()}
        dimensions = [Dimension(valueReference=str(references[d])) if isinstance(d, str) else Dimension(start=str(d))
                      for d in shape]
        is_float = dtype == np.float64
        call = f"fmi3Set{'Float64' if is_float else 'Int32'}({name})"

        def getter():
            return getattr(self, name).ravel().tolist()

        def setter(values):
            try:
                array = np.asarray(values, dtype=np.float64).ravel()
                current = getattr(self, name)
                if array.size != current.size:
                    raise ValueError(f"{name} expects {current.size} values, got {array.size}")
                if not np.all(np.isfinite(array)):
                    bad = np.flatnonzero(~np.isfinite(array))
                    raise ValueError(
                        f"{name} contains {bad.size} NaN/Inf value(s) (first at flat index {int(bad[0])}); "
                        "check the FMU or source connected to this input"
                    )
                current[...] = array.reshape(current.shape)
                if on_set is not None:
                    on_set()
            except Exception as exc:
                self._fail(call, str(exc))

        def reject(values):
            self._fail(call, f"{name} is an output and cannot be set")

        writable = causality in (Fmi3Causality.input, Fmi3Causality.parameter)
        kwargs = dict(causality=causality, description=description, dimensions=dimensions,
                      getter=getter, setter=setter if writable else reject, variability=variability)
        if is_float:
            if unit:
                kwargs["unit"] = unit
            variable = Float64(name, **kwargs)
            self.register_variable(variable)
            if not hasattr(self, "_float64_arrays"):
                self._float64_arrays = {}
            self._float64_arrays[variable.value_reference] = name
        else:
            self.register_variable(Int32(name, **kwargs))

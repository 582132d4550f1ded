"""The Python side of the project's FMI 3.0 layer (carried in each FMU as resources/fmi3_runtime.py).

The C layer (fmi3Functions.c) owns the FMI state machine and the variable table; this module
owns the values and the model. Every variable's values live in a numpy array allocated here and
registered with the C layer (pointer and length), so ``fmi3Get*``/``fmi3Set*`` copy memory in C
and never enter Python, while the model reads and writes the same memory through
:class:`Values`. The C layer enters Python only for the calls that change the model:
initialization, ``fmi3DoStep`` (once per call, whatever the number of internal steps; a method
bound once, called without argument objects: time, step and the result travel through a small
array, the step exchange), configuration, FMU state, reset and free.

It also writes the modelDescription.xml from an FMU's declaration (:func:`model_description`), so
the XML, the table and the start values come from one place (``<package>/fmu.py``).

Failures never escape as exceptions from ``do_step`` and ``initialize``: they are logged through
the FMU's logger callback with the instance name, the call and the simulated time, and reported
as a status. (A NaN or infinity in an output after a step is caught by the C layer.) Any
exception that escapes elsewhere is turned into ``fmi3Error`` by the C layer.

A KeyboardInterrupt (SIGINT, e.g. Ctrl-C in a Python importer, lands in whatever Python code runs
when the signal arrives, here too) is the exception: it leaves ``do_step`` and ``initialize`` as it
came, and the C layer fails the call as "interrupted" (the instance goes into the Error mode) and
hands the interrupt back to the importer after the call returns, so a Python host still stops.

Each FMU's limit table (``FmuDeclaration.limits``) is enforced in two places: the C layer refuses
a Float64 value outside its limit in ``fmi3SetFloat64``; :meth:`RuntimeInstance.check_limits`
checks every parameter (start values and integers included) before the model is built and every
structural parameter before arrays are sized.
"""
from __future__ import annotations

import copy
import ctypes
import hashlib
import importlib
import importlib.util
import json
import logging
import math
import os
import sys
import threading
import traceback
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np


def _load_sibling(name: str):
    """A module beside this file, under a name unique to this copy (each FMU carries its own)."""
    unique = f"{__name__}__{name}"
    module = sys.modules.get(unique)
    if module is None:
        spec = importlib.util.spec_from_file_location(unique, Path(__file__).with_name(f"{name}.py"))
        module = importlib.util.module_from_spec(spec)
        sys.modules[unique] = module
        spec.loader.exec_module(module)
    return module


_state_format = _load_sibling("state_format")
StateFormatError = _state_format.StateFormatError

#: fmi3Status (include/fmi3FunctionTypes.h). These codes and the ones below mirror C enums by value:
#: tests/test_fmi_layer.py reads the C files and fails when the two sides differ.
OK, WARNING, DISCARD, ERROR, FATAL = range(5)

#: Codes of the C layer's variable table (variables.h: T_*, C_*, V_*).
TYPE_CODES = {"Float64": 1, "Int32": 7, "UInt64": 10, "Boolean": 11, "String": 12}
CAUSALITY_CODES = {"parameter": 1, "calculatedParameter": 2, "structuralParameter": 3, "input": 4, "output": 5,
                   "independent": 7}
VARIABILITY_CODES = {"constant": 1, "fixed": 2, "tunable": 3, "discrete": 4, "continuous": 5}
DTYPES = {"Float64": np.float64, "Int32": np.int32, "UInt64": np.uint64, "Boolean": np.bool_}

#: No array of an FMU may exceed this (a structural parameter of 10**9 is a typing error).
MAX_ARRAY_BYTES = 1 << 30

#: The step exchange with fmi3DoStep: t, h, internal steps (in); status, internal steps completed
#: (out); the most internal steps one call may run (written once, from the declaration).
IO_TIME, IO_STEP, IO_SUBSTEPS, IO_STATUS, IO_COMPLETED, IO_MAX_SUBSTEPS = range(6)
STEP_IO_SIZE = 6  # as the C layer's enum (fmi3Functions.c), which checks the size it is given

_REGISTER = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_int, ctypes.c_int,
                             ctypes.c_int, ctypes.c_void_p, ctypes.c_uint64, ctypes.c_char_p, ctypes.c_double,
                             ctypes.c_double, ctypes.c_char_p, ctypes.c_char_p)
_COUNTERS = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint64)
_LOG = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_int, ctypes.c_char_p)
_GET_STRING = ctypes.CFUNCTYPE(ctypes.c_char_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint64)
_SET_STRING = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint64, ctypes.c_char_p)


#: Float64 variables without a limit: any finite number (NaN and infinities are refused on set).
_FINITE = (-sys.float_info.max, sys.float_info.max)


def _register_limit(variable) -> tuple[float, float, bytes]:
    """(minimum, maximum, text) the C layer checks fmi3SetFloat64 against."""
    if variable.limit is None:
        return (*_FINITE, b"") if variable.type == "Float64" else (-math.inf, math.inf, b"")
    return (float(variable.limit.minimum), float(variable.limit.maximum),
            variable.limit.text(variable.unit).encode())


# ---- the modelDescription.xml ---------------------------------------------------------------------
def _format_value(variable, value) -> str:
    if variable.type == "Float64":
        return " ".join(repr(float(x)) for x in np.ravel(np.asarray(value, dtype=np.float64)))
    if variable.type == "Boolean":
        return " ".join("true" if bool(x) else "false" for x in np.ravel(np.asarray(value)))
    if variable.type == "String":
        return str(value)
    return " ".join(str(int(x)) for x in np.ravel(np.asarray(value)))


def _resolved_start(variable, shape: tuple):
    """The start value of ``variable`` for ``shape`` (resolved dimensions), or None."""
    start = variable.start
    if callable(start):
        start = start()
    if start is None:
        return None
    if not shape:
        return start
    array = np.asarray(start)
    size = int(np.prod(shape))
    if array.size == size:
        return array.reshape(shape)
    if array.size == 1:
        return np.full(shape, array.ravel()[0])
    return None


def declared_shape(variable, variables_by_name: dict) -> tuple:
    """Dimensions with each structural parameter replaced by its start value."""
    return tuple(int(variables_by_name[d].start) if isinstance(d, str) else int(d) for d in variable.shape)


def instantiation_token(declaration, source_digest: str) -> str:
    """A token that changes with the declaration and with the package's source code."""
    text = repr([(v.name, v.type, v.causality, v.variability, v.shape, v.unit) for v in declaration.all_variables()])
    digest = hashlib.sha256((text + source_digest + declaration.version).encode()).hexdigest()
    return "{%s-%s-%s-%s-%s}" % (digest[:8], digest[8:12], digest[12:16], digest[16:20], digest[20:32])


def model_description(declaration, model_identifier: str, token: str, generation_date: str,
                      needs_execution_tool: bool = False) -> str:
    """modelDescription.xml of an FMU declared by ``declaration`` (see declare.py);
    ``needs_execution_tool``: the FMU carries no Python runtime and needs one installed."""
    from_decl = declaration.all_variables()
    by_name = {v.name: v for v in from_decl}
    refs = {v.name: vr for vr, v in enumerate(from_decl)}
    units = sorted({v.unit for v in from_decl if v.unit} | set(declaration.extra_units))
    si = sys.modules[type(declaration).__module__].SI_UNITS
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        '<fmiModelDescription fmiVersion="3.0" modelName=%s instantiationToken=%s description=%s author=%s '
        'version=%s generationTool="aaa-cosim FMI layer" generationDateAndTime=%s variableNamingConvention="flat">'
        % (quoteattr(declaration.model_name), quoteattr(token), quoteattr(declaration.description),
           quoteattr(declaration.author), quoteattr(declaration.version), quoteattr(generation_date)),
        '  <CoSimulation modelIdentifier=%s canHandleVariableCommunicationStepSize="false" '
        'fixedInternalStepSize="%r" canGetAndSetFMUState="%s" canSerializeFMUState="%s" '
        'canBeInstantiatedOnlyOncePerProcess="false" hasEventMode="false" providesIntermediateUpdate="false" '
        'mightReturnEarlyFromDoStep="false" needsExecutionTool="%s"/>'
        % (quoteattr(model_identifier), float(declaration.internal_step), str(declaration.saves_state).lower(),
           str(declaration.saves_state).lower(), str(needs_execution_tool).lower()),
    ]
    if units:
        lines.append("  <UnitDefinitions>")
        for unit in units:
            exponents = " ".join(f'{k}="{e}"' for k, e in si[unit].items())
            lines.append(f"    <Unit name={quoteattr(unit)}><BaseUnit {exponents}/></Unit>")
        lines.append("  </UnitDefinitions>")
    lines += [
        "  <LogCategories>",
        '    <Category name="logStatusError" description="errors: what failed, where and how to fix it"/>',
        '    <Category name="logStatusWarning" description="warnings of the model (e.g. large strain)"/>',
        '    <Category name="logEvents" description="information"/>',
        "  </LogCategories>",
        '  <DefaultExperiment startTime="0.0" stopTime="%r" stepSize="%r"/>'
        % (float(declaration.stop_time), float(declaration.internal_step)),
        "  <ModelVariables>",
    ]
    for vr, v in enumerate(from_decl):
        attributes = [f"name={quoteattr(v.name)}", f'valueReference="{vr}"', f'causality="{v.causality}"',
                      f'variability="{v.variability}"']
        description = v.description
        if v.limit is not None:
            description = f"{description} (plausible range {v.limit.text(v.unit)})".lstrip()
        if description:
            attributes.append(f"description={quoteattr(description)}")
        if v.causality in ("parameter", "structuralParameter"):
            attributes.append('initial="exact"')
        elif v.causality == "calculatedParameter":
            attributes.append('initial="calculated"')
        if v.unit and v.type == "Float64":
            attributes.append(f"unit={quoteattr(v.unit)}")
        if v.limit is not None:
            low, high = v.limit.minimum, v.limit.maximum
            if v.type != "Float64":
                low, high = int(low), int(high)
            attributes += [f'min="{low!r}"', f'max="{high!r}"']
        children = []
        for d in v.shape:
            children.append(f'<Dimension valueReference="{refs[d]}"/>' if isinstance(d, str)
                            else f'<Dimension start="{int(d)}"/>')
        start = _resolved_start(v, declared_shape(v, by_name)) if v.has_start else None
        if v.has_start and start is None:
            raise ValueError(f"{declaration.model_name}.{v.name}: a {v.causality} needs a start value")
        if start is not None and v.type == "String":
            children.insert(0, f"<Start value={quoteattr(str(start))}/>")
        elif start is not None:
            attributes.append(f"start={quoteattr(_format_value(v, start))}")
        head = f"    <{v.type} " + " ".join(attributes)
        lines.append(head + ("/>" if not children else ">" + "".join(children) + f"</{v.type}>"))
    lines.append("  </ModelVariables>")
    lines.append("  <ModelStructure>")
    for vr, v in enumerate(from_decl):
        if v.causality == "output":
            lines.append(f'    <Output valueReference="{vr}"/>')
    for vr, v in enumerate(from_decl):
        if v.causality in ("output", "calculatedParameter"):
            lines.append(f'    <InitialUnknown valueReference="{vr}"/>')
    lines.append("  </ModelStructure>")
    lines.append("</fmiModelDescription>")
    return "\n".join(lines) + "\n"


# ---- values shared with the C layer -------------------------------------------------------------------
class Values:
    """The FMU's variables as attributes: scalars as Python numbers, arrays as numpy views of the
    buffers the C layer reads and writes, strings as ``str``. Assigning writes into the buffer.

    The 1 kHz path goes through here several times per step, so each variable is a property of
    a class made for the instance's current buffers (remade whenever the runtime reallocates
    them): reading or writing a scalar costs about 0.1 us, half of a ``__getattribute__`` lookup.
    Arrays are views of the FMU's own memory, so a model may also write an output in place
    (``values.x[...] = ...``, or its kernels writing into ``values.x``)."""

    __slots__ = ("_instance",)

    def __init__(self, instance: "RuntimeInstance"):
        object.__setattr__(self, "_instance", instance)

    def _rebind(self) -> None:
        instance = self._instance
        counts, references = instance.set_count_view, instance.references

        def set_count(values, name: str) -> int:
            return counts[references[name]]
        set_count.__doc__ = Values.set_count.__doc__

        def resource_folder(values) -> Path | None:
            return instance.resources
        resource_folder.__doc__ = Values.resource_folder.__doc__
        namespace = {"__slots__": (), "set_count": set_count, "resource_folder": resource_folder}
        for vr, v in enumerate(instance.variables):
            namespace[v.name] = _value_property(instance, vr, v)
        object.__setattr__(self, "__class__", type(f"{instance.model_name}Values", (Values,), namespace))

    def __getattr__(self, name):  # only for names that are no variable
        raise AttributeError(f"{_instance_of(self).model_name} has no variable {name!r}")

    def set_count(self, name: str) -> int:
        """How often the importer has set ``name`` (e.g. to tell whether an optional input is used)."""
        instance = _instance_of(self)
        return instance.set_count_view[instance.references[name]]

    def resource_folder(self) -> Path | None:
        """This instance's extracted ``resources/`` folder: the files the FMU carries (the package
        module may have been imported from another instance's folder, since removed)."""
        return _instance_of(self).resources

    def __deepcopy__(self, memo):  # the values are saved with the buffers, not with the model
        return self

    def __reduce__(self):
        raise TypeError("Values are not part of the model state")


_instance_of = Values._instance.__get__


def _value_property(instance: "RuntimeInstance", vr: int, variable) -> property:
    """Read and write access to one variable's buffer (or the C layer's string)."""
    if variable.type == "String":
        def get_string(values):
            return instance.read_string(vr)

        def set_string(values, value):
            instance.write_string(vr, value)
        return property(get_string, set_string, doc=variable.description)
    if variable.shape:
        array = instance.views[vr]

        def get_array(values):
            return array

        def set_array(values, value):
            array[...] = value
        return property(get_array, set_array, doc=variable.description)
    scalar = memoryview(instance.buffers[vr])  # reads and writes a Python number several times faster than numpy

    def get_scalar(values):
        return scalar[0]

    def set_scalar(values, value):
        scalar[0] = value
    return property(get_scalar, set_scalar, doc=variable.description)


class _Snapshot:
    """An FMU state: every buffer, the strings, the set counters and the adapter's attributes;
    ``from_bytes`` when it was read from serialized bytes (checked against the model when set)."""

    def __init__(self, buffers, strings, set_counts, adapter_class, adapter_state, values_attributes,
                 from_bytes=False):
        self.from_bytes = from_bytes
        self.buffers = buffers
        self.strings = strings
        self.set_counts = set_counts
        self.adapter_class = adapter_class
        self.adapter_state = adapter_state
        self.values_attributes = values_attributes


def _mismatch(value, live, path: str, codec, seen: set) -> str | None:
    """Where ``value`` (a state's) differs in kind from ``live`` (the model's), or None. Absent parts
    (None on either side, an attribute on one side) and lengths may differ: they change at run time."""
    if value is None or live is None:
        return None
    if type(value) is not type(live):
        if isinstance(value, (int, float)) and isinstance(live, (int, float)) and type(value) is not bool \
                and type(live) is not bool:
            return None
        return f"{path} is a {type(value).__name__}, the model's a {type(live).__name__}"
    if id(value) in seen:
        return None
    seen.add(id(value))
    if isinstance(value, np.ndarray):
        if value.dtype != live.dtype or value.ndim != live.ndim:
            return f"{path} is a {value.dtype} array of {value.ndim} dimensions, the model's {live.dtype} of {live.ndim}"
        return None
    if isinstance(value, dict):
        for key in value.keys() & live.keys():
            found = _mismatch(value[key], live[key], f"{path}[{key!r}]", codec, seen)
            if found:
                return found
        return None
    if isinstance(value, (list, tuple)):
        if len(value) == len(live):
            for k, (a, b) in enumerate(zip(value, live)):
                found = _mismatch(a, b, f"{path}[{k}]", codec, seen)
                if found:
                    return found
        return None
    if codec.owns(value) and hasattr(value, "__dict__"):
        # attributes made on first use (work arrays) may be on one side only: the common ones must agree
        mine, theirs = vars(value), vars(live)
        for key in mine.keys() & theirs.keys():
            found = _mismatch(mine[key], theirs[key], f"{path}.{key}", codec, seen)
            if found:
                return found
    return None


class _Router(logging.Handler):
    """Forwards a package's warnings to the FMU instance whose call is running in this thread."""

    def __init__(self):
        super().__init__(level=logging.WARNING)
        self.current = threading.local()

    def emit(self, record):
        instance = getattr(self.current, "instance", None)
        if instance is None:
            return
        try:
            status = ERROR if record.levelno >= logging.ERROR else WARNING
            instance.log(status, f"{record.name}: {record.getMessage()}")
            if status == WARNING:
                instance.warned()
        except Exception:  # logging must never fail a call
            pass


class RuntimeInstance:
    """One FMU instance: buffers registered with the C layer, the values, the adapter (model)."""

    def __init__(self, declaration, instance_name: str, c_instance: int, callbacks, router: _Router,
                 token: str = "", codec=None, resources: Path | None = None):
        self.declaration = declaration
        #: this instance's extracted resources/ (a package loaded before may live in another one)
        self.resources = resources
        self.token = token
        self.codec = codec  # the FMU state's bytes (state_format.Codec over the package's classes)
        self.model_name = declaration.model_name
        self.instance_name = instance_name
        self.variables = declaration.all_variables()
        self.references = {v.name: vr for vr, v in enumerate(self.variables)}
        self._c = ctypes.c_void_p(c_instance)
        self._register, counters, step_io, self._log, self._get_string, self._set_string = callbacks
        self._router = router
        self._current = router.current  # this thread's running instance, for the package's log records
        self.buffers: list[np.ndarray | None] = [None] * len(self.variables)
        self.views: list[np.ndarray | None] = [None] * len(self.variables)
        self.values = Values(self)
        self.set_counts = np.zeros(len(self.variables), dtype=np.uint64)
        self.set_count_view = memoryview(self.set_counts)  # plain ints, read by Values.set_count
        counters(self._c, self.set_counts.ctypes.data, len(self.variables))
        self._step_io = np.zeros(STEP_IO_SIZE)
        self._step_io[IO_MAX_SUBSTEPS] = declaration.max_steps_per_call
        self._io = memoryview(self._step_io)
        if step_io(self._c, self._step_io.ctypes.data, self._step_io.size) != 0:
            raise MemoryError("the FMI layer did not take the step exchange")
        self.adapter = None
        self._allocate(reset=True)

    # -- buffers ------------------------------------------------------------------------------------
    def shape_of(self, variable) -> tuple:
        shape = []
        for d in variable.shape:
            shape.append(int(self.buffers[self.references[d]][0]) if isinstance(d, str) else int(d))
        return tuple(shape)

    def _allocate(self, reset: bool) -> None:
        """(Re)allocate the buffers whose size changed (all of them when ``reset``) and register them."""
        changed = reset
        for vr, v in enumerate(self.variables):
            if v.type == "String":
                if reset or self.buffers[vr] is None:
                    self._register(self._c, vr, TYPE_CODES[v.type], CAUSALITY_CODES[v.causality],
                                   VARIABILITY_CODES[v.variability], None, 1, v.name.encode(),
                                   *_register_limit(v), b"")
                    self._set_string(self._c, vr, 0, str(v.start if v.start is not None else "").encode())
                    self.buffers[vr] = np.zeros(0)  # marks "registered"
                continue
            shape = self.shape_of(v)
            size = int(np.prod(shape)) if shape else 1
            dtype = DTYPES[v.type]
            current = self.buffers[vr]
            if not reset and current is not None and current.size == size:
                continue
            nbytes = size * np.dtype(dtype).itemsize
            if nbytes > MAX_ARRAY_BYTES:
                raise ValueError(
                    f"{v.name} would need {nbytes / 2**30:.1f} GiB ({' x '.join(map(str, shape))} values): check "
                    f"the structural parameters {', '.join(d for d in v.shape if isinstance(d, str))}")
            buffer = np.zeros(size, dtype=dtype)
            changed = True
            start = _resolved_start(v, shape) if v.causality != "independent" else None
            if start is not None:
                buffer[:] = np.ravel(np.asarray(start)).astype(dtype)
            self.buffers[vr] = buffer
            self.views[vr] = buffer.reshape(shape) if shape else buffer
            status = self._register(self._c, vr, TYPE_CODES[v.type], CAUSALITY_CODES[v.causality],
                                    VARIABILITY_CODES[v.variability], buffer.ctypes.data, size, v.name.encode(),
                                    *_register_limit(v), self._size_text(v, shape))
            if status != 0:
                raise MemoryError(f"the FMI layer could not register {v.name}")
        if changed:
            self.values._rebind()
            self._time = memoryview(self.buffers[self.references["time"]])  # written every step

    def _size_text(self, variable, shape: tuple) -> bytes:
        """What sizes an array ("'x' is sized by n_tool_points = 31 x 3"), with the coupling rule the
        structural parameter follows, for the C layer's message on a wrong number of values."""
        named = [d for d in variable.shape if isinstance(d, str)]
        if not named:
            return b""
        dims = " x ".join(f"{d} = {n}" if isinstance(d, str) else str(n) for d, n in zip(variable.shape, shape))
        rules = [self.declaration.size_rules[d] for d in dict.fromkeys(named) if d in self.declaration.size_rules]
        return (f"'{variable.name}' is sized by {dims}" + "".join(f"; {r}" for r in rules)).encode()

    # Strings live in the C layer (numbers in the buffers, reached through Values).
    def read_string(self, vr: int) -> str:
        raw = self._get_string(self._c, vr, 0)
        return raw.decode() if raw is not None else ""

    def write_string(self, vr: int, value) -> None:
        self._set_string(self._c, vr, 0, str(value).encode())

    # -- logging ---------------------------------------------------------------------------------------
    def log(self, status: int, message: str) -> None:
        self._log(self._c, status, f"{self.model_name} instance '{self.instance_name}': {message}".encode())

    def _fail(self, call: str, exc: BaseException) -> None:
        if isinstance(exc, KeyboardInterrupt):  # the C layer logs it and hands it back to the importer
            raise exc
        if isinstance(exc, ValueError):  # the model's own refusals name the parameter and the fix
            reason = str(exc)
        elif isinstance(exc, MemoryError):
            reason = "out of memory: use a coarser mesh or fewer elements, or free memory in the importer's process"
        else:  # no refusal the model meant: say so, and how to get what a report needs
            reason = (f"an internal error of the {self.model_name} model ({type(exc).__name__}: {exc}); this is a "
                      "defect of the FMU, not of the importer's input: report it with this log (the environment "
                      "variable AAA_COSIM_FMU_TRACEBACK=1 adds the traceback)")
        if os.environ.get("AAA_COSIM_FMU_TRACEBACK"):  # for the FMU's developers
            reason += "\n" + "".join(traceback.format_exception(exc))
        self.log(ERROR, f"{call} failed: {reason}")

    # -- limits -----------------------------------------------------------------------------------------
    def check_limits(self, causality: str, buffers=None) -> None:
        """Raise ValueError naming the first variable of ``causality`` whose value is outside its limit
        (variable, value, range and why), or a structural parameter no array could have; in the FMU's
        buffers, or in ``buffers`` (a state's, before it is set)."""
        buffers = self.buffers if buffers is None else buffers
        for vr, v in enumerate(self.variables):
            if v.causality != causality or v.type == "String":
                continue
            values = buffers[vr]
            if v.causality == "structuralParameter" and int(values[0]) > 10**9:
                raise ValueError(f"{v.name} = {int(values[0])} is not a plausible array size")
            if v.limit is None:
                continue
            low, high = v.limit.minimum, v.limit.maximum
            inside = (values >= low) & (values <= high)
            if not inside.all():
                index = int(np.flatnonzero(~inside)[0])
                value = values[index].item()
                where = f"{v.name}[{index}]" if values.size > 1 else v.name
                raise ValueError(f"{where} = {value!r}{' ' + v.unit if v.unit else ''} is {v.outside_limit(value)}")

    # -- calls from the C layer -------------------------------------------------------------------------
    def configure(self) -> None:
        self.check_limits("structuralParameter")
        self._allocate(reset=False)
        self.adapter = None

    def initialize(self, start_time: float) -> float:
        """Build the model from the parameters; its internal step, or -1 when it failed (logged)."""
        self._router.current.instance = self
        try:
            self.adapter = None
            self.check_limits("parameter")
            step = float(self.buffers[self.references["internal_step"]][0])
            if not (math.isfinite(step) and step > 0):
                raise ValueError(f"internal_step must be a positive number of seconds (got {step})")
            self._time[0] = start_time
            self.adapter = self.declaration.adapter(self.values)
            return step
        except BaseException as exc:
            self.adapter = None
            self._fail("fmi3ExitInitializationMode (building the model)", exc)
            return -1.0
        finally:
            self._router.current.instance = None

    def do_step(self) -> None:
        """One fmi3DoStep: from the step exchange's t, ``substeps`` internal steps of ``h / substeps``.
        The exchange arrives with status OK and all steps completed; a failure writes ERROR and the
        steps it completed, a warning logged during the step WARNING (``warned``)."""
        io = self._io
        t, h, substeps = io[IO_TIME], io[IO_STEP], io[IO_SUBSTEPS]
        current = self._current
        current.instance = self
        done = 0
        try:
            if substeps == 1.0:  # h / 1 is h: the same numbers as the loop
                self.adapter.step(t, h)
            else:
                adapter, substeps = self.adapter, int(substeps)
                dt = h / substeps
                for k in range(substeps):
                    adapter.step(t + k * dt if k else t, dt)
                    done += 1
        except BaseException as exc:
            io[IO_COMPLETED] = done
            io[IO_STATUS] = ERROR
            self._fail(f"fmi3DoStep(t = {t:.9g}, h = {h:.9g}) at t = {t + done * (h / substeps):.9g}", exc)
            return
        finally:
            current.instance = None
        self._time[0] = t + h

    def warned(self) -> None:
        """A warning was logged during this call: a step reports fmi3Warning."""
        if self._io[IO_STATUS] < WARNING:
            self._io[IO_STATUS] = WARNING

    def terminate(self) -> None:
        terminate = getattr(self.adapter, "terminate", None)
        if terminate is not None:
            terminate()

    def reset(self) -> None:
        self.adapter = None
        self.buffers = [None] * len(self.variables)
        self.views = [None] * len(self.variables)
        self.set_counts[:] = 0
        self._allocate(reset=True)

    def free(self) -> None:
        self.adapter = None
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:
                pass

    # -- FMU state ----------------------------------------------------------------------------------------
    def get_state(self) -> _Snapshot:
        strings = {vr: self.read_string(vr) for vr, v in enumerate(self.variables) if v.type == "String"}
        buffers = [None if v.type == "String" else self.buffers[vr].copy() for vr, v in enumerate(self.variables)]
        if self.adapter is None:
            return _Snapshot(buffers, strings, self.set_counts.copy(), None, None, ())
        if not self.declaration.saves_state:
            raise ValueError(f"{self.model_name} cannot save its state (canGetAndSetFMUState is false in its "
                             "modelDescription.xml): its model holds other FMUs' instances")
        state = {k: v for k, v in vars(self.adapter).items() if not isinstance(v, Values)}
        values_attributes = tuple(k for k, v in vars(self.adapter).items() if isinstance(v, Values))
        return _Snapshot(buffers, strings, self.set_counts.copy(), type(self.adapter), copy.deepcopy(state),
                         values_attributes)

    def set_state(self, snapshot: _Snapshot) -> float:
        """Restore ``snapshot``: 1.0; 0.0 when a state read from bytes was refused (logged) and the
        instance is as it was. An exception: the restore failed part way."""
        if snapshot.from_bytes and snapshot.adapter_class is not None:
            try:
                self._check_model_state(snapshot)
            except StateFormatError as exc:
                self.log(ERROR, f"fmi3SetFMUState: refused, nothing was set: {exc}")
                return 0.0
        self._apply(snapshot)
        return 1.0

    def _check_model_state(self, snapshot: _Snapshot) -> None:
        """A state read from bytes must hold the model its parameters build: the same classes, the
        same attributes, arrays of the same types and dimensions (their lengths may change at run
        time). The model to compare with is the live one when the parameters are the same, else one
        built from the state's parameters; on any mismatch the instance is left as it was."""
        template, before = self.adapter, None
        parameters = [vr for vr, v in enumerate(self.variables)
                      if v.causality in ("parameter", "structuralParameter")]
        same = template is not None and all(
            self.read_string(vr) == snapshot.strings[vr] if self.variables[vr].type == "String"
            else np.array_equal(self.buffers[vr], snapshot.buffers[vr]) for vr in parameters)
        try:
            if not same:
                before = self.get_state()
                self._apply(_Snapshot(snapshot.buffers, snapshot.strings, snapshot.set_counts, None, None, ()))
                try:
                    template = self.declaration.adapter(self.values)
                except Exception as exc:
                    raise StateFormatError(f"this serialized state's parameters do not build a model ({exc})") \
                        from None
            live = {k: v for k, v in vars(template).items() if not isinstance(v, Values)}
            mismatch = _mismatch(snapshot.adapter_state, live, "model", self.codec, set())
            if mismatch:
                raise StateFormatError(f"this serialized state's model does not match the model its parameters "
                                       f"build: {mismatch}")
        except BaseException:
            if before is not None:
                self._apply(before)
            raise

    def _apply(self, snapshot: _Snapshot) -> None:
        for vr, v in enumerate(self.variables):  # sizes first: they size the other buffers
            if v.causality == "structuralParameter":
                self.buffers[vr][:] = snapshot.buffers[vr]
        self._allocate(reset=False)
        for vr, v in enumerate(self.variables):
            if v.type == "String":
                self.write_string(vr, snapshot.strings[vr])
            else:
                self.buffers[vr][:] = snapshot.buffers[vr]
        self.set_counts[:] = snapshot.set_counts
        if snapshot.adapter_class is None:
            self.adapter = None
            return
        adapter = snapshot.adapter_class.__new__(snapshot.adapter_class)
        adapter.__dict__.update(copy.deepcopy(snapshot.adapter_state))
        for name in snapshot.values_attributes:
            setattr(adapter, name, self.values)
        self.adapter = adapter

    def discard(self, snapshot: _Snapshot) -> None:
        """Free a state's memory now (fmi3FreeFMUState). Its objects are the snapshot's own copies and
        refer to each other (a force field and its law), which reference counting alone would leave
        to the cycle collector, holding tens of MB per Tissue state until it runs: empty them (only
        the package's own objects and plain containers; anything else may be shared)."""
        seen, stack = set(), [snapshot.adapter_state]
        while stack:
            item = stack.pop()
            if id(item) in seen:
                continue
            seen.add(id(item))
            if type(item) is dict:
                stack.extend(item.values())
                item.clear()
            elif type(item) in (list, tuple):
                stack.extend(item)
                if type(item) is list:
                    item.clear()
            elif self.codec.owns(item) and hasattr(item, "__dict__"):
                stack.append(vars(item))
        snapshot.adapter_state = snapshot.buffers = None

    def serialize(self, snapshot: _Snapshot, mode: int, built: int, steps_done: int, start_time: float,
                  step_size: float) -> bytes:
        """The state's bytes (state_format.py): data only, with the FMU's identity and a SHA-256."""
        document = {
            "model": self.model_name, "token": self.token, "layer": [mode, built, steps_done, start_time, step_size],
            "variables": [[v.name, v.type] for v in self.variables],
        }
        trees = {
            "buffers": snapshot.buffers, "strings": {str(k): v for k, v in snapshot.strings.items()},
            "set_counts": snapshot.set_counts, "adapter_class": snapshot.adapter_class,
            "adapter_state": snapshot.adapter_state, "values_attributes": snapshot.values_attributes,
        }
        return self.codec.encode(document, trees)

    def deserialize(self, data: bytes) -> tuple:
        """(snapshot, mode, built, steps_done, start_time, step_size) from a state's bytes; every
        field is checked before anything is returned (the C layer checks the mode); StateFormatError
        (a ValueError) names what is wrong."""
        document, trees = self.codec.decode(data)
        if document.get("model") != self.model_name:
            raise StateFormatError(f"this serialized state is of {document.get('model')!r}, not of {self.model_name}")
        if document.get("token") != self.token:
            raise StateFormatError(
                f"this serialized state is from another build of {self.model_name} (instantiationToken "
                f"{document.get('token')!r}, this FMU {self.token!r}): restore it with the FMU that wrote it")
        if document.get("variables") != [[v.name, v.type] for v in self.variables]:
            raise StateFormatError("this serialized state declares other variables than this FMU")
        layer = document.get("layer")
        if not (isinstance(layer, list) and len(layer) == 5 and all(type(x) in (int, float) for x in layer)
                and type(layer[0]) is int and layer[1] in (0, 1) and type(layer[2]) is int):
            raise StateFormatError("this serialized state has a malformed layer record")
        mode, built, steps_done, start_time, step_size = layer
        if not 0 <= steps_done <= 2 ** 53:
            raise StateFormatError(f"this serialized state has {steps_done} internal steps done, out of range")
        if not (math.isfinite(start_time) and math.isfinite(step_size) and step_size >= 0.0):
            raise StateFormatError(f"this serialized state has start time {start_time!r} and step {step_size!r}; "
                                   "both must be finite and the step positive")
        snapshot = self._checked_snapshot(trees)
        internal_step = float(snapshot.buffers[self.references["internal_step"]][0])
        if built and step_size != internal_step:
            raise StateFormatError(f"this serialized state steps by {step_size!r} s but its internal_step is "
                                   f"{internal_step!r} s")
        if not math.isfinite(start_time + steps_done * step_size):
            raise StateFormatError("this serialized state's time is not finite")
        return snapshot, mode, int(built), steps_done, float(start_time), float(step_size)

    def _checked_snapshot(self, trees: dict) -> _Snapshot:
        """The snapshot of a decoded state after checking every value against this FMU's table."""
        buffers, strings = trees.get("buffers"), trees.get("strings")
        if not (isinstance(buffers, list) and len(buffers) == len(self.variables)):
            raise StateFormatError("this serialized state holds another number of variables than this FMU")
        for vr, v in enumerate(self.variables):
            b = buffers[vr]
            if v.type == "String":
                if b is not None:
                    raise StateFormatError(f"this serialized state holds numbers for the string {v.name}")
            elif not (isinstance(b, np.ndarray) and b.ndim == 1 and b.dtype == DTYPES[v.type]):
                raise StateFormatError(f"this serialized state holds no {v.type} values for {v.name}")
        sizes = self._sizes(buffers)
        for vr, v in enumerate(self.variables):
            if v.type != "String" and buffers[vr].size != sizes[vr]:
                raise StateFormatError(f"this serialized state holds {buffers[vr].size} values for {v.name}, whose "
                                       f"structural parameters make it {sizes[vr]}")
            if v.type == "Float64" and v.causality != "output" and not np.isfinite(buffers[vr]).all():
                raise StateFormatError(f"this serialized state holds a NaN or infinity in {v.name}")
        for causality in ("structuralParameter", "parameter"):
            try:
                self.check_limits(causality, buffers)
            except ValueError as exc:
                raise StateFormatError(f"this serialized state holds {exc}") from None
        expected = {str(vr) for vr, v in enumerate(self.variables) if v.type == "String"}
        if not (isinstance(strings, dict) and set(strings) == expected
                and all(isinstance(s, str) and "\0" not in s for s in strings.values())):
            raise StateFormatError("this serialized state's strings do not match this FMU's string variables")
        set_counts = trees.get("set_counts")
        if not (isinstance(set_counts, np.ndarray) and set_counts.dtype == np.uint64
                and set_counts.shape == (len(self.variables),)):
            raise StateFormatError("this serialized state's set counters do not match this FMU's variables")
        adapter_class, state = trees.get("adapter_class"), trees.get("adapter_state")
        attributes = trees.get("values_attributes")
        if adapter_class is None:
            if state is not None or attributes != ():
                raise StateFormatError("this serialized state has a model state but no model")
        elif not (adapter_class is self.declaration.adapter and isinstance(state, dict)
                  and all(isinstance(k, str) for k in state) and isinstance(attributes, tuple)
                  and all(isinstance(a, str) and a.isidentifier() and a not in state for a in attributes)):
            raise StateFormatError("this serialized state's model is not the one this FMU builds")
        return _Snapshot(buffers, {int(k): v for k, v in strings.items()}, set_counts, adapter_class, state,
                         attributes, from_bytes=True)

    def _sizes(self, buffers) -> list[int]:
        """Each variable's number of values when ``buffers`` hold the structural parameters."""
        sizes = []
        for v in self.variables:
            size = 1
            for d in v.shape:
                n = int(buffers[self.references[d]][0]) if isinstance(d, str) else int(d)
                if not 0 <= n <= 10**9:
                    raise StateFormatError(f"this serialized state sets {d} = {n}, which no array can have")
                size *= n
            sizes.append(size)
        return sizes


# ---- instantiation ------------------------------------------------------------------------------------
#: sys._aaa_cosim_embedded of an interpreter the FMI layer started from the runtime the FMU carries
#: (PYTHON_STARTED_CARRIED in python_embed.h)
CARRIED_RUNTIME = 2

_routers: dict[str, _Router] = {}
_codecs: dict[str, object] = {}


def _load_package(resources: Path, unique: str, package: str, token: str):
    """Import the FMU's package from its resources under ``unique`` (never a copy the host has)."""
    module = sys.modules.get(unique)
    if module is not None:
        return module
    package_dir = resources / package
    cache_spec = importlib.util.spec_from_file_location(unique + "__numba_cache", resources / "numba_cache.py")
    cache = importlib.util.module_from_spec(cache_spec)
    cache_spec.loader.exec_module(cache)
    if getattr(sys, "_aaa_cosim_embedded", 0) == CARRIED_RUNTIME:
        cache.use_carried_kernels(resources)
    cache.enable_stable_numba_cache(package_dir, unique)
    spec = importlib.util.spec_from_file_location(unique, package_dir / "__init__.py",
                                                  submodule_search_locations=[str(package_dir)])
    module = importlib.util.module_from_spec(spec)
    module.__fmu_instantiation_token__ = token  # the build loaded under this name (see instantiate)
    sys.modules[unique] = module
    try:
        spec.loader.exec_module(module)
        # Importers may delete the extraction folder while the process lives on and instantiates
        # the FMU again: import every module now so nothing is looked up there later.
        for path in sorted(package_dir.glob("*.py")):
            if path.stem != "__init__":
                importlib.import_module(unique + "." + path.stem)
        # ... and load the cached kernels now, not at their first call inside a step
        cache.load_cached_kernels(unique)
    except BaseException:
        for name in [n for n in sys.modules if n == unique or n.startswith(unique + ".")]:
            del sys.modules[name]
        raise
    return module


def _check_model_description(resources: Path, meta: dict) -> None:
    """Refuse an FMU whose modelDescription.xml is not the one it was built with: an importer reads
    value references, types and sizes from that file, and a changed one would pair them wrongly.
    Some importers extract only the binaries and resources (FMPy's simulate_fmu reads the XML from
    the archive): without the file beside the resources there is nothing to compare."""
    expected = meta.get("model_description_sha256")
    path = resources.parent / "modelDescription.xml"
    if expected is None:
        raise ValueError("resources/fmu.json records no digest of the modelDescription.xml: the FMU is from an "
                         "older build; build it again (python -m orchestration build)")
    try:
        actual = hashlib.sha256(path.read_bytes()).hexdigest()
    except FileNotFoundError:
        return
    except OSError as exc:
        raise ValueError(f"cannot read {path} ({exc.strerror or exc}): extract the FMU where its importer can "
                         "read it") from None
    if actual != expected:
        raise ValueError(f"{path} is not the modelDescription.xml this FMU was built with (its SHA-256 differs): "
                         "the FMU was changed after its build; use the FMU as built, or build it again "
                         "(python -m orchestration build)")


def instantiate(resources: str, model_identifier: str, token: str, instance_name: str, c_instance: int,
                register: int, counters: int, step_io: int, log: int, get_string: int, set_string: int):
    resources = Path(resources)
    meta = json.loads((resources / "fmu.json").read_text())
    if token != meta["instantiation_token"]:
        raise ValueError(f"instantiationToken {token!r} does not match this FMU's {meta['instantiation_token']!r}: "
                         "the modelDescription.xml and the resources are from different builds")
    _check_model_description(resources, meta)
    # A stable name (states serialized by one process load in another, numba's cache refers to
    # it); another build of the same FMU in this process gets a name of its own. Each build has
    # its own copy of this module, so the build under a name is told by the package's token.
    unique = f"{model_identifier}_{meta['package']}"
    loaded = sys.modules.get(unique)
    if loaded is not None and getattr(loaded, "__fmu_instantiation_token__", None) != token:
        unique = f"{unique}_{''.join(c for c in token if c.isalnum())[:16]}"
    package = _load_package(resources, unique, meta["package"], token)
    module_name, _, attribute = meta["declaration"].partition(":")
    declaration = getattr(importlib.import_module(f"{unique}.{module_name}"), attribute)
    router = _routers.get(unique)
    if router is None:
        router = _routers[unique] = _Router()
        package_logger = logging.getLogger(package.__name__)
        package_logger.addHandler(router)
        # the importer hears the messages through the FMI log; not a second time from its root logger
        package_logger.propagate = False
    callbacks = (_REGISTER(register), _COUNTERS(counters), _COUNTERS(step_io), _LOG(log),
                 _GET_STRING(get_string), _SET_STRING(set_string))
    codec = _codecs.get(unique)
    if codec is None:
        modules = [m for n, m in sys.modules.items() if (n == unique or n.startswith(unique + ".")) and m is not None]
        codec = _codecs[unique] = _state_format.Codec(unique, modules)
    return RuntimeInstance(declaration, instance_name, c_instance, callbacks, router, token, codec, resources)

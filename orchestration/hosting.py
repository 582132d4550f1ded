"""Hosting one FMU instance for the master: the component host protocol and its in-process host.

All values crossing the protocol are 1-D float64 arrays; Int32 and Boolean (and the other
integer types) are carried exactly as float64. The hot path (``set_inputs``, ``start_step``,
``finish_step``, ``get_outputs``) calls the FMU's exported functions directly through ctypes
with preallocated value-reference arrays and numpy buffers: FMPy's list-building getters cost
about 900 us for the 8064-value tissue surface, the raw call about 7 us.

Outputs are laid out in one float64 buffer grouped by type, Float64 ports first, so that all
observed Float64 ports are read with one ``fmi3GetFloat64`` call straight into the buffer (the
other types through a small native buffer, converted by one copy per type). The layout is a
pure function of the port lists (:func:`slot_layout`), which is what lets the worker host
(orchestration/worker.py) place the same buffers in shared memory.
"""
from __future__ import annotations

import ctypes
import logging
import shutil
import tempfile
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from .errors import FmuCallError
from .ports import FmuDescription, PortInfo

logger = logging.getLogger(__name__)

FMI_OK, FMI_WARNING, FMI_DISCARD, FMI_ERROR, FMI_FATAL = range(5)

#: FMI type -> numpy dtype of its native buffer. Int64/UInt64 beyond 2**53 do not survive float64.
NATIVE_DTYPES = {
    "Float64": np.float64, "Float32": np.float32,
    "Int8": np.int8, "UInt8": np.uint8, "Int16": np.int16, "UInt16": np.uint16,
    "Int32": np.int32, "UInt32": np.uint32, "Int64": np.int64, "UInt64": np.uint64,
    "Boolean": np.bool_,
}
_LOG_LEVELS = {FMI_OK: logging.INFO, FMI_WARNING: logging.WARNING, FMI_DISCARD: logging.WARNING,
               FMI_ERROR: logging.ERROR, FMI_FATAL: logging.CRITICAL}


@runtime_checkable
class ComponentHost(Protocol):
    """What the master calls on every stepped component (see prompts/orch_iface.md)."""

    name: str
    ports: dict[str, PortInfo]
    messages: list[tuple[int, str]]

    def instantiate(self) -> None: ...
    def set_values(self, values: dict[str, object]) -> None: ...
    def enter_initialization(self, start_time: float) -> None: ...
    def configure(self, inputs: list[str], observed: list[str]) -> None: ...
    def set_inputs(self, values: dict[str, np.ndarray]) -> None: ...
    def get_outputs(self) -> dict[str, np.ndarray]: ...
    def get_values(self, names: list[str]) -> dict[str, np.ndarray]: ...
    def exit_initialization(self) -> None: ...
    def start_step(self, t: float, h: float, inputs: dict[str, np.ndarray]) -> None: ...
    def finish_step(self) -> dict[str, np.ndarray]: ...
    def wait_handle(self) -> object | None: ...
    def terminate(self) -> None: ...


class PortConfigurationError(ValueError):
    """A port list given to ``configure`` names a port that cannot be used that way."""


def check_port_lists(component: str, ports: dict[str, PortInfo], inputs: list[str],
                     observed: list[str]) -> None:
    """Raise :class:`PortConfigurationError` unless every name is a usable numeric port."""
    for kind, names in (("input", inputs), ("observed", observed)):
        if len(set(names)) != len(names):
            duplicates = sorted({n for n in names if names.count(n) > 1})
            raise PortConfigurationError(f"{component}: {kind} ports listed twice: {', '.join(duplicates)}")
        for name in names:
            port = ports.get(name)
            if port is None:
                raise PortConfigurationError(
                    f"{component} has no port {name!r} ({kind}); its ports are: {', '.join(sorted(ports))}")
            if port.type not in NATIVE_DTYPES:
                raise PortConfigurationError(
                    f"{component}.{name} is a {port.type} variable: only numeric and Boolean ports can be "
                    f"connected (set strings with set_values)")
            if kind == "input" and port.causality not in ("input", "parameter"):
                raise PortConfigurationError(
                    f"{component}.{name} is a {port.causality}, not an input: it cannot be written while stepping")


def slot_layout(ports: dict[str, PortInfo], names: list[str]) -> tuple[dict[str, tuple[int, int]], int]:
    """Offsets ``name -> (start, stop)`` in one float64 buffer, grouped by type (Float64 first), and its size."""
    order = sorted(range(len(names)), key=lambda i: (ports[names[i]].type != "Float64", ports[names[i]].type, i))
    layout, offset = {}, 0
    for i in order:
        size = ports[names[i]].size
        layout[names[i]] = (offset, offset + size)
        offset += size
    return layout, offset


def _pointer(array: np.ndarray, fmi_type: str):
    ctype = np.ctypeslib.as_ctypes_type(np.dtype(NATIVE_DTYPES[fmi_type]))
    return array.ctypes.data_as(ctypes.POINTER(ctype))


def _value_references(vrs: list[int]):
    from fmpy.fmi3 import fmi3ValueReference

    return (fmi3ValueReference * len(vrs))(*vrs)


@dataclass
class _InputPort:
    """A writable port: its float64 slot and, for non-Float64 types, the native buffer it is cast to."""

    name: str
    call: str
    size: int
    vr: object
    slot: np.ndarray
    native: np.ndarray
    pointer: object
    setter: object
    exact: bool  # integer and Boolean values must survive the cast unchanged


@dataclass
class _OutputGroup:
    """Observed ports of one type, read with one call into ``native`` then cast into ``slot``."""

    call: str
    count: int
    size: int
    vrs: object
    slot: np.ndarray
    native: np.ndarray
    pointer: object
    getter: object
    cast: bool


class InProcessFmu:
    """One FMU instance loaded into this process through FMPy's ``FMU3Slave``.

    ``log_to_logger=False`` keeps log messages only in ``messages`` (the worker process uses
    that: it sends them to the master, which logs them).
    """

    def __init__(self, name: str, description: FmuDescription, *, log_to_logger: bool = True):
        self.name = name
        self.description = description
        self.ports: dict[str, PortInfo] = dict(description.ports)
        self.messages: list[tuple[int, str]] = []
        self._logger = logging.getLogger(f"orchestration.fmu.{name}") if log_to_logger else None
        self._slave = None
        self._component = None
        self._unzip_dir: str | None = None
        self._initialized = False
        self._terminated = False
        self._failed = False  # after fmi3Error the standard allows no fmi3Terminate
        self._time: float | None = None
        self._inputs: dict[str, _InputPort] = {}
        self._input_list: list[_InputPort] = []
        self._groups: list[_OutputGroup] = []
        self._output_views: dict[str, np.ndarray] = {}
        self._configured = False

    # -- lifecycle ---------------------------------------------------------------------------------
    def instantiate(self) -> None:
        from fmpy import extract
        from fmpy.fmi3 import FMU3Slave, fmi3Boolean, fmi3Float64

        if self._slave is not None:
            raise RuntimeError(f"{self.name}: instantiate() was called twice")
        description = self.description
        self._unzip_dir = tempfile.mkdtemp(prefix=f"fmu_{self.name}_")
        try:
            extract(str(description.path), self._unzip_dir)
            self._slave = FMU3Slave(guid=description.instantiation_token, unzipDirectory=self._unzip_dir,
                                    modelIdentifier=description.model_identifier, instanceName=self.name)
            self._slave.instantiate(loggingOn=True, logMessage=self._on_log)
        except Exception as exc:  # FMPy raises plain Exception for a failed load/instantiation
            reason = self._logged_reason(0) if self.messages else str(exc)
            self._release_library()
            raise FmuCallError(self.name, "fmi3InstantiateCoSimulation", None, reason) from None
        self._component = self._slave.component
        functions = self._slave._functions
        self._raw = functions
        self._do_step_raw = functions["fmi3DoStep"]
        # fmi3DoStep's out-arguments, allocated once
        self._event_needed = fmi3Boolean()
        self._terminate_requested = fmi3Boolean()
        self._early_return = fmi3Boolean()
        self._last_time = fmi3Float64()
        self._step_refs = tuple(ctypes.pointer(x) for x in (self._event_needed, self._terminate_requested,
                                                             self._early_return, self._last_time))

    def set_values(self, values: dict[str, object]) -> None:
        """Parameters and start values of any FMI type; structural parameters are set first."""
        self._require_instance("set_values")
        unknown = [n for n in values if n not in self.ports]
        if unknown:
            raise PortConfigurationError(f"{self.name} has no variable(s) {', '.join(map(repr, unknown))}; "
                                         f"its variables are: {', '.join(sorted(self.ports))}")
        # every value is converted (and refused) before any call, so a refusal changes nothing
        converted = {name: _convert_for_setter(self.name, self.ports[name], value) for name, value in values.items()}
        for name in converted:
            if not hasattr(self._slave, f"set{self.ports[name].type}"):
                raise PortConfigurationError(f"{self.name}.{name}: setting {self.ports[name].type} variables is "
                                             "not supported")
        structural = [n for n in converted if self.ports[n].causality == "structuralParameter"]
        if structural:  # FMI 3.0: structural parameters are set in Configuration Mode
            self._checked("fmi3EnterConfigurationMode", self._slave.enterConfigurationMode, len(self.messages))
            try:
                for name in structural:
                    self._set_value(name, converted[name])
            finally:
                self._checked("fmi3ExitConfigurationMode", self._slave.exitConfigurationMode, len(self.messages))
        for name in converted:
            if name not in structural:
                self._set_value(name, converted[name])

    def _set_value(self, name: str, converted: list) -> None:
        port = self.ports[name]
        setter = getattr(self._slave, f"set{port.type}")
        mark = len(self.messages)
        self._checked(f"fmi3Set{port.type}({name})", lambda: setter([port.value_reference], converted), mark)

    def get_values(self, names: list[str]) -> dict[str, np.ndarray]:
        """Current values of numeric variables of any causality, as float64 arrays (not the hot path:
        calculated parameters such as surface triangles, read once)."""
        self._require_instance("get_values")
        result: dict[str, np.ndarray] = {}
        for name in names:
            port = self.ports.get(name)
            if port is None:
                raise PortConfigurationError(f"{self.name} has no variable {name!r}")
            getter = getattr(self._slave, f"get{port.type}", None)
            if getter is None or port.type == "String":
                raise PortConfigurationError(f"{self.name}.{name}: reading {port.type} variables is not supported")
            box: list = []
            mark = len(self.messages)
            self._checked(f"fmi3Get{port.type}({name})",
                          lambda: box.append(getter([port.value_reference], nValues=port.size)), mark)
            result[name] = np.asarray(box[0], dtype=np.float64).reshape(port.size)
        return result

    def enter_initialization(self, start_time: float) -> None:
        self._require_instance("enter_initialization")
        self._time = float(start_time)
        mark = len(self.messages)
        status = self._raw["fmi3EnterInitializationMode"](self._component, False, 0.0, self._time, False, 0.0)
        self._check("fmi3EnterInitializationMode", status, mark)
        self._initialized = True

    def exit_initialization(self) -> None:
        self._require_instance("exit_initialization")
        mark = len(self.messages)
        status = self._raw["fmi3ExitInitializationMode"](self._component)
        self._check("fmi3ExitInitializationMode", status, mark)

    def configure(self, inputs: list[str], observed: list[str]) -> None:
        inputs, observed = list(inputs), list(observed)
        check_port_lists(self.name, self.ports, inputs, observed)
        _, in_size = slot_layout(self.ports, inputs)
        _, out_size = slot_layout(self.ports, observed)
        self._bind(inputs, observed, np.zeros(in_size), np.zeros(out_size))

    def _bind(self, inputs: list[str], observed: list[str], in_buffer: np.ndarray, out_buffer: np.ndarray) -> None:
        """Build the ports over float64 buffers laid out by :func:`slot_layout` (maybe shared memory)."""
        self._require_instance("configure")
        in_layout, _ = slot_layout(self.ports, inputs)
        out_layout, _ = slot_layout(self.ports, observed)
        self._inputs = {}
        for name in inputs:
            port = self.ports[name]
            start, stop = in_layout[name]
            slot = in_buffer[start:stop]
            is_float64 = port.type == "Float64"
            native = slot if is_float64 else np.zeros(port.size, dtype=NATIVE_DTYPES[port.type])
            self._inputs[name] = _InputPort(
                name=name, call=f"fmi3Set{port.type}({name})", size=port.size,
                vr=_value_references([port.value_reference]), slot=slot, native=native,
                pointer=_pointer(native, port.type), setter=self._raw[f"fmi3Set{port.type}"],
                exact=port.type not in ("Float64", "Float32"))
        self._input_list = [self._inputs[n] for n in inputs]
        self._groups = []
        by_type: dict[str, list[str]] = {}
        for name in sorted(observed, key=lambda n: out_layout[n][0]):
            by_type.setdefault(self.ports[name].type, []).append(name)
        for fmi_type, names in by_type.items():
            start, stop = out_layout[names[0]][0], out_layout[names[-1]][1]
            slot = out_buffer[start:stop]
            cast = fmi_type != "Float64"
            native = np.zeros(stop - start, dtype=NATIVE_DTYPES[fmi_type]) if cast else slot
            self._groups.append(_OutputGroup(
                call=f"fmi3Get{fmi_type}({', '.join(names)})", count=len(names), size=stop - start,
                vrs=_value_references([self.ports[n].value_reference for n in names]), slot=slot,
                native=native, pointer=_pointer(native, fmi_type), getter=self._raw[f"fmi3Get{fmi_type}"],
                cast=cast))
        self._output_views = {name: out_buffer[a:b] for name, (a, b) in out_layout.items()}
        self._configured = True

    # -- hot path ----------------------------------------------------------------------------------
    def set_inputs(self, values: dict[str, np.ndarray]) -> None:
        inputs = self._inputs
        for name, value in values.items():
            port = inputs.get(name)
            if port is None:
                raise self._unconfigured_input(name)
            value = np.asarray(value, dtype=np.float64)
            if value.size != port.size:
                raise ValueError(f"{self.name}.{name} expects {port.size} value(s), got {value.size}")
            np.copyto(port.slot, value.reshape(port.size))
            self._push(port)

    def _push(self, port: _InputPort) -> None:
        """Write the values in ``port.slot`` to the FMU."""
        mark = len(self.messages)
        if port.native is not port.slot:
            np.copyto(port.native, port.slot, casting="unsafe")
            if port.exact and not np.array_equal(port.native, port.slot):
                raise ValueError(f"{self.name}.{port.name} takes whole numbers"
                                 f"{' (0 or 1)' if port.native.dtype == np.bool_ else ''}; got {port.slot.tolist()}")
        status = port.setter(self._component, port.vr, 1, port.pointer, port.size)
        if status or len(self.messages) != mark:
            self._check(port.call, status, mark)

    def _push_indices(self, indices) -> None:
        """Write the inputs at ``indices`` of the configured input list (all when None)."""
        ports = self._input_list if indices is None else [self._input_list[i] for i in indices]
        for port in ports:
            self._push(port)

    def _pull(self) -> None:
        """Read every observed port into the output buffer."""
        component = self._component
        if component is None:
            self._require_instance("get_outputs")
        for group in self._groups:
            mark = len(self.messages)
            status = group.getter(component, group.vrs, group.count, group.pointer, group.size)
            if status or len(self.messages) != mark:
                self._check(group.call, status, mark)
            if group.cast:
                np.copyto(group.slot, group.native, casting="unsafe")

    def get_outputs(self) -> dict[str, np.ndarray]:
        self._pull()
        return {name: view.copy() for name, view in self._output_views.items()}

    def _do_step(self, t: float, h: float) -> None:
        if self._component is None:
            self._require_instance("start_step")
        self._time = t
        mark = len(self.messages)
        refs = self._step_refs
        status = self._do_step_raw(self._component, t, h, True, refs[0], refs[1], refs[2], refs[3])
        if status or len(self.messages) != mark:
            self._check("fmi3DoStep", status, mark)
        self._time = t + h

    def start_step(self, t: float, h: float, inputs: dict[str, np.ndarray]) -> None:
        if inputs:
            self.set_inputs(inputs)
        self._do_step(t, h)

    def finish_step(self) -> dict[str, np.ndarray]:
        return self.get_outputs()

    def wait_handle(self) -> None:
        return None

    def terminate(self) -> None:
        """fmi3Terminate, fmi3FreeInstance, unload and delete the extracted files; never raises."""
        if self._terminated:
            return
        self._terminated = True
        if self._slave is not None and self._component is not None:
            if self._initialized and not self._failed:
                try:
                    status = self._raw["fmi3Terminate"](self._component)
                    if status > FMI_WARNING:
                        logger.warning("%s: fmi3Terminate returned status %d", self.name, status)
                except Exception as exc:  # terminate must never raise
                    logger.warning("%s: fmi3Terminate failed: %s", self.name, exc)
            try:
                self._raw["fmi3FreeInstance"](self._component)
            except Exception as exc:
                logger.warning("%s: fmi3FreeInstance failed: %s", self.name, exc)
            self._component = None
        self._release_library()
        self._inputs, self._input_list, self._groups, self._output_views = {}, [], [], {}

    def _release_library(self) -> None:
        if self._slave is not None:
            try:
                self._slave.freeLibrary()
            except Exception as exc:
                logger.warning("%s: unloading the FMU library failed: %s", self.name, exc)
        if self._unzip_dir is not None:
            shutil.rmtree(self._unzip_dir, ignore_errors=True)
            self._unzip_dir = None

    # -- logging and errors ------------------------------------------------------------------------
    def _on_log(self, environment, status, category, message) -> None:
        text = message.decode("utf-8", "replace") if isinstance(message, bytes) else str(message)
        self.messages.append((int(status), text))
        if self._logger is not None:
            self._logger.log(_LOG_LEVELS.get(int(status), logging.ERROR), "%s", text)

    def _logged_reason(self, mark: int) -> str:
        """The last error (else warning) message logged since ``mark``, else the last error ever."""
        recent = self.messages[mark:]
        for threshold in (FMI_ERROR, FMI_WARNING):
            for status, text in reversed(recent):
                if status >= threshold:
                    return text
        for status, text in reversed(self.messages):
            if status >= FMI_ERROR:
                return text
        return "the FMU logged no reason"

    def _check(self, call: str, status: int, mark: int) -> None:
        """Raise unless ``status`` is OK/Warning and no error-level message was logged since ``mark``.

        An FMU that logs an error but returns OK from a call is reported at that call, where the
        cause is, rather than at a later one.
        """
        if status > FMI_WARNING:
            self._failed = True
            raise FmuCallError(self.name, call, self._time, self._logged_reason(mark), status)
        logged_error = max((s for s, _ in self.messages[mark:]), default=FMI_OK)
        if logged_error >= FMI_ERROR:
            raise FmuCallError(self.name, call, self._time, self._logged_reason(mark), logged_error)

    def _checked(self, call: str, action, mark: int) -> None:
        from fmpy.fmi1 import FMICallException

        try:
            action()
        except FMICallException as exc:
            self._failed = True
            raise FmuCallError(self.name, call, self._time, self._logged_reason(mark), exc.status) from None
        self._check(call, FMI_OK, mark)

    def _require_instance(self, what: str) -> None:
        if self._terminated:
            raise RuntimeError(f"{self.name}: {what}() after terminate()")
        if self._component is None:
            raise RuntimeError(f"{self.name}: call instantiate() before {what}()")

    def _unconfigured_input(self, name: str) -> Exception:
        if not self._configured:
            return RuntimeError(f"{self.name}: call configure(inputs, observed) before setting inputs")
        return PortConfigurationError(f"{self.name}.{name} is not among the configured inputs "
                                      f"({', '.join(self._inputs) or 'none'}): list it in configure()")


def _convert_for_setter(component: str, port: PortInfo, value: object) -> list:
    """``value`` as the list FMPy's setter for ``port.type`` takes; ValueError naming the port if it cannot be."""
    if port.type == "String":
        items = [value] if isinstance(value, str) or not isinstance(value, (list, tuple, np.ndarray)) else list(value)
        bad = [v for v in items if not isinstance(v, str)]
        if bad:
            raise PortConfigurationError(f"{component}.{port.name} is a String parameter; got {bad[0]!r}: "
                                         f"give text, e.g. {port.start!r}")
        return items
    items = np.asarray(value, dtype=object).reshape(-1).tolist()
    if port.type == "Boolean":
        out = []
        for v in items:
            if isinstance(v, (bool, np.bool_)) or (isinstance(v, (int, float, np.number)) and v in (0, 1)):
                out.append(bool(v))
            else:
                raise PortConfigurationError(f"{component}.{port.name} is Boolean; got {v!r}: give true/false")
        return out
    if port.type.startswith("Float"):
        try:
            return [float(v) for v in items]
        except (TypeError, ValueError):
            raise PortConfigurationError(f"{component}.{port.name} is {port.type}; got {value!r}: give numbers") from None
    if port.type in NATIVE_DTYPES:  # integer types
        out = []
        for v in items:
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.number)) or int(v) != v:
                raise PortConfigurationError(f"{component}.{port.name} is {port.type}; got {v!r}: give a whole number")
            info = np.iinfo(NATIVE_DTYPES[port.type])
            if not info.min <= int(v) <= info.max:
                raise PortConfigurationError(f"{component}.{port.name} is {port.type}; {v!r} is out of its range "
                                             f"[{info.min}, {info.max}]")
            out.append(int(v))
        return out
    raise PortConfigurationError(f"{component}.{port.name}: setting {port.type} variables is not supported")

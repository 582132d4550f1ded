"""Hosting one FMU instance for the master: the component host protocol and its in-process host.

All values crossing the protocol are 1-D float64 arrays; integer types, Booleans and enumeration
values are carried exactly as float64. The FMU is called through the project's FMI 3.0 binding
(:mod:`orchestration.hosts.fmi3`): the hot path (``set_inputs``, ``start_step``, ``finish_step``,
``get_outputs``) is the binding's ``push``/``do_step``/``pull`` over preallocated value-reference
arrays and float64 buffers laid out by :func:`~orchestration.hosts.buffers.slot_layout`: Float64 ports first, so that all
observed Float64 ports are read with one ``fmi3GetFloat64`` call straight into the buffer (the
other types through a small native buffer, converted by one copy per type). The layout is a pure
function of the port lists, which is what lets the worker host (orchestration/worker.py) place
the same buffers in shared memory.

After ``finish_step`` a host tells what fmi3DoStep reported: ``terminate_requested`` (the FMU asks
to end the simulation: fmi3Terminate is still allowed, no further step is), ``early_return`` and
``last_successful_time`` (the time the FMU reached).

String and Binary variables are set with ``set_values`` (Binary as bytes or a hex string) and read
with ``get_native``; they are not moved through the float64 buffers.
"""
from __future__ import annotations

import logging
import shutil
import tempfile
from typing import Protocol, runtime_checkable

import numpy as np

from orchestration.errors import LOG_LEVELS, FmuBinaryError, FmuCallError
from orchestration.hosts.buffers import exact_in_float64
from orchestration.hosts.fmi3 import (
    NATIVE_DTYPES, Fmi3Instance, Fmi3Library, StepResult, required_functions, resource_path)
from orchestration.hosts.description import INTEGER_RANGES, FmuDescription, PortInfo, parse_binary

logger = logging.getLogger(__name__)

__all__ = ["ComponentHost", "InProcessFmu", "PortConfigurationError", "check_port_lists"]


@runtime_checkable
class ComponentHost(Protocol):
    """What the master calls on every stepped component (see prompts/orch_iface.md).

    After ``finish_step``: ``terminate_requested`` (the component asks to end the run),
    ``early_return`` (it stopped before the end of the step) and ``last_successful_time`` (the
    time it reached; the end of the step unless one of the two is set).

    ``asynchronous`` (a class attribute, known before ``instantiate``): ``start_step`` only sends
    the step off (to a worker process) and ``finish_step`` waits for it, so the master starts such
    a step as early as it may and collects it once ``step_done()`` says it has ended, or when a
    consumer needs it. Otherwise the step is done by ``start_step`` (``step_done()`` is True).
    """

    asynchronous: bool
    name: str
    ports: dict[str, PortInfo]
    messages: list[tuple[int, str]]
    terminate_requested: bool
    early_return: bool
    last_successful_time: float

    def instantiate(self) -> None: ...
    def set_values(self, values: dict[str, object]) -> None: ...
    def enter_initialization(self, start_time: float) -> None: ...
    def configure(self, inputs: list[str], observed: list[str]) -> None: ...
    def set_inputs(self, values: dict[str, np.ndarray]) -> None: ...
    def get_outputs(self) -> dict[str, np.ndarray]: ...
    def get_values(self, names: list[str]) -> dict[str, np.ndarray]: ...
    def exit_initialization(self) -> None: ...
    def start_step(self, t: float, h: float, inputs: dict[str, np.ndarray]) -> None: ...
    def finish_step(self) -> dict[str, np.ndarray]: ...   # outputs valid until the next step (copy to keep)
    def step_done(self) -> bool: ...
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
                    f"{component}.{name} is a {port.type} variable: only numeric, Boolean and Enumeration ports can "
                    f"be connected or observed (set String and Binary values with set_values)")
            if kind == "input" and port.causality not in ("input", "parameter"):
                raise PortConfigurationError(
                    f"{component}.{name} is a {port.causality}, not an input: it cannot be written while stepping")


def _needed_in_process(name: str) -> bool:
    """Whether an FMU's file ``name`` is used when its model runs in this process."""
    return name != "resources/runtime.zip" and not name.startswith("resources/numba_cache/")


class InProcessFmu:
    """One FMU instance loaded into this process through the FMI 3.0 binding.

    ``instance`` is the :class:`~orchestration.hosts.fmi3.Fmi3Instance` once instantiated.
    ``log_to_logger=False`` keeps log messages only in ``messages`` (the worker process uses
    that: it sends them to the master, which logs them).
    """

    asynchronous = False

    def __init__(self, name: str, description: FmuDescription, *, log_to_logger: bool = True):
        self.name = name
        self.description = description
        self.ports: dict[str, PortInfo] = dict(description.ports)
        self.messages: list[tuple[int, str]] = []
        self.instance: Fmi3Instance | None = None
        self.terminate_requested = False
        self.early_return = False
        self.last_successful_time = 0.0
        self._logger = logging.getLogger(f"orchestration.fmu.{name}") if log_to_logger else None
        self._library: Fmi3Library | None = None
        self._unzip_dir: str | None = None
        self._initialized = False
        self._left_initialization = False  # fmi3Terminate is illegal before (free the instance only)
        self._terminated = False
        self._input_slots: dict[str, np.ndarray] = {}
        self._input_index: dict[str, int] = {}
        self._output_views: dict[str, np.ndarray] = {}
        self._configured = False
        # the hot path's inputs and their push, bound by configure()
        self._input_ports: dict = {}
        self._push_port = self._not_ready

    # -- lifecycle ---------------------------------------------------------------------------------
    def instantiate(self) -> None:
        from fmpy import extract

        if self.instance is not None or self._library is not None:
            raise RuntimeError(f"{self.name}: instantiate() was called twice")
        if self._terminated:
            raise RuntimeError(f"{self.name}: instantiate() after terminate()")
        description = self.description
        self._unzip_dir = tempfile.mkdtemp(prefix=f"fmu_{self.name}_")
        try:
            # the runtime an FMU carries, and the kernels compiled for it, are for importers without
            # this Python (python_embed.h): the model runs here on this process's own
            extract(str(description.path), self._unzip_dir, include=_needed_in_process)
            # checked before it is loaded (Fmi3Library): a truncated binary would kill this process
            self._library = Fmi3Library.from_extracted(self._unzip_dir, description.model_identifier,
                                                       required_functions(self.ports))
            self.instance = Fmi3Instance(self._library, self.name, description.instantiation_token,
                                         resource_path(self._unzip_dir), messages=self.messages,
                                         on_message=self._log if self._logger is not None else None)
        except FmuCallError:
            self._release_library()
            raise
        except FmuBinaryError as exc:  # named by the .fmu the user gave, not by its temporary copy
            reason = f"{description.path}: {str(exc).replace(self._unzip_dir + '/', '')}"
            self._release_library()
            raise FmuCallError(self.name, "loading the FMU binary", None, reason) from None
        except Exception as exc:  # a bad archive, a missing or unloadable binary
            self._release_library()
            raise FmuCallError(self.name, "fmi3InstantiateCoSimulation", None, str(exc)) from None

    def set_values(self, values: dict[str, object]) -> None:
        """Parameters and start values of any FMI type; structural parameters are set first, in
        Configuration Mode (so only before ``enter_initialization``)."""
        instance = self._require_instance("set_values")
        unknown = [n for n in values if n not in self.ports]
        if unknown:
            raise PortConfigurationError(f"{self.name} has no variable(s) {', '.join(map(repr, unknown))}; "
                                         f"its variables are: {', '.join(sorted(self.ports))}")
        # every value is converted (and refused) before any call, so a refusal changes nothing
        converted = {name: _convert_for_setter(self.name, self.ports[name], value) for name, value in values.items()}
        structural = [n for n in converted if self.ports[n].causality == "structuralParameter"]
        if structural and self._initialized:
            raise PortConfigurationError(
                f"{self.name}: structural parameters ({', '.join(structural)}) are set in Configuration Mode, "
                "which an FMU enters only before initialization: set them before enter_initialization()")
        if structural:  # FMI 3.0: structural parameters are set in Configuration Mode
            instance.enter_configuration_mode()
            try:
                for name in structural:
                    self._set_value(name, converted[name])
            except BaseException:
                if not instance.failed:  # leave the mode; the first error is the one reported
                    try:
                        instance.exit_configuration_mode()
                    except FmuCallError:
                        pass
                raise
            instance.exit_configuration_mode()
        for name in converted:
            if name not in structural:
                self._set_value(name, converted[name])

    def _set_value(self, name: str, converted: list) -> None:
        port = self.ports[name]
        self.instance.set(port.type, [port.value_reference], converted, label=name)

    def get_native(self, names: list[str]) -> dict[str, object]:
        """Current values in the FMU's own types: numpy arrays of the native dtype, lists of str
        (String) or bytes (Binary). Not the hot path."""
        instance = self._require_instance("get_native")
        result: dict[str, object] = {}
        for name in names:
            port = self.ports.get(name)
            if port is None:
                raise PortConfigurationError(f"{self.name} has no variable {name!r}")
            if port.type not in NATIVE_DTYPES and port.type not in ("String", "Binary"):
                raise PortConfigurationError(f"{self.name}.{name}: reading {port.type} variables is not supported")
            result[name] = instance.get(port.type, [port.value_reference], port.size, label=name)
        return result

    def get_values(self, names: list[str]) -> dict[str, np.ndarray]:
        """Current values of numeric variables of any causality, as float64 arrays (not the hot path:
        calculated parameters such as surface triangles, read once)."""
        self._require_instance("get_values")
        for name in names:
            port = self.ports.get(name)
            if port is not None and port.type not in NATIVE_DTYPES:
                raise PortConfigurationError(f"{self.name}.{name}: reading {port.type} variables as numbers is not "
                                             "supported (get_native reads them)")
        result: dict[str, np.ndarray] = {}
        for name, native in self.get_native(names).items():
            if native.dtype.kind in "iu" and not exact_in_float64(native):
                raise FmuCallError(self.name, f"get_values({name})", self.instance.time,
                                   f"{name} holds a value beyond 2**53, which float64 does not hold exactly")
            result[name] = native.astype(np.float64).reshape(self.ports[name].size)
        return result

    def enter_initialization(self, start_time: float) -> None:
        instance = self._require_instance("enter_initialization")
        instance.enter_initialization_mode(float(start_time))
        self._initialized = True
        self.last_successful_time = float(start_time)

    def exit_initialization(self) -> None:
        self._require_instance("exit_initialization").exit_initialization_mode()
        self._left_initialization = True

    def configure(self, inputs: list[str], observed: list[str]) -> None:
        inputs, observed = list(inputs), list(observed)
        check_port_lists(self.name, self.ports, inputs, observed)
        self.bind(inputs, observed)

    def bind(self, inputs: list[str], observed: list[str], in_buffer: np.ndarray | None = None,
             out_buffer: np.ndarray | None = None) -> None:
        """Bind the ports over float64 buffers laid out by :func:`~orchestration.hosts.buffers.slot_layout` (new ones, or shared memory)."""
        instance = self._require_instance("configure")
        instance.bind(self.ports, inputs, observed, in_buffer, out_buffer)
        self._input_slots = instance.input_slots
        self._input_index = {name: i for i, name in enumerate(inputs)}
        self._output_views = instance.output_views
        self._input_ports = instance.input_ports
        self._push_port = instance.push_port
        self._configured = True

    def unbind(self) -> None:
        if self.instance is not None:
            self.instance.unbind()
        self._input_slots, self._input_index, self._output_views, self._input_ports = {}, {}, {}, {}
        self._push_port = self._not_ready

    # -- hot path ----------------------------------------------------------------------------------
    def set_inputs(self, values: dict[str, np.ndarray]) -> None:
        ports = self._input_ports
        push = self._push_port
        for name, value in values.items():
            port = ports.get(name)
            if port is None:
                raise self._unconfigured_input(name)
            try:  # a flat array of the port's size (what the master routes): copied as it is
                if value.size != port.size:
                    raise ValueError
                port.slot[:] = value
            except (AttributeError, ValueError, TypeError):  # anything else converted, or refused
                value = np.asarray(value, dtype=np.float64)
                if value.size != port.size:
                    raise ValueError(f"{self.name}.{name} expects {port.size} value(s), got {value.size}") from None
                np.copyto(port.slot, value.reshape(port.size))
            push(port)

    def get_outputs(self) -> dict[str, np.ndarray]:
        try:
            self.instance.pull()
        except AttributeError:  # no instance (yet, or any more)
            if self.instance is None:
                self._require_instance("get_outputs")
            raise
        return {name: view.copy() for name, view in self._output_views.items()}

    def step(self, t: float, h: float) -> StepResult:
        """fmi3DoStep; records its out-flags in ``terminate_requested``, ``early_return`` and
        ``last_successful_time`` and returns them all (see :class:`~orchestration.hosts.fmi3.StepResult`)."""
        if self.instance is None:
            self._require_instance("start_step")
        result = StepResult(*self.instance.do_step(t, h))
        _, self.terminate_requested, self.early_return, self.last_successful_time = result
        return result

    def start_step(self, t: float, h: float, inputs: dict[str, np.ndarray]) -> None:
        if inputs:
            self.set_inputs(inputs)
        try:
            _, self.terminate_requested, self.early_return, self.last_successful_time = self.instance.do_step(t, h)
        except AttributeError:  # no instance (yet, or any more)
            if self.instance is None:
                self._require_instance("start_step")
            raise

    def finish_step(self) -> dict[str, np.ndarray]:
        try:
            self.instance.pull()
        except AttributeError:  # no instance (yet, or any more)
            if self.instance is None:
                self._require_instance("finish_step")
            raise
        return self._output_views  # views of the output buffer: valid until the next step

    def step_done(self) -> bool:
        return True  # synchronous: start_step did the step

    def terminate(self) -> None:
        """fmi3Terminate, fmi3FreeInstance, unload and delete the extracted files; never raises."""
        if self._terminated:
            return
        self._terminated = True
        instance = self.instance
        if instance is not None:
            # In Initialization Mode (a run that failed before it started) fmi3Terminate is not a
            # legal call: the instance is only freed.
            if self._left_initialization and not instance.failed and not instance.freed:
                try:
                    instance.terminate()
                except FmuCallError as exc:
                    logger.warning("%s: fmi3Terminate failed: %s", self.name, exc.reason)
                except Exception as exc:  # terminate must never raise
                    logger.warning("%s: fmi3Terminate failed: %s", self.name, exc)
            try:
                instance.free()
            except Exception as exc:
                logger.warning("%s: fmi3FreeInstance failed: %s", self.name, exc)
        self.unbind()
        self._configured = False
        self._release_library()
        self.instance = None

    def _release_library(self) -> None:
        library, self._library = self._library, None
        instance = self.instance
        if library is not None and not (instance is not None and instance.fatal):
            # after fmi3Fatal the instance is never freed: its library stays loaded
            try:
                library.close()
            except Exception as exc:
                logger.warning("%s: unloading the FMU library failed: %s", self.name, exc)
        if self._unzip_dir is not None:
            shutil.rmtree(self._unzip_dir, ignore_errors=True)
            self._unzip_dir = None

    # -- logging and errors ------------------------------------------------------------------------
    def _log(self, status: int, text: str) -> None:
        self._logger.log(LOG_LEVELS.get(status, logging.ERROR), "%s", text)

    def _not_ready(self, *args) -> None:
        """Stands for the binding's push before configure() and after terminate()."""
        self._require_instance("set_inputs")
        raise RuntimeError(f"{self.name}: call configure(inputs, observed) before setting inputs")

    def _unconfigured_input(self, name: str) -> Exception:
        if not self._configured:
            self._require_instance("set_inputs")
            return RuntimeError(f"{self.name}: call configure(inputs, observed) before setting inputs")
        return PortConfigurationError(f"{self.name}.{name} is not among the configured inputs "
                                      f"({', '.join(self._input_slots) or 'none'}): list it in configure()")

    def _require_instance(self, what: str) -> Fmi3Instance:
        if self._terminated:
            raise RuntimeError(f"{self.name}: {what}() after terminate()")
        if self.instance is None:
            raise RuntimeError(f"{self.name}: call instantiate() before {what}()")
        return self.instance


def _convert_for_setter(component: str, port: PortInfo, value: object) -> list:
    """``value`` as the list :meth:`Fmi3Instance.set` takes for ``port.type``; PortConfigurationError
    naming the port if it cannot be. Binary values are bytes or hex strings; an Enumeration takes
    its values or its item names."""
    if port.type == "Binary":
        items = [value] if isinstance(value, (str, bytes, bytearray)) or not isinstance(
            value, (list, tuple, np.ndarray)) else list(value)
        out = []
        for v in items:
            if isinstance(v, (bytes, bytearray)):
                out.append(bytes(v))
                continue
            try:
                out.append(parse_binary(v) if isinstance(v, str) else None)
            except ValueError:
                out.append(None)
            if out[-1] is None:
                raise PortConfigurationError(f"{component}.{port.name} is a Binary parameter; got {v!r}: give bytes "
                                             f"in hexadecimal, e.g. \"{(port.start or bytes([1, 171])).hex()}\"")
        return out
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
    if port.type in INTEGER_RANGES:  # integer types and enumerations
        out = []
        for v in items:
            if port.type == "Enumeration" and isinstance(v, str):
                value = port.item_value(v)
                if value is None:
                    raise PortConfigurationError(
                        f"{component}.{port.name} is the enumeration {port.declared_type}; {v!r} is not one of its items: "
                        f"{', '.join(name for name, _ in port.items)}")
                out.append(value)
                continue
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.number)) or int(v) != v:
                raise PortConfigurationError(f"{component}.{port.name} is {port.type}; got {v!r}: give a whole number")
            low, high = INTEGER_RANGES[port.type]
            if not low <= int(v) <= high:
                raise PortConfigurationError(f"{component}.{port.name} is {port.type}; {v!r} is out of its range "
                                             f"[{low}, {high}]")
            out.append(int(v))
        return out
    raise PortConfigurationError(f"{component}.{port.name}: setting {port.type} variables is not supported")

"""A thin typed binding over the FMI 3.0 Co-Simulation C API (ctypes), used by every FMU host.

Two classes:

* :class:`Fmi3Library`: the shared library of an extracted FMU, with a ctypes signature for each
  FMI 3.0 function an importer of Co-Simulation FMUs calls; ``close()`` unloads it.
* :class:`Fmi3Instance`: one Co-Simulation instance. Lifecycle calls (configuration and
  initialization modes, ``terminate``, ``free``), typed ``get``/``set`` for every FMI 3.0 variable
  type (numeric, Boolean, Enumeration, String, Binary), and ``do_step`` returning its out-flags.
  The hot path works over float64 buffers: ``bind(ports, inputs, observed)`` lays the ports out
  in two buffers (:mod:`~orchestration.hosts.buffers`; they may be shared memory), ``push`` writes input slots to
  the FMU, ``do_step`` steps, ``pull`` reads every observed port into the output buffer. Value
  reference arrays, native buffers and pointers are built once by ``bind``; a step makes no
  Python list.

One error path: a call that returns fmi3Discard/Error/Fatal, or after which the FMU logged an
error, raises :class:`~orchestration.errors.FmuCallError` carrying the function (with the
variables it was about), the simulated time, the status and the reason the FMU logged. The log
messages themselves are collected in ``messages`` as ``(status, text)``.

fmi3DoStep's out-flags: ``do_step`` returns them as a tuple (field names: :class:`StepResult`). An
fmi3Discard together with ``terminateSimulation`` is the FMU ending the simulation, not an error: it is returned like any
other step (``terminate_requested`` set), and ``fmi3Terminate`` stays allowed. An fmi3Discard
without it raises (the orchestrator does not retry a step with a smaller size).

Values cross the hot path as float64: integer types up to 32 bits and Booleans exactly; a 64-bit
integer (or enumeration) value beyond 2**53 is refused when read rather than rounded.
"""
from __future__ import annotations

import ctypes
import os
import platform
import struct
import sys
from pathlib import Path
from typing import Callable, Mapping, NamedTuple, Sequence

import numpy as np

from orchestration.errors import FMI_DISCARD, FMI_ERROR, FMI_FATAL, FMI_OK, FMI_WARNING, FmuBinaryError, FmuCallError
from orchestration.hosts.buffers import (EXACT_INTEGER, InputPort, OutputGroup, PortLike, exact_in_float64,
                                         slot_layout)

# -- C types ---------------------------------------------------------------------------------------
c_instance = ctypes.c_void_p
c_status = ctypes.c_int
c_vr = ctypes.c_uint32
c_vr_p = ctypes.POINTER(c_vr)
c_bool_p = ctypes.POINTER(ctypes.c_bool)
c_double_p = ctypes.POINTER(ctypes.c_double)
c_binary = ctypes.POINTER(ctypes.c_uint8)

LogMessageCallback = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_char_p)
IntermediateUpdateCallback = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_double, ctypes.c_bool, ctypes.c_bool,
                                              ctypes.c_bool, ctypes.c_bool, c_bool_p, c_double_p)

#: FMI variable type -> (the C functions' suffix, ctypes type, numpy dtype) for the types that are
#: moved as numbers. Enumerations are Int64 values (fmi3GetInt64/fmi3SetInt64).
_NUMERIC: dict[str, tuple[str, type, type]] = {
    "Float32": ("Float32", ctypes.c_float, np.float32),
    "Float64": ("Float64", ctypes.c_double, np.float64),
    "Int8": ("Int8", ctypes.c_int8, np.int8),
    "UInt8": ("UInt8", ctypes.c_uint8, np.uint8),
    "Int16": ("Int16", ctypes.c_int16, np.int16),
    "UInt16": ("UInt16", ctypes.c_uint16, np.uint16),
    "Int32": ("Int32", ctypes.c_int32, np.int32),
    "UInt32": ("UInt32", ctypes.c_uint32, np.uint32),
    "Int64": ("Int64", ctypes.c_int64, np.int64),
    "UInt64": ("UInt64", ctypes.c_uint64, np.uint64),
    "Boolean": ("Boolean", ctypes.c_bool, np.bool_),
    "Enumeration": ("Int64", ctypes.c_int64, np.int64),
}
#: FMI type -> numpy dtype of its native buffer, for every type the hot path moves.
NATIVE_DTYPES = {name: dtype for name, (_, _, dtype) in _NUMERIC.items()}
#: Types whose values float64 holds exactly only up to 2**53 in magnitude.
_WIDE_TYPES = ("Int64", "UInt64", "Enumeration")
#: Every FMI 3.0 variable type the binding can get and set.
VALUE_TYPES = tuple(_NUMERIC) + ("String", "Binary")


def function_suffix(fmi_type: str) -> str:
    """The suffix of the get/set functions of ``fmi_type`` ("Int64" for an Enumeration)."""
    if fmi_type in _NUMERIC:
        return _NUMERIC[fmi_type][0]
    if fmi_type in ("String", "Binary"):
        return fmi_type
    raise ValueError(f"FMI type {fmi_type!r} has no get/set functions here (types: {', '.join(VALUE_TYPES)})")


# -- signatures ------------------------------------------------------------------------------------
def _signatures() -> dict[str, tuple[object, list]]:
    size = ctypes.c_size_t
    sig: dict[str, tuple[object, list]] = {
        "fmi3GetVersion": (ctypes.c_char_p, []),
        "fmi3SetDebugLogging": (c_status, [c_instance, ctypes.c_bool, size, ctypes.POINTER(ctypes.c_char_p)]),
        "fmi3InstantiateCoSimulation": (c_instance, [
            ctypes.c_char_p, ctypes.c_char_p, ctypes.c_char_p,   # instanceName, instantiationToken, resourcePath
            ctypes.c_bool, ctypes.c_bool,                        # visible, loggingOn
            ctypes.c_bool, ctypes.c_bool,                        # eventModeUsed, earlyReturnAllowed
            c_vr_p, size,                                        # requiredIntermediateVariables
            ctypes.c_void_p, LogMessageCallback, IntermediateUpdateCallback]),
        "fmi3FreeInstance": (None, [c_instance]),
        "fmi3EnterInitializationMode": (c_status, [c_instance, ctypes.c_bool, ctypes.c_double, ctypes.c_double,
                                                   ctypes.c_bool, ctypes.c_double]),
        "fmi3ExitInitializationMode": (c_status, [c_instance]),
        "fmi3EnterConfigurationMode": (c_status, [c_instance]),
        "fmi3ExitConfigurationMode": (c_status, [c_instance]),
        "fmi3Terminate": (c_status, [c_instance]),
        "fmi3Reset": (c_status, [c_instance]),
        "fmi3DoStep": (c_status, [c_instance, ctypes.c_double, ctypes.c_double, ctypes.c_bool,
                                  c_bool_p, c_bool_p, c_bool_p, c_double_p]),
        "fmi3GetString": (c_status, [c_instance, c_vr_p, size, ctypes.POINTER(ctypes.c_char_p), size]),
        "fmi3SetString": (c_status, [c_instance, c_vr_p, size, ctypes.POINTER(ctypes.c_char_p), size]),
        "fmi3GetBinary": (c_status, [c_instance, c_vr_p, size, ctypes.POINTER(size), ctypes.POINTER(c_binary), size]),
        "fmi3SetBinary": (c_status, [c_instance, c_vr_p, size, ctypes.POINTER(size), ctypes.POINTER(c_binary), size]),
        "fmi3GetFMUState": (c_status, [c_instance, ctypes.POINTER(ctypes.c_void_p)]),
        "fmi3SetFMUState": (c_status, [c_instance, ctypes.c_void_p]),
        "fmi3FreeFMUState": (c_status, [c_instance, ctypes.POINTER(ctypes.c_void_p)]),
    }
    for suffix, ctype, _ in {v[0]: v for v in _NUMERIC.values()}.values():
        pointer = ctypes.POINTER(ctype)
        sig[f"fmi3Get{suffix}"] = (c_status, [c_instance, c_vr_p, size, pointer, size])
        sig[f"fmi3Set{suffix}"] = (c_status, [c_instance, c_vr_p, size, pointer, size])
    return sig


SIGNATURES = _signatures()


def platform_tuple() -> str:
    """The FMI 3.0 platform tuple of this machine, e.g. "x86_64-linux"."""
    machine = platform.machine().lower()
    machine = {"amd64": "x86_64", "arm64": "aarch64"}.get(machine, machine)
    system = {"linux": "linux", "darwin": "darwin", "win32": "windows", "cygwin": "windows"}.get(sys.platform,
                                                                                                  sys.platform)
    return f"{machine}-{system}"


def _library_extension() -> str:
    return {"darwin": ".dylib", "win32": ".dll"}.get(sys.platform, ".so")


def _unload(handle: int) -> None:
    if sys.platform == "win32":  # pragma: no cover - only Linux is built and tested
        ctypes.windll.kernel32.FreeLibrary(ctypes.c_void_p(handle))
    else:
        dlclose = ctypes.CDLL(None).dlclose
        dlclose.argtypes = [ctypes.c_void_p]
        dlclose(handle)


# -- checking a binary before it is loaded ------------------------------------------------------------
# dlopen maps an FMU's binary into this process: a truncated one (a copy or download cut short) kills
# the process with SIGBUS when the loader touches a segment beyond the file's end, before any FMI call
# could fail, and a binary for another machine fails with a message of the loader's. So a binary is
# read first, as data (a small ELF reader: header, segments, dynamic symbols), and refused with a
# message naming the file and the fix.

#: The FMI functions the master calls on every Co-Simulation FMU it hosts; the get/set functions of
#: the types of its variables come on top (:func:`required_functions`).
CORE_FUNCTIONS = ("fmi3InstantiateCoSimulation", "fmi3FreeInstance", "fmi3EnterInitializationMode",
                  "fmi3ExitInitializationMode", "fmi3DoStep", "fmi3Terminate")
#: What to do about a binary that cannot be loaded (the project's FMUs are built from this checkout).
BINARY_FIX = ("rebuild the project's FMUs with `python -m orchestration build` (an FMU from elsewhere: get a "
              "complete copy built for this machine)")
#: ELF e_machine of each machine name platform.machine() gives (the FMI platform tuple's first part).
_ELF_MACHINES = {"x86_64": 62, "aarch64": 183, "i386": 3, "i686": 3, "armv7l": 40, "ppc64le": 21, "s390x": 22,
                 "riscv64": 243}
#: Platforms whose shared libraries are ELF files (sys.platform prefixes).
_ELF_PLATFORMS = ("linux", "freebsd", "netbsd", "openbsd")
_ELF_LAYOUTS = {  # ELF class -> struct formats (after e_ident) of the header, a segment, a section, a symbol
    1: ("HHIIIIIHHHHHH", "IIIIIIII", "IIIIIIIIII", "IIIBBH"),
    2: ("HHIQQQIHHHHHH", "IIQQQQQQ", "IIQQQQIIQQ", "IBBHQQ"),
}


def required_functions(ports: Mapping[str, object]) -> tuple[str, ...]:
    """The FMI functions the master needs of an FMU with ``ports`` (PortInfo: ``type``, ``causality``):
    the core ones, configuration mode for structural parameters, and the get and set functions of
    the types of its variables (set only where one can be set)."""
    needed = list(CORE_FUNCTIONS)
    writable = ("parameter", "structuralParameter", "input")
    for port in ports.values():
        if port.type not in VALUE_TYPES:
            continue
        suffix = function_suffix(port.type)
        needed.append(f"fmi3Get{suffix}")
        if port.causality in writable:
            needed.append(f"fmi3Set{suffix}")
        if port.causality == "structuralParameter":
            needed += ["fmi3EnterConfigurationMode", "fmi3ExitConfigurationMode"]
    return tuple(dict.fromkeys(needed))


def elf_problem(data: bytes, required: Sequence[str] = ()) -> str | None:
    """Why the shared library ``data`` cannot be loaded into this process, or None: not ELF, another
    word size, byte order or machine, not a shared library, truncated (a segment, the section table
    or the symbol table beyond the end of the data), or ``required`` functions it does not export
    (checked where it has a section table, as every linker writes one)."""
    size = len(data)
    if size < 64:
        return f"is {size} bytes long, too short for a shared library"
    if data[:4] != b"\x7fELF":
        return f"is not an ELF shared library (it starts with {data[:4]!r})"
    elf_class, encoding = data[4], data[5]
    bits = 8 * struct.calcsize("P")
    if elf_class not in _ELF_LAYOUTS or 32 * elf_class != bits:
        return f"is a {32 * elf_class if elf_class in _ELF_LAYOUTS else '?'}-bit library; this Python is {bits}-bit"
    order = {1: "<", 2: ">"}.get(encoding)
    if order is None or {"<": "little", ">": "big"}[order] != sys.byteorder:
        return f"has the wrong byte order for this machine ({sys.byteorder}-endian)"
    header, segment, section, symbol = (struct.Struct(order + layout) for layout in _ELF_LAYOUTS[elf_class])
    (e_type, machine, _, _, phoff, shoff, _, _, phentsize, phnum, shentsize, shnum, _) = header.unpack_from(data, 16)
    if e_type != 3:  # ET_DYN
        return f"is not a shared library (ELF type {e_type})"
    expected = _ELF_MACHINES.get(platform.machine().lower())
    if expected is not None and machine != expected:
        return f"is built for another processor (ELF machine {machine}; this machine is {platform.machine()})"

    def beyond(what: str, end: int) -> str:
        return f"is truncated: its {what} ends at byte {end} but the file has {size} bytes"

    if phentsize != segment.size or phoff + phnum * phentsize > size:
        return beyond("program header table", phoff + phnum * phentsize)
    for i in range(phnum):
        fields = segment.unpack_from(data, phoff + i * phentsize)
        p_type = fields[0]
        offset, filesz = (fields[2], fields[5]) if elf_class == 2 else (fields[1], fields[4])
        if p_type in (1, 2) and offset + filesz > size:  # PT_LOAD, PT_DYNAMIC: what dlopen maps
            return beyond(f"segment {i}", offset + filesz)
    if not shnum:
        return None  # no section table (stripped): the segments are what loading needs
    if shentsize != section.size or shoff + shnum * shentsize > size:
        return beyond("section table", shoff + shnum * shentsize)
    sections = [section.unpack_from(data, shoff + i * shentsize) for i in range(shnum)]
    for i, (_, sh_type, _, _, offset, length, *_rest) in enumerate(sections):
        if sh_type != 8 and offset + length > size:  # 8: SHT_NOBITS (.bss) has no bytes in the file
            return beyond(f"section {i}", offset + length)
    exported = set()
    for _, sh_type, _, _, offset, length, link, _, _, entsize in sections:
        if sh_type != 11 or not entsize or link >= shnum:  # 11: SHT_DYNSYM, its names in section `link`
            continue
        names = sections[link]
        strings = data[names[4]:names[4] + names[5]]
        for start in range(offset, offset + length - entsize + 1, entsize):
            fields = symbol.unpack_from(data, start)
            name, info, other, shndx = (fields[0], fields[1], fields[2], fields[3]) if elf_class == 2 else (
                fields[0], fields[3], fields[4], fields[5])
            # defined, global or weak, default or protected visibility: what dlsym finds
            if shndx and (info >> 4) in (1, 2) and (other & 3) in (0, 3):
                end = strings.find(b"\0", name)
                exported.add(strings[name:end if end >= 0 else len(strings)].decode("utf-8", "replace"))
    missing = [name for name in required if name not in exported]
    if missing:
        return f"does not export {', '.join(missing)}, which the master calls"
    return None


def binary_problem(path: Path | str, required: Sequence[str] = ()) -> str | None:
    """Why the shared library at ``path`` cannot be loaded ("the FMU binary <path> is truncated: ...;
    <the fix>"), or None; a file that cannot be read is a problem too. Only ELF platforms are
    checked (Linux and the BSDs)."""
    if not sys.platform.startswith(_ELF_PLATFORMS):
        return None  # pragma: no cover - only Linux is built and tested
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        return f"the FMU binary {path} cannot be read ({exc.strerror or exc}); {BINARY_FIX}"
    problem = elf_problem(data, required)
    return f"the FMU binary {path} {problem}; {BINARY_FIX}" if problem else None


def fmu_binary_problem(fmu: Path | str, model_identifier: str, ports: Mapping[str, object]) -> str | None:
    """``binary_problem`` of the binary for this machine inside the FMU archive ``fmu`` (what an
    in-process host would load), or None; read from the archive, nothing is extracted."""
    import zipfile
    import zlib

    if not sys.platform.startswith(_ELF_PLATFORMS):
        return None  # pragma: no cover - only Linux is built and tested
    member = f"binaries/{platform_tuple()}/{model_identifier}{_library_extension()}"
    try:
        with zipfile.ZipFile(fmu) as archive:
            data = archive.read(member)
    except KeyError:
        return f"{fmu} has no binary for this machine ({member}); {BINARY_FIX}"
    except (OSError, zipfile.BadZipFile, zlib.error, EOFError, ValueError, RuntimeError) as exc:
        return f"the binary {member} in {fmu} cannot be read ({exc}); {BINARY_FIX}"
    problem = elf_problem(data, required_functions(ports))
    return f"the binary {member} in {fmu} {problem}; {BINARY_FIX}" if problem else None


class Fmi3Library:
    """The shared library of one extracted FMU with typed FMI 3.0 functions.

    Functions the library does not export are left out of ``functions``; calling one raises
    :class:`FmuCallError` through :meth:`Fmi3Instance.call`.
    """

    def __init__(self, path: Path | str, required: Sequence[str] = ()):
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"no FMU binary {self.path} (this machine's platform is {platform_tuple()})")
        # read as data first: a truncated binary would kill this process (SIGBUS) inside dlopen
        problem = binary_problem(self.path, required)
        if problem:
            raise FmuBinaryError(problem)
        self._dll = ctypes.CDLL(str(self.path))
        self._handle: int | None = self._dll._handle
        self.functions: dict[str, object] = {}
        for name, (restype, argtypes) in SIGNATURES.items():
            try:
                function = getattr(self._dll, name)
            except AttributeError:
                continue
            function.restype = restype
            function.argtypes = argtypes
            self.functions[name] = function

    @classmethod
    def from_extracted(cls, unzip_dir: Path | str, model_identifier: str, required: Sequence[str] = ()) -> Fmi3Library:
        """The binary of ``model_identifier`` for this platform in an extracted FMU; ``required``:
        the functions it must export (:func:`required_functions`), else FmuBinaryError."""
        path = Path(unzip_dir) / "binaries" / platform_tuple() / f"{model_identifier}{_library_extension()}"
        return cls(path, required)

    def version(self) -> str:
        function = self.functions.get("fmi3GetVersion")
        return function().decode() if function is not None else "unknown"

    def close(self) -> None:
        """Unload the library (idempotent). No instance of it may be used afterwards."""
        handle, self._handle = self._handle, None
        self.functions = {}
        if handle is not None:
            self._dll = None
            _unload(handle)


# -- results and port records of the hot path ------------------------------------------------------
class StepResult(NamedTuple):
    """fmi3DoStep's out-arguments, in the order :meth:`Fmi3Instance.do_step` returns them (as a plain
    tuple, which is cheaper to make on the hot path: ``StepResult(*flags)`` names them)."""

    event_handling_needed: bool
    terminate_requested: bool
    early_return: bool
    last_successful_time: float


def _value_references(vrs: Sequence[int]):
    return (c_vr * len(vrs))(*vrs)


def _pointer(array: np.ndarray, fmi_type: str):
    return array.ctypes.data_as(ctypes.POINTER(_NUMERIC[fmi_type][1]))


# -- the instance ----------------------------------------------------------------------------------
class Fmi3Instance:
    """One FMI 3.0 Co-Simulation instance of a loaded :class:`Fmi3Library`.

    ``messages`` (a list given by the caller or a new one) collects every log message as
    ``(status, text)``; ``on_message(status, text)`` is called for each as well. ``time`` is the
    simulated time errors are reported at (set by ``enter_initialization_mode`` and ``do_step``).
    Instantiation failure raises :class:`FmuCallError` naming fmi3InstantiateCoSimulation.
    """

    def __init__(self, library: Fmi3Library, name: str, instantiation_token: str, resource_path: str | None, *,
                 messages: list | None = None, on_message: Callable[[int, str], None] | None = None,
                 logging_on: bool = True, visible: bool = False):
        self.library = library
        self.name = name
        self.messages: list[tuple[int, str]] = messages if messages is not None else []
        self.time: float | None = None
        #: after fmi3Error the instance is in the Error mode (no fmi3Terminate); after fmi3Fatal no call at all
        self.failed = False
        self.fatal = False
        #: error-level messages logged so far, where compiled code can read it (orchestration.run.compiled_loop)
        self.logged_errors = np.zeros(1, dtype=np.int64)
        self._on_message = on_message
        self._functions = library.functions
        self._do_step_raw = library.functions.get("fmi3DoStep") or self._no_do_step
        self._log_callback = LogMessageCallback(self._log)       # kept alive as long as the instance
        self._update_callback = IntermediateUpdateCallback()       # NULL: no intermediate updates
        # the instance's address (a Python int converts to a pointer argument faster than a c_void_p)
        self._handle: int | None = None
        self.live_handle: int | None = None   # the handle while calls are allowed (not freed, no fmi3Fatal)
        self._inputs: list[InputPort] = []
        self._input_ports: dict[str, InputPort] = {}
        self._input_index: dict[str, int] = {}
        self._groups: list[OutputGroup] = []
        self.input_slots: dict[str, np.ndarray] = {}
        self.output_views: dict[str, np.ndarray] = {}
        # fmi3DoStep's out-arguments, allocated once
        # (eventHandlingNeeded, terminateSimulation and earlyReturn side by side in one 32-bit word:
        # one read tells whether any is set)
        self._flags = (ctypes.c_bool * 4)()
        self._flag_word = ctypes.c_uint32.from_buffer(self._flags)
        self._last_time = ctypes.c_double()
        address = ctypes.addressof(self._flags)
        self._step_refs = (ctypes.cast(address, c_bool_p), ctypes.cast(address + 1, c_bool_p),
                           ctypes.cast(address + 2, c_bool_p), ctypes.pointer(self._last_time))
        instantiate = self._function("fmi3InstantiateCoSimulation")
        mark = len(self.messages)
        address = instantiate(name.encode(), instantiation_token.encode(),
                              resource_path.encode() if resource_path is not None else None,
                              visible, logging_on, False, False, None, 0, None,
                              self._log_callback, self._update_callback)
        if not address:
            reason = self.logged_reason(mark) if len(self.messages) > mark else "it returned NULL and logged no reason"
            raise FmuCallError(name, "fmi3InstantiateCoSimulation", None, reason)
        self._handle = self.live_handle = int(address)

    # -- errors ------------------------------------------------------------------------------------
    def _log(self, environment, status, category, message) -> None:
        try:
            text = message.decode("utf-8", "replace") if message is not None else ""
            self.messages.append((int(status), text))
            if status >= FMI_ERROR:
                self.logged_errors[0] += 1
            if self._on_message is not None:
                self._on_message(int(status), text)
        except Exception:  # never raise into the FMU's C code
            pass

    def logged_reason(self, mark: int) -> str:
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

    def check_status(self, call: str, status: int, mark: int) -> None:
        """Raise unless ``status`` is OK/Warning and no error-level message was logged since ``mark``.

        An FMU that logs an error but returns OK from a call is reported at that call, where the
        cause is, rather than at a later one.
        """
        if status > FMI_WARNING:
            if status >= FMI_ERROR:
                self.failed = True
            if status >= FMI_FATAL:
                self.fatal = True
                self.live_handle = None
            raise FmuCallError(self.name, call, self.time, self.logged_reason(mark), status)
        logged = max((s for s, _ in self.messages[mark:]), default=FMI_OK)
        if logged >= FMI_ERROR:
            raise FmuCallError(self.name, call, self.time, self.logged_reason(mark), logged)

    def _function(self, name: str):
        function = self._functions.get(name)
        if function is None:
            raise FmuCallError(self.name, name, self.time, f"the FMU's binary does not export {name}")
        return function

    def _require(self, call: str) -> int:
        if self._handle is None:
            raise RuntimeError(f"{self.name}: {call} after fmi3FreeInstance")
        if self.fatal:
            raise FmuCallError(self.name, call, self.time, "the FMU returned fmi3Fatal before: no call is allowed",
                               FMI_FATAL)
        return self._handle

    def call(self, name: str, *args, label: str | None = None) -> None:
        """Call FMI function ``name`` on this instance with ``args``; raise on failure."""
        handle = self._require(name)
        function = self._function(name)
        mark = len(self.messages)
        status = function(handle, *args)
        self.check_status(f"{name}({label})" if label else name, status, mark)

    # -- lifecycle ---------------------------------------------------------------------------------
    def enter_configuration_mode(self) -> None:
        self.call("fmi3EnterConfigurationMode")

    def exit_configuration_mode(self) -> None:
        self.call("fmi3ExitConfigurationMode")

    def enter_initialization_mode(self, start_time: float, tolerance: float | None = None,
                                  stop_time: float | None = None) -> None:
        self.time = float(start_time)
        self.call("fmi3EnterInitializationMode", tolerance is not None, tolerance or 0.0, self.time,
                  stop_time is not None, stop_time if stop_time is not None else 0.0)

    def exit_initialization_mode(self) -> None:
        self.call("fmi3ExitInitializationMode")

    def terminate(self) -> None:
        self.call("fmi3Terminate")

    def reset(self) -> None:
        self.call("fmi3Reset")
        self.failed = False

    def free(self) -> None:
        """fmi3FreeInstance (idempotent; skipped after fmi3Fatal, when the standard allows no call)."""
        handle, self._handle, self.live_handle = self._handle, None, None
        self.unbind()
        if handle is not None and not self.fatal:
            self._function("fmi3FreeInstance")(handle)

    @property
    def freed(self) -> bool:
        return self._handle is None

    # -- typed get/set (not the hot path) ----------------------------------------------------------
    def _typed_call(self, verb: str, fmi_type: str, vrs: Sequence[int], label: str | None):
        """What a typed get or set needs: handle, value references, the function, the call's name
        for errors ("fmi3GetFloat64(label)") and the log mark its messages start at."""
        handle = self._require(verb.lower())
        name = f"fmi3{verb}{function_suffix(fmi_type)}"
        call = f"{name}({label})" if label else name
        return handle, _value_references(vrs), self._function(name), call, len(self.messages)

    def get(self, fmi_type: str, vrs: Sequence[int], n_values: int | None = None, label: str | None = None):
        """Values of ``vrs`` (``n_values`` in all, default one each): a numpy array of the native dtype,
        a list of str (String) or a list of bytes (Binary)."""
        handle, refs, function, call, mark = self._typed_call("Get", fmi_type, vrs, label)
        n_values = len(vrs) if n_values is None else int(n_values)
        if fmi_type == "String":
            values = (ctypes.c_char_p * n_values)()
            status = function(handle, refs, len(vrs), values, n_values)
            self.check_status(call, status, mark)
            return [(v or b"").decode("utf-8") for v in values]
        if fmi_type == "Binary":
            sizes = (ctypes.c_size_t * n_values)()
            values = (c_binary * n_values)()
            status = function(handle, refs, len(vrs), sizes, values, n_values)
            self.check_status(call, status, mark)
            return [ctypes.string_at(v, s) if s else b"" for v, s in zip(values, sizes)]
        out = np.zeros(n_values, dtype=NATIVE_DTYPES[fmi_type])
        status = function(handle, refs, len(vrs), _pointer(out, fmi_type), n_values)
        self.check_status(call, status, mark)
        return out

    def set(self, fmi_type: str, vrs: Sequence[int], values, label: str | None = None) -> None:
        """Set ``vrs`` to ``values`` (numbers, str or bytes as the type needs; arrays flat)."""
        handle, refs, function, call, mark = self._typed_call("Set", fmi_type, vrs, label)
        if fmi_type == "String":
            items = [values] if isinstance(values, str) else list(values)
            array = (ctypes.c_char_p * len(items))(*[v.encode("utf-8") for v in items])
            status = function(handle, refs, len(vrs), array, len(items))
        elif fmi_type == "Binary":
            items = [values] if isinstance(values, (bytes, bytearray)) else list(values)
            buffers = [(ctypes.c_uint8 * len(b)).from_buffer_copy(b) if len(b) else None for b in items]
            sizes = (ctypes.c_size_t * len(items))(*[len(b) for b in items])
            pointers = (c_binary * len(items))(*[ctypes.cast(b, c_binary) if b is not None else None
                                                 for b in buffers])
            status = function(handle, refs, len(vrs), sizes, pointers, len(items))
        else:
            array = np.ascontiguousarray(np.asarray(values).reshape(-1), dtype=NATIVE_DTYPES[fmi_type])
            status = function(handle, refs, len(vrs), _pointer(array, fmi_type), array.size)
        self.check_status(call, status, mark)

    # -- the hot path ------------------------------------------------------------------------------
    def bind(self, ports: Mapping[str, PortLike], inputs: Sequence[str], observed: Sequence[str],
             in_buffer: np.ndarray | None = None, out_buffer: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
        """Lay out ``inputs`` and ``observed`` ports in float64 buffers (new ones unless given, e.g.
        shared memory of the :func:`slot_layout` sizes) and prepare every call of the hot path.

        Returns the two buffers; ``input_slots`` and ``output_views`` name the ports' views.
        """
        self._require("bind")
        inputs, observed = list(inputs), list(observed)
        for name in inputs + observed:
            if ports[name].type not in NATIVE_DTYPES:
                raise ValueError(f"{self.name}.{name} is a {ports[name].type} variable: it cannot be moved as numbers")
        in_layout, in_size = slot_layout(ports, inputs)
        out_layout, out_size = slot_layout(ports, observed)
        in_buffer = np.zeros(in_size) if in_buffer is None else in_buffer
        out_buffer = np.zeros(out_size) if out_buffer is None else out_buffer
        if in_buffer.shape != (in_size,) or out_buffer.shape != (out_size,) \
                or in_buffer.dtype != np.float64 or out_buffer.dtype != np.float64:
            raise ValueError(f"{self.name}: bind() needs float64 buffers of {in_size} and {out_size} values")
        self._inputs = []
        for name in inputs:
            port = ports[name]
            start, stop = in_layout[name]
            slot = in_buffer[start:stop]
            cast = port.type != "Float64"
            native = np.zeros(port.size, dtype=NATIVE_DTYPES[port.type]) if cast else slot
            self._inputs.append(InputPort(
                name=name, call=f"fmi3Set{function_suffix(port.type)}({name})", size=port.size,
                vr=_value_references([port.value_reference]), slot=slot, native=native,
                pointer=_pointer(native, port.type), setter=self._function(f"fmi3Set{function_suffix(port.type)}"),
                exact=port.type not in ("Float64", "Float32"), cast=cast))
        self._input_index = {name: i for i, name in enumerate(inputs)}
        self._input_ports = {port.name: port for port in self._inputs}
        self._groups = []
        by_type: dict[str, list[str]] = {}
        for name in sorted(observed, key=lambda n: out_layout[n][0]):
            by_type.setdefault(ports[name].type, []).append(name)
        for fmi_type, names in by_type.items():
            start, stop = out_layout[names[0]][0], out_layout[names[-1]][1]
            slot = out_buffer[start:stop]
            cast = fmi_type != "Float64"
            native = np.zeros(stop - start, dtype=NATIVE_DTYPES[fmi_type]) if cast else slot
            suffix = function_suffix(fmi_type)
            self._groups.append(OutputGroup(
                call=f"fmi3Get{suffix}({', '.join(names)})", count=len(names), size=stop - start,
                vrs=_value_references([ports[n].value_reference for n in names]), slot=slot,
                native=native, pointer=_pointer(native, fmi_type), getter=self._function(f"fmi3Get{suffix}"),
                cast=cast, wide=fmi_type in _WIDE_TYPES,
                names=tuple((n, out_layout[n][0] - start, out_layout[n][1] - start) for n in names)))
        self.input_slots = {name: in_buffer[a:b] for name, (a, b) in in_layout.items()}
        self.output_views = {name: out_buffer[a:b] for name, (a, b) in out_layout.items()}
        return in_buffer, out_buffer

    def unbind(self) -> None:
        """Drop every view of the bound buffers (so shared memory can be closed)."""
        self._inputs, self._input_index, self._input_ports, self._groups = [], {}, {}, []
        self.input_slots, self.output_views = {}, {}

    @property
    def input_names(self) -> list[str]:
        return [p.name for p in self._inputs]

    @property
    def output_groups(self) -> list[OutputGroup]:
        """The bound observed ports, one group per type in buffer order: what :meth:`pull` reads."""
        return self._groups

    def input_index(self, name: str) -> int | None:
        return self._input_index.get(name)

    @property
    def input_ports(self) -> dict[str, InputPort]:
        """The bound inputs by name: records with ``slot`` (the float64 view) and ``size``, for :meth:`push_port`."""
        return self._input_ports

    def write_inputs(self, values: Mapping[str, np.ndarray]) -> None:
        """Copy ``values`` (float64-convertible arrays of the ports' sizes) into their input slots and
        push each to the FMU. KeyError for a name that is not a bound input, ValueError for a wrong size."""
        ports = self._input_ports
        for name, value in values.items():
            port = ports[name]
            value = np.asarray(value, dtype=np.float64)
            if value.size != port.size:
                raise ValueError(f"{self.name}.{name} expects {port.size} value(s), got {value.size}")
            np.copyto(port.slot, value.reshape(port.size))
            self._push(port)

    def push(self, indices: Sequence[int] | None = None) -> None:
        """Write the input slots at ``indices`` of the bound input list (all when None) to the FMU."""
        if indices is None:
            for port in self._inputs:
                self._push(port)
        else:
            inputs = self._inputs
            for i in indices:
                self._push(inputs[i])

    def _push(self, port: InputPort) -> None:
        if port.cast:
            np.copyto(port.native, port.slot, casting="unsafe")
            if port.exact and not np.array_equal(port.native, port.slot):
                raise ValueError(f"{self.name}.{port.name} takes whole numbers"
                                 f"{' (0 or 1)' if port.native.dtype == np.bool_ else ''}; got {port.slot.tolist()}")
        handle = self.live_handle
        if handle is None:
            self._require("push")
        messages = self.messages
        mark = len(messages)
        status = port.setter(handle, port.vr, 1, port.pointer, port.size)
        if status or len(messages) != mark:
            self.check_status(port.call, status, mark)

    #: Write one bound input's slot to the FMU (``port`` from :attr:`input_ports`).
    push_port = _push

    def pull(self) -> None:
        """Read every observed port into the output buffer."""
        handle = self.live_handle
        if handle is None:
            self._require("pull")
        messages = self.messages
        for group in self._groups:
            mark = len(messages)
            status = group.getter(handle, group.vrs, group.count, group.pointer, group.size)
            if status or len(messages) != mark:
                self.check_status(group.call, status, mark)
            if group.cast:
                if group.wide and not exact_in_float64(group.native):
                    self.refuse_wide(group)
                np.copyto(group.slot, group.native, casting="unsafe")

    def refuse_wide(self, group: OutputGroup) -> None:
        for name, a, b in group.names:
            values = group.native[a:b]
            if not exact_in_float64(values):
                bad = next(v for v in values.tolist() if abs(v) > EXACT_INTEGER)
                raise FmuCallError(self.name, group.call, self.time,
                                   f"{name} = {int(bad)} is beyond 2**53 and would not survive the master's float64 "
                                   "values exactly")

    def do_step(self, t: float, h: float, no_set_fmu_state_prior: bool = True) -> tuple[bool, bool, bool, float]:
        """fmi3DoStep from ``t`` over ``h``; returns its out-flags ``(event_handling_needed,
        terminate_requested, early_return, last_successful_time)`` (see :class:`StepResult` and the
        module's notes on fmi3Discard). ``last_successful_time`` is the FMU's when it returned early
        or asked to terminate, else ``t + h``."""
        handle = self.live_handle
        if handle is None:
            self._require("fmi3DoStep")
        messages = self.messages
        mark = len(messages)
        refs = self._step_refs  # (indexed, not *refs: a star call builds a list)
        status = self._do_step_raw(handle, t, h, no_set_fmu_state_prior, refs[0], refs[1], refs[2], refs[3])
        if status or len(messages) != mark:
            self.step_problem(t, status, mark)
        if self._flag_word.value:
            event, terminate, early, _ = self._flags
            last = self.time = self._last_time.value if terminate or early else t + h
            return event, terminate, early, last
        end = self.time = t + h
        return False, False, False, end

    def _no_do_step(self, *args) -> None:
        self._function("fmi3DoStep")  # raises: the binary does not export it

    def step_problem(self, t: float, status: int, mark: int) -> None:
        """Raise for a failed fmi3DoStep, unless it is fmi3Discard with terminateSimulation."""
        self.time = t
        if status == FMI_DISCARD:
            if self._flags[1]:
                return
            messages = self.messages
            reason = self.logged_reason(mark) if len(messages) > mark else "the FMU logged no reason"
            raise FmuCallError(self.name, "fmi3DoStep", t,
                               f"{reason} (fmi3Discard without terminateSimulation: the FMU could not complete the "
                               "step, and the master does not retry with a smaller one)", status)
        self.check_status("fmi3DoStep", status, mark)


def resource_path(unzip_dir: Path | str) -> str:
    """FMI 3.0's resourcePath argument: the extracted ``resources`` folder with a trailing separator."""
    return os.path.join(str(unzip_dir), "resources") + os.sep

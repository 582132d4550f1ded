"""The serialized FMU state: data, never code (carried in each FMU as resources/state_format.py).

``fmi3SerializeFMUState`` bytes cross a trust boundary: importers store them in files and read
them back (fmusim's ``--initial-fmu-state-file``), possibly from another machine or another
person. So they are parsed as data, with no pickle or other format that can name code to run:

```
offset  size  field
0       8     magic b"AAAFMUST"
8       4     format version (uint32, little-endian), FORMAT_VERSION
12      4     reserved, 0
16      8     body length in bytes (uint64); the whole state is 56 + body length bytes
24      32    SHA-256 of the body
56      ...   body: uint64 length of the document, the document (UTF-8 JSON), zero padding to
              8 bytes, then the raw arrays (little-endian, C order), each at an 8-byte offset
```

The document holds the FMU's identity (model name, instantiationToken, which changes with the
package's source code: a state of another build is refused), the C layer's fields (mode, step,
time), every variable's values (as arrays, with their sizes), the strings, and the model's
objects as a tree. A tree node is a JSON number, string, true/false/null, or a tagged object:

``{"l": [...]}`` list, ``{"t": [...]}`` tuple, ``{"d": [[key, value], ...]}`` dict,
``{"a": k}`` the k-th array, ``{"n": [dtype, value]}`` a numpy scalar, ``{"f": x}`` a float
that JSON cannot spell (NaN, infinities, as text), ``{"o": [class, id, state]}`` an object,
``{"r": id}`` a second reference to an object, ``{"c": class}`` a class, ``{"m": [object,
name]}`` a bound method.

Objects and classes are named relative to the FMU's own package (``model.TissueModel``) and are
resolved only among the classes and functions that package defines (:class:`Codec` is made with
that allow list); an object is made with ``cls.__new__`` and given its state with the class's own
``__setstate__`` (or its ``__dict__``), as :mod:`copy` does. Nothing in the bytes can name a
function outside the package, and nothing is called but the package's own code. Arrays are
plain numeric or boolean numpy arrays: their dtype is checked against an allow list and their
size against the bytes that hold them before anything is read.
"""
from __future__ import annotations

import hashlib
import json
import math
import struct
import types

import numpy as np

MAGIC = b"AAAFMUST"
FORMAT_VERSION = 1
_PREFIX = struct.Struct("<8sIIQ32s")  # magic, version, reserved, body length, SHA-256 of the body
PREFIX_SIZE = _PREFIX.size
_LENGTH = struct.Struct("<Q")
_ALIGN = 8
#: The arrays a state may hold: plain little-endian numbers and booleans (no objects, no strings).
ARRAY_DTYPES = frozenset(np.dtype(t).str for t in (
    np.float64, np.float32, np.int64, np.int32, np.int16, np.int8, np.uint64, np.uint32, np.uint16, np.uint8,
    np.bool_, np.complex128))
#: Nesting deeper than this is no model state (and would exhaust the parser's stack).
MAX_DEPTH = 64
#: A state's JSON document beyond this is not one this layer wrote.
MAX_DOCUMENT_BYTES = 64 << 20


class StateFormatError(ValueError):
    """Bytes that are not a state this FMU can restore; the message says why."""


def _aligned(n: int) -> int:
    return (n + _ALIGN - 1) // _ALIGN * _ALIGN


class Codec:
    """Encodes and decodes a tree of plain data and of the objects of one package.

    ``package`` is the module name the FMU's package is imported under; ``modules`` its modules.
    Only classes and functions defined in those modules can be named by a state."""

    def __init__(self, package: str, modules):
        self.package = package
        self._allowed: dict[str, object] = {}
        for module in modules:
            relative = module.__name__[len(package):].lstrip(".") or "__init__"
            for name, value in vars(module).items():
                if isinstance(value, (type, types.FunctionType)) and getattr(value, "__module__", None) == module.__name__:
                    self._allowed[f"{relative}.{name}"] = value
        self._names = {id(v): k for k, v in self._allowed.items()}

    # -- encoding ------------------------------------------------------------------------------------
    def encode(self, document: dict, trees: dict) -> bytes:
        """The state's bytes: ``document`` (plain JSON data) plus each of ``trees`` encoded."""
        arrays: list[np.ndarray] = []
        memo: dict[int, int] = {}
        keep: list = []  # the objects memo's ids refer to stay alive while encoding
        encoded = dict(document)
        encoded["trees"] = {name: self._encode(value, arrays, memo, keep, 0) for name, value in trees.items()}
        layout, offset = [], 0
        for array in arrays:
            layout.append([array.dtype.str, list(array.shape), offset])
            offset = _aligned(offset + array.nbytes)
        encoded["arrays"] = layout
        text = json.dumps(encoded, allow_nan=False, separators=(",", ":")).encode()
        head = _LENGTH.pack(len(text)) + text
        start = _aligned(len(head))
        body = bytearray(start + offset)
        body[:len(head)] = head
        for array, (_, _, at) in zip(arrays, layout):
            body[start + at:start + at + array.nbytes] = np.ascontiguousarray(array).tobytes()
        digest = hashlib.sha256(body).digest()
        return _PREFIX.pack(MAGIC, FORMAT_VERSION, 0, len(body), digest) + bytes(body)

    def _name_of(self, value) -> str:
        name = self._names.get(id(value))
        if name is None:
            raise TypeError(f"{getattr(value, '__module__', '?')}.{getattr(value, '__qualname__', value)!s} is not "
                            f"defined in the FMU's package {self.package}: it cannot be part of a serialized state")
        return name

    def _encode(self, value, arrays, memo, keep, depth):
        if depth > MAX_DEPTH:
            raise TypeError(f"the model state nests deeper than {MAX_DEPTH} levels")
        if value is None or isinstance(value, (bool, str)):
            return value
        if isinstance(value, int) and type(value) is int:
            return value
        if type(value) is float:
            return value if math.isfinite(value) else {"f": repr(value)}
        if type(value) is np.ndarray:
            if value.dtype.str not in ARRAY_DTYPES:
                raise TypeError(f"an array of dtype {value.dtype} cannot be part of a serialized state")
            arrays.append(value)
            return {"a": len(arrays) - 1}
        if isinstance(value, np.generic):
            if value.dtype.str not in ARRAY_DTYPES:
                raise TypeError(f"a numpy scalar of dtype {value.dtype} cannot be part of a serialized state")
            item = value.item()
            return {"n": [value.dtype.str, item if not isinstance(item, float) or math.isfinite(item) else repr(item)]}
        d = depth + 1
        if type(value) is list:
            return {"l": [self._encode(v, arrays, memo, keep, d) for v in value]}
        if type(value) is tuple:
            return {"t": [self._encode(v, arrays, memo, keep, d) for v in value]}
        if type(value) is dict:
            return {"d": [[self._encode(k, arrays, memo, keep, d), self._encode(v, arrays, memo, keep, d)]
                          for k, v in value.items()]}
        if isinstance(value, (type, types.FunctionType)):
            return {"c": self._name_of(value)}
        if isinstance(value, types.MethodType):
            if not self._in_package(value.__func__):
                raise TypeError(f"the method {value.__func__.__qualname__} is not defined in the FMU's package")
            return {"m": [self._encode(value.__self__, arrays, memo, keep, d), value.__func__.__name__]}
        cls = type(value)
        name = self._name_of(cls)
        if id(value) in memo:
            return {"r": memo[id(value)]}
        memo[id(value)] = len(memo)
        keep.append(value)
        return {"o": [name, memo[id(value)], self._encode(value.__getstate__(), arrays, memo, keep, d)]}

    # -- decoding ------------------------------------------------------------------------------------
    def decode(self, data: bytes) -> tuple[dict, dict]:
        """(document, trees) from a state's bytes; StateFormatError when they are not one."""
        view = memoryview(data)
        if len(view) < PREFIX_SIZE:
            raise StateFormatError(f"{len(view)} bytes are too few for an FMU state of this layer (at least "
                                   f"{PREFIX_SIZE})")
        magic, version, reserved, length, digest = _PREFIX.unpack_from(view, 0)
        if magic != MAGIC:
            raise StateFormatError("these bytes are not an FMU state serialized by this FMI layer (wrong magic)")
        if version != FORMAT_VERSION or reserved != 0:
            raise StateFormatError(f"the state is in format version {version}; this FMU reads version "
                                   f"{FORMAT_VERSION}: serialize it again with this build of the FMU")
        if length != len(view) - PREFIX_SIZE:
            raise StateFormatError(f"the state says its body has {length} bytes but {len(view) - PREFIX_SIZE} "
                                   "follow the header: it is truncated or has bytes appended")
        body = view[PREFIX_SIZE:]
        if hashlib.sha256(body).digest() != digest:
            raise StateFormatError("the state's SHA-256 does not match its contents: the bytes were damaged "
                                   "(or changed) after fmi3SerializeFMUState wrote them")
        if len(body) < _LENGTH.size:
            raise StateFormatError("the state has no document")
        (text_length,) = _LENGTH.unpack_from(body, 0)
        if text_length > min(MAX_DOCUMENT_BYTES, len(body) - _LENGTH.size):
            raise StateFormatError("the state's document length is out of range")
        try:
            document = json.loads(bytes(body[_LENGTH.size:_LENGTH.size + text_length]).decode())
        except (ValueError, RecursionError) as exc:
            raise StateFormatError(f"the state's document is not valid JSON ({exc})") from None
        if not isinstance(document, dict):
            raise StateFormatError("the state's document is not a JSON object")
        start = _aligned(_LENGTH.size + text_length)
        arrays = self._arrays(document.get("arrays"), body[start:] if start <= len(body) else body[:0])
        trees = document.pop("trees", None)
        if not isinstance(trees, dict):
            raise StateFormatError("the state has no model trees")
        memo: dict[int, object] = {}
        try:
            decoded = {name: self._decode(tree, arrays, memo, 0) for name, tree in trees.items()}
        except RecursionError:
            raise StateFormatError(f"the state's model tree nests deeper than {MAX_DEPTH} levels") from None
        return document, decoded

    @staticmethod
    def _arrays(layout, data) -> list[np.ndarray]:
        if not isinstance(layout, list):
            raise StateFormatError("the state has no array table")
        arrays, end = [], 0
        for k, entry in enumerate(layout):
            if not (isinstance(entry, list) and len(entry) == 3 and isinstance(entry[0], str)
                    and isinstance(entry[1], list) and all(type(n) is int and n >= 0 for n in entry[1])
                    and type(entry[2]) is int and entry[2] >= 0):
                raise StateFormatError(f"array {k} of the state has a malformed entry")
            dtype, shape, offset = entry
            if dtype not in ARRAY_DTYPES:
                raise StateFormatError(f"array {k} of the state has dtype {dtype!r}, which no state holds")
            if offset != _aligned(end) or len(shape) > 8:
                raise StateFormatError(f"array {k} of the state is not where the layout puts it")
            count = math.prod(shape)
            nbytes = count * np.dtype(dtype).itemsize
            if offset + nbytes > len(data):
                raise StateFormatError(f"array {k} of the state ({nbytes} bytes) runs past the end of the state")
            arrays.append(np.frombuffer(data, dtype=dtype, count=count, offset=offset).reshape(shape).copy())
            end = offset + nbytes
        if _aligned(end) != len(data):
            raise StateFormatError("the state has bytes after its last array")
        return arrays

    def owns(self, obj) -> bool:
        """Whether ``obj`` is an instance of one of the package's classes."""
        return id(type(obj)) in self._names

    def _in_package(self, function) -> bool:
        module = getattr(function, "__module__", None) or ""
        return module == self.package or module.startswith(self.package + ".")

    def _lookup(self, name):
        value = self._allowed.get(name) if isinstance(name, str) else None
        if value is None:
            raise StateFormatError(f"the state names {name!r}, which is no class of the FMU's package")
        return value

    def _decode(self, node, arrays, memo, depth):
        if depth > MAX_DEPTH:
            raise StateFormatError(f"the state's model tree nests deeper than {MAX_DEPTH} levels")
        if node is None or isinstance(node, (bool, str, int, float)):
            return node
        if not (isinstance(node, dict) and len(node) == 1):
            raise StateFormatError(f"the state holds a malformed node ({type(node).__name__})")
        (tag, value), = node.items()
        d = depth + 1
        if tag == "l" and isinstance(value, list):
            return [self._decode(v, arrays, memo, d) for v in value]
        if tag == "t" and isinstance(value, list):
            return tuple(self._decode(v, arrays, memo, d) for v in value)
        if tag == "d" and isinstance(value, list):
            result = {}
            for pair in value:
                if not (isinstance(pair, list) and len(pair) == 2):
                    raise StateFormatError("the state holds a malformed dict entry")
                key = self._decode(pair[0], arrays, memo, d)
                if not isinstance(key, (str, int, float, bool, tuple, type(None))):
                    raise StateFormatError("the state holds a dict key that is no plain value")
                result[key] = self._decode(pair[1], arrays, memo, d)
            return result
        if tag == "a" and type(value) is int and 0 <= value < len(arrays):
            return arrays[value]
        if tag == "f" and value in ("nan", "inf", "-inf"):
            return float(value)
        if tag == "n" and isinstance(value, list) and len(value) == 2 and value[0] in ARRAY_DTYPES:
            item = value[1]
            if isinstance(item, str) and item in ("nan", "inf", "-inf"):
                item = float(item)
            if not isinstance(item, (bool, int, float)):
                raise StateFormatError("the state holds a malformed numpy scalar")
            try:
                return np.array(item, dtype=value[0])[()]
            except (OverflowError, ValueError):
                raise StateFormatError(f"the numpy scalar {item!r} does not fit {value[0]}") from None
        if tag == "c":
            return self._lookup(value)
        if tag == "m" and isinstance(value, list) and len(value) == 2 and isinstance(value[1], str):
            owner = self._decode(value[0], arrays, memo, d)
            function = getattr(type(owner), value[1], None) if id(type(owner)) in self._names else None
            if not (isinstance(function, types.FunctionType) and self._in_package(function)):
                raise StateFormatError(f"the state names a method {value[1]!r} its object's class does not define")
            return types.MethodType(function, owner)
        if tag == "r" and type(value) is int and value in memo:
            return memo[value]
        if tag == "o" and isinstance(value, list) and len(value) == 3 and type(value[1]) is int:
            cls = self._lookup(value[0])
            if not isinstance(cls, type) or value[1] != len(memo):
                raise StateFormatError(f"the state holds a malformed object of {value[0]!r}")
            obj = cls.__new__(cls)
            memo[value[1]] = obj  # before its state: the state may refer back to it
            state = self._decode(value[2], arrays, memo, d)
            _set_state(obj, state, value[0])
            return obj
        raise StateFormatError(f"the state holds an unknown or malformed node {tag!r}")


def _set_state(obj, state, name: str) -> None:
    """Give ``obj`` the state ``__getstate__`` returned, as copy and pickle do."""
    setstate = getattr(type(obj), "__setstate__", None)
    if setstate is not None:
        try:
            obj.__setstate__(state)
        except Exception as exc:
            raise StateFormatError(f"the state of a {name} could not be restored ({type(exc).__name__}: {exc})") \
                from None
        return
    slots = None
    if isinstance(state, tuple) and len(state) == 2:
        state, slots = state
    for part in (state, slots):
        if part is None:
            continue
        if not (isinstance(part, dict) and all(isinstance(k, str) for k in part)):
            raise StateFormatError(f"the state of a {name} is not a mapping of attribute names")
    if state:
        obj.__dict__.update(state)
    for key, value in (slots or {}).items():
        object.__setattr__(obj, key, value)

"""Scene files: what a simulation couples, at which rates, and what it records.

A scene is a TOML file (annotated example: ``scenes/README.md``)::

    [scene]                      name, description, duration (s), hosting, realtime
    [fmu.<instance>]             path (to an .fmu), step (s: number or "1/30"), parameters (table)
    [source.<name>]              kind = "piecewise_linear" | "csv" | "rigid_surface" (continuous, no step)
    [block.<name>]               kind = "device_plant" (stepped built-in component), step, options
    [[connection]]               from = "a.port", to = "b.port", transition, ordering
    [record]                     <component> = [ports], surfaces, plots
    [summary]                    peaks, energy, warnings, deadlines

``load_scene`` parses and checks everything it can *before anything runs* and raises
``SceneError`` holding every problem found, each with where it is and how to fix it; nothing a
user writes in a scene produces a traceback. Times are exact rationals (``fractions.Fraction``):
a step given as ``0.001`` is 1/1000, ``"1/30"`` is 1/30.
"""
from __future__ import annotations

import logging
import math
import re
import tomllib
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np

from . import transitions as tr
from .fmi3 import fmu_binary_problem
from .ports import (INTEGER_RANGES, MAX_PORT_VALUES, NUMERIC_TYPES, READABLE, WRITABLE, FmuDescription, PortInfo,
                    conversion_problem, parse_binary, read_fmu)

logger = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parent.parent
SCENE_DIR = REPO_ROOT / "scenes"
FMU_DIR = REPO_ROOT / "fmus"

TRANSITIONS = tuple(tr.REGISTRY)
ORDERINGS = ("gauss-seidel", "jacobi")
HOSTINGS = ("in-process", "out-of-process")

_SCENE_KEYS = {"name", "description", "duration", "hosting", "realtime", "start_time", "worker_timeout"}
_FMU_KEYS = {"path", "step", "parameters", "hosting"}
_CONNECTION_KEYS = {"from", "to", "transition", "ordering"}
_SUMMARY_KEYS = {"peaks", "energy", "warnings", "deadlines"}
_SURFACE_KEYS = {"component", "positions", "triangles", "every", "point_data", "name"}
_PLOT_KEYS = {"file", "title", "panels"}
_PANEL_KEYS = {"ylabel", "series"}
_SERIES_KEYS = {"stream", "column", "label", "norm"}

# -- plausibility limits: values no scene of this project can mean ---------------------------------
#: The shortest communication step, s. The fastest loop here is the 1 kHz haptic loop (studies go
#: down to 4 kHz); a step below 1 us is a typo (a unit slip) and would take hours per simulated second.
MIN_STEP = Fraction(1, 10**6)
#: The longest communication step, s. The slowest component, the tissue, steps at 30 Hz (studies
#: down to 10 Hz); a step above 1 s cannot track a haptic interaction at all.
MAX_STEP = Fraction(1)
#: The most component steps one run may take (the sum over stepped components of duration / step).
#: This machine makes about 3500 steps per second of wall time (the default scene: 8120 steps in
#: 2.3 s), so the limit is about 50 minutes of computing: a longer run is almost always a duration
#: in ms typed as s. It is refused, not warned about, so that `validate` and the exit code stop a
#: script or study before it blocks a machine for hours; split a genuinely long session into runs.
MAX_RUN_STEPS = 10_000_000
#: The deepest nesting of tables and lists a scene may have. The format nests at most 5 levels
#: ([record] plots, panels, series, a table); far deeper nesting is no scene, and would exhaust
#: the interpreter's recursion limit (the TOML parser's, and ours) with a RecursionError, or (dotted
#: keys) the parser's memory. Checked on the text before parsing (``_nesting_problem``) and on the
#: parsed tree (``_too_deep``: scene_from_dict is also given trees that never were text).
MAX_NESTING = 32

#: A scene name names its result folder (results/<name>): a plain name, never a path.
_SCENE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,99}")
#: A component name is a file name (<component>.csv) and the first part of "component.port".
_COMPONENT_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_-]{0,63}")
#: A file the scene asks the recording to write (a figure, a surface series) inside the result folder.
_FILE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,99}")


class SceneError(ValueError):
    """A scene has problems; ``problems`` lists every one ("where: what is wrong; the fix")."""

    def __init__(self, path, problems: list[str]):
        self.path = Path(path) if path is not None else None
        self.problems = list(problems)
        head = f"{self.path}: " if self.path else ""
        count = f"{len(self.problems)} problem{'s' if len(self.problems) != 1 else ''}"
        super().__init__(f"{head}{count}\n" + "\n".join(f"  - {p}" for p in self.problems))


@dataclass
class ComponentSpec:
    """One component of a scene: an FMU, a stepped block or a continuous source."""

    name: str
    kind: str                                   # "fmu", or a block kind ("device_plant", "piecewise_linear", ...)
    step: Fraction | None                       # None for continuous sources
    parameters: dict = field(default_factory=dict)
    path: Path | None = None                    # FMUs
    table: dict = field(default_factory=dict)   # blocks: their TOML table
    ports: dict[str, PortInfo] = field(default_factory=dict)
    description: FmuDescription | None = None
    base_dir: Path | None = None                # blocks: where their relative paths start
    hosting: str | None = None                  # FMUs: "in-process" | "out-of-process" (None: the scene's)

    def new_block(self):
        """A fresh instance of a block or source (each run gets its own: a scene is data)."""
        from .blocks import make_block

        return make_block(self.name, self.table, self.base_dir)

    @property
    def is_fmu(self) -> bool:
        return self.kind == "fmu"

    @property
    def is_continuous(self) -> bool:
        return self.step is None


@dataclass(frozen=True)
class ConnectionSpec:
    source: str
    source_port: str
    target: str
    target_port: str
    transition: str | None
    ordering: str
    index: int

    @property
    def label(self) -> str:
        return f"connection {self.index} ({self.source}.{self.source_port} -> {self.target}.{self.target_port})"


@dataclass(frozen=True)
class SurfaceSpec:
    component: str
    positions: str
    triangles: str
    every: int = 1
    point_data: tuple[str, ...] = ()
    name: str = "surface"


@dataclass
class Scene:
    path: Path | None
    name: str
    description: str
    duration: Fraction
    components: dict[str, ComponentSpec]
    connections: list[ConnectionSpec]
    record: dict[str, list[str]]
    surfaces: list[SurfaceSpec]
    plots: list[dict]
    summary: dict
    hosting: str = "out-of-process"
    realtime: bool = False
    #: run-faults (issue 14): seconds a worker process may take to answer during the run;
    #: None: automatic, max(10 s, 100 x its slowest recent reply) (see orchestration.worker)
    worker_timeout: float | None = None

    def incoming(self, component: str) -> list[ConnectionSpec]:
        return [c for c in self.connections if c.target == component]

    def outgoing(self, component: str) -> list[ConnectionSpec]:
        return [c for c in self.connections if c.source == component]


# -- small parsers that collect problems instead of raising ------------------------------------
def parse_time(value, where: str, problems: list[str], *, allow_zero: bool = False) -> Fraction | None:
    """A time in seconds as an exact Fraction: a number (0.001 is 1/1000) or a string "1/30"."""
    try:
        if isinstance(value, bool):
            raise TypeError
        if isinstance(value, Fraction):
            result = value
        elif isinstance(value, (int, float)):
            if not np.isfinite(value):
                raise ValueError
            result = float_time(value) if isinstance(value, float) else Fraction(value)
        elif isinstance(value, str):
            result = _parse_time_text(value)
        else:
            raise TypeError
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        problems.append(f"{where}: {value!r} is not a time in seconds; write a finite number (0.001) "
                        "or a ratio (\"1/30\")")
        return None
    if result < 0 or (result == 0 and not allow_zero):
        problems.append(f"{where}: must be positive (got {value!r} s)")
        return None
    return result


def _parse_time_text(text: str) -> Fraction:
    """ "0.001", "1e-3" or "1/30" as a Fraction; ValueError otherwise. Decimals go through a float
    first: ``Fraction("1e-999999999")`` would compute 10**999999999 and never return."""
    text = text.strip()
    if "/" in text:
        numerator, denominator = text.split("/", 1)
        return Fraction(int(numerator), int(denominator))
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(text)
    return float_time(value)


def step_problem(step: Fraction) -> str | None:
    """Why ``step`` cannot be meant as a communication step (outside MIN_STEP..MAX_STEP), or None."""
    if step < MIN_STEP:
        return (f"{format_time(step).strip(chr(34))} s is shorter than {MIN_STEP} s, the shortest step a component "
                f"of this project can mean (the haptic loop runs at 1 kHz); give the step in seconds, e.g. 0.001")
    if step > MAX_STEP:
        return (f"{float(step):g} s is longer than {MAX_STEP} s, the longest step a component of this project can "
                "mean (the tissue runs at 30 Hz); give the step in seconds, e.g. \"1/30\"")
    return None


def float_time(value: float) -> Fraction:
    """The time a float means: 0.001 is 1/1000, and 0.03333333333333333 (1/30 rounded, as model
    descriptions write it) is 1/30, the simple ratio whose nearest float it is."""
    exact = Fraction(repr(value))
    if exact.denominator > 10**6:
        simple = exact.limit_denominator(10**6)
        if float(simple) == value:
            return simple
    return exact


def _parse_endpoint(text, where: str, problems: list[str]) -> tuple[str, str] | None:
    if not isinstance(text, str) or text.count(".") != 1 or not all(text.split(".")):
        problems.append(f"{where}: {text!r} is not \"component.port\" (e.g. \"contact.tool_force\")")
        return None
    comp, port = text.split(".")
    return comp.strip(), port.strip()


def _unknown_keys(table: dict, allowed: set, where: str, problems: list[str]) -> None:
    for key in table:
        if key not in allowed:
            problems.append(f"{where}: unknown key {key!r}; valid keys: {', '.join(sorted(allowed))}")


def resolve_fmu_path(value, scene_dir: Path) -> tuple[Path | None, list[Path]]:
    """An FMU path relative to the scene folder, else to ``fmus/``; returns (path or None, tried)."""
    raw = Path(str(value))
    tried = [raw] if raw.is_absolute() else [scene_dir / raw, FMU_DIR / raw]
    for candidate in tried:
        if candidate.is_file():
            return candidate.resolve(), tried
    return None, tried


def _type_matches(port: PortInfo, value) -> bool:
    values = np.ravel(np.asarray(value, dtype=object)) if isinstance(value, list) else [value]
    if port.type == "String":
        return all(isinstance(v, str) for v in values)
    if port.type == "Binary":
        return all(isinstance(v, str) and _is_hex(v) for v in values)
    if port.type == "Enumeration":
        return all((isinstance(v, int) and not isinstance(v, bool)) or (isinstance(v, str) and port.item_value(v) is not None)
                   for v in values)
    if port.type == "Boolean":
        return all(isinstance(v, bool) for v in values)
    if port.type.startswith("Float"):
        return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
    return all(isinstance(v, int) and not isinstance(v, bool) for v in values)


def _is_hex(text: str) -> bool:
    try:
        parse_binary(text)
    except ValueError:
        return False
    return True


def _expected(port: PortInfo) -> str:
    """What a parameter of ``port``'s type is written as in a scene."""
    if port.type == "Binary":
        return "Binary values, written in hexadecimal (\"0a1bff\")"
    if port.type == "Enumeration":
        items = ", ".join(f"{name!r} ({value})" for name, value in port.items)
        return f"Enumeration values: an item name or its value ({items})" if items else "Enumeration values (integers)"
    return f"{port.type} values"


def format_time(value: Fraction) -> str:
    """A time as a scene writes it: a decimal when exact (0.002), else a ratio in quotes ("1/30")."""
    d = value.denominator
    while d % 2 == 0:
        d //= 2
    while d % 5 == 0:
        d //= 5
    if d == 1:
        return repr(float(value)) if value.denominator != 1 else str(value.numerator)
    return f'"{value.numerator}/{value.denominator}"'


def _size_of(value) -> int:
    return int(np.asarray(value, dtype=object).size) if isinstance(value, list) else 1


def _type_of(port: PortInfo) -> str:
    """"Int32", or "Enumeration Mode" for an enumeration with its declared type."""
    if port.type == "Enumeration" and port.declared_type:
        return f"Enumeration {port.declared_type}"
    return port.type


# -- loading -------------------------------------------------------------------------------------
def load_scene(path: Path | str, overrides: dict | None = None) -> Scene:
    """Read and check a scene; raise ``SceneError`` listing every problem.

    ``path`` is a TOML file, or the bare name of a shipped scene (``scenes/<name>.toml``).
    ``overrides`` maps ``"component.parameter"`` (``"component.step"`` for the step,
    ``"scene.duration"`` or ``"duration"``) to values that replace the file's, as studies, ``--set``
    and ``--duration`` do.
    """
    try:
        path = Path(path)
        # Only a bare name means a shipped scene: "x/virtual_wall" is a path, not that scene.
        if not path.suffix and len(path.parts) == 1 and not path.exists():
            candidate = SCENE_DIR / f"{path.name}.toml"
            if candidate.is_file():
                path = candidate
        found = path.is_file()
    except (TypeError, ValueError, OSError) as exc:  # a NUL byte, a name too long for the file system
        raise SceneError(None, [f"scene {str(path)!r}: not a usable file name ({exc})"]) from None
    if not found:
        shipped = ", ".join(sorted(p.stem for p in SCENE_DIR.glob("*.toml")))
        raise SceneError(path, [f"scene file not found; shipped scenes: {shipped} (or give a path to a .toml file)"])
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SceneError(path, [f"not UTF-8 text (byte {exc.object[exc.start]:#04x} at offset {exc.start}): "
                                "TOML files are UTF-8; save the file as UTF-8"]) from None
    except OSError as exc:
        raise SceneError(path, [f"cannot read the file: {exc.strerror or exc}"]) from None
    deep = _nesting_problem(text)  # before the parser, which deep nesting makes recurse or grow as n**2
    if deep is not None:
        raise SceneError(path, [deep])
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(path, [f"TOML syntax error: {exc}"]) from None
    except RecursionError:
        raise SceneError(path, [f"TOML syntax error: tables or lists nested too deeply to parse; a scene nests at most "
                                f"{MAX_NESTING} levels"]) from None
    return scene_from_dict(data, path.parent, path, overrides)


def _too_deep(data) -> str | None:
    """Where ``data`` nests deeper than MAX_NESTING ("fmu.x.parameters.y[0]..."), or None; iterative,
    so that the check itself cannot exhaust the recursion limit."""
    stack = [(data, "", 0)]
    while stack:
        node, where, depth = stack.pop()
        if depth > MAX_NESTING:
            return where[:60] + ("..." if len(where) > 60 else "")
        if isinstance(node, dict):
            stack.extend((v, f"{where}.{k}" if where else str(k), depth + 1) for k, v in node.items())
        elif isinstance(node, list):
            stack.extend((v, f"{where}[{i}]", depth + 1) for i, v in enumerate(node))
    return None


#: The tokens of TOML text that matter to its nesting: strings (skipped whole: their content is not
#: structure), comments, line ends, brackets, braces, '=', ',' and '.'; anything else is a bare
#: word (a key part or a scalar). An unterminated string runs to the end of its line (a multi-line
#: one to the end of the text), as far as the parser would read it.
_TOML_TOKEN = re.compile("|".join((
    r'(?P<string>"""(?:[^"\\]|\\.|"(?!""))*(?:"""(?:"{1,2}(?!"))?)?',      # """multi-line basic"""
    r"'''(?:[^']|'(?!''))*(?:'''(?:'{1,2}(?!'))?)?",                       # '''multi-line literal'''
    r'"(?:[^"\\\n]|\\.)*"?',                                               # "basic"
    r"'[^'\n]*'?)",                                                        # 'literal'
    r"(?P<skip>\#[^\n]*|[ \t\r]+)",                                        # comments, blanks
    r"(?P<newline>\n)",
    r"(?P<mark>[\[\]{}=,.])",
    r"(?P<word>[^\s\[\]{}=,.#\"']+)",
)), re.DOTALL)


def _toml_depth(text: str, limit: int) -> tuple[int, int]:
    """(depth, offset): the first place TOML ``text`` nests deeper than ``limit`` levels, or the
    deepest nesting it has (offset -1).

    Depth as ``_too_deep`` counts it in the parsed tree (a top-level value is at 1): a key of n
    parts lies n levels below its table (dotted keys in a [table.header] and in { inline tables }
    too), an array's items one level below the array, the items of an [[array.of.tables]] one
    below its name. One pass over the tokens, linear in the text and never recursive; for valid
    TOML it is the parsed depth, for invalid TOML an estimate (the parser then reports the error).
    """
    stack: list[tuple[str, int]] = []   # open arrays and inline tables: ("[", its items' depth) or ("{", its own)
    state = "key"                       # "key" (reading one), "value" (expecting one), "after" (one ended)
    table = base = dots = 0             # the current [table]'s depth; the depth being read; a key's dots
    header = None                       # inside [a.b] / [[a.b]]: its key parts so far
    array_of_tables = False             # ... and whether it is [[a.b]]
    arrays: set[tuple[str, ...]] = set()  # the [[arrays.of.tables]] seen
    statement_start = True              # a '[' here opens a table header, not an array
    deepest = 0
    for match in _TOML_TOKEN.finditer(text):
        kind, token = match.lastgroup, match.group()
        if kind == "skip":
            continue
        if kind == "newline":
            if not stack and header is None:  # inside an array, items go on over lines
                state, base, dots, statement_start = "key", table, 0, True
            continue
        depth = 0
        if header is not None:          # [a.b] or [[a.b]]: its key parts so far in `header`
            if token == "[" and not header and not array_of_tables:
                array_of_tables = True
            elif token == "]":
                # Each array of tables on the path adds a level: [[a]] then [a.b] puts b in a's last item.
                path = tuple(header)
                if array_of_tables:
                    arrays.add(path)
                table = len(path) + sum(path[:i] in arrays for i in range(1, len(path) + 1))
                depth, header, state = table, None, "after"
            elif token != ".":
                header.append(token.strip("\"'") if kind == "string" else token)
            if header is not None:
                depth = len(header)
        elif state == "key":
            if token == "[" and statement_start and not stack:
                header, array_of_tables = [], False
            elif token == ".":
                dots += 1
                depth = base + dots + 1
            elif token == "=":
                base += dots + 1
                depth, state = base, "value"
            elif token == "}" and stack and stack[-1][0] == "{":   # {} or a trailing comma
                stack.pop()
                state = "after"
            statement_start = False
        elif state == "value":
            depth = base if token != "]" else 0
            if token == "[":
                base += 1
                stack.append(("[", base))
            elif token == "{":
                stack.append(("{", base))
                state, dots = "key", 0
            elif token == "]" and stack and stack[-1][0] == "[":   # [] or a trailing comma
                stack.pop()
                state = "after"
            else:                       # a scalar (or something the parser will refuse)
                state = "after"
        elif token == "," and stack:    # "after" a value: the next item or key
            bracket, base = stack[-1]
            state, dots = ("value" if bracket == "[" else "key"), 0
        elif token in ("]", "}") and stack and stack[-1][0] == ("[" if token == "]" else "{"):
            stack.pop()
        if depth > deepest:
            deepest = depth
            if depth > limit:
                return depth, match.start()
    return deepest, -1


def _nesting_problem(text: str) -> str | None:
    """Why TOML ``text`` nests too deeply to be a scene (a problem for SceneError), or None.

    Checked before the TOML parser runs, because the parser itself is the danger: it recurses once
    per nested bracket or brace (a RecursionError), and a dotted key ``x.x.x... = 1`` of n parts
    costs it memory and time growing as n**2 (70,000 parts, a 140 KB file, took 24 GB).
    """
    depth, offset = _toml_depth(text, MAX_NESTING)
    if offset < 0:
        return None
    line = text.count("\n", 0, offset) + 1
    return (f"top level: TOML nested too deeply: line {line} nests tables, lists or dotted keys (a.b.c = ...) more than "
            f"{MAX_NESTING} levels deep; a scene nests at most 5 levels (see scenes/README.md): check the "
            "brackets and the dots of the keys on that line")


def _table(value, where: str, problems: list[str], fix: str) -> dict:
    """``value`` if it is a table; else a problem and an empty table (so checking goes on)."""
    if isinstance(value, dict):
        return value
    problems.append(f"{where}: must be a table ({fix}), got {type(value).__name__} {_short(value)}")
    return {}


def _list(value, where: str, problems: list[str], fix: str) -> list:
    if isinstance(value, list):
        return value
    problems.append(f"{where}: must be a list ({fix}), got {type(value).__name__} {_short(value)}")
    return []


def _each_table(items: list, where: str, keys, problems: list[str], shape: str):
    """``(where[i], item)`` for each table in ``items``; a problem for each item that is not a
    table (it is skipped) and for each unknown key."""
    for i, item in enumerate(items):
        at = f"{where}[{i}]"
        if not isinstance(item, dict):
            problems.append(f"{at}: must be a table {shape}")
            continue
        _unknown_keys(item, keys, at, problems)
        yield at, item


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _strings(values: list, where: str, problems: list[str], what: str) -> list[str]:
    """The strings of ``values``; a problem for each item that is not one."""
    good = []
    for i, item in enumerate(values):
        if isinstance(item, str):
            good.append(item)
        else:
            problems.append(f"{where}[{i}]: {_short(item)} is not {what} (write it in quotes)")
    return good


#: Control characters (Unicode category Cc: U+0000-U+001F, U+007F-U+009F). None belongs in a name, a
#: path or a parameter: a NUL ends the string where C reads it (the FMU got "regulate" of
#: "regulate\u0000garbage", a mesh path was cut short), the others (a tab, an escape sequence) are
#: typing accidents that no file name, port or mode means. TOML writes them only as escapes (\u0000).
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")
#: Keys whose strings are free text for people (a description, a figure's title and labels): they
#: may hold tabs and line breaks, nothing else of Cc.
_FREE_TEXT_KEYS = frozenset({"description", "title", "ylabel", "label"})
_LINE_CONTROLS = frozenset("\t\n\r")


def _location(path: tuple) -> str:
    """Where a parsed value is, as the other problems say it: "[fmu.tissue] parameters.mesh_file",
    "connection 2 from", "[record] surfaces[0].name"."""
    if not path:
        return "top level"
    head, rest = path[0], path[1:]
    if head in ("fmu", "source", "block") and rest and isinstance(rest[0], str):
        where, rest = f"[{head}.{rest[0]}]", rest[1:]
    elif head == "connection" and rest and isinstance(rest[0], int):
        where, rest = f"connection {rest[0] + 1}", rest[1:]
    else:
        where = f"[{head}]"
    tail = "".join(f"[{part}]" if isinstance(part, int) else f".{part}" for part in rest).lstrip(".")
    return f"{where} {tail}" if tail else where


def _control_problem(text: str, where: str, what: str, free_text: bool = False) -> str | None:
    """Why ``text`` (a string of the scene) cannot be used: it holds a control character; or None."""
    bad = [m for m in _CONTROL.finditer(text) if not (free_text and m.group() in _LINE_CONTROLS)]
    if not bad:
        return None
    char, at = bad[0].group(), bad[0].start()
    name = {"\x00": "NUL", "\t": "TAB", "\n": "LF, a line break", "\r": "CR", "\x1b": "ESC"}.get(char)
    shown = f"{name} (U+{ord(char):04X})" if name else f"U+{ord(char):04X}"
    return (f"{where}: {what} {_short(text)} holds the control character {shown} at position {at}; names, paths and "
            "parameters are printable text (a NUL would cut the string short where it is used): remove it "
            "(a TOML escape such as \\u0000 or \\t writes one)")


def _control_character_problems(data: dict, overrides: dict | None) -> list[str]:
    """Every key and string of the scene (and of its overrides) that holds a control character;
    iterative, like ``_too_deep``, after which it runs."""
    problems: list[str] = []
    stack: list[tuple[object, tuple]] = [(data, ())]
    while stack:
        node, path = stack.pop()
        if isinstance(node, dict):
            for key in node:
                problem = _control_problem(key, _location(path), "the key") if isinstance(key, str) else None
                if problem:
                    problems.append(problem)
            # reversed onto the stack: the problems come in the file's order
            stack.extend((value, path + (key,)) for key, value in reversed(node.items()))
        elif isinstance(node, list):
            stack.extend((value, path + (i,)) for i, value in reversed(list(enumerate(node))))
        elif isinstance(node, str):
            key = next((part for part in reversed(path) if isinstance(part, str)), None)
            problem = _control_problem(node, _location(path), "the value", free_text=key in _FREE_TEXT_KEYS)
            if problem:
                problems.append(problem)
    for key, value in (overrides or {}).items():
        texts = [("the key", key)] + [("the value", v) for v in _flat(value)]
        for what, text in texts:
            problem = _control_problem(text, f"override {key!r}", what) if isinstance(text, str) else None
            if problem:
                problems.append(problem)
    return problems


def scene_name_problem(name) -> str | None:
    """Why ``name`` cannot name a scene (and its result folder results/<name>), or None."""
    if not isinstance(name, str):
        return f"must be a string (got {_short(name)})"
    if not _SCENE_NAME.fullmatch(name):
        return (f"{_short(name)} is not a plain name: a scene name names its result folder results/<name>, so it "
                "is 1-100 letters, digits, '_', '-' or '.', not starting with '.' or '-' (no '/', no path); "
                "choose the folder with `run --out DIR` instead")
    return None


def _component_name_problem(section: str, name: str) -> str | None:
    if not _COMPONENT_NAME.fullmatch(name) or name == "scene":
        return (f"[{section}.{name}]: {name!r} is not a usable component name: write 1-64 letters, digits, '_' or "
                "'-', starting with a letter or '_' (it names <component>.csv and the \"component.port\" of "
                "connections; 'scene' is reserved for scene.duration)")
    return None


def scene_from_dict(data: dict, base_dir: Path, path: Path | None = None, overrides: dict | None = None) -> Scene:
    """Build and check a scene from parsed TOML (``base_dir`` resolves relative paths)."""
    problems: list[str] = []
    deep = _too_deep(data)
    if deep is not None:
        raise SceneError(path, [f"{deep}: tables or lists nested more than {MAX_NESTING} levels deep; a scene "
                                "nests at most 5 (see scenes/README.md)"])
    problems += _control_character_problems(data, overrides)
    allowed_top = {"scene", "fmu", "source", "block", "connection", "record", "summary"}
    _unknown_keys(data, allowed_top, "top level", problems)
    overrides = dict(overrides or {})
    for key in list(overrides):
        if not isinstance(key, str) or (key != "duration" and (key.count(".") != 1 or not all(key.split(".")))):
            problems.append(f"override {key!r}: write component.parameter (e.g. contact.stiffness) or scene.duration")
            overrides.pop(key)

    head = _table(data.get("scene", {}), "[scene]", problems, "name, description, duration, ...")
    _unknown_keys(head, _SCENE_KEYS, "[scene]", problems)
    duration_where = "[scene] duration"
    for key in [k for k in overrides if k.startswith("scene.")]:
        field_name = key.split(".", 1)[1]
        if field_name not in _SCENE_KEYS:
            problems.append(f"override {key!r}: [scene] has no key {field_name!r}; valid keys: "
                            f"{', '.join(sorted(_SCENE_KEYS))}")
        elif field_name == "duration":
            duration_where = "scene.duration (override)"
        head = {**head, field_name: overrides.pop(key)}
    if "duration" in overrides:  # after scene.duration: `run --duration` wins over `--set scene.duration=`
        head = {**head, "duration": overrides.pop("duration")}
        duration_where = "duration (from the command line or a study)"
    name = head.get("name", path.stem if path else "scene")
    problem = scene_name_problem(name)
    if problem:
        where = "[scene] name" if "name" in head else f"[scene] name (taken from the file name {path.name!r})"
        problems.append(f"{where}: {problem}")
    description = head.get("description", "")
    if not isinstance(description, str):
        problems.append(f"[scene] description: must be a string (got {_short(description)})")
    duration = parse_time(head.get("duration", 1.0), duration_where, problems)
    if head.get("start_time", 0) not in (0, 0.0) or isinstance(head.get("start_time"), bool):
        problems.append("[scene] start_time: only 0 is supported; shift your sources instead")
    hosting = head.get("hosting", "out-of-process")
    if hosting not in HOSTINGS:
        problems.append(f"[scene] hosting: {_short(hosting)} is not one of {', '.join(HOSTINGS)}")
    realtime = head.get("realtime", False)
    if not isinstance(realtime, bool):
        problems.append(f"[scene] realtime: must be true or false (got {_short(realtime)})")
    # How long a worker may take to answer one call; None: derived from its recent replies (worker.py).
    # A day bounds it: a longer wait is a hang, and 10**400 would not even convert to seconds.
    worker_timeout = head.get("worker_timeout")
    if worker_timeout is not None and (isinstance(worker_timeout, bool) or not isinstance(worker_timeout, (int, float))
                                       or not 0 < worker_timeout <= 86400):
        problems.append(f"[scene] worker_timeout: seconds a worker may take to answer, a number in (0, 86400] "
                        f"(got {_short(worker_timeout)}); leave it out for the automatic max(10 s, 100 x slowest reply)")
        worker_timeout = None

    components: dict[str, ComponentSpec] = {}
    sections = {section: _table(data.get(section, {}), section, problems, f"one [{section}.<name>] table each")
                for section in ("fmu", "source", "block")}
    declared = {name for table in sections.values() for name in table}
    for section, table in sections.items():
        for component in table:
            problem = _component_name_problem(section, component)
            if problem:
                problems.append(problem)
    _load_fmus(sections["fmu"], base_dir, components, overrides, problems)
    _load_blocks(sections["source"], "source", base_dir, components, overrides, problems)
    _load_blocks(sections["block"], "block", base_dir, components, overrides, problems)
    for key in overrides:
        problems.append(f"override {key!r}: no such component parameter in the scene")
    if not components and not declared:
        problems.append("the scene has no [fmu.<name>] or [block.<name>]: nothing to simulate")

    if duration is not None:
        problem = duration_problem(components.values(), duration) or run_size_problem(components.values(), duration)
        if problem:
            problems.append(f"{duration_where}: {problem}")
    connections = _load_connections(data.get("connection", []), components, problems, declared)
    _check_algebraic_loops(connections, components, problems)
    record, surfaces, plots = _load_record(_table(data.get("record", {}), "[record]", problems,
                                                  "<component> = [ports], surfaces, plots"), components, problems,
                                           declared)
    summary = _table(data.get("summary", {}), "[summary]", problems, "peaks, energy, warnings")
    _unknown_keys(summary, _SUMMARY_KEYS, "[summary]", problems)
    for key in ("peaks", "energy", "warnings"):
        items = _list(summary.get(key, []), f"[summary] {key}", problems, 'of "component.port"')
        for i, item in enumerate(items):
            ref = _parse_endpoint(item, f"[summary] {key}[{i}]", problems)
            if ref and (ref[0] not in components or ref[1] not in components[ref[0]].ports):
                if ref[0] not in declared or ref[0] in components:  # else: that component's problem is reported
                    problems.append(f"[summary] {key}[{i}]: {item!r} is not a port of the scene")
            elif ref and components[ref[0]].ports[ref[1]].type not in NUMERIC_TYPES:
                problems.append(f"[summary] {key}[{i}]: {item!r} is a {components[ref[0]].ports[ref[1]].type} variable; "
                                "the summary takes numbers, Booleans and enumerations")
    if problems:
        raise SceneError(path, problems)
    return Scene(path=path, name=name, description=description, duration=duration,
                 components=components, connections=connections, record=record, surfaces=surfaces, plots=plots,
                 summary=summary, hosting=hosting, realtime=realtime,
                 worker_timeout=None if worker_timeout is None else float(worker_timeout))


def _apply_overrides(name: str, parameters: dict, overrides: dict) -> dict:
    parameters = dict(parameters)
    for key in [k for k in overrides if k.split(".", 1)[0] == name]:
        parameters[key.split(".", 1)[1]] = overrides.pop(key)
    return parameters


def _load_fmus(tables: dict, base_dir: Path, components: dict, overrides: dict, problems: list[str]) -> None:
    for name, table in tables.items():
        where = f"[fmu.{name}]"
        if not isinstance(table, dict):
            problems.append(f"{where}: must be a table with path, step and parameters")
            continue
        _unknown_keys(table, _FMU_KEYS, where, problems)
        if f"{name}.step" in overrides:  # "tissue.step" overrides the step, not a parameter
            table = {**table, "step": overrides.pop(f"{name}.step")}
        parameters = _apply_overrides(name, _table(table.get("parameters", {}), f"{where} parameters", problems,
                                                   f"[fmu.{name}.parameters] with name = value lines"), overrides)
        if "path" not in table:
            problems.append(f"{where}: no path; add path = \"Tissue.fmu\" (looked up next to the scene, then in fmus/)")
            continue
        if not isinstance(table["path"], str) or not table["path"].strip():
            problems.append(f"{where} path: must be the file name of an .fmu in quotes, e.g. path = \"Tissue.fmu\" "
                            f"(got {_short(table['path'])})")
            continue
        try:
            fmu_path, tried = resolve_fmu_path(table["path"], base_dir)
        except (ValueError, OSError) as exc:  # a NUL byte, a name too long for the file system
            problems.append(f"{where} path: {_short(table['path'])} is not a usable file name ({exc})")
            continue
        if fmu_path is None:
            problems.append(f"{where} path: {table['path']!r} not found (looked in {', '.join(str(t.parent) for t in tried)}); "
                            "build the FMUs with `python -m orchestration build`")
            continue
        # Array sizes follow the structural parameters: only plausible sizes go into the description
        # (a wrong one is reported by _check_parameters, and must not make read_fmu build huge shapes).
        sizes = {k: v for k, v in parameters.items()
                 if isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= MAX_PORT_VALUES}
        try:
            description = read_fmu(fmu_path, sizes)
        except (OSError, ValueError) as exc:
            problems.append(f"{where} path: {exc}")
            continue
        # what a run loads into a process: a truncated binary passes the description and kills it
        binary = fmu_binary_problem(fmu_path, description.model_identifier, description.ports)
        if binary:
            problems.append(f"{where} path: {binary}")
            continue
        fixed = description.fixed_internal_step
        step_value = table.get("step", description.default_step)
        if step_value is None and fixed is not None:
            step_value = format_time(fixed).strip('"')
        if step_value is None:
            problems.append(f"{where}: no step and the FMU declares no default step; add step = 0.001")
            continue
        step = parse_time(step_value, f"{where} step", problems)
        if step is not None and step_problem(step):
            problems.append(f"{where} step: {step_problem(step)}")
            step = None
        ports = description.ports
        for port in ports.values():
            if port.size > MAX_PORT_VALUES:
                problems.append(f"{where}: {port.name} would hold {port.size} values "
                                f"({'x'.join(map(str, port.shape))}), more than {MAX_PORT_VALUES} (a mesh far larger "
                                "than any this project runs): check the structural parameters that size it")
        if step is not None and "internal_step" in ports:
            # the project's FMUs: the scene's step is the model's own rate
            given = parameters.get("internal_step")
            number = isinstance(given, (int, float)) and not isinstance(given, bool) and _finite(given)
            if given is not None and (not number or abs(float(given) - float(step)) > 1e-12 * float(step)):
                problems.append(f"{where} parameters.internal_step = {_short(given)} differs from step = {step_value}; "
                                "remove the parameter (the master sets it from step)")
            parameters["internal_step"] = float(step)
        elif step is not None and fixed is not None and step % fixed != 0:
            # FMI 3.0: any communication step, unless the FMU computes in fixed internal steps
            below = step // fixed * fixed
            fixes = " or ".join(f"step = {format_time(s)}" for s in (below, below + fixed) if s > 0)
            internal = format_time(fixed).strip('"')
            problems.append(f"{where} step: {step_value} s is not a whole multiple of this FMU's fixed internal step "
                            f"{internal} s (fixedInternalStepSize); use {fixes}")
        _check_parameters(where, parameters, ports, problems)
        hosting = table.get("hosting")
        if hosting is not None and hosting not in HOSTINGS:
            problems.append(f"{where} hosting: {hosting!r} is not one of {', '.join(HOSTINGS)}")
        components[name] = ComponentSpec(name=name, kind="fmu", step=step, parameters=parameters, path=fmu_path,
                                         ports=ports, description=description, hosting=hosting)


def _check_parameters(where: str, parameters: dict, ports: dict[str, PortInfo], problems: list[str]) -> None:
    settable = ("parameter", "structuralParameter", "input")
    for key, value in parameters.items():
        port = ports.get(key)
        if port is None:
            names = sorted(n for n, p in ports.items() if p.causality in settable)
            problems.append(f"{where} parameters.{key}: no such parameter or input; settable: {', '.join(names)}")
            continue
        if port.causality not in settable:
            problems.append(f"{where} parameters.{key}: is a {port.causality}, not settable")
            continue
        if not _type_matches(port, value):
            problems.append(f"{where} parameters.{key}: expects {_expected(port)} (got {_short(value)})")
            continue
        problem = _value_problem(port, value)
        if problem:
            problems.append(f"{where} parameters.{key}: {problem}")
            continue
        if port.is_array and _size_of(value) not in (port.size, 1):
            problems.append(f"{where} parameters.{key}: expects {port.size} values ({'x'.join(map(str, port.shape))}), "
                            f"got {_size_of(value)}")


def _flat(value) -> list:
    """The scalars of a value or of a nested list of values."""
    if isinstance(value, list):
        return [v for item in value for v in _flat(item)]
    return [value]


def _finite(value) -> bool:
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer beyond any float (TOML integers have no size limit)
        return False


def _value_problem(port: PortInfo, value) -> str | None:
    """Why a value of the right type cannot be set: not finite, out of the type's range, or an array
    size beyond MAX_PORT_VALUES (a structural parameter); None if it can."""
    values = _flat(value)
    numbers = [v for v in values if isinstance(v, (int, float)) and not isinstance(v, bool)]
    if port.type.startswith("Float"):
        bad = [v for v in values if not _finite(v)]
        if bad:
            return f"{_short(bad[0])} is not a finite number; the FMU computes with it (give a finite value)"
    elif port.type in INTEGER_RANGES and port.type != "Enumeration":
        low, high = INTEGER_RANGES[port.type]
        bad = [v for v in values if isinstance(v, int) and not low <= v <= high]
        if bad:
            return f"{bad[0]} is outside the range of {port.type} ({low}..{high})"
        if port.causality == "structuralParameter" and any(isinstance(v, int) and v > MAX_PORT_VALUES for v in values):
            return (f"{max(values)} is more than {MAX_PORT_VALUES}: a structural parameter sizes arrays, and one this "
                    "large is far beyond any mesh this project runs (the AAA wall has 2688 surface nodes)")
    elif port.type == "Enumeration":
        numbers = [v for v in values if isinstance(v, int)]
        known = {item for _, item in port.items}
        bad = [v for v in numbers if known and v not in known]
        if bad:
            return f"{bad[0]} is not a value of {_type_of(port)}: {_expected(port)}"
    # Last: the FMU's own plausible range (min/max in its modelDescription.xml), once the value is
    # a finite number of its type at all.
    below = [v for v in numbers if port.minimum is not None and v < port.minimum]
    above = [v for v in numbers if port.maximum is not None and v > port.maximum]
    if below or above:
        low = "-inf" if port.minimum is None else f"{port.minimum:g}"
        high = "inf" if port.maximum is None else f"{port.maximum:g}"
        return f"{_short((below or above)[0])} is outside the range the FMU declares for it, {low} to {high}"
    return None


def _load_blocks(tables: dict, section: str, base_dir: Path, components: dict, overrides: dict,
                 problems: list[str]) -> None:
    from .blocks import BlockConfigError, make_block

    for name, table in tables.items():
        where = f"[{section}.{name}]"
        if name in components:
            problems.append(f"{where}: the name {name!r} is used twice; component names must be unique")
            continue
        if not isinstance(table, dict):
            problems.append(f"{where}: must be a table with kind = ...")
            continue
        table = _apply_overrides(name, table, overrides)
        step = None
        if "step" in table:  # exact here; the block gets the float the master will step it with
            step = parse_time(table["step"], f"{where} step", problems)
            if step is not None and step_problem(step):
                problems.append(f"{where} step: {step_problem(step)}")
                step = None
            table = {**table, "step": float(step) if step is not None else 0.001}
        try:
            block = make_block(name, table, base_dir)
        except BlockConfigError as exc:
            problems.extend(f"{where} {p}" for p in exc.problems)
            continue
        continuous = not hasattr(block, "start_step")
        if section == "source" and not continuous:
            problems.append(f"{where}: kind {table.get('kind')!r} is stepped; declare it as [block.{name}]")
            continue
        if section == "block" and continuous:
            problems.append(f"{where}: kind {table.get('kind')!r} is a continuous source; declare it as [source.{name}]")
            continue
        if not continuous and step is None:
            if "step" in table:  # given and refused above
                continue
            step = parse_time(getattr(block, "step", None), f"{where} step", problems)
        components[name] = ComponentSpec(name=name, kind=str(table.get("kind")), step=step, table=table,
                                         ports=dict(block.ports), base_dir=base_dir)


def _load_connections(items, components: dict[str, ComponentSpec], problems: list[str],
                      declared: set[str] = frozenset()) -> list[ConnectionSpec]:
    """Connections; one to a component that is declared but could not be loaded (its problem is
    reported already) is skipped silently rather than reported again as unknown."""
    if not isinstance(items, list):
        problems.append("connection: write each connection as a [[connection]] table")
        return []
    connections: list[ConnectionSpec] = []
    targets: dict[tuple[str, str], str] = {}
    for index, item in enumerate(items, start=1):
        where = f"connection {index}"
        if not isinstance(item, dict):
            problems.append(f"{where}: must be a table with from and to")
            continue
        _unknown_keys(item, _CONNECTION_KEYS, where, problems)
        src = _parse_endpoint(item.get("from"), f"{where} from", problems)
        dst = _parse_endpoint(item.get("to"), f"{where} to", problems)
        if src is None or dst is None:
            continue
        where = f"connection {index} ({item['from']} -> {item['to']})"
        ok = True
        for (comp, port), role, allowed in ((src, "from", READABLE), (dst, "to", WRITABLE)):
            spec = components.get(comp)
            if spec is None:
                if comp not in declared:
                    problems.append(f"{where}: unknown component {comp!r}; components: "
                                    f"{', '.join(components) or 'none'}")
                ok = False
                continue
            info = spec.ports.get(port)
            if info is None:
                names = sorted(n for n, p in spec.ports.items() if p.causality in allowed)
                problems.append(f"{where}: {comp} has no port {port!r}; "
                                f"{'outputs' if role == 'from' else 'inputs'}: {', '.join(names)}")
                ok = False
            elif info.causality not in allowed:
                article = "an" if info.causality[0] in "aeiou" else "a"
                problems.append(f"{where}: {comp}.{port} is {article} {info.causality}; a connection goes "
                                f"{'from an output' if role == 'from' else 'to an input or parameter'}")
                ok = False
        transition = item.get("transition")
        if transition is not None and transition not in TRANSITIONS:
            problems.append(f"{where} transition: {transition!r} is not one of {', '.join(TRANSITIONS)}")
            ok = False
        ordering = item.get("ordering", "gauss-seidel")
        if ordering not in ORDERINGS:
            problems.append(f"{where} ordering: {ordering!r} is not one of {', '.join(ORDERINGS)}")
            ok = False
        if not ok:
            continue
        out_spec, in_spec = components[src[0]], components[dst[0]]
        out_port, in_port = out_spec.ports[src[1]], in_spec.ports[dst[1]]
        conversion = conversion_problem(out_port, in_port)
        if conversion:
            problems.append(f"{where}: type mismatch, {src[0]}.{src[1]} is {_type_of(out_port)} and {dst[0]}.{dst[1]} "
                            f"is {_type_of(in_port)}: {conversion}")
        if out_port.size != in_port.size:
            hint = _size_hint(in_spec, in_port, out_port)
            problems.append(f"{where}: size mismatch, {out_port.size} values "
                            f"({'x'.join(map(str, out_port.shape)) or 'scalar'}) -> {in_port.size} "
                            f"({'x'.join(map(str, in_port.shape)) or 'scalar'}){hint}")
        if out_port.unit and in_port.unit and out_port.unit != in_port.unit:
            problems.append(f"{where}: unit mismatch, {out_port.unit} -> {in_port.unit} ({src[0]}.{src[1]} is in "
                            f"{out_port.unit}, {dst[0]}.{dst[1]} in {in_port.unit}); the master converts no units")
        key = (dst[0], dst[1])
        if key in targets:
            problems.append(f"{where}: {dst[0]}.{dst[1]} is already driven by {targets[key]}; an input has one source")
        targets[key] = where
        is_parameter = in_port.causality != "input"
        rates_known = not (out_spec.is_fmu and out_spec.step is None) and not (in_spec.is_fmu and in_spec.step is None)
        rates_differ = (rates_known and not out_spec.is_continuous and not is_parameter and out_spec.step != in_spec.step)
        if rates_differ and transition is None:
            choices = " | ".join(f'"{name}"' for name in tr.REGISTRY)
            problems.append(f"{where}: connects a {_rate(out_spec)} output to a {_rate(in_spec)} input; name the rate "
                            f"transition: transition = {choices}")
        if transition is not None and not out_spec.is_continuous:
            problem = tr.REGISTRY[transition].scene_problem(out_spec.step, in_spec.step)
            if problem:
                problems.append(f"{where} transition: {problem}")
        if src[0] == dst[0]:
            problems.append(f"{where}: connects a component to itself")
        connections.append(ConnectionSpec(src[0], src[1], dst[0], dst[1], transition, ordering, index))
    return connections


def _rate(spec: ComponentSpec) -> str:
    if spec.step is None:
        return "continuous"
    hz = 1 / spec.step
    return f"{float(hz):g} Hz"


def _size_hint(spec: ComponentSpec, in_port: PortInfo, out_port: PortInfo) -> str:
    if not spec.is_fmu or not spec.description:
        return ""
    md = spec.description.model_description
    for v in md.modelVariables:
        if v.name == in_port.name and v.dimensions:
            refs = [d.valueReference for d in v.dimensions if d.valueReference is not None]
            names = [w.name for w in md.modelVariables if w.valueReference in refs]
            if names and len(out_port.shape) == len(in_port.shape):
                fix = ", ".join(f"{n} = {out_port.shape[i]}" for i, n in enumerate(names) if i < len(out_port.shape))
                return f"; set {spec.name} parameter {fix}"
    return ""


def duration_problem(components, duration: Fraction) -> str | None:
    """Why a run of ``duration`` cannot end exactly on every stepped component's grid, or None.

    A run ends where every component has made whole steps: a duration that is not a multiple of a
    step would overshoot it, so it is refused (with the nearest durations that work).
    """
    steps = [c.step for c in components if c.step is not None]
    if not steps:
        return None
    period = Fraction(0)
    for step in steps:  # the lcm of rationals: lcm of numerators over gcd of denominators
        period = step if period == 0 else Fraction(math.lcm(period.numerator, step.numerator),
                                                     math.gcd(period.denominator, step.denominator))
    if (duration / period).denominator == 1:
        return None
    below = (duration // period) * period
    options = [d for d in (below, below + period) if d > 0]
    offending = ", ".join(f"{c.name} ({c.step} s)" for c in components
                          if c.step is not None and (duration / c.step).denominator != 1)
    return (f"{float(duration):g} s is not a whole number of steps of {offending}; a run ends on every "
            f"component's grid: use a multiple of {period} s, e.g. "
            + " or ".join(f"{float(d):.6g}" for d in options))


def run_size_problem(components, duration: Fraction) -> str | None:
    """Why a run of ``duration`` is too long to be meant (more than MAX_RUN_STEPS steps), or None."""
    stepped = [c for c in components if c.step is not None]
    total = sum(duration / c.step for c in stepped)
    if total <= MAX_RUN_STEPS:
        return None
    fastest = min(stepped, key=lambda c: c.step)
    longest = MAX_RUN_STEPS / sum(1 / c.step for c in stepped)
    return (f"{float(duration):g} s means {float(total):.3g} component steps ({fastest.name} alone takes "
            f"{float(duration / fastest.step):.3g}), more than the limit of {MAX_RUN_STEPS:.0e} steps per run "
            f"(about 50 minutes of computing on a 2-core machine); give the duration in seconds, at most "
            f"{float(longest):.6g} s with these steps, or split a long session into several runs")


def _check_algebraic_loops(connections: list[ConnectionSpec], components: dict, problems: list[str]) -> None:
    """A cycle of Gauss-Seidel connections has no order to step in: one of them must be Jacobi."""
    graph: dict[str, set[str]] = {}
    for c in connections:
        if c.ordering == "gauss-seidel" and c.source in components and c.target in components \
                and not components[c.source].is_continuous \
                and components[c.target].ports.get(c.target_port, PortInfo("", "input", "")).causality == "input":
            graph.setdefault(c.source, set()).add(c.target)
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        state[node] = 2
        stack.pop()
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                problems.append(f"algebraic loop of gauss-seidel connections {' -> '.join(cycle)}: set "
                                "ordering = \"jacobi\" on one of them (that input then uses the value from before the step)")
                return


def _load_record(table: dict, components: dict, problems: list[str], declared=frozenset()):
    """What to record; a component that is declared but could not be loaded (its problem is
    reported already) is skipped rather than reported again as unknown."""
    record: dict[str, list[str]] = {}
    surfaces: list[SurfaceSpec] = []
    plots: list[dict] = []
    for key, value in table.items():
        if key == "surfaces":
            items = _list(value, "[record] surfaces", problems, "write each as a [[record.surfaces]] table")
            for i, item in enumerate(items):
                surface = _load_surface(f"[record] surfaces[{i}]", item, components, problems, declared)
                if surface is None:
                    continue
                # <name>.pvd and the folder <name>/ beside <component>.csv and units.json
                taken = {s.name for s in surfaces} | {k for k in table if k not in ("surfaces", "plots")} | {"units"}
                if surface.name in taken:
                    problems.append(f"[record] surfaces[{i}] name: {surface.name!r} is already the name of another "
                                    "recorded file (a surface, a component's CSV or units); give another name")
                else:
                    surfaces.append(surface)
        elif key == "plots":
            items = _list(value, "[record] plots", problems, "write each figure as a [[record.plots]] table")
            plots = [item for i, item in enumerate(items) if _plot_ok(i, item, components, problems, declared)]
        else:
            comp = components.get(key)
            if comp is None:
                if key not in declared:
                    problems.append(f"[record] {key}: unknown component; components: {', '.join(components)}")
                continue
            if not isinstance(value, list):
                problems.append(f"[record] {key}: must be a list of port names (got {_short(value)})")
                continue
            ports = _strings(value, f"[record] {key}", problems, "a port name")
            seen: set[str] = set()
            for port in ports:
                info = comp.ports.get(port)
                if port in seen:
                    # The CSV would have two columns of one name and the run would refuse it.
                    problems.append(f"[record] {key}: {port!r} is listed twice; list each port once")
                seen.add(port)
                if info is None:
                    problems.append(f"[record] {key}: no port {port!r}")
                elif info.type not in NUMERIC_TYPES:
                    problems.append(f"[record] {key}.{port}: a {info.type} variable cannot be recorded; the CSV records "
                                    "numbers, Booleans and enumerations (their values)")
                elif info.size > 64:
                    problems.append(f"[record] {key}.{port}: {info.size} values is too many for a CSV column set; "
                                    "record surfaces with [[record.surfaces]]")
            if comp.is_continuous and not comp.is_fmu:  # an FMU without a step has its own problem
                problems.append(f"[record] {key}: a continuous source has no steps to record at; record the input it drives")
                continue
            record[key] = list(dict.fromkeys(ports))
    _check_result_names(table, record, surfaces, plots, problems)
    _check_plot_columns(table, record, plots, components, problems)
    return record, surfaces, plots


#: files every run writes in its result folder, whatever the scene (recording, summary)
_FIXED_RESULTS = {"summary.json": "the run's summary", "units.json": "the units of the CSV columns"}
#: labels of the summary's "results" table (summary.json) that are not a stream or a surface
_SUMMARY_LABELS = ("folder", "units", "plots", "surface_errors", "row_errors")


def _check_result_names(table: dict, record: dict, surfaces: list, plots: list, problems: list[str]) -> None:
    """Every file and folder a run writes into its result folder has one writer: the fixed files,
    ``<component>.csv``, each figure, and each surface's ``<name>.pvd`` and frame folder ``<name>/``.
    Two writers of one name lose a result or end the run with an error, so validate refuses them
    (compared without case: many file systems do not tell ``Forces.png`` from ``forces.png``)."""
    claimed: dict[str, tuple[str, str]] = {name.casefold(): (name, f"{name}, {role}")
                                          for name, role in _FIXED_RESULTS.items()}

    def claim(name: str, owner: str, where: str, what: str, fix: str) -> None:
        key = name.casefold()
        if key not in claimed:
            claimed[key] = (name, owner)
            return
        first, holder = claimed[key]
        case = " (the names differ only in case, which many file systems do not tell apart)" if first != name else ""
        problems.append(f"{where}: {what} {name} in the result folder, which is already {holder}{case}; {fix}")

    for component in record:
        claim(f"{component}.csv", f"the CSV of [record] {component}", f"[record] {component}", "writes",
              "rename one of the components")
        if component in _SUMMARY_LABELS:
            problems.append(f"[record] {component}: {component!r} is a name summary.json's results use for "
                            "something else; rename the component to record it")
    raw_plots = table.get("plots") if isinstance(table.get("plots"), list) else []
    for figure in plots:
        i = next((k for k, item in enumerate(raw_plots) if item is figure), "?")
        claim(figure["file"], f"the figure of [record] plots[{i}]", f"[record] plots[{i}] file",
              f"{figure['file']!r} would write", "give each figure a file of its own")
    raw_surfaces = table.get("surfaces") if isinstance(table.get("surfaces"), list) else []
    for surface in surfaces:
        i = next((k for k, item in enumerate(raw_surfaces) if isinstance(item, dict)
                  and item.get("name", f"{item.get('component')}_surface") == surface.name), "?")
        where, fix = f"[record] surfaces[{i}] name", "give the surface another name"
        claim(f"{surface.name}.pvd", f"the ParaView collection of [record] surfaces[{i}]", where,
              f"{surface.name!r} would write", fix)
        claim(surface.name, f"the frame folder of [record] surfaces[{i}]", where,
              f"{surface.name!r} would write its frame folder", fix)
        if surface.name in _SUMMARY_LABELS and surface.name != "units":  # "units": reported by _load_record
            problems.append(f"{where}: {surface.name!r} is a name summary.json's results use for something else; "
                            "give the surface another name")



#: a column of an array port as the CSV header writes it: "tool_force[2]"
_ELEMENT = re.compile(r"(?P<port>.+)\[(?P<index>0|[1-9][0-9]*)\]")


def _check_plot_columns(table: dict, record: dict, plots: list, components: dict, problems: list[str]) -> None:
    """A figure's series reads its column from the stream's CSV: a column the scene does not record
    would only draw an empty panel at the end of the run, so validate refuses it. A stream whose
    [record] entry has a problem of its own (reported already) or whose component did not load is
    not checked again."""
    raw_plots = table.get("plots") if isinstance(table.get("plots"), list) else []
    for figure in plots:
        i = next((k for k, item in enumerate(raw_plots) if item is figure), "?")
        for j, panel in enumerate(figure.get("panels", [])):
            for k, series in enumerate(panel.get("series", [])):
                at = f"[record] plots[{i}] panels[{j}] series[{k}]"
                stream, column = series["stream"], series["column"]
                if stream not in components or (stream in table and stream not in record):
                    continue
                if stream not in record:
                    problems.append(f"{at} stream: {stream} is not recorded, so there is no {stream}.csv to plot: add "
                                    f"{stream} = [\"{column}\"] to [record]")
                    continue
                ports = record[stream]
                element = _ELEMENT.fullmatch(column)
                if column in ports:
                    continue
                if element and element["port"] in ports:
                    info = components[stream].ports.get(element["port"])
                    if info is None or 1 < info.size and int(element["index"]) < info.size:
                        continue
                    if info.size == 1:
                        problems.append(f"{at} column: {stream}.{element['port']} is a single value, its column is "
                                        f"{element['port']!r} (not {column!r})")
                    else:
                        problems.append(f"{at} column: {column!r} is beyond {stream}.{element['port']}, which has "
                                        f"{info.size} values ([0] to [{info.size - 1}])")
                    continue
                problems.append(f"{at} column: {stream} records no column {column!r} (it records "
                                f"{', '.join(ports) or 'nothing'}); add {column!r} to [record] {stream} or plot one "
                                "of those")

def _load_surface(where: str, item, components: dict, problems: list[str], declared) -> SurfaceSpec | None:
    if not isinstance(item, dict):
        problems.append(f"{where}: must be a table {{ component, positions, triangles }}")
        return None
    _unknown_keys(item, _SURFACE_KEYS, where, problems)
    component = item.get("component")
    comp = components.get(component) if isinstance(component, str) else None
    if comp is None:
        if not isinstance(component, str) or component not in declared:
            problems.append(f"{where}: unknown component {_short(component)}; components: {', '.join(components)}")
        return None
    ok = True
    for role in ("positions", "triangles"):
        if not isinstance(item.get(role), str) or item.get(role) not in comp.ports:
            problems.append(f"{where} {role}: {comp.name} has no port {_short(item.get(role))}")
            ok = False
            continue
        # what the recording needs (recording.write_surface): flat (n, 3) numbers, triangles in integers
        port = comp.ports[item[role]]
        integer = port.type in INTEGER_RANGES and port.type != "Enumeration"
        if port.type not in NUMERIC_TYPES or port.type == "Boolean" or port.size % 3 or port.size == 0 or (
                role == "triangles" and not integer):
            kind = "integer node ids, 3 per triangle" if role == "triangles" else "numbers, 3 per node (x, y, z)"
            problems.append(f"{where} {role}: {comp.name}.{port.name} is {port.describe()}; {role} are {kind}")
            ok = False
    nodes = comp.ports[item["positions"]].size // 3 if ok else None
    point_data = _strings(_list(item.get("point_data", []), f"{where} point_data", problems, "of port names"),
                          f"{where} point_data", problems, "a port name")
    for extra in point_data:
        if extra not in comp.ports:
            problems.append(f"{where} point_data: {comp.name} has no port {extra!r}")
            ok = False
        elif nodes is not None and comp.ports[extra].size not in (nodes, 3 * nodes):
            problems.append(f"{where} point_data: {comp.name}.{extra} holds {comp.ports[extra].size} values; point "
                            f"data has one or three per node ({nodes} or {3 * nodes})")
            ok = False
    if comp.is_continuous and not comp.is_fmu:
        problems.append(f"{where}: {comp.name} is a continuous source, it has no steps to record frames at; "
                        "record the surface of a stepped component")
        ok = False
    every = item.get("every", 1)
    if not isinstance(every, int) or isinstance(every, bool) or every < 1:
        problems.append(f"{where} every: must be a positive integer, a frame every so many steps (got {_short(every)})")
        ok = False
    name = item.get("name", comp.name + "_surface")
    if not isinstance(name, str) or not _FILE_NAME.fullmatch(name):
        problems.append(f"{where} name: {_short(name)} is not a plain name: it names <name>.pvd in the result "
                        "folder, so it is letters, digits, '_', '-' or '.', not starting with '.' (no '/')")
        ok = False
    if not ok:
        return None
    return SurfaceSpec(comp.name, item["positions"], item["triangles"], every, tuple(point_data), name)


def _plot_ok(index: int, figure, components: dict, problems: list[str], declared) -> bool:
    """Check one [[record.plots]] figure as plots.plot_signals will draw it at the end of the run."""
    where = f"[record] plots[{index}]"
    if not isinstance(figure, dict):
        problems.append(f"{where}: must be a table {{ file, title, panels }}")
        return False
    count = len(problems)
    _unknown_keys(figure, _PLOT_KEYS, where, problems)
    file = figure.get("file")
    if not isinstance(file, str) or not _FILE_NAME.fullmatch(file) or not file.lower().endswith(".png"):
        problems.append(f"{where} file: {_short(file)} is not a plain .png file name in the result folder "
                        "(e.g. \"forces.png\"; no '/')")
    if not isinstance(figure.get("title", ""), str):
        problems.append(f"{where} title: must be a string")
    panels = figure.get("panels")
    if not isinstance(panels, list) or not panels:
        problems.append(f"{where} panels: must be a non-empty list of {{ ylabel, series = [...] }}")
        panels = []
    for at, panel in _each_table(panels, f"{where} panels", _PANEL_KEYS, problems, "{ ylabel, series = [...] }"):
        if not isinstance(panel.get("ylabel", ""), str):
            problems.append(f"{at} ylabel: must be a string")
        series_list = _list(panel.get("series", []), f"{at} series", problems, "of { stream, column, label }")
        for at_series, series in _each_table(series_list, f"{at} series", _SERIES_KEYS, problems,
                                             "{ stream, column, label }"):
            stream, column = series.get("stream"), series.get("column")
            if not isinstance(stream, str) or (stream not in components and stream not in declared):
                problems.append(f"{at_series} stream: {_short(stream)} is not a component of the scene")
            if not isinstance(column, str) or not column:
                problems.append(f"{at_series} column: must be a port name (got {_short(column)})")
            if not isinstance(series.get("label", ""), str):
                problems.append(f"{at_series} label: must be a string")
            if not isinstance(series.get("norm", False), bool):
                problems.append(f"{at_series} norm: must be true or false")
    return len(problems) == count

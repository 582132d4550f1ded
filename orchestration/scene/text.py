"""A scene's text and names, checked before and beside parsing: nesting depth, control characters,
names that become file names."""
from __future__ import annotations

import re

from orchestration.scene.model import MAX_NESTING
from orchestration.scene.tables import short_text
from orchestration.scene.values import flat_values


#: A scene name names its result folder (results/<name>): a plain name, never a path.
_SCENE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,99}")
#: A component name is a file name (<component>.csv) and the first part of "component.port".
_COMPONENT_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_-]{0,63}")
#: A file the scene asks the recording to write (a figure, a surface series) inside the result folder.
FILE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,99}")


def too_deep(data) -> str | None:
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

    Depth as ``too_deep`` counts it in the parsed tree (a top-level value is at 1): a key of n
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


def nesting_problem(text: str) -> str | None:
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
            f"{MAX_NESTING} levels deep; a scene nests at most 5 levels (see docs/scenes.md): check the "
            "brackets and the dots of the keys on that line")


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
    return (f"{where}: {what} {short_text(text)} holds the control character {shown} at position {at}; names, paths and "
            "parameters are printable text (a NUL would cut the string short where it is used): remove it "
            "(a TOML escape such as \\u0000 or \\t writes one)")


def control_character_problems(data: dict, overrides: dict | None) -> list[str]:
    """Every key and string of the scene (and of its overrides) that holds a control character;
    iterative, like ``too_deep``, after which it runs."""
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
        texts = [("the key", key)] + [("the value", v) for v in flat_values(value)]
        for what, text in texts:
            problem = _control_problem(text, f"override {key!r}", what) if isinstance(text, str) else None
            if problem:
                problems.append(problem)
    return problems


def scene_name_problem(name) -> str | None:
    """Why ``name`` cannot name a scene (and its result folder results/<name>), or None."""
    if not isinstance(name, str):
        return f"must be a string (got {short_text(name)})"
    if not _SCENE_NAME.fullmatch(name):
        return (f"{short_text(name)} is not a plain name: a scene name names its result folder results/<name>, so it "
                "is 1-100 letters, digits, '_', '-' or '.', not starting with '.' or '-' (no '/', no path); "
                "choose the folder with `run --out DIR` instead")
    return None


def component_name_problem(section: str, name: str) -> str | None:
    if not _COMPONENT_NAME.fullmatch(name) or name == "scene":
        return (f"[{section}.{name}]: {name!r} is not a usable component name: write 1-64 letters, digits, '_' or "
                "'-', starting with a letter or '_' (it names <component>.csv and the \"component.port\" of "
                "connections; 'scene' is reserved for scene.duration)")
    return None

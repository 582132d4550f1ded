"""Write the FMU reference pages (``docs/fmus/<fmu>.md``) from the FMUs' declarations.

Each FMU package declares its variables once, in ``src/<package>/fmu.py`` (an ``FmuDeclaration``,
see ``src/fmi3_layer/declare.py``); the modelDescription.xml is generated from it, and so are these
pages: every parameter and port with its type, causality, variability, unit, start value, array
size, plausible range with its reason, and description.

    .venv/bin/python tools/fmu_reference.py           # rewrite docs/fmus/*.md
    .venv/bin/python tools/fmu_reference.py --check   # exit 1 naming the pages that are out of date

The pages are committed (readable on GitHub too); ``tests/test_docs.py`` fails when one is out of
date. The declarations are read as the build reads them: in a fresh interpreter, from a copy of
each package with the data the build adds to it (Contact's start values are those of the Tissue
FMU's default mesh), so the start values are those of the built FMUs.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
OUT_DIR = REPO / "docs" / "fmus"
REGENERATE = ".venv/bin/python tools/fmu_reference.py"

#: causality -> section title, in the order of the page
SECTIONS = {
    "structuralParameter": "Structural parameters (array sizes, set in Configuration Mode)",
    "parameter": "Parameters",
    "calculatedParameter": "Calculated parameters",
    "input": "Inputs",
    "output": "Outputs",
    "independent": "Independent variable",
}
#: arrays with more start values than this are summarised ("7686 values")
LISTED_VALUES = 12


def _build_side():
    """The project's FMUs as the build knows them, and the build's step that adds data to a package
    copy. The one place this tool depends on the build (``fmu_build``)."""
    from fmu_build.package import add_build_data
    from fmu_build.specs import FMU_SPECS

    return FMU_SPECS, add_build_data


def module_contract(package_copy: Path, model_identifier: str):
    """The coupling contract the package carries, as the build reads it (None without one)."""
    from fmu_build.documentation import coupling_contract

    return coupling_contract(package_copy, model_identifier)


# -- reading the declarations (in a fresh interpreter: python tools/fmu_reference.py --declarations) --
def _start_summary(start, shape: tuple):
    """A JSON-able description of a start value for ``shape`` (resolved dimensions)."""
    import numpy as np

    if callable(start):
        start = start()
    if start is None:
        return None
    if not shape:
        if isinstance(start, (bool, np.bool_)):
            return {"kind": "bool", "value": bool(start)}
        if isinstance(start, str):
            return {"kind": "str", "value": start}
        if isinstance(start, (int, np.integer)):
            return {"kind": "int", "value": int(start)}
        return {"kind": "float", "value": float(start)}
    values = np.asarray(start).ravel()
    size = int(np.prod(shape))
    if values.size == 1 and size != 1:
        values = np.full(size, values[0])
    items = values.tolist()
    uniform = items[0] if items and all(x == items[0] for x in items) else None
    return {"kind": "array", "size": len(items), "uniform": uniform,
            "values": items if len(items) <= LISTED_VALUES else None}


def _read_declarations() -> list[dict]:
    """The declarations of the project's FMUs (as the build reads them), as plain data."""
    import importlib

    specs, add_build_data = _build_side()
    result = []
    with tempfile.TemporaryDirectory(prefix="fmu_reference_") as tmp:
        root = Path(tmp)
        for spec in specs.values():
            # as the build copies a package: the shared _fmi.py link becomes a file
            shutil.copytree(Path(spec.source_root) / spec.package, root / spec.package, symlinks=False,
                            ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc"))
        sys.path.insert(0, str(root))  # the copies before the installed packages
        for spec in specs.values():
            add_build_data(spec, root / spec.package)
        for name, spec in specs.items():
            module_name, _, attribute = spec.declaration.partition(":")
            module = importlib.import_module(f"{spec.package}.{module_name}")
            decl = getattr(module, attribute)
            variables = decl.all_variables()
            by_name = {v.name: v for v in variables}
            rows = []
            for v in variables:
                shape = tuple(int(by_name[d].start) if isinstance(d, str) else int(d) for d in v.shape)
                rows.append({
                    "name": v.name, "type": v.type, "causality": v.causality, "variability": v.variability,
                    "unit": v.unit, "description": v.description, "shape": list(v.shape),
                    "default_shape": list(shape),
                    "start": _start_summary(v.start, shape) if v.has_start else None,
                    "limit": None if v.limit is None else {"minimum": v.limit.minimum, "maximum": v.limit.maximum,
                                                           "why": v.limit.why},
                })
            result.append({
                "name": name, "model_identifier": spec.model_identifier, "package": spec.package,
                "source": (_relative(Path(spec.source_root)) / Path(module.__file__).relative_to(root)).as_posix(),
                "model_name": decl.model_name, "description": decl.description,
                "internal_step": float(decl.internal_step), "stop_time": float(decl.stop_time),
                "version": decl.version, "max_steps_per_call": int(decl.max_steps_per_call),
                "variables": rows,
                "coupling": module_contract(root / spec.package, spec.model_identifier),
            })
    return result


def _relative(folder: Path) -> Path:
    folder = folder.resolve()
    return folder.relative_to(REPO) if folder.is_relative_to(REPO) else folder


def declarations() -> list[dict]:
    """The declarations, read in a fresh interpreter (never imports an FMU package into this one)."""
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--declarations"], cwd=REPO,
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"reading the FMU declarations failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# -- rendering ------------------------------------------------------------------------------------
def number(x, integer: bool = False) -> str:
    """A number as a reader writes it: 1120, 0.45, 1.044e6, 1e-6, 1e10."""
    if integer or (isinstance(x, int) and not isinstance(x, bool)):
        x = int(x)
        if abs(x) < 1_000_000:
            return str(x)
        x = float(x)
    x = float(x)
    if not math.isfinite(x):
        return repr(x)
    if x.is_integer() and abs(x) < 1e6:
        return str(int(x))
    text = repr(x)
    if "e" in text:
        mantissa, exponent = text.split("e")
    elif abs(x) >= 1e6:  # an integral value: 1044000.0 -> 1.044e6
        digits = str(int(abs(x)))
        exponent = str(len(digits) - 1)
        significant = digits.rstrip("0")
        mantissa = ("-" if x < 0 else "") + significant[0] + ("." + significant[1:] if len(significant) > 1 else "")
    else:
        return text
    if "." in mantissa:
        mantissa = mantissa.rstrip("0").rstrip(".")
    return f"{mantissa}e{int(exponent)}"


def seconds(x: float) -> str:
    """A step as a reader writes it: 0.001, or 1/30 where the decimal does not end."""
    text = number(x)
    n = round(1 / x) if x > 0 else 0
    if len(text) > 8 and n > 1 and abs(1 / x - n) < 1e-9 * n:
        return f"1/{n}"
    return text


def _cell(text: str) -> str:
    """Text for a table cell: no line breaks, pipes escaped."""
    return " ".join(str(text).split()).replace("|", "\\|")


def _value(x, type_: str) -> str:
    if type_ == "Boolean":
        return "true" if x else "false"
    if type_ == "String":
        return f'`"{x}"`'
    return number(x, integer=type_ != "Float64")


def _start(variable: dict) -> str:
    start = variable["start"]
    if start is None:
        return ""
    type_ = variable["type"]
    if start["kind"] != "array":
        return _value(start["value"], type_)
    if start["size"] == 0:
        return "(none)"
    if start["values"] is not None and (start["uniform"] is None or start["size"] <= 3):
        return "[" + ", ".join(_value(x, type_) for x in start["values"]) + "]"
    if start["uniform"] is not None:
        return f"{_value(start['uniform'], type_)} (all {start['size']})"
    return f"{start['size']} values"


def _size(variable: dict) -> str:
    shape, default = variable["shape"], variable["default_shape"]
    if not shape:
        return ""
    text = " x ".join(f"`{d}`" if isinstance(d, str) else str(d) for d in shape)
    if any(isinstance(d, str) for d in shape):
        text += " (" + " x ".join(str(d) for d in default) + ")"
    return text


def _range(variable: dict) -> str:
    limit = variable["limit"]
    if limit is None:
        return ""
    integer = variable["type"] != "Float64"
    unit = f" {variable['unit']}" if variable["unit"] else ""
    return (f"[{number(limit['minimum'], integer)}, {number(limit['maximum'], integer)}]{unit}: "
            f"{limit['why']}")


def render_page(decl: dict) -> str:
    """The reference page of one FMU."""
    lines = [
        f"<!-- Generated by tools/fmu_reference.py from {decl['source']}: do not edit by hand. -->",
        f"<!-- Regenerate: {REGENERATE} -->",
        "",
        f"# {decl['model_name']} (`{decl['model_identifier']}.fmu`)",
        "",
        f"{decl['description']}.",
        "",
        f"Generated from the declaration in `{decl['source']}` (`{decl['package']}`), the table the",
        "FMU's modelDescription.xml is generated from; do not edit this page, run",
        f"`{REGENERATE}`.",
        "",
        f"- FMI 3.0 Co-Simulation, model identifier `{decl['model_identifier']}`, version {decl['version']}",
        f"- internal step {seconds(decl['internal_step'])} s (`fixedInternalStepSize`, parameter `internal_step`): "
        "a communication step is a whole multiple of it",
        f"- one `fmi3DoStep` runs at most {number(decl['max_steps_per_call'], True)} internal steps",
        f"- default experiment: 0 to {number(decl['stop_time'])} s",
        "",
        "Arrays are flat in row-major order: `[n, 3]` is `x0, y0, z0, x1, ...`. A size in backquotes is",
        "a structural parameter (its default in parentheses). A value outside its range is refused",
        "(`fmi3Error` naming the variable, the value and the range): Float64 values when they are set,",
        "every parameter again when initialization ends, structural parameters when configuration ends.",
        "Which port connects to which and at what rate: [Coupling of the three FMUs](../coupling.md);",
        "the components behind the ports: [Components and ports](../ports.md).",
    ]
    for causality, title in SECTIONS.items():
        rows = [v for v in decl["variables"] if v["causality"] == causality]
        if not rows:
            continue
        lines += ["", f"## {title}", "",
                  "| name | type (variability) | unit | start | array size | description; range: why |",
                  "|---|---|---|---|---|---|"]
        for v in rows:
            about = _cell(v["description"])
            if v["limit"] is not None:
                about += f"<br>**range** {_cell(_range(v))}"
            cells = [_cell(f"`{v['name']}`"), _cell(f"{v['type']} ({v['variability']})"), _cell(v["unit"] or ""),
                     _cell(_start(v)), _cell(_size(v)), about]
            lines.append("| " + " | ".join(cells) + " |")
    if decl.get("coupling"):
        lines += _coupling_lines(decl["coupling"])
    return "\n".join(lines) + "\n"


def _coupling_lines(contract: dict) -> list[str]:
    """The FMU's part of the coupling contract (``src/fmi3_layer/coupling.py``, in the FMU as
    ``documentation/coupling.json``)."""
    steps = ", ".join(f"{fmu} {step} s" for fmu, step in contract["steps"].items())
    lines = ["", "## Coupling", "",
             "How a master composes this FMU with the other two into the scene it was made for, as the FMU's",
             "`documentation/index.html` and `documentation/coupling.json` state it (from",
             "`src/fmi3_layer/coupling.py`; the rules explained: [Coupling of the three FMUs](../coupling.md)).",
             f"Steps: {steps}. Where the FMU can tell a rule is broken it refuses the call and quotes the rule."]
    for title, links, own, other in (("Inputs", contract["inputs"], "target", "source"),
                                     ("Outputs to the other FMUs", contract["outputs"], "source", "target")):
        lines += ["", f"### {title}", "", f"| {'input' if own == 'target' else 'output'} | "
                  f"{'from' if own == 'target' else 'to'} | transition | ordering | "
                  "the consumer stepping [t, t + h] sees |", "|---|---|---|---|---|"]
        lines += [f"| `{link[own].split('.', 1)[1]}` | `{link[other]}` | {link['transition']} | "
                  f"{link['ordering'] or '-'} | {_cell(link['sees'])} |" for link in links]
    lines += ["", "### Sizes that must agree", ""]
    lines += [f"- `{' = '.join(a['parameters'])}`: {a['why']}" for a in contract["agreements"]]
    lines += ["", "### Rules", ""]
    lines += [f"- **{name}**: {text}" for name, text in contract["rules"].items()]
    return lines


def render(decls: list[dict]) -> dict[Path, str]:
    """``{path of the page: its text}`` for every FMU."""
    return {OUT_DIR / f"{decl['model_name'].lower()}.md": render_page(decl) for decl in decls}


def stale(pages: dict[Path, str]) -> list[Path]:
    """The pages whose file differs from what the declarations give (missing ones included)."""
    return [path for path, text in pages.items()
            if not path.exists() or path.read_text(encoding="utf-8") != text]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if a page is out of date; write nothing")
    parser.add_argument("--declarations", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.declarations:
        print(json.dumps(_read_declarations()))
        return 0
    pages = render(declarations())
    outdated = stale(pages)
    if args.check:
        for path in outdated:
            print(f"out of date: {path.relative_to(REPO)} (run {REGENERATE})", file=sys.stderr)
        return 1 if outdated else 0
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    for path in outdated:
        path.write_text(pages[path], encoding="utf-8")
        print(f"wrote {path.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

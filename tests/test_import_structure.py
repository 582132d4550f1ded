"""The packages' import structure: every module imports, no import circle, no borrowed privates.

Imports are read from the source (those inside functions too: a circle hidden in a function is
still a circle), resolved to the project's modules, and searched for strongly connected parts.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE_ROOTS = {"orchestration": ROOT, "fmu_build": ROOT, "tissue_fmu": ROOT / "src", "haptic_fmu": ROOT / "src",
                 "catheter_fmu": ROOT / "src", "anatomy": ROOT / "src"}


def _module_files() -> dict[str, Path]:
    modules = {}
    for package, base in PACKAGE_ROOTS.items():
        for path in sorted((base / package).rglob("*.py")):
            parts = path.relative_to(base).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join(parts)] = path
    return modules


MODULES = _module_files()


def _is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


def _imports(name: str) -> list[tuple[str, ast.AST]]:
    """(imported name, node) for every import statement of a module, at any depth."""
    tree = ast.parse(MODULES[name].read_text(), str(MODULES[name]))
    package = name if _is_package(name) else name.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, node) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module
            found.append((source, node))
            found += [(f"{source}.{alias.name}", node) for alias in node.names]
    return found


def _project_targets(source: str, imported: str) -> set[str]:
    """The project modules an import runs: the deepest module named and the packages above it
    that the importing module does not already sit in."""
    parts = imported.split(".")
    while parts and ".".join(parts) not in MODULES:
        parts.pop()
    if not parts:
        return set()
    targets = set()
    for depth in range(1, len(parts) + 1):
        target = ".".join(parts[:depth])
        if target in MODULES and target != source and not source.startswith(target + "."):
            targets.add(target)
    return targets


def import_graph() -> dict[str, set[str]]:
    return {name: set().union(*[_project_targets(name, imported) for imported, _ in _imports(name)] or [set()])
            for name in MODULES}


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected parts of more than one module (Tarjan)."""
    index, low, on_stack, stack, circles = {}, {}, set(), [], []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph[node]):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            part = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                part.append(member)
                if member == node:
                    break
            if len(part) > 1:
                circles.append(sorted(part))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return circles


def test_the_circle_finder_finds_a_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert import_circles(graph) == [["a", "b", "c"]]
    assert import_circles({"a": {"b"}, "b": set()}) == []


def test_no_import_circles():
    circles = import_circles(import_graph())
    assert not circles, "import circles (break each by moving what both sides need into a module " \
                        f"below them): {circles}"


def test_no_module_imports_another_modules_privates():
    borrowed = []
    for name in MODULES:
        for imported, node in _imports(name):
            leaf = imported.rpartition(".")[2]
            if isinstance(node, ast.ImportFrom) and leaf.startswith("_") and not leaf.startswith("__") \
                    and imported not in MODULES:
                borrowed.append(f"{name}: {imported}")
    assert not borrowed, f"private names imported from another module: {borrowed}"


@pytest.mark.parametrize("name", sorted(name for name in MODULES if not name.endswith(".__main__")))
def test_every_module_imports(name):
    """(A ``__main__`` module runs its program when imported: it is left out.)"""
    importlib.import_module(name)


#: The orchestrator's packages along its pipeline (docs/orchestrator.md): each imports only the
#: packages before it (and the FMU build, which imports nothing of the orchestrator).
LAYERS = ("fmu_build", "orchestration.checks", "orchestration.errors", "orchestration.stopping", "orchestration.hosts", "orchestration.plan",
          "orchestration.blocks", "orchestration.scene", "orchestration.observers", "orchestration.run",
          "orchestration.studies", "orchestration.app", "orchestration.__main__", "orchestration.studies.__main__")


def _layer(name: str) -> int | None:
    """The index of the most specific layer ``name`` belongs to."""
    found = [(len(layer), index) for index, layer in enumerate(LAYERS) if name == layer or name.startswith(layer + ".")]
    return max(found)[1] if found else None


def test_the_orchestrators_packages_import_only_those_before_them():
    graph = import_graph()
    upward = [f"{source} -> {target}" for source, targets in graph.items() for target in targets
              if _layer(source) is not None and _layer(target) is not None and _layer(target) > _layer(source)]
    assert not upward, f"imports against the pipeline's order {LAYERS}: {upward}"
    assert all(_layer(name) is not None for name in MODULES if name.startswith(("orchestration.", "fmu_build."))), \
        [name for name in MODULES if name.startswith(("orchestration.", "fmu_build.")) and _layer(name) is None]

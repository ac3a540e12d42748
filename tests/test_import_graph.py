"""The package's import graph: no cycles, and the contracts in `oodrl.core` import nothing above
them (only each other, `oodrl.errors`, `oodrl.validation` and `oodrl.numerics`).

Every import counts, wherever it sits: module level, inside a function, or under
`TYPE_CHECKING`. An in-function import hides a cycle from Python but not from a reader.
"""

from __future__ import annotations

import ast
from pathlib import Path

import oodrl

PACKAGE = Path(oodrl.__file__).parent
#: What a contract in oodrl.core may import besides oodrl.core itself: the errors, the parameter
#: checks, and the machine-independent arithmetic (numpy only; a threshold rule computes with it).
BELOW_CORE = {"oodrl.errors", "oodrl.validation", "oodrl.numerics"}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph() -> dict[str, set[str]]:
    """Module → the oodrl modules it imports (a package import counts as its __init__)."""
    modules = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                # `from oodrl.core import stream` imports the module oodrl.core.stream.
                targets |= {f"{node.module}.{a.name}" for a in node.names} | {node.module}
        graph[name] = {t for t in targets if t in modules and t != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

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
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def without_packages(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """Drop the edges out of package __init__ modules that only re-export their submodules:
    `oodrl.core` importing `oodrl.core.detector`, which imports `oodrl.core.trajectory`, is no
    cycle even though `from oodrl.core.trajectory import …` also executes `oodrl.core`."""
    packages = {name for name in graph if (PACKAGE.parent / name.replace(".", "/")).is_dir()}
    return {
        name: {t for t in targets if not (name in packages and t.startswith(name + "."))}
        for name, targets in graph.items()
    }


def test_the_import_graph_finds_imports_inside_functions_and_type_checking():
    graph = import_graph()
    assert "oodrl.core.stream" in graph["oodrl.core.detector"]
    # oodrl.cli imports its commands inside functions (a light CLI import).
    assert len(graph["oodrl.cli"]) > 10


def test_the_package_has_no_import_cycles():
    found = cycles(without_packages(import_graph()))
    assert not found, f"import cycles: {found}"


def test_the_contracts_import_nothing_above_them():
    graph = import_graph()
    above = {
        (name, target)
        for name, targets in graph.items()
        if name.startswith("oodrl.core")
        for target in targets
        if not target.startswith("oodrl.core") and target not in BELOW_CORE
    }
    assert not above, f"oodrl.core imports modules above it: {sorted(above)}"


def test_a_cycle_is_found():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]

"""The shape of the code: no import cycle between mapkit's modules or subpackages, no function over
80 lines, few `# type: ignore` comments.

The import graph is read from the source (every ``import`` and ``from ... import``: at module level,
inside functions and under ``if TYPE_CHECKING:``), so a lazy import that only hides a cycle counts
as the cycle it hides. cli/ and viewer/ take part as ``mapkit.cli`` and ``mapkit.viewer`` (how they
install). Run this file as a script to print the graph's cycles.
"""

from __future__ import annotations

import ast
import io
import re
import sys
import tokenize
from collections.abc import Iterable, Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"mapkit": ROOT / "mapkit", "mapkit.cli": ROOT / "cli", "mapkit.viewer": ROOT / "viewer"}

KNOWN_CYCLES_BEING_FIXED: list[tuple[str, str]] = []
"""(importer, imported) module-name prefixes whose edges this test leaves out while a cycle through them
is being fixed; empty: there is none."""

MAX_FUNCTION_LINES = 60
MAX_TYPE_IGNORES = 5
_TYPE_IGNORE = re.compile(r"#\s*type:\s*ignore")


def _sources() -> Iterator[tuple[str, Path]]:
    """(dotted module name, file) of every module of mapkit, mapkit.cli and mapkit.viewer."""
    for package, directory in PACKAGES.items():
        for path in sorted(directory.rglob("*.py")):
            parts = path.relative_to(directory).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            yield ".".join((package, *parts)), path


def _imported(module: str, is_package: bool, node: ast.Import | ast.ImportFrom, modules: set[str]) -> Iterator[str]:
    """The mapkit modules one import statement names (a ``from P import name`` names the submodule
    ``P.name`` where there is one, else the package ``P``)."""
    if isinstance(node, ast.Import):
        for alias in node.names:
            if alias.name in modules:
                yield alias.name
        return
    base = node.module or ""
    if node.level:
        anchor = module.split(".") if is_package else module.split(".")[:-1]
        anchor = anchor[: len(anchor) - (node.level - 1)]
        base = ".".join([*anchor, base] if base else anchor)
    for alias in node.names:
        sub = f"{base}.{alias.name}"
        if sub in modules:
            yield sub
        elif base in modules:
            yield base


def import_graph() -> dict[str, set[str]]:
    """module → the mapkit modules it imports anywhere in its source."""
    sources = dict(_sources())
    modules = set(sources)
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, path in sources.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                targets = _imported(module, path.name == "__init__.py", node, modules)
                graph[module].update(t for t in targets if t != module)
    return graph


def _allowed(edge: tuple[str, str]) -> bool:
    def under(name: str, prefix: str) -> bool:
        return name == prefix or name.startswith(prefix + ".")

    return any(under(edge[0], a) and under(edge[1], b) for a, b in KNOWN_CYCLES_BEING_FIXED)


def subpackage(module: str) -> str:
    """The stage a module belongs to: ``mapkit.esdf._build`` → ``mapkit.esdf``; top-level modules
    (``mapkit._stores``, ``mapkit.geometry``) and the package itself stand for themselves."""
    parts = module.split(".")
    return ".".join(parts[:2])


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's components of more than one node: each is a set of mutually importing modules."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10 * len(graph) + 100))
    try:
        for v in sorted(graph):
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(limit)
    return found


def _one_cycle(component: Iterable[str], graph: dict[str, set[str]]) -> list[str]:
    """A shortest cycle through the first node of a strongly connected component, for the message."""
    nodes = set(component)
    start = min(nodes)
    paths = {start: [start]}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph[v] & nodes):
                if w == start:
                    return [*paths[v], start]
                if w not in paths:
                    paths[w] = [*paths[v], w]
                    nxt.append(w)
        frontier = nxt
    return [start]


def cycles() -> tuple[list[list[str]], list[list[str]]]:
    """(module cycles, subpackage cycles) after leaving out the edges of :data:`KNOWN_CYCLES_BEING_FIXED`:
    one per set of mutually importing modules (subpackages), as a path ending where it starts."""
    graph = {m: {t for t in targets if not _allowed((m, t))} for m, targets in import_graph().items()}
    modules = [_one_cycle(c, graph) for c in strongly_connected(graph)]
    stages: dict[str, set[str]] = {}
    for m, targets in graph.items():
        stages.setdefault(subpackage(m), set()).update(subpackage(t) for t in targets if subpackage(t) != subpackage(m))
    packages = [_one_cycle(c, stages) for c in strongly_connected(stages)]
    return modules, packages


def long_functions(limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """``path:line name (n lines)`` of every function or method longer than `limit` lines."""
    found = []
    for _, path in _sources():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = (node.end_lineno or node.lineno) - node.lineno + 1
                if n > limit:
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    return found


def type_ignores() -> list[str]:
    """``path:line`` of every ``# type: ignore`` comment (comments only, not strings that mention it)."""
    found = []
    for _, path in _sources():
        text = path.read_text(encoding="utf-8")
        for tok in tokenize.generate_tokens(io.StringIO(text).readline):
            if tok.type == tokenize.COMMENT and _TYPE_IGNORE.search(tok.string):
                found.append(f"{path.relative_to(ROOT)}:{tok.start[0]}")
    return found


def test_the_graph_sees_lazy_and_type_checking_imports():
    graph = import_graph()
    assert "mapkit.esdf._build" in graph and "mapkit.cli.main" in graph and "mapkit.viewer._app" in graph
    # lazy (inside a function) and TYPE_CHECKING-only imports are edges too
    assert "mapkit.esdf._world" in graph["mapkit.esdf._build"]
    assert "mapkit.esdf" in graph["mapkit.planner._loss"]
    # `from package import submodule` points at the submodule
    assert "mapkit.esdf._checks" in graph["mapkit.esdf._store"]


def test_strongly_connected_finds_a_cycle_and_its_path():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    (component,) = strongly_connected(graph)
    assert component == ["a", "b", "c"]
    assert _one_cycle(component, graph) == ["a", "b", "c", "a"]


def test_no_import_cycle_between_mapkit_modules_or_subpackages():
    modules, packages = cycles()
    message = "\n".join(
        ["import cycles (break them by moving the shared piece into a module both import):"]
        + [" → ".join(c) for c in modules + packages]
    )
    assert not modules and not packages, message


def test_no_function_is_longer_than_60_lines():
    found = long_functions()
    assert not found, f"functions over {MAX_FUNCTION_LINES} lines (split them into named steps):\n" + "\n".join(found)


def test_few_type_ignores():
    found = type_ignores()
    assert len(found) <= MAX_TYPE_IGNORES, (
        f"{len(found)} `# type: ignore` comments (at most {MAX_TYPE_IGNORES}); type these instead:\n" + "\n".join(found)
    )


if __name__ == "__main__":
    module_cycles, package_cycles = cycles()
    print("module cycles:", *[" → ".join(c) for c in module_cycles] or ["none"], sep="\n  ")
    print("subpackage cycles:", *[" → ".join(c) for c in package_cycles] or ["none"], sep="\n  ")
    print("functions over 80 lines:", *long_functions() or ["none"], sep="\n  ")
    print(f"type: ignore comments: {len(type_ignores())}", *type_ignores(), sep="\n  ")

"""The package's rooms (the first package under app/, or a top-level module) import each other without
cycles; the runtime never imports the training room, and the package never imports tests/ or bench/.

Every import statement counts, including those inside functions and under `TYPE_CHECKING`: a lazy import
is still a dependency.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
APP = ROOT / "app"

#: Room imports that still close a cycle, each with the change that removes it; the aim is none. An entry
#: whose rooms no longer import each other fails `test_known_cycle_edges_still_exist`: it goes with its fix.
KNOWN_CYCLE_EDGES: dict[tuple[str, str], str] = {}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(APP.rglob("*.py"))}


def imported(name: str, path: Path, known: dict[str, Path]) -> Iterator[str]:
    """The names of the modules that `path` (module `name`) imports, resolved to modules where they are."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join([*base, *([node.module] if node.module else [])])
            else:
                source = node.module or ""
            for alias in node.names:
                yield f"{source}.{alias.name}" if f"{source}.{alias.name}" in known else source


def room(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def import_edges() -> set[tuple[str, str]]:
    """(importer, imported) for every import of one app module by another."""
    known = modules()
    return {
        (name, target)
        for name, path in known.items()
        for target in imported(name, path, known)
        if target in known and target != name
    }


def room_cycles(edges: set[tuple[str, str]]) -> list[set[str]]:
    """The strongly connected sets of rooms (more than one room each)."""
    graph: dict[str, set[str]] = defaultdict(set)
    for a, b in edges:
        if room(a) != room(b):
            graph[room(a)].add(room(b))
    return [component for component in strongly_connected(graph) if len(component) > 1]


def strongly_connected(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components of a directed graph (successors by node), by Tarjan's algorithm."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    components: list[set[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                component.add(w)
                if w == v:
                    break
            components.append(component)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return components


def describe(cycle: set[str], edges: set[tuple[str, str]]) -> str:
    crossing = sorted(
        f"{a} -> {b}" for a, b in edges if room(a) in cycle and room(b) in cycle and room(a) != room(b)
    )
    return f"rooms {sorted(cycle)}: " + "; ".join(crossing)


def test_rooms_import_each_other_without_cycles() -> None:
    edges = {(a, b) for a, b in import_edges() if (room(a), room(b)) not in KNOWN_CYCLE_EDGES}
    cycles = room_cycles(edges)
    assert not cycles, "\n".join(describe(c, edges) for c in cycles)


def test_known_cycle_edges_still_exist() -> None:
    gone = set(KNOWN_CYCLE_EDGES) - {(room(a), room(b)) for a, b in import_edges()}
    assert not gone, f"no longer imported, delete from KNOWN_CYCLE_EDGES: {sorted(gone)}"


def test_the_cycle_check_sees_a_cycle() -> None:
    edges = {("app.a.x", "app.b.y"), ("app.b.y", "app.c.z"), ("app.c.z", "app.a.w"), ("app.d.v", "app.a.x")}
    assert room_cycles(edges) == [{"a", "b", "c"}]


def test_runtime_rooms_do_not_import_training() -> None:
    # `vlmap train` and `vlmap fit-proposer` reach app.training through app/cli.py's table of module names.
    offenders = sorted(
        f"{a} -> {b}" for a, b in import_edges() if room(b) == "training" and room(a) != "training"
    )
    assert not offenders


def test_the_package_does_not_import_tests_or_bench() -> None:
    known = modules()
    offenders = sorted(
        f"{name} -> {target}"
        for name, path in known.items()
        for target in imported(name, path, known)
        if target.split(".")[0] in {"tests", "bench"}
    )
    assert not offenders

"""The layers, checked on the sources with ``ast`` (nothing is imported): ``raw_schemas`` -> ``assets_lib`` ->
``pipelines`` -> ``imulab``. No module imports a layer above its own, the module import graph has no cycle, and
nothing under ``raw_schemas`` or ``assets_lib`` imports dagster. Also runnable alone: ``python tests/test_architecture.py``.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LAYERS = ("raw_schemas", "assets_lib", "pipelines", "imulab")


def _module_name(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def project_modules() -> dict[str, Path]:
    return {_module_name(p): p for layer in LAYERS for p in sorted((REPO / layer).rglob("*.py"))}


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """Project modules (and third-party top-level names) imported anywhere in a module, function bodies included."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            subs = {f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in modules}
            out |= subs or {mod}
    return out


def import_graph() -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """(project module -> project modules it imports, project module -> top-level names of everything it imports)."""
    modules = project_modules()
    graph, tops = {}, {}
    for name, path in modules.items():
        imp = imports_of(name, path, modules)
        tops[name] = {m.split(".")[0] for m in imp}
        resolved = set()
        for m in imp:
            while m and m not in modules:  # ``import a.b.c`` of a name inside a module: the module
                m = m.rpartition(".")[0]
            if m and m != name:
                resolved.add(m)
        graph[name] = resolved
    return graph, tops


def upward_imports(graph) -> list[str]:
    layer = {n: LAYERS.index(n.split(".")[0]) for n in graph}
    return sorted(f"{a} imports {b}" for a, deps in graph.items() for b in deps if layer[b] > layer[a])


def cycles(graph) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]
    sys.setrecursionlimit(max(10000, sys.getrecursionlimit()))

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_layers_import_only_downward():
    graph, _ = import_graph()
    assert len(graph) > 50  # the walk found the packages
    assert upward_imports(graph) == []


def test_no_import_cycle():
    graph, _ = import_graph()
    assert cycles(graph) == []


def test_science_and_contracts_never_import_dagster():
    _, tops = import_graph()
    bad = sorted(n for n, t in tops.items() if n.split(".")[0] in ("raw_schemas", "assets_lib") and t & {"dagster", "dagster_celery"})
    assert bad == []


def test_the_checker_sees_violations():
    """The checks can fail: an upward edge and a cycle planted in a copy of the graph are found."""
    graph, _ = import_graph()
    g = {k: set(v) for k, v in graph.items()}
    g["assets_lib.store.keys"].add("pipelines.jobs")
    assert upward_imports(g) == ["assets_lib.store.keys imports pipelines.jobs"]
    g = {k: set(v) for k, v in graph.items()}
    g["assets_lib.store.keys"].add("assets_lib.store.archive")  # archive imports keys
    assert ["assets_lib.store.archive", "assets_lib.store.keys"] in cycles(g)


if __name__ == "__main__":
    g, t = import_graph()
    print("upward:", upward_imports(g) or "none")
    print("cycles:", cycles(g) or "none")

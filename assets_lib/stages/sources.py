"""Which project sources a stage depends on: its module and every ``assets_lib`` / ``raw_schemas`` module it imports,
transitively (read with ``ast``, nothing is executed), so a stage's code version changes exactly when code it runs
changes, and adding an unrelated module leaves every stored version valid."""

from __future__ import annotations

import ast
import functools
import hashlib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: top-level packages whose sources count (third-party code is versioned by the environment, not here)
PROJECT_PACKAGES = ("assets_lib", "raw_schemas")


def module_file(name: str, root: Path = ROOT) -> Path | None:
    """The source file of project module ``name`` (a package's ``__init__.py``) under ``root``, or None."""
    parts = name.split(".")
    if parts[0] not in PROJECT_PACKAGES:
        return None
    base = Path(root).joinpath(*parts)
    for f in (base.with_suffix(".py"), base / "__init__.py"):
        if f.is_file():
            return f
    return None


def _imported(name: str, path: Path) -> set[str]:
    """Project modules named by the import statements of one module (anywhere in it, function bodies included).
    Parsed once per process and file state (stages share most of their closures)."""
    st = path.stat()
    return set(_imported_cached(name, str(path), st.st_mtime_ns, st.st_size))


@functools.lru_cache(maxsize=4096)
def _imported_cached(name: str, path_s: str, mtime_ns: int, size: int) -> frozenset[str]:
    path = Path(path_s)
    is_pkg = path.name == "__init__.py"
    package = name if is_pkg else name.rpartition(".")[0]
    out: set[str] = set()
    for node in _statements(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out |= {f"{mod}.{a.name}" for a in node.names}  # ``from pkg import module``
    return frozenset(m for m in out if m.split(".")[0] in PROJECT_PACKAGES)


#: fields of a node that hold statements (bodies of modules, functions, classes, if/for/while/with/try and match
#: cases, except handlers): an import is a statement, so walking statements finds every one that ``ast.walk``
#: finds, without visiting the expressions (most of a module's nodes)
_BODY_FIELDS = ("body", "orelse", "finalbody", "handlers", "cases")


def _statements(tree: ast.AST):
    """Every statement node of ``tree`` at any depth (plus except handlers and match cases, which hold bodies)."""
    todo = [tree]
    while todo:
        node = todo.pop()
        yield node
        for name in _BODY_FIELDS:
            children = getattr(node, name, None)
            if isinstance(children, list):
                todo += [c for c in children if isinstance(c, ast.AST)]


def _with_parents(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[: i + 1]) for i in range(len(parts))]


def module_closure(name: str, root: Path = ROOT) -> tuple[str, ...]:
    """``name`` and every project module it imports transitively (importing a module runs its packages'
    ``__init__`` too, so those count), sorted. Cached for the installed sources (``root`` = ``ROOT``)."""
    return _cached_closure(name) if Path(root) == ROOT else _closure(name, Path(root))


@functools.cache
def _cached_closure(name: str) -> tuple[str, ...]:
    return _closure(name, ROOT)


def _closure(name: str, root: Path) -> tuple[str, ...]:
    seen: set[str] = set()
    todo = [name]
    while todo:
        m = todo.pop()
        for mod in _with_parents(m):
            if mod in seen:
                continue
            f = module_file(mod, root)
            if f is None:
                continue
            seen.add(mod)
            todo += sorted(_imported(mod, f))
    return tuple(sorted(seen))


def source_digest(name: str, root: Path = ROOT) -> str:
    """sha256 (10 hex digits) over the names and bytes of ``module_closure(name)``. Cached for ``ROOT``."""
    return _cached_digest(name) if Path(root) == ROOT else _digest(name, Path(root))


@functools.cache
def _cached_digest(name: str) -> str:
    return _digest(name, ROOT)


def _digest(name: str, root: Path) -> str:
    h = hashlib.sha256()
    for mod in module_closure(name, root):
        h.update(mod.encode() + b"\0")
        h.update(module_file(mod, root).read_bytes())
    return h.hexdigest()[:10]

"""No import cycles, and no module over the line limit (:data:`MAX_MODULE_LINES`): the
``import`` statements of every module under ``jaxrefl/`` (read with ``ast``, those inside
functions included, those under ``if TYPE_CHECKING:`` left out) form no cycle among the
modules of one subpackage, nor among the subpackages.

A cycle says a name lives in the wrong module: a module imports one that (directly or
through others) imports it back, so one of them can only work by importing inside a
function or by the order in which Python happens to load them. A package's ``__init__`` is a
module of its own (a submodule importing a name from its own package's ``__init__`` closes a
cycle); importing ``a.b.c`` is an edge to ``a.b.c`` only, since Python loads the parents
``a`` and ``a.b`` first whatever they import.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "jaxrefl"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}
SUBPACKAGES = sorted(
    p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()
)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _import_nodes(tree: ast.AST):
    """Every Import / ImportFrom in ``tree``, at any depth, except under TYPE_CHECKING."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
            continue
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            stack.extend(node.orelse)
            continue
        stack.extend(ast.iter_child_nodes(node))


def imported_modules(source: str, module: str, is_package: bool, known: set[str]) -> set[str]:
    """The modules of ``known`` that the code ``source`` of ``module`` imports."""
    package = module.split(".") if is_package else module.split(".")[:-1]
    found: set[str] = set()
    for node in _import_nodes(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name in known)
            continue
        base = package[: len(package) - node.level + 1] if node.level else []
        target = ".".join(base + (node.module.split(".") if node.module else []))
        for alias in node.names:
            sub = f"{target}.{alias.name}"
            if sub in known:  # ``from pkg import module``
                found.add(sub)
            elif target in known:  # ``from module import name``
                found.add(target)
    return found


@functools.cache
def _graph() -> dict[str, set[str]]:
    known = set(MODULES)
    return {
        name: imported_modules(
            path.read_text(encoding="utf-8"), name, path.name == "__init__.py", known
        )
        for name, path in MODULES.items()
    }


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of ``graph`` with more than one node, or one node
    that imports itself (Tarjan's algorithm), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    counter = 0

    def visit(v: str) -> None:
        nonlocal counter
        index[v] = low[v] = counter
        counter += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in graph.get(v, ()):
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _group(module: str) -> str:
    """The subpackage a module belongs to; each of the root's own modules (``jaxrefl``,
    ``jaxrefl._errors``, ``jaxrefl.plot``, ...) is a group of its own."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in SUBPACKAGES else module


def test_cycle_finder_sees_cycles_and_imports_inside_functions():
    known = {"p", "p.a", "p.b", "p.c", "p.d"}
    a = imported_modules("def f():\n    from .b import g\n", "p.a", False, known)
    b = imported_modules("from p import c\nfrom . import a\n", "p.b", False, known)
    c = imported_modules(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .a import x\n",
        "p.c",
        False,
        known,
    )
    d = imported_modules("from . import name_in_init\nimport p.c\n", "p.d", False, known)
    assert (a, b, c, d) == ({"p.b"}, {"p.c", "p.a"}, set(), {"p", "p.c"})
    graph = {"p.a": a, "p.b": b, "p.c": c, "p.d": d, "p": {"p.d"}}
    assert cycles(graph) == [["p", "p.d"], ["p.a", "p.b"]]


@pytest.mark.parametrize("subpackage", SUBPACKAGES)
def test_no_import_cycle_inside_a_subpackage(subpackage):
    graph = _graph()
    mine = {m for m in graph if _group(m) == subpackage}
    sub = {m: graph[m] & mine for m in mine}
    found = cycles(sub)
    assert not found, f"import cycles in jaxrefl.{subpackage}: {found}"


def test_no_import_cycle_between_subpackages():
    graph = _graph()
    groups: dict[str, set[str]] = {}
    for m, targets in graph.items():
        groups.setdefault(_group(m), set()).update(
            _group(t) for t in targets if _group(t) != _group(m)
        )
    assert not cycles(groups), f"import cycles between subpackages: {cycles(groups)}"


#: A module is one idea: past this many lines it holds several (docs/architecture.md).
MAX_MODULE_LINES = 600


def test_no_module_above_the_line_limit():
    long = {
        name: n
        for name, path in MODULES.items()
        if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES
    }
    assert not long, f"split these modules by idea (over {MAX_MODULE_LINES} lines): {long}"

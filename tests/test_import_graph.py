"""No import loops inside torchseq (issue 21, item 3).

The import graph is built statically from the source (``ast``), so the test sees every
``import`` and ``from ... import``, including those inside functions (lazy imports close a loop
as surely as top-level ones: they only move the failure to the first call). Rules:

- Relative imports are resolved against the importing module's package.
- Imports under ``if TYPE_CHECKING:`` are skipped (they never run).
- A package's ``__init__.py`` is its own module, named after the package (``torchseq.events``).
  ``from pkg import name`` is an edge to the submodule ``pkg.name`` when that module exists,
  otherwise to ``pkg`` itself (the name comes from its ``__init__``). ``import a.b.c`` is an
  edge to ``a.b.c`` only: Python also initialises ``a`` and ``a.b`` first, but counting that
  would make every package that re-exports its submodules a loop. So a submodule that takes a
  name from its own package's ``__init__`` while that ``__init__`` imports the submodule back
  *is* counted as a loop (it works only by import order), and a submodule importing a sibling
  by its full path is not.

A loop is a strongly connected component of more than one module (or a module importing
itself); each is reported as one cycle through it.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "torchseq"

# Loops fixed by other branches of issue 21; the lead removes each entry after merging its fix.
# Each entry is the set of modules of one loop. The test fails if an entry no longer matches a
# loop in the code, so a fixed loop must leave this list in the same commit.


def module_files(package: Path = PACKAGE) -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, is_package) for every ``.py`` under ``package``."""
    out = {}
    for path in sorted(package.rglob("*.py")):
        parts = list(path.relative_to(package.parent).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        if is_package:
            parts = parts[:-1]
        out[".".join(parts)] = (path, is_package)
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST):
    """Every Import / ImportFrom node of ``tree``, skipping ``if TYPE_CHECKING:`` bodies."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            stack.extend(node.orelse)
            continue
        stack.extend(ast.iter_child_nodes(node))


def import_graph(package: Path = PACKAGE) -> dict[str, set[str]]:
    """Module -> the torchseq modules it imports (see the module docstring for the rules)."""
    files = module_files(package)
    graph: dict[str, set[str]] = {}
    for name, (path, is_package) in files.items():
        edges = graph.setdefault(name, set())
        here = name if is_package else name.rpartition(".")[0]  # the package relative to
        for node in _imports(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                edges.update(a.name for a in node.names if a.name in files)
                continue
            if node.level:
                base = here.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != package.name:
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                if sub in files:
                    edges.add(sub)
                elif target in files:
                    edges.add(target)
                else:
                    raise AssertionError(f"{path}: cannot resolve `from {target} import "
                                         f"{alias.name}`")
    return graph


def strongly_connected(graph: dict[str, set[str]]) -> list[set[str]]:
    """Tarjan's strongly connected components, iteratively (no recursion limit)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[set[str]] = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    comp = set()
                    while True:
                        top = stack.pop()
                        on_stack.discard(top)
                        comp.add(top)
                        if top == node:
                            break
                    out.append(comp)
    return out


def loops(graph: dict[str, set[str]]) -> list[set[str]]:
    """The import loops: components of several modules, or a module importing itself."""
    return sorted((c for c in strongly_connected(graph)
                   if len(c) > 1 or next(iter(c)) in graph[next(iter(c))]), key=sorted)


def one_cycle(graph: dict[str, set[str]], comp: set[str]) -> list[str]:
    """A cycle through the component, from its first module back to it (for the message)."""
    start = min(comp)
    parent = {start: None}
    queue = [start]
    while queue:  # breadth first, inside the component, until an edge returns to start
        node = queue.pop(0)
        for child in sorted(graph[node] & comp):
            if child == start:
                path = [node]
                while parent[path[-1]] is not None:
                    path.append(parent[path[-1]])
                return [start] + path[::-1][1:] + [start] if node != start else [start, start]
            if child not in parent:
                parent[child] = node
                queue.append(child)
    raise AssertionError(f"no cycle in {comp}")


def describe(graph, comp) -> str:
    return " -> ".join(m.removeprefix("torchseq.") for m in one_cycle(graph, comp))


def test_no_import_loops():
    graph = import_graph()
    found = loops(graph)
    assert not found, "import loops (no two modules may import each other):\n" + "\n".join(
        describe(graph, c) for c in found)


def _tree(tmp_path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        path = tmp_path / "torchseq" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return tmp_path / "torchseq"


def test_the_graph_sees_every_kind_of_import(tmp_path):
    """A small package with each kind of import, against the edges written out by hand."""
    pkg = _tree(tmp_path, {
        "__init__.py": "from .a import f\nfrom torchseq import b\n",
        "a.py": "def f():\n    from . import sub\n    import torchseq.sub.c\n",
        "b.py": ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .a import f\n"
                 "else:\n    from .sub.c import g\nimport numpy\n"),
        "sub/__init__.py": "from .c import g\n",
        "sub/c.py": "from .. import b\nfrom . import VALUE\nfrom ..a import f\n",
    })
    assert import_graph(pkg) == {
        "torchseq": {"torchseq.a", "torchseq.b"},
        "torchseq.a": {"torchseq.sub", "torchseq.sub.c"},
        "torchseq.b": {"torchseq.sub.c"},
        "torchseq.sub": {"torchseq.sub.c"},
        "torchseq.sub.c": {"torchseq.b", "torchseq.sub", "torchseq.a"},
    }


def test_loops_are_found_and_named(tmp_path):
    """Two-module, three-module and __init__ loops are each found; an acyclic chain is not."""
    pkg = _tree(tmp_path, {
        "__init__.py": "",
        "x.py": "from .y import f\n",
        "y.py": "def f():\n    from .x import g\n",
        "p.py": "from .q import f\n",
        "q.py": "from .r import f\n",
        "r.py": "import torchseq.p\n",
        "s/__init__.py": "from .t import h\n",
        "s/t.py": "from . import CONSTANT\n",
        "u.py": "from .v import f\n",
        "v.py": "from .x import g\n",
    })
    graph = import_graph(pkg)
    assert loops(graph) == [{"torchseq.p", "torchseq.q", "torchseq.r"},
                            {"torchseq.s", "torchseq.s.t"}, {"torchseq.x", "torchseq.y"}]
    assert describe(graph, {"torchseq.p", "torchseq.q", "torchseq.r"}) == "p -> q -> r -> p"
    assert describe(graph, {"torchseq.x", "torchseq.y"}) == "x -> y -> x"

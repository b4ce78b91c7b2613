"""No import loops inside torchseq (issue 21, item 3): the graph of
``import_graph_helpers`` (its docstring gives the rules).

A loop is a strongly connected component of more than one module (or a module importing
itself); each is reported as one cycle through it.
"""

from __future__ import annotations

from pathlib import Path

from import_graph_helpers import import_graph

# Loops fixed by other branches of issue 21; the lead removes each entry after merging its fix.
# Each entry is the set of modules of one loop. The test fails if an entry no longer matches a
# loop in the code, so a fixed loop must leave this list in the same commit.


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

"""The export package has no import loop (imports inside functions count too).

Read from the source with ``ast`` (nothing is imported): an edge ``a -> b`` for every
``import b`` / ``from b import ...`` anywhere in ``a``; a loop is a strongly connected
component of more than one module.
"""

import ast
from pathlib import Path

import torchseq

ROOT = Path(torchseq.__file__).parent


def import_graph(package: Path = ROOT) -> dict[str, set[str]]:
    mods = {}
    for p in package.rglob("*.py"):
        name = ".".join(("torchseq", *p.relative_to(package).with_suffix("").parts))
        mods[name.removesuffix(".__init__")] = p
    edges = {m: set() for m in mods}
    for m, p in mods.items():
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            edges[m] |= {n for n in names if n in mods and n != m and n != "torchseq"
                         and not m.startswith(n + ".")}
    return edges


def loops(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (iterative Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], 0
    for root in edges:
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(edges[w]))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
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
    return out


def test_the_loop_finder_finds_a_loop():
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert loops(edges) == [["a", "b", "c"]]
    assert loops({"a": {"b"}, "b": set()}) == []


def test_no_import_loop_in_the_export_package():
    found = [c for c in loops(import_graph())
             if any(m.startswith("torchseq.export") for m in c)]
    assert not found, f"import loops: {found}"

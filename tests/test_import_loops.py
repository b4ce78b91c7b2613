"""No two modules import each other, directly or around a circle (imports inside functions
count too). The graph is read from the source with ``ast``; nothing is imported.

``from package import name`` is an edge to ``package.name`` when that is a module, else to
the package's ``__init__``. The packages checked are listed in ``CHECKED``; a package joins
the list once its loops are gone.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "torchseq"
CHECKED = ["torchseq.layers", "torchseq.neural"]


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """``{module: modules it imports}`` over every ``.py`` file of the package."""
    files = {module_name(p, root): p for p in root.rglob("*.py")}
    graph = {}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        edges = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base
                           for a in node.names]
            else:
                continue
            edges |= {t for t in targets if t in files and t != name}
        graph[name] = edges
    return graph


def cycles(graph: dict[str, set[str]], within: list[str]) -> list[list[str]]:
    """One cycle per strongly connected component of the modules under ``within``."""
    keep = {m for m in graph if any(m == p or m.startswith(p + ".") for p in within)}
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):  # Tarjan's algorithm
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v] & keep:
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

    for v in sorted(keep):
        if v not in index:
            visit(v)
    return out


def test_the_graph_sees_imports_inside_functions(tmp_path):
    pkg = tmp_path / "torchseq"
    (pkg / "a").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a" / "__init__.py").write_text("from torchseq.a.x import f\n")
    (pkg / "a" / "x.py").write_text("def f():\n    from torchseq.a import y\n")
    (pkg / "a" / "y.py").write_text("from .x import f\n")
    graph = import_graph(pkg)
    assert graph["torchseq.a.x"] == {"torchseq.a.y"}
    assert cycles(graph, ["torchseq.a"]) == [["torchseq.a.x", "torchseq.a.y"]]


@pytest.mark.parametrize("package", CHECKED)
def test_no_import_loops(package):
    assert cycles(import_graph(), [package]) == []

"""The import graph of torchseq, built statically from the source (``ast``).

The graph sees every ``import`` and ``from ... import``, including those inside functions
(lazy imports close a loop as surely as top-level ones: they only move the failure to the first
call). Rules:

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
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "torchseq"


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


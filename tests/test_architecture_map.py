"""docs/architecture.md names every module of torchseq/, and only modules that exist.

The map names files by their path under ``torchseq/`` in backticks (```events/stream.py```),
and packages by their folder (```events/```); a package's ``__init__.py`` is named by its
folder.
"""

import re
from pathlib import Path

from import_graph_helpers import import_graph

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "torchseq"
MAP = ROOT / "docs" / "architecture.md"

def modules() -> set[str]:
    """Every module as the map names it: ``events/stream.py``, ``events/`` for a package."""
    out = set()
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE).as_posix()
        if path.name == "__init__.py":
            rel = rel.removesuffix("__init__.py") or "torchseq"
        out.add(rel)
    return out - {"torchseq"}  # the root __init__ is the package itself


def named(text: str) -> set[str]:
    """Backticked ``.py`` paths and ``folder/`` names in the map (``x/__init__.py`` is ``x/``).

    In a table row that starts with a package (```events/```), a bare ```stream.py``` is that
    package's file. Paths under ``tests/`` (the map cites the tests that keep it true) are not
    modules.
    """
    found = set()
    for line in text.splitlines():
        names = re.findall(r"`([\w/]+\.py|[a-z_]+/)`", line)
        row = re.match(r"\| `([a-z_]+/)` \|", line)
        if row:
            names = [n if "/" in n else row.group(1) + n for n in names]
        found.update(names)
    found = {n.removesuffix("__init__.py") for n in found if not n.startswith("tests/")}
    return found - {"", "torchseq/"}  # the root package itself


def test_every_module_is_on_the_map():
    text = MAP.read_text(encoding="utf-8")
    have, names = modules(), named(text)
    missing = sorted(have - names)
    assert not missing, f"docs/architecture.md does not name these modules: {missing}"
    gone = sorted(names - have)
    assert not gone, f"docs/architecture.md names files that do not exist: {gone}"


# Imports that go up a floor on purpose, each with its reason.
UPWARD_ALLOWED = {
    ("versions.py", "torchseq"): "reads torchseq.__version__ (inside the function)",
    ("maps/build.py", "torchseq"): "records torchseq.__version__ in the map",
}


def floors(text: str) -> dict[str, int]:
    """Floor of each file or package named in the map's floors block (parentheses ignored)."""
    block = text.split("## Floors", 1)[1].split("```", 2)[1]
    out, floor = {}, None
    for line in block.splitlines():
        line = re.sub(r"\([^)]*\)", "", line)
        m = re.match(r"(\d+)\s", line)
        if m:
            floor = int(m.group(1))
        for name in re.findall(r"[\w]+/|[\w]+\.py", line):
            out[name] = floor
    return out


def floor_of(module: str, table: dict[str, int]) -> int | None:
    """The floor of a dotted module name: its package's, or its own file's."""
    parts = module.split(".")[1:]
    if parts and parts[-1] == "__main__":  # python -m torchseq[.export]: the front end's door
        return table["cli/"]
    if not parts:
        return table.get("__init__.py", 4)  # the root package: the public face on floor 4
    if f"{parts[0]}/" in table:
        return table[f"{parts[0]}/"]
    if f"{parts[0]}.py" in table:
        return table[f"{parts[0]}.py"]
    return None


def _rel(module: str) -> str:
    parts = module.split(".")[1:]
    path = "/".join(parts)
    return (path + ".py") if (PACKAGE / (path + ".py")).exists() else (path or "torchseq")


def test_imports_run_down_the_floors():
    table = floors(MAP.read_text(encoding="utf-8"))
    graph = import_graph()
    unplaced = sorted(m for m in graph if floor_of(m, table) is None)
    assert not unplaced, f"modules on no floor of docs/architecture.md: {unplaced}"
    upward = []
    for a, targets in graph.items():
        for b in targets:
            if floor_of(b, table) <= floor_of(a, table):
                continue
            key = (_rel(a), _rel(b))
            if key in UPWARD_ALLOWED:
                continue
            upward.append(f"{key[0]} (floor {floor_of(a, table)}) imports {key[1]} "
                          f"(floor {floor_of(b, table)})")
    assert not upward, "imports that run up the floors:\n" + "\n".join(sorted(upward))


def test_the_upward_exceptions_are_current():
    """Each allowed upward import still exists (a stale exception must be deleted)."""
    graph = import_graph()
    edges = {(_rel(a), _rel(b)) for a, bs in graph.items() for b in bs}
    stale = sorted(k for k in UPWARD_ALLOWED if k not in edges)
    assert not stale, f"these imports are gone: remove them from UPWARD_ALLOWED: {stale}"

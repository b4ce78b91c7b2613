"""docs/architecture.md names every module of torchseq/, and only modules that exist.

The map names files by their path under ``torchseq/`` in backticks (```events/stream.py```),
and packages by their folder (```events/```); a package's ``__init__.py`` is named by its
folder.
"""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "torchseq"
MAP = ROOT / "docs" / "architecture.md"

# The front end is moving into torchseq/cli/ (issue 21, branch issue-21cli). The map already
# describes the new package; until the move is merged the old files are accepted unnamed and
# the new ones named without existing. When the old files are gone this test fails: delete
# FRONT_END_MOVE and the two lines that use it, and make the map's cli/ rows match the files.
FRONT_END_MOVE = {  # old file -> where the map says its job now lives
    "cli.py": "cli/__init__.py",
    "cli_eval.py": "cli/eval.py",
    "cli_train.py": "cli/train.py",
    "cli_map.py": "cli/map.py",
    "cli_presets.py": "cli/presets.py",
    "cli_help.py": "cli/flags.py",
    "cli_warnings.py": "cli/runs.py",
    "frontend.py": "cli/flags.py, cli/event_options.py, cli/runs.py",
    "plots.py": "cli/report.py",
    "export/cli.py": "cli/export.py",
}


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
    old_front_end = {f for f in FRONT_END_MOVE if f in have}
    missing = sorted(have - names - old_front_end)
    assert not missing, f"docs/architecture.md does not name these modules: {missing}"
    new_front_end = {n for n in names if n.startswith("cli/")} if old_front_end else set()
    gone = sorted(names - have - new_front_end)
    assert not gone, f"docs/architecture.md names files that do not exist: {gone}"


def test_the_front_end_move_list_is_current():
    """FRONT_END_MOVE lists files that still exist: once the move is merged it must go."""
    moved = [f for f in FRONT_END_MOVE if not (PACKAGE / f).exists()]
    assert not moved, (f"front-end files moved: {moved}; delete FRONT_END_MOVE from "
                       "tests/test_architecture_map.py and check the map's cli/ rows")

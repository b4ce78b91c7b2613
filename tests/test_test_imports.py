"""Tests import shared helpers by the module names pytest gives them (``conftest``,
``export_helpers``), never as ``tests.X``: a ``tests.X`` import loads a second copy of the
module, with its own caches, so every cached fit runs twice a session. No test module imports
another (``from test_x import``): what two test modules share lives in a helper module."""

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def imported_modules(source: str) -> list[str]:
    """The absolute module names a source imports, at any depth (also inside functions)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append(node.module)
        elif isinstance(node, ast.Import):
            found += [a.name for a in node.names]
    return found


def imported_tests_modules(source: str) -> list[str]:
    """The ``tests.X`` modules a source imports (``import tests.X``, ``from tests.X import``)."""
    return [m for m in imported_modules(source) if m == "tests" or m.startswith("tests.")]


def imported_test_modules(source: str) -> list[str]:
    """The test modules (``test_*``) a source imports: ``import test_x``, ``from test_x``."""
    return [m for m in imported_modules(source) if m.split(".")[0].startswith("test_")]


def test_the_checker_sees_both_forms():
    source = ("from tests.conftest import x\nimport tests.export_helpers\n"
              "def f():\n    from tests import y\n")
    assert sorted(imported_tests_modules(source)) == ["tests", "tests.conftest",
                                                 "tests.export_helpers"]
    assert imported_tests_modules("from conftest import x\nimport testsuite\n") == []
    source = "from test_a import x\nimport test_b\ndef f():\n    from test_c import y\n"
    assert sorted(imported_test_modules(source)) == ["test_a", "test_b", "test_c"]
    assert imported_test_modules("from conftest import x\nimport testsuite\n") == []


def test_no_test_imports_a_helper_as_tests_dot_name():
    bad = {p.name: imported_tests_modules(p.read_text()) for p in sorted(TESTS.glob("*.py"))}
    assert {k: v for k, v in bad.items() if v} == {}


def test_no_test_imports_another_test_module():
    bad = {p.name: imported_test_modules(p.read_text()) for p in sorted(TESTS.glob("*.py"))}
    assert {k: v for k, v in bad.items() if v} == {}

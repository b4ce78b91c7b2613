"""Tests import shared helpers by the module names pytest gives them (``conftest``,
``export_helpers``, ``test_spiking``), never as ``tests.X``: a ``tests.X`` import loads a
second copy of the module, with its own caches, so every cached fit runs twice a session."""

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def imported_tests_modules(source: str) -> list[str]:
    """The ``tests.X`` modules a source imports (``import tests.X``, ``from tests.X import``)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and \
                (node.module == "tests" or node.module.startswith("tests.")):
            found.append(node.module)
        elif isinstance(node, ast.Import):
            found += [a.name for a in node.names if a.name == "tests"
                      or a.name.startswith("tests.")]
    return found


def test_the_checker_sees_both_forms():
    source = ("from tests.conftest import x\nimport tests.export_helpers\n"
              "def f():\n    from tests import y\n")
    assert sorted(imported_tests_modules(source)) == ["tests", "tests.conftest",
                                                 "tests.export_helpers"]
    assert imported_tests_modules("from conftest import x\nimport testsuite\n") == []


def test_no_test_imports_a_helper_as_tests_dot_name():
    bad = {p.name: imported_tests_modules(p.read_text()) for p in sorted(TESTS.glob("*.py"))}
    assert {k: v for k, v in bad.items() if v} == {}

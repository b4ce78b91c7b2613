"""The README stays a front door: short, its commands valid, its test command the one CI runs."""

import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")
BLOCKS = re.findall(r"```(bash|python)\n(.*?)```", README, flags=re.S)


def commands():
    for kind, body in BLOCKS:
        if kind == "bash":
            for line in body.replace("\\\n", " ").splitlines():
                line = line.split(" #")[0].strip()
                if line:
                    yield line


def test_readme_fits_a_few_screens():
    assert len(README.splitlines()) <= 212


@pytest.mark.parametrize("line", [c for c in commands() if c.startswith("torchseq ")])
def test_every_torchseq_command_parses(line):
    from torchseq.cli.eval import build_parser as eval_parser
    from torchseq.cli.export import build_parser as export_parser
    from torchseq.cli.map import build_parser as map_parser
    from torchseq.cli.train import build_parser as train_parser

    command, *args = shlex.split(line)[1:]
    parser = {"eval": eval_parser, "train": train_parser, "export": export_parser,
              "map": lambda: map_parser("torchseq map")}[command]()
    parser.parse_args(args)  # an unknown flag or a bad value exits 2


def test_python_examples_compile():
    for i, (kind, body) in enumerate(BLOCKS):
        if kind == "python":
            compile(body, f"README.md python block {i}", "exec")


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert any(c.endswith(".venv/bin/python -m pytest -q") for c in commands())
    assert ".venv/bin/python -m pytest -q\n" in ci and "-c constraints.txt" in ci
    assert "pip install -c constraints.txt -e ." in README  # the quickstart uses it too
    # the quick run leaves out the tests marked slow (tests/conftest.py): CI runs them too
    assert ".venv/bin/python -m pytest -q -m slow\n" in ci

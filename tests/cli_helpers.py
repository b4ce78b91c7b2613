"""Command-line helpers shared by the CLI test modules: a script's main run in-process."""

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def load_script(name):
    """Import eval.py / train.py as a module, to call its main in-process (fast)."""
    spec = importlib.util.spec_from_file_location(f"{name}_script", ROOT / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def run_inprocess(name, capsys, *args):
    """Run a script's main as its __main__ does; return (exit code, stderr)."""
    from torchseq.cli.runs import run_main

    module = load_script(name)
    code = run_main(module.main, f"{name}.py", [*args, "--no-progress"])
    return code, capsys.readouterr().err


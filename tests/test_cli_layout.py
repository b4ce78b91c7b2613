"""The front end is the torchseq/cli/ package (issue 21): the old root modules are gone, the
export API keeps its names, and the console script's entry point is the package's main."""

import importlib.util
from pathlib import Path

import pytest

GONE = ("torchseq.frontend", "torchseq.cli_eval", "torchseq.cli_train", "torchseq.cli_map",
        "torchseq.cli_presets", "torchseq.cli_warnings", "torchseq.cli_help", "torchseq.plots",
        "torchseq.export.cli")


@pytest.mark.parametrize("name", GONE)
def test_the_old_front_end_modules_are_gone(name):
    # not in the package under test (an editable install of another checkout may still
    # resolve the name to that checkout's file: it must not be this one's)
    import torchseq

    package = Path(torchseq.__file__).resolve().parent
    try:
        spec = importlib.util.find_spec(name)
    except ModuleNotFoundError:
        spec = None
    assert spec is None or package not in Path(spec.origin).resolve().parents


def test_the_export_api_keeps_its_names_where_the_docs_give_them():
    # docs/guide/export.md: from torchseq.export import export_checkpoint (no shim needed: the
    # names listed in docs/reference/api.md did not move)
    import torchseq.export as export
    from torchseq.export.checkpoint import export_checkpoint
    from torchseq.export.errors import ExportError
    from torchseq.export.onnx_float import ExportError as raised_by_the_onnx_step

    assert export.export_checkpoint is export_checkpoint
    assert export.ExportError is ExportError is raised_by_the_onnx_step


def test_the_console_script_and_python_m_dispatch_to_the_package(capsys):
    from pathlib import Path

    import tomllib

    from torchseq.cli import COMMANDS, main

    root = Path(__file__).resolve().parents[1]
    scripts = tomllib.loads((root / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["torchseq"] == "torchseq.cli:main"
    assert set(COMMANDS) == {"eval", "train", "export", "map"}
    for command in COMMANDS:
        with pytest.raises(SystemExit) as stop:
            main([command, "--help"] if command != "map" else [command, "build", "--help"])
        assert stop.value.code == 0
        assert capsys.readouterr().out.startswith("usage: torchseq " + command)



@pytest.mark.parametrize("argv", ["None", "['eval', '--help']"])
def test_only_the_process_command_line_freezes_the_collector(argv):
    # main() with no argv is the process's own command (console script, python -m torchseq):
    # the objects of the command's imports are frozen (gc.freeze), so the cycle collector skips
    # them in its full passes and at exit; a list (tests, scripts in process) freezes nothing
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    code = ("import gc, sys\nfrom torchseq.cli import main\n"
            "sys.argv = ['torchseq', 'eval', '--help']\n"
            f"try:\n    main({argv})\nexcept SystemExit:\n    pass\n"
            "print('frozen', gc.get_freeze_count())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=root, env={"PYTHONPATH": str(root)}, check=True).stdout
    frozen = int(out.split("frozen")[-1])
    assert (frozen > 10_000) if argv == "None" else frozen == 0

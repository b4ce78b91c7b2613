"""Every run file records what made it: torchseq, torch, Python, platform, git commit."""

import json
import platform
import subprocess
from pathlib import Path

import pytest
import torch

import torchseq
from torchseq.cli import main as torchseq_main
from torchseq.versions import VERSIONS_KEY, _git_commit, versions, versions_line

ROOT = Path(__file__).resolve().parents[1]


def test_version_flag_prints_every_version(capsys):
    assert torchseq_main(["--version"]) == 0
    out = capsys.readouterr().out.strip()
    assert out == versions_line()
    assert out.startswith(f"torchseq {torchseq.__version__}, torch {torch.__version__}, "
                          f"Python {platform.python_version()}, {platform.platform()}")


def test_versions_name_the_checkout_commit():
    try:
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"],
                              capture_output=True, text=True, timeout=10)
    except OSError:
        pytest.skip("no git on this machine")
    if head.returncode != 0 or not (ROOT / ".git").exists():
        pytest.skip("not running from a git checkout")
    v = versions()
    assert v["git_commit"] == head.stdout.strip() and isinstance(v["git_dirty"], bool)
    assert f"git {head.stdout.strip()[:12]}" in versions_line(v)


def test_no_commit_outside_a_checkout(tmp_path):
    assert _git_commit(tmp_path) == (None, None)
    v = {**versions(), "git_commit": None, "git_dirty": None}
    assert "git" not in versions_line(v)


@pytest.mark.slow
def test_every_run_file_records_versions(tmp_path, capsys):
    from torchseq.cli.eval import cli as eval_cli
    from torchseq.cli.export import main as export_main
    from torchseq.cli.train import cli as train_cli

    expected = versions()
    quiet = ["--no-progress", "--no-tensorboard"]
    small = ["--engine", "seqslam", "--demo-frames", "40", "--ds", "6", *quiet]
    assert eval_cli([*small, "--out", str(tmp_path / "eval")]) == 0
    assert eval_cli([*small, "--sweep", "ds=4,6", "--out", str(tmp_path / "sweep")]) == 0
    assert train_cli(["--demo-frames", "40", "--neural-hidden", "256", "--neural-n-output", "40",
                      *quiet, "--out", str(tmp_path / "train")]) == 0
    capsys.readouterr()
    assert export_main([str(tmp_path / "train" / "model.pt"), "--out",
                        str(tmp_path / "export"), "--no-nir"]) == 0
    assert f"made with {versions_line(expected)}" in capsys.readouterr().out.splitlines()
    files = ["eval/metrics.json", "eval/config.json", "sweep/sweep.json", "sweep/config.json",
             "train/train.json", "train/config.json", "export/validation.json"]
    for name in files:
        assert json.loads((tmp_path / name).read_text())[VERSIONS_KEY] == expected, name
    # a recorded config replays: the versions are a record, not a setting
    assert eval_cli(["--config", str(tmp_path / "eval" / "config.json"), "--out",
                     str(tmp_path / "replay"), *quiet]) == 0
    assert train_cli(["--config", str(tmp_path / "train" / "config.json"), "--out",
                      str(tmp_path / "retrain"), *quiet]) == 0

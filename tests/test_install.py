"""A pip user's install: a wheel (not editable) in a fresh virtual environment runs the demo.

The new environment sees this interpreter's packages (torch, numpy, ...) through a ``.pth``
line instead of downloading them again; torchseq itself comes only from the wheel.
"""

import json
import os
import shutil
import site
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def sh(*cmd, **kw):
    proc = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=600,
                          **kw)
    assert proc.returncode == 0, f"{cmd}: {proc.stdout[-1500:]}\n{proc.stderr[-1500:]}"
    return proc


def tree_state(root: Path) -> dict:
    """``{path: mtime_ns}`` of everything under the build outputs setuptools makes in ``root``."""
    state = {}
    for top in [root / "build", *root.glob("*.egg-info")]:
        for p in [top, *top.rglob("*")] if top.exists() else []:
            state[str(p)] = p.stat().st_mtime_ns
    return state


@pytest.mark.slow
def test_wheel_in_a_fresh_venv_runs_torchseq_eval(tmp_path):
    pytest.importorskip("setuptools", reason="building the wheel needs setuptools")
    # build from a copy of what the wheel is made of: setuptools writes build/ and
    # *.egg-info beside pyproject.toml, which must not be the source tree
    src = tmp_path / "src"
    shutil.copytree(ROOT / "torchseq", src / "torchseq",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    before = tree_state(ROOT)
    wheels = tmp_path / "wheels"
    sh(sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
       "-w", wheels, src)
    assert tree_state(ROOT) == before, "the build wrote into the source tree"
    assert (src / "build").is_dir()  # where it did write
    wheel, = wheels.glob("torchseq-*.whl")
    venv = tmp_path / "venv"
    sh(sys.executable, "-m", "venv", venv)
    py = venv / "bin" / "python"
    purelib = sh(py, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))").stdout
    deps = [p for p in site.getsitepackages() if Path(p, "torch").is_dir()]
    Path(purelib.strip(), "deps.pth").write_text("\n".join(deps) + "\n")
    sh(py, "-m", "pip", "install", "--no-deps", "--no-index", "--ignore-installed", "-q", wheel)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    work = tmp_path / "work"  # not the source tree: only the installed package can be found
    work.mkdir()
    where = sh(py, "-c", "import torchseq; print(torchseq.__file__)", cwd=work, env=env).stdout
    assert str(venv) in where
    out = sh(venv / "bin" / "torchseq", "eval", "--engine", "seqslam", "--demo-frames", "40",
             "--no-tensorboard", "--no-progress", "--out", "run", cwd=work, env=env)
    assert "seqslam: recall@1" in out.stdout
    metrics = json.loads((work / "run" / "metrics.json").read_text())
    assert metrics["seqslam"]["n_queries"] == 49 and metrics["seqslam"]["recall_at_1"] > 0.5
    usage = subprocess.run([py, "-m", "torchseq", "--help"], capture_output=True, text=True,
                           cwd=work, env=env, timeout=120)
    assert usage.returncode == 0 and "eval" in usage.stdout and "export" in usage.stdout
    bad = subprocess.run([venv / "bin" / "torchseq", "train", "--eps", "nan"],
                         capture_output=True, text=True, cwd=work, env=env, timeout=120)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines() == [
        "torchseq train: error: argument --eps: must be a finite number, got 'nan'"]

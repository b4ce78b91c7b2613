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
import zipfile
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
    with zipfile.ZipFile(wheel) as zf:  # PEP 561: type checkers read the package's hints
        assert "torchseq/py.typed" in zf.namelist()
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
    bad = subprocess.run([venv / "bin" / "torchseq", "train", "--neural-eps", "nan"],
                         capture_output=True, text=True, cwd=work, env=env, timeout=120)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines() == [
        "torchseq train: error: argument --neural-eps: must be a finite number, got 'nan'"]


@pytest.mark.slow
def test_editable_install_keeps_a_users_own_torch(tmp_path):
    """``pip install -e .`` beside a different torch (here a fake 2.6.0) leaves it in place.

    pyproject.toml declares torch as a range; an exact pin would make pip replace the user's
    torch (or, offline as here, fail to install). pip runs with no index and no config, so
    nothing is downloaded: every other dependency comes from this interpreter's packages.
    """
    pytest.importorskip("setuptools", reason="the editable build needs setuptools")
    src = tmp_path / "src"
    shutil.copytree(ROOT / "torchseq", src / "torchseq",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    venv = tmp_path / "venv"
    sh(sys.executable, "-m", "venv", "--without-pip", venv)
    py = venv / "bin" / "python"
    purelib = Path(sh(py, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))")
                   .stdout.strip())
    # this interpreter's packages (pip, setuptools, numpy, the real torch ...) after the venv's
    deps = [p for p in site.getsitepackages() if Path(p, "torch").is_dir()]
    (purelib / "deps.pth").write_text("\n".join(deps) + "\n")
    fake = '__version__ = "2.6.0"  # a user\'s own torch\n'
    (purelib / "torch").mkdir()
    (purelib / "torch" / "__init__.py").write_text(fake)
    info = purelib / "torch-2.6.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: torch\nVersion: 2.6.0\n")
    (info / "RECORD").write_text("torch/__init__.py,,\n")
    (info / "INSTALLER").write_text("pip\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH" and not k.startswith("PIP_")}
    env["PIP_CONFIG_FILE"] = os.devnull  # no find-links, extra index or constraints
    proc = subprocess.run([py, "-m", "pip", "install", "--no-index", "--no-build-isolation",
                           "-q", "-e", src], capture_output=True, text=True, timeout=600,
                          env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-1500:] + proc.stderr[-1500:]
    assert (purelib / "torch" / "__init__.py").read_text() == fake
    assert sorted(p.name for p in purelib.glob("torch-*.dist-info")) == ["torch-2.6.0.dist-info"]
    version = sh(py, "-c", "import importlib.metadata as m; print(m.version('torch'), "
                 "m.version('torchseq'))", env=env, cwd=tmp_path).stdout.split()
    import torchseq
    assert version == ["2.6.0", torchseq.__version__]

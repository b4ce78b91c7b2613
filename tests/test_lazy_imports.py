"""A run imports only what it uses: no plotting, ONNX, event-reader, index or logging packages
for ``import torchseq`` or for a SeqSLAM eval up to its report (issue 21, start-up cost)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# packages a plain SeqSLAM run on image frames never needs (each costs 0.1-1 s to import)
HEAVY = ("matplotlib", "PIL", "onnx", "onnxruntime", "tensorboard", "torch.utils.tensorboard",
         "lz4", "zstandard", "h5py", "pyarrow", "faiss", "ray", "numba", "sklearn", "scipy")

PROBE = """
import json, sys
HEAVY = {heavy!r}
def loaded():
    return sorted(m for m in HEAVY if m in sys.modules)
{body}
"""


def _run(body: str, tmp_path) -> dict:
    code = PROBE.format(heavy=HEAVY, body=body)
    env = dict(os.environ, PYTHONPATH=str(ROOT), MPLBACKEND="")
    env.pop("MPLBACKEND")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_import_torchseq_loads_no_heavy_package(tmp_path):
    got = _run("import torchseq, torchseq.cli, torchseq.cli.eval, torchseq.cli.plots\n"
               "print(json.dumps({'loaded': loaded()}))", tmp_path)
    assert got["loaded"] == []


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_seqslam_eval_loads_no_heavy_package_before_its_report(tmp_path):
    body = """
import torchseq.cli
import torchseq.cli.eval as cli_eval
seen = {}
real = cli_eval.report
def report(*args, **kwargs):
    seen['before_report'] = loaded()
    return real(*args, **kwargs)
cli_eval.report = report
code = torchseq.cli.main(['eval', '--engine', 'seqslam', '--demo-frames', '60', '--out', 'o',
                          '--no-tensorboard'])
seen['code'] = code
seen['after_report'] = loaded()
print(json.dumps(seen))
"""
    got = _run(body, tmp_path)
    assert got["code"] == 0
    assert got["before_report"] == []
    assert "tensorboard" not in got["after_report"]  # --no-tensorboard: never imported
    # a SeqSLAM run's figures are drawn with NumPy/OpenCV (report_images): no matplotlib
    assert "matplotlib" not in got["after_report"]
    assert (tmp_path / "o" / "seqslam_difference_matrix.png").stat().st_size > 1000
    assert (tmp_path / "o" / "metrics.json").exists()


def test_neural_inference_imports_numba_only_on_its_first_online_step(tmp_path):
    """The compiled step's numba import (and compilation) lands on the first ``step`` only:
    building the inference module and running a whole traverse never import numba."""
    body = """
from torchseq.demo import make_demo
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
demo = make_demo(n_reference=40, size=(48, 64), seed=3)
model = NeuralSeqSLAM(NeuralConfig(hidden=512, n_output=40))
model.fit(demo.reference, log=False)
inf = model.inference()
inf.run(demo.query)
seen = {'kernel': inf.kernels['step'], 'before_step': loaded()}
inf.step(demo.query[:1])
seen['after_step'] = loaded()
print(json.dumps(seen))
"""
    got = _run(body, tmp_path)
    assert got["kernel"] == "stages_or_numba"
    assert "numba" not in got["before_step"]
    assert "numba" in got["after_step"]

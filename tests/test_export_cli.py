"""``python -m torchseq.export`` and ``export_checkpoint``: files, validation.json, exit codes."""

import json
import subprocess
import sys

import numpy as np
import pytest
from export_helpers import small_setup

from torchseq.export import export_checkpoint
from torchseq.export.cli import ExportError, main
from torchseq.export.int_format import read_integer_model

FILES = ("model_float.onnx", "model_quant.onnx", "model_int.tsq", "model_int.onnx",
         "validation.json")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    model, demo, *_ = small_setup()
    folder = tmp_path_factory.mktemp("ckpt")
    model.save(folder / "small.pt")
    np.save(folder / "query.npy", demo.query.numpy()[:40])
    np.save(folder / "gt.npy", demo.ground_truth[:, :40].astype(np.int64))
    return folder


def test_cli_writes_everything_and_passes(checkpoint, tmp_path, capsys):
    out = tmp_path / "export"
    code = main([str(checkpoint / "small.pt"), "--out", str(out), "--query",
                 str(checkpoint / "query.npy"), "--ground-truth", str(checkpoint / "gt.npy")])
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(FILES)
    report = json.loads((out / "validation.json").read_text())
    agreements = {k: v for k, v in report.items() if k.endswith("_agreement")}
    assert {"float_onnx_agreement", "quant_onnx_agreement", "integer_agreement",
            "integer_onnx_agreement"} <= set(agreements)
    assert all(0.0 <= v <= 1.0 for v in agreements.values())
    assert report["integer_onnx_bit_exact"] is True and report["passed"] is True
    assert report["float_onnx_max_abs_error"] < 1e-4
    assert set(report["recall_at_1"]) >= {"pytorch", "integer_numpy", "integer_onnx"}
    assert report["files_bytes"]["model_int.tsq"] == (out / "model_int.tsq").stat().st_size
    assert read_integer_model(out / "model_int.tsq").params["n_units"] == 40
    assert capsys.readouterr().out.strip().endswith("PASS")


@pytest.mark.slow
def test_export_checkpoint_on_the_demo_route(tmp_path):
    from torchseq.demo import make_demo
    from torchseq.neural import NeuralConfig, NeuralSeqSLAM

    model = NeuralSeqSLAM(NeuralConfig(hidden=1024, n_output=100))
    model.fit(make_demo().reference, log=False)
    model.save(tmp_path / "demo.pt")
    assert export_checkpoint(tmp_path / "demo.pt", tmp_path / "out") is True
    report = json.loads((tmp_path / "out" / "validation.json").read_text())
    assert report["query_source"].startswith("demo")
    assert report["n_query"] == 249 and report["integer_pool"] == [4, 4]
    assert report["integer_agreement"] >= 0.99
    assert report["recall_at_1"]["integer_onnx"] >= 0.9  # measured 0.924 (1024 L2 units)


def test_a_failed_check_exits_1(checkpoint, tmp_path, monkeypatch, capsys):
    import torchseq.export.validate as validate

    monkeypatch.setattr(validate, "MIN_AGREEMENT", 1.01)  # no variant can reach it
    code = main([str(checkpoint / "small.pt"), "--out", str(tmp_path), "--query",
                 str(checkpoint / "query.npy")])
    assert code == 1
    report = json.loads((tmp_path / "validation.json").read_text())
    assert report["passed"] is False and report["checks"]["integer_agreement"] is False
    assert report["checks"]["integer_onnx_bit_exact"] is True and "recall_at_1" not in report
    assert "FAIL: float_onnx_agreement, integer_agreement" in capsys.readouterr().out


def test_corrupt_checkpoint_fails_with_one_line(checkpoint, tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes((checkpoint / "small.pt").read_bytes()[:1000])
    with pytest.raises(ExportError):
        export_checkpoint(bad, tmp_path / "o")
    proc = subprocess.run([sys.executable, "-m", "torchseq.export", str(bad), "--out",
                           str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "bad.pt" in lines[0]
    assert not (tmp_path / "o" / "validation.json").exists()


def test_bad_ground_truth_is_rejected(checkpoint, tmp_path):
    np.save(tmp_path / "gt.npy", np.zeros((3, 3), np.int64))
    code = main([str(checkpoint / "small.pt"), "--out", str(tmp_path / "o"), "--query",
                 str(checkpoint / "query.npy"), "--ground-truth", str(tmp_path / "gt.npy")])
    assert code == 2

"""``python -m torchseq.export`` and ``export_checkpoint``: files, validation.json, exit codes."""

import importlib.util
import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from conftest import coarse_units_expected
from export_helpers import small_setup

from torchseq.cli.export import main
from torchseq.export import export_checkpoint
from torchseq.export.errors import ExportError
from torchseq.export.int_format import read_integer_model

FILES = ("model_float.onnx", "model_quant.onnx", "model_int.tsq", "model_int.onnx",
         "validation.json") + (("model.nir",) if importlib.util.find_spec("nir") else ())


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    model, demo, *_ = small_setup()
    folder = tmp_path_factory.mktemp("ckpt")
    np.save(folder / "ref.npy", demo.reference.numpy())  # the NIR calibrates on it
    model.save(folder / "small.pt", extra={"reference": {"source": str(folder / "ref.npy")}})
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
    printed = capsys.readouterr().out
    assert printed.strip().endswith("PASS")
    # the chip report and the timed spiking model are opt-in (--chip-report, --timed-spiking)
    assert "chip" not in printed and "timed" not in printed
    assert {"chips", "timed"}.isdisjoint(report.get("nir", {}))
    # an existing export is refused, as eval/train/map refuse an existing --out
    again = [str(checkpoint / "small.pt"), "--out", str(out), "--query",
             str(checkpoint / "query.npy"), "--no-nir"]
    assert main(again) == 2
    assert f"--out {out} already holds files; give a new folder or --overwrite" in \
        capsys.readouterr().err
    assert main([*again, "--overwrite"]) == 0  # a fresh folder: no stale model.nir beside it
    assert "model.nir" not in {p.name for p in out.iterdir()}
    assert json.loads((out / "validation.json").read_text())["nir"] == {"skipped": "--no-nir"}
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    assert main([str(checkpoint / "small.pt"), "--out", str(tmp_path / "other"),
                 "--overwrite"]) == 2  # --overwrite replaces only a previous export
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


@pytest.mark.slow
def test_export_checkpoint_on_the_demo_route(tmp_path):
    from torchseq.demo import make_demo
    from torchseq.neural import NeuralConfig, NeuralSeqSLAM

    model = NeuralSeqSLAM(NeuralConfig(unit_search="off", hidden=1024, n_output=100))
    with coarse_units_expected():  # a small model: units of several frames
        model.fit(make_demo().reference, log=False)
    model.save(tmp_path / "demo.pt", extra={"reference": {
        "source": "demo", "demo_frames": 200, "demo_seed": 0, "frame_size": [96, 128]}})
    assert export_checkpoint(tmp_path / "demo.pt", tmp_path / "out") is True
    report = json.loads((tmp_path / "out" / "validation.json").read_text())
    assert report["query_source"].startswith("the checkpoint's own reference: demo")
    assert report["n_query"] == 249 and report["integer_pool"] == [4, 4]
    assert report["integer_agreement"] >= 0.99
    assert report["recall_at_1"]["integer_onnx"] >= 0.9  # measured 0.924 (1024 L2 units)


@pytest.fixture(scope="module")
def camera_checkpoint(tmp_path_factory):
    """A model fitted on a 120x160 reference file (not the demo), as train.py records it."""
    from torchseq.demo import make_demo
    from torchseq.neural import NeuralConfig, NeuralSeqSLAM

    folder = tmp_path_factory.mktemp("camera")
    route = make_demo(n_reference=50, size=(120, 160), seed=7)
    frames = route.reference.round().clamp(0, 255).to(torch.uint8).numpy()
    np.save(folder / "ref.npy", frames)
    model = NeuralSeqSLAM(NeuralConfig(unit_search="off", hidden=512, n_output=50))
    model.fit(torch.from_numpy(frames).float(), log=False)
    model.save(folder / "cam.pt", extra={"reference": {
        "source": str(folder / "ref.npy"), "n_frames": 50, "frame_size": [120, 160]}})
    return folder


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_default_validation_uses_the_checkpoints_own_reference(camera_checkpoint, tmp_path):
    # main validated every checkpoint on the synthetic demo route (recall ~0, FAIL) and took
    # the device input size (96x128) from it
    out = tmp_path / "out"
    assert export_checkpoint(camera_checkpoint / "cam.pt", out) is True
    report = json.loads((out / "validation.json").read_text())
    assert str(camera_checkpoint / "ref.npy") in report["query_source"]
    assert report["n_query"] == 50 and report["device_frame_size"] == [120, 160]
    assert report["integer_pool"] == [5, 5]
    assert report["recall_at_1"]["pytorch"] >= 0.9  # a replay of the learnt route


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_frame_size_sets_the_device_input_not_the_query(camera_checkpoint, tmp_path):
    out = tmp_path / "out"
    code = main([str(camera_checkpoint / "cam.pt"), "--out", str(out), "--frame-size", "48x64"])
    assert code == 0
    report = json.loads((out / "validation.json").read_text())
    assert report["device_frame_size"] == [48, 64] and report["integer_pool"] == [2, 2]
    assert report["query_frame_size"] == [120, 160]
    assert report["device_frame_size_source"] == "--frame-size"
    stored = read_integer_model(out / "model_int.tsq")
    assert (stored.params["pool_h"], stored.params["pool_w"]) == (2, 2)


def test_onnx_files_carry_the_device_contract(camera_checkpoint, tmp_path):
    from torchseq.export.contract import read_contract

    out = tmp_path / "out"
    assert export_checkpoint(camera_checkpoint / "cam.pt", out) is True
    report = json.loads((out / "validation.json").read_text())
    for name in ("model_float.onnx", "model_quant.onnx"):
        meta = read_contract(out / name)
        assert meta["torchseq.contract_version"] == "1" and meta["torchseq.input_size"] == "24x32"
        assert "COLOR_BGR2GRAY" in meta["torchseq.grey"] and "floor(i*H/h)" in meta[
            "torchseq.resize"]
        assert meta["torchseq.initial_state"] == "zeros float32 (B, 50)"
        assert float(meta["torchseq.confidence_threshold"]) == pytest.approx(
            report["suggested_confidence_threshold"], rel=1e-5)
    meta = read_contract(out / "model_int.onnx")
    assert meta["torchseq.device_frame_size"] == "120x160"
    assert meta["torchseq.integer_pool"] == "5x5"
    assert meta["torchseq.input"] == "frames uint8 (B, 120, 160)"
    assert meta["torchseq.initial_state"] == "zeros int32 (B, 50)"


def test_checkpoint_without_a_recorded_reference_needs_a_query(checkpoint, tmp_path):
    from torchseq.neural import NeuralSeqSLAM

    NeuralSeqSLAM.load(checkpoint / "small.pt").save(tmp_path / "bare.pt")  # records nothing
    with pytest.raises(ExportError, match="does not record which reference"):
        export_checkpoint(tmp_path / "bare.pt", tmp_path / "o")


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_a_failed_check_exits_1(checkpoint, tmp_path, monkeypatch, capsys):
    import torchseq.export.validate as validate

    monkeypatch.setattr(validate, "MIN_AGREEMENT", 1.01)  # no variant can reach it
    monkeypatch.setattr(validate, "MIN_UINT8_AGREEMENT", 1.01)
    code = main([str(checkpoint / "small.pt"), "--out", str(tmp_path), "--query",
                 str(checkpoint / "query.npy")])
    assert code == 1
    report = json.loads((tmp_path / "validation.json").read_text())
    assert report["passed"] is False and report["checks"]["integer_agreement"] is False
    assert report["checks"]["integer_onnx_bit_exact"] is True and "recall_at_1" not in report
    assert ("FAIL: float_onnx_agreement, integer_agreement, uint8_input_agreement"
            in capsys.readouterr().out)


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_frames_that_are_not_grey_levels_fail_the_uint8_check(checkpoint, tmp_path, capsys):
    # event frames are window means (about 0..0.3), not grey levels: rounding them to the
    # integer device's uint8 input erases them, which used to pass silently (integer vs
    # PyTorch compared on the same erased frames)
    query = np.load(checkpoint / "query.npy") / 255.0
    np.save(tmp_path / "q01.npy", query)
    code = main([str(checkpoint / "small.pt"), "--out", str(tmp_path / "out"), "--query",
                 str(tmp_path / "q01.npy")])
    assert code == 1
    report = json.loads((tmp_path / "out" / "validation.json").read_text())
    assert report["checks"]["uint8_input_agreement"] is False
    assert report["checks"]["integer_agreement"] is True  # the erased frames agree
    out = capsys.readouterr().out
    assert "warning: the integer device's uint8 input changes" in out
    assert "not grey levels" in out and "FAIL: uint8_input_agreement" in out


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_corrupt_checkpoint_fails_with_one_line(checkpoint, tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes((checkpoint / "small.pt").read_bytes()[:1000])
    with pytest.raises(ExportError):
        export_checkpoint(bad, tmp_path / "o")
    proc = subprocess.run([sys.executable, "-m", "torchseq.export", str(bad), "--out",
                           str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("python -m torchseq.export: error:")
    assert "bad.pt" in lines[0]
    assert not (tmp_path / "o" / "validation.json").exists()


def test_bad_ground_truth_is_rejected(checkpoint, tmp_path):
    np.save(tmp_path / "gt.npy", np.zeros((3, 3), np.int64))
    code = main([str(checkpoint / "small.pt"), "--out", str(tmp_path / "o"), "--query",
                 str(checkpoint / "query.npy"), "--ground-truth", str(tmp_path / "gt.npy")])
    assert code == 2


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_device_input_does_not_follow_the_validation_query(camera_checkpoint, tmp_path):
    # validating on 48x64 frames must not make a 48x64 device for a 120x160 camera
    query = np.load(camera_checkpoint / "ref.npy")[:30]
    small = torch.nn.functional.adaptive_avg_pool2d(torch.from_numpy(query).float()[:, None],
                                                    (48, 64))[:, 0].round().numpy()
    np.save(tmp_path / "q.npy", small.astype(np.uint8))
    out = tmp_path / "out"
    assert main([str(camera_checkpoint / "cam.pt"), "--out", str(out), "--query",
                 str(tmp_path / "q.npy")]) == 0
    report = json.loads((out / "validation.json").read_text())
    assert report["query_frame_size"] == [48, 64]
    assert report["device_frame_size"] == [120, 160] and report["integer_pool"] == [5, 5]
    assert report["device_frame_size_source"] == "the checkpoint's reference frames"


def test_summary_lines_report_the_nir_validation(tmp_path):
    from torchseq.cli.export import summary_lines

    report = {"query_source": "q", "device_frame_size": [4, 8], "device_frame_size_source": "s",
              "camera_frame_size": [4, 8],
              "checks": {"nir_consumers_agree": False}, "passed": False,
              "nir": {"file": "model.nir",
                      "spiking": {"agreement_with_rate_model": 0.5, "recall_at_1": 0.25},
                      "consumers": {"snntorch": {"agreement": 0.75, "streams": 3,
                                                 "time_steps": 14, "spike_agreement": 0.9,
                                                 "streams_recall_at_1": 0.5},
                                    "norse": {"skipped": "norse is not installed"}}}}
    (tmp_path / "validation.json").write_text(json.dumps(report))
    lines = summary_lines(tmp_path)
    assert "nir: model.nir, spiking model agreement with the rate model 0.5, recall_at_1 0.25" \
        in lines
    assert "nir_snntorch: agreement 0.75 with the spiking model on the same inputs (3 streams " \
           "of 14 frames), spike agreement 0.9" in lines
    assert "nir_norse: skipped: norse is not installed" in lines
    assert lines[-1] == "FAIL: nir_consumers_agree"
    report["nir"] = {"skipped": "--no-nir"}
    (tmp_path / "validation.json").write_text(json.dumps(report))
    assert "nir: skipped (--no-nir)" in summary_lines(tmp_path)


def test_device_line_says_where_the_size_came_from_and_what_the_host_does():
    from torchseq.cli.export import device_line

    report = {"device_frame_size": [24, 32], "camera_frame_size": [32, 64],
              "device_frame_size_source": "the checkpoint's reference frames"}
    assert device_line(report) == (
        "device input: uint8 24x32: camera frames 32x64 (from the checkpoint's reference "
        "frames) resized on the host (not a multiple of the model's input)")
    report["device_frame_size"] = [32, 64]  # pooled on the device: the camera's own size
    assert device_line(report) == ("device input: uint8 32x64 (the camera frames' size, from "
                                   "the checkpoint's reference frames)")

"""Traverses of descriptors: files, the descriptor hook, both engines, the exact reproduction."""

import csv
import json

import h5py
import numpy as np
import pytest
import torch
from conftest import shared_data

import torchseq.cli.eval as cli_eval
from torchseq import load_traverse
from torchseq.cli.errors import UsageError
from torchseq.cli.runs import run_main
from torchseq.descriptors import (
    DescriptorError,
    describe,
    descriptor_kind,
    load_descriptors,
    load_hook,
    neural_config,
    neural_input,
    save_descriptors,
)
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig


def run_eval(tmp_path, name, *args):
    out = tmp_path / name
    code = run_main(cli_eval.main, "eval.py", [*args, "--out", str(out), "--no-tensorboard",
                                               "--no-progress"])
    assert code == 0
    rows = list(csv.DictReader(open(out / "matches.csv")))
    return rows, json.loads((out / "metrics.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("preset", [None, "openseqslam"])
def test_own_descriptors_reproduce_the_pixel_run_exactly(tmp_path, preset, corridor):
    """SeqSLAM's patch-normalised descriptors as (T, D) files: same matches, same scores."""
    root = corridor.root
    flags = ["--preset", preset] if preset else []
    config = SeqSLAMConfig.preset(preset) if preset else SeqSLAMConfig()
    engine = SeqSLAM(config)
    for side in ("ref", "query"):
        frames = load_traverse(root / side, progress=False, size=config.image_size)
        save_descriptors(tmp_path / f"{side}.npy", engine.descriptors(frames))
    common = ["--engine", "seqslam", "--ground-truth", str(root / "ground_truth.csv"), *flags]
    pix_rows, pix = run_eval(tmp_path, "pixels", "--reference", str(root / "ref"),
                             "--query", str(root / "query"), *common)
    desc_rows, desc = run_eval(tmp_path, "desc", "--reference", str(tmp_path / "ref.npy"),
                               "--query", str(tmp_path / "query.npy"), *common)
    assert pix_rows == desc_rows  # every match and score, as written
    for key in ("recall_at_1", "recall_at_5", "auc", "recall", "operating_point"):
        assert pix["seqslam"][key] == desc["seqslam"][key]
    assert desc["inputs"]["descriptors"] == {"dim": 2048, "hook": None}
    # the Python API: the same tensors
    a = engine.match(corridor.ref, corridor.query)
    b = engine.match_descriptors(load_descriptors(tmp_path / "ref.npy"),
                                 load_descriptors(tmp_path / "query.npy"))
    assert torch.equal(a.matches.reference, b.matches.reference)
    torch.testing.assert_close(a.matches.score, b.matches.score, rtol=0, atol=0,
                               equal_nan=True)
    assert torch.equal(a.ranked, b.ranked)


def test_file_layouts_read_the_same(tmp_path):
    x = np.random.default_rng(0).random((7, 5)).astype(np.float32)
    np.save(tmp_path / "d.npy", x)
    np.savez(tmp_path / "d.npz", descriptors=x, names=np.arange(7))
    with h5py.File(tmp_path / "d.h5", "w") as f:
        f["descriptors"] = x
        f["extra"] = np.arange(3)
    kap = tmp_path / "kapture"
    (kap / "database").mkdir(parents=True)
    (kap / "global_features.txt").write_text(
        "# kapture format: 1.1\n# name, dtype, dsize, metric_type\ncosplace, float32, 5, L2\n")
    for i, row in enumerate(x):  # natural order: db2 before db10
        row.tofile(kap / "database" / f"db{i * 5}.jpg.gfeat")
    for name, kind in (("d.npy", "npy"), ("d.npz", "npz"), ("d.h5", "hdf5"),
                       ("kapture/database", "kapture")):
        assert descriptor_kind(tmp_path / name) == kind
        got = load_descriptors(tmp_path / name)
        assert got.dtype == torch.float32 and np.array_equal(got.numpy(), x), name


def test_what_is_not_descriptors(tmp_path):
    np.save(tmp_path / "frames.npy", np.zeros((4, 8, 8), np.float32))
    assert descriptor_kind(tmp_path / "frames.npy") is None
    np.savez(tmp_path / "frames.npz", frames=np.zeros((4, 8, 8)), times=np.arange(4))
    assert descriptor_kind(tmp_path / "frames.npz") is None
    with pytest.raises(DescriptorError, match=r"must be \(T, D\), got \(4, 8, 8\)"):
        load_descriptors(tmp_path / "frames.npy")
    with pytest.raises(DescriptorError, match="no 'descriptors' array among frames, times"):
        load_descriptors(tmp_path / "frames.npz")
    np.save(tmp_path / "nan.npy", np.array([[0.0, np.nan]]))
    with pytest.raises(DescriptorError, match="NaN"):
        load_descriptors(tmp_path / "nan.npy")
    (tmp_path / "k").mkdir()
    np.zeros(3, np.float32).tofile(tmp_path / "k" / "a.jpg.gfeat")
    with pytest.raises(DescriptorError, match="without a global_features.txt"):
        load_descriptors(tmp_path / "k")
    with pytest.raises(DescriptorError, match="no such file"):
        load_descriptors(tmp_path / "missing.npy")


HOOK = '''
import torch

def describe(frames):
    """(B, H, W) -> (B, 12): coarse block means."""
    return torch.nn.functional.adaptive_avg_pool2d(frames[:, None], (3, 4)).flatten(1)

class Net(torch.nn.Module):
    def forward(self, frames):
        return describe(frames) * 2.0

calls = []

def counted(frames):
    calls.append(frames.shape[0])
    return describe(frames)
'''


def test_descriptor_hook_runs_batched_and_equals_its_file(tmp_path, monkeypatch):
    (tmp_path / "myhook.py").write_text(HOOK)
    monkeypatch.syspath_prepend(str(tmp_path))
    frames = torch.rand(10, 12, 16) * 255
    fn = load_hook("myhook:describe")
    whole = fn(frames)
    for batch in (1, 3, 64):
        assert torch.allclose(describe(iter(frames), fn, "cpu", batch), whole)
    counted = load_hook("myhook:counted")
    describe(iter(frames), counted, "cpu", 4)
    import myhook
    assert myhook.calls == [4, 4, 2]
    net = load_hook("myhook:Net")  # a module class: built, put in eval mode
    assert isinstance(net, torch.nn.Module) and not net.training
    assert torch.allclose(describe(iter(frames), net), 2 * whole)
    for bad, msg in (("myhook", "module:callable"), ("nosuchmod:f", "cannot import"),
                     ("myhook:nothing", "has no nothing")):
        with pytest.raises(DescriptorError, match=msg):
            load_hook(bad)
    with pytest.raises(DescriptorError, match=r"to \(2, D\)"):
        describe(iter(frames[:2]), lambda x: x.sum(), "cpu", 2)


@pytest.mark.slow
def test_descriptor_hook_on_the_command_line_equals_the_file(tmp_path, monkeypatch):
    root = shared_data("corridor")
    (tmp_path / "myhook.py").write_text(HOOK)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    fn = load_hook("myhook:describe")
    for side in ("ref", "query"):
        save_descriptors(tmp_path / f"{side}.npy", fn(load_traverse(root / side,
                                                                    progress=False)))
    common = ["--engine", "seqslam", "--tolerance", "2", "--metric", "cosine", "--ds", "6"]
    hook_rows, hook = run_eval(tmp_path, "hook", "--reference", str(root / "ref"), "--query",
                               str(root / "query"), "--descriptor", "myhook:describe",
                               "--descriptor-batch", "7", *common)
    file_rows, _ = run_eval(tmp_path, "file", "--reference", str(tmp_path / "ref.npy"),
                            "--query", str(tmp_path / "query.npy"), *common)
    assert hook_rows == file_rows
    assert hook["inputs"]["descriptors"] == {"dim": 12, "hook": "myhook:describe"}
    assert (tmp_path / "hook" / "seqslam_matched_pairs.png").exists()  # thumbnails kept


def test_neural_engine_takes_descriptors_as_l1(tmp_path):
    d = 40
    cfg = neural_config(NeuralConfig(hidden=256, n_output=60), d)
    assert cfg.input_size == (1, d) and cfg.patch_size == 0
    model = NeuralSeqSLAM(cfg)
    assert model.l1.in_features == d  # L1 has one unit per descriptor value
    rng = np.random.default_rng(0)
    ref = rng.normal(size=(60, d)).astype(np.float32) * 0.01 + 3  # any scale and offset
    x = neural_input(torch.as_tensor(ref))
    assert x.shape == (60, 1, d)
    assert torch.allclose(x.mean(-1)[:, 0], torch.zeros(60), atol=1e-5)
    assert torch.allclose(x.std(-1, unbiased=False)[:, 0], torch.ones(60), atol=1e-4)
    model.fit(x)
    query = ref + rng.normal(size=ref.shape).astype(np.float32) * 0.002
    res = model.run(neural_input(torch.as_tensor(query)))
    assert (res.matches.reference == torch.arange(60)).float().mean() > 0.9


def test_neural_and_seqslam_on_descriptor_files_from_the_command_line(tmp_path):
    rng = np.random.default_rng(1)
    route = rng.normal(size=(80, 32)).astype(np.float32)
    np.save(tmp_path / "r.npy", route)
    np.save(tmp_path / "q.npy", route + rng.normal(size=route.shape).astype(np.float32) * 0.3)
    rows, m = run_eval(tmp_path, "both", "--reference", str(tmp_path / "r.npy"), "--query",
                       str(tmp_path / "q.npy"), "--tolerance", "1", "--metric", "l2",
                       "--neural-hidden", "512")
    assert m["seqslam"]["recall_at_1"] > 0.8 and m["neural"]["recall_at_1"] > 0.8
    assert m["neural"]["parameters"]["input_size"] == [1, 32]
    assert m["seqslam"]["parameters"]["metric"] == "l2"


def test_command_line_refusals(tmp_path):
    np.save(tmp_path / "r.npy", np.zeros((30, 8), np.float32))
    np.save(tmp_path / "q16.npy", np.zeros((30, 16), np.float32))
    base = ["--reference", str(tmp_path / "r.npy"), "--out", str(tmp_path / "o"),
            "--no-tensorboard", "--no-progress"]
    with pytest.raises(UsageError, match="8 values, query descriptors 16"):
        cli_eval.main([*base, "--query", str(tmp_path / "q16.npy")])
    root = shared_data("corridor")
    with pytest.raises(UsageError, match="holds descriptors and the other frames"):
        cli_eval.main([*base, "--query", str(root / "query"), "--overwrite"])
    with pytest.raises(UsageError, match="--image-size shapes SeqSLAM's own descriptors"):
        cli_eval.main([*base, "--query", str(tmp_path / "r.npy"), "--image-size", "16x16",
                       "--engine", "seqslam", "--overwrite"])
    with pytest.raises(UsageError, match="--neural-input-size has no effect on descriptors"):
        cli_eval.main([*base, "--query", str(tmp_path / "r.npy"), "--neural-input-size",
                       "8x8", "--engine", "neural", "--overwrite"])

"""Float ONNX export: the traced step equals PyTorch (tolerance, decisions), dynamic batch."""

import numpy as np
import onnx
import pytest
import torch
from conftest import coarse_units_expected
from export_helpers import small_setup

from torchseq.export.onnx_float import (
    StreamingStep,
    build_float_onnx,
    export_float_onnx,
)
from torchseq.export.sessions import run_float_onnx, session
from torchseq.export.validate import quantise_onnx
from torchseq.preprocess import resize


@pytest.fixture(scope="module")
def setup():
    model, demo, *_ = small_setup()
    small = resize(demo.query.float(), model.config.input_size)
    return model, demo, small, build_float_onnx(model)


def test_streaming_step_equals_model_step(setup):
    model, demo, small, _ = setup
    step = StreamingStep(model)
    state = torch.zeros(3, model.n_units)
    ref_state = None
    for t in range(5):
        out, ref_state = model.step(small[3 * t:3 * t + 3], ref_state)
        act, new_state, ref, conf = step(small[3 * t:3 * t + 3], state)
        assert torch.allclose(act, out.activity, atol=1e-5)
        assert torch.equal(ref, out.reference)
        assert torch.allclose(conf, out.confidence, atol=1e-5)
        state = new_state


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [1, 3])
def test_onnx_matches_pytorch_with_dynamic_batch(setup, batch, dtype):
    """The float32 graph against the PyTorch step in float32 and in float64."""
    model, _, small, proto = setup
    sess = session(proto)
    step = StreamingStep(model).to(dtype)
    tol = 1e-5 if dtype == torch.float32 else 1e-4  # float32 graph vs a float64 reference
    state = np.zeros((batch, model.n_units), np.float32)
    state_pt = torch.zeros(batch, model.n_units, dtype=dtype)
    for t in range(0, 30, batch):
        frames = small[t:t + batch]
        act, state, ref, conf = sess.run(None, {"frames": frames.numpy(), "state": state})
        act_pt, state_pt, ref_pt, conf_pt = step(frames.to(dtype), state_pt)
        assert act.shape == (batch, model.n_units)
        np.testing.assert_allclose(act, act_pt.numpy(), atol=tol, rtol=tol)
        np.testing.assert_allclose(conf, conf_pt.numpy(), atol=tol, rtol=tol)
        assert np.array_equal(ref, ref_pt.numpy())


def test_whole_traverse_against_model_run(setup, tmp_path):
    model, demo, small, _ = setup
    path = tmp_path / "step.onnx"
    assert export_float_onnx(model, path) == path.stat().st_size
    onnx.checker.check_model(str(path), full_check=True)
    ref, conf, act = run_float_onnx(session(path), small.numpy())
    result = model.run(demo.query)
    assert np.abs(act - result.activity.numpy()).max() < 1e-4
    assert np.array_equal(ref, result.matches.reference.numpy())


def test_quantised_onnx_quantises_the_weight_matmuls(setup):
    model, demo, small, proto = setup
    quant = quantise_onnx(proto)
    ops = [n.op_type for n in quant.graph.node]
    assert ops.count("MatMulInteger") == 2
    ref, _, _ = run_float_onnx(session(quant), small.numpy())
    ref_pt = model.run(demo.query).matches.reference.numpy()
    assert np.mean(ref == ref_pt) >= 0.9  # measured 0.93-0.99 on the data of docs/results/export.md


def test_unfitted_model_is_rejected():
    from torchseq.neural import NeuralConfig, NeuralSeqSLAM

    with pytest.raises(ValueError, match="fit"):
        StreamingStep(NeuralSeqSLAM(NeuralConfig(unit_search="off", hidden=64, n_output=4)))


def test_onnx_keeps_the_lowest_index_tie_rule_on_flat_frames(setup):
    model, _, small, proto = setup
    frames = small[:4].clone()
    frames[1] = 90.0  # flat: z-scores 0, every L2 sum 0, the k-WTA is one big tie
    frames[3, :, :16] = 30.0  # half flat
    act, _, ref, conf = session(proto).run(
        None, {"frames": frames.numpy(), "state": np.zeros((4, model.n_units), np.float32)})
    out, _ = model.step(frames)
    np.testing.assert_allclose(act, out.activity.numpy(), atol=1e-5)
    assert np.array_equal(ref, out.reference.numpy())


def test_seqslam_patch_mode_exports_the_same_centred_input():
    from torchseq.demo import make_demo
    from torchseq.neural import NeuralConfig, NeuralSeqSLAM

    demo = make_demo(n_reference=60, size=(48, 64), seed=2)
    model = NeuralSeqSLAM(NeuralConfig(
        unit_search="off", hidden=512, n_output=40, patch_mode="seqslam"))
    with coarse_units_expected():  # a small model: units of several frames
        model.fit(demo.reference, log=False)
    small = resize(demo.query.float(), model.config.input_size)
    x = model.encode(small)
    assert x.min() >= -127 and x.max() <= 128 and abs(float(x.mean())) < 1.0  # centred
    want = model.run(small)
    sess = session(build_float_onnx(model))
    ref, _, act = run_float_onnx(sess, small.numpy())
    assert np.array_equal(ref, want.matches.reference.numpy())
    np.testing.assert_allclose(act, want.activity.numpy(), atol=1e-4)
    assert float((want.matches.reference - torch.arange(len(small)) * 0.8).abs().lt(3)
                 .float().mean()) > 0.9  # it recognises the route (it did not before centring)

"""NumPy integer runtime and integer ONNX graph: bit-exact with each other and with an
independent plain-Python oracle of the spec; agreement with the float model."""

import math

import numpy as np
import pytest
import torch
from conftest import coarse_units_expected
from export_helpers import small_setup
from int_oracle import oracle_step

from torchseq.demo import make_demo
from torchseq.export import IntegerInputError
from torchseq.export.int_functional import kwta_code
from torchseq.export.int_kernels import input_stage, isqrt, round_div
from torchseq.export.int_model import choose_pool, device_frames, integer_model
from torchseq.export.int_onnx import build_integer_onnx
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.export.sessions import run_integer_onnx, session
from torchseq.layers.functional import kwta
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.preprocess import patch_normalise

TINY = {
    "zscore": {},
    "cohorts_mean_unrectified": {"n_cohorts": 3, "rectify": False, "hebbian": "mean"},
    "raw_input": {"patch_size": 0},
}


def _tiny(kind: str):
    demo = make_demo(n_reference=12, size=(16, 16), seed=3)
    cfg = NeuralConfig(unit_search="off", input_size=(8, 8), hidden=64, n_output=9, **TINY[kind])
    model = NeuralSeqSLAM(cfg)
    with coarse_units_expected():  # a small model: units of several frames
        model.fit(demo.reference, log=False)
    pool = choose_pool((16, 16), (8, 8))
    frames = device_frames(demo.query, (8, 8), pool)
    frames[3] = 77  # a flat frame: zero variance everywhere, all-tied k-WTA
    return integer_model(model, pool), frames


@pytest.mark.parametrize("kind", list(TINY))
def test_runtime_and_onnx_match_the_plain_python_oracle(kind):
    model, frames = _tiny(kind)
    ref_n, conf_n, act_n = IntegerRuntime(model).run(frames)
    ref_o, conf_o, act_o = run_integer_onnx(session(build_integer_onnx(model)), frames)
    state = [0] * model.params["n_units"]
    for t in range(frames.shape[0]):
        state, ref, conf = oracle_step(model, frames[t].tolist(), state)
        assert act_n[t].tolist() == state, f"step {t}"
        assert (int(ref_n[t]), int(conf_n[t])) == (ref, conf), f"step {t}"
    assert np.array_equal(act_n, act_o) and np.array_equal(ref_n, ref_o)
    assert np.array_equal(conf_n, conf_o)


def test_round_div_and_isqrt_against_python_ints():
    rng = np.random.default_rng(0)
    for top, bmax in ((2**60, 2**40), (2**51, 2**40), (2**40, 2**20), (2**30, 2**30)):
        # the first case takes integer division, the others the float64 one
        a = np.concatenate([rng.integers(-top, top, 2000), np.arange(-20, 21)])
        b = np.concatenate([rng.integers(1, bmax, 2000), np.full(41, 4)])
        b[:50] = 2 * np.abs(a[:50]) + 1  # quotients just below one half
        b[50:100] += b[50:100] % 2  # even: the halves below are exact
        a[50:100] = b[50:100] * rng.integers(-9, 9, 50) + b[50:100] // 2
        b[100:110] = 2**20  # powers of two (the rescaling shifts)
        got = round_div(a, b)
        for x, y, q in zip(a.tolist(), b.tolist(), got.tolist()):
            want = (2 * abs(x) + y) // (2 * y)
            assert q == (want if x >= 0 else -want)
        if top < 2**52:  # the same integers held in float64 give the same quotients
            assert round_div(a.astype(np.float64), b.astype(np.float64)).tolist() == got.tolist()
    with pytest.raises(ValueError, match="below 2\\*\\*53"):
        round_div(np.array([2.0**52]), np.array([3.0]))
    k = rng.integers(1, 2**31 - 1, 1000)
    v = np.concatenate([rng.integers(0, 2**62 - 1, 3000), np.arange(0, 300), k * k, k * k - 1,
                        np.array([2**62 - 1, (2**31 - 1) ** 2, (2**31 - 1) ** 2 - 1])])
    assert isqrt(v).tolist() == [math.isqrt(x) for x in v.tolist()]


def test_input_stage_is_the_float_zscore_on_a_fixed_grid():
    model, _, pool, frames, im = small_setup()
    p = im.params
    x = input_stage(frames, p)  # (T, D) int32
    pooled = torch.from_numpy(frames).double().reshape(len(frames), 24, pool[0], 32,
                                                       pool[1]).mean((2, 4))
    z = patch_normalise(pooled, p["patch"], "zscore").reshape(len(frames), -1).numpy()
    step = 2.0 ** -p["x_frac"]
    assert x.dtype == np.int32
    assert np.abs(x * step - z).max() <= step / 2 + 2e-3  # rounding plus the isqrt's 2**-8


@pytest.mark.parametrize("kernel", ["numpy", "torch"])
def test_kwta_int_matches_the_float_kwta_with_ties(kernel):
    rng = np.random.default_rng(1)
    h = rng.integers(-5, 6, size=(50, 40)).astype(np.int32)  # many ties at the threshold
    for k in (1, 7, 40):
        want = kwta(torch.from_numpy(h).double(), k, binary=True).numpy() > 0
        assert np.array_equal(np.asarray(kwta_code(h, k, kernel=kernel), bool), want)
        assert (np.asarray(kwta_code(h, k, kernel=kernel), bool).sum(1) == k).all()


def test_bit_exact_over_a_whole_traverse_batched():
    _, _, _, frames, im = small_setup()
    rt, sess = IntegerRuntime(im), session(build_integer_onnx(im))
    ref_n, conf_n, act_n = rt.run(frames)
    ref_o, conf_o, act_o = run_integer_onnx(sess, frames)
    assert act_n.dtype == act_o.dtype == np.int32
    assert np.array_equal(act_n, act_o) and np.array_equal(ref_n, ref_o)
    assert np.array_equal(conf_n, conf_o)
    # three independent streams at once, state fed back (B = 3)
    streams = np.stack([frames[:20], frames[20:40], frames[40:60]], 1)  # (T, 3, H, W)
    state_n = rt.initial_state(3)
    state_o = state_n.copy()
    for t in range(streams.shape[0]):
        out, state_n = rt.step(streams[t], state_n)
        act, state_o, ref, conf = sess.run(None, {"frames": streams[t], "state": state_o})
        assert np.array_equal(out.activity, act) and np.array_equal(state_n, state_o)
        assert np.array_equal(out.reference, ref) and np.array_equal(out.confidence, conf)
    for s in range(3):  # each stream equals its own single-stream run
        assert np.array_equal(state_n[s], rt.run(frames[20 * s:20 * s + 20])[2][-1])


@pytest.mark.parametrize("seed", [1, 2])
def test_integer_decisions_agree_with_the_float_model(seed):
    model, demo, _, frames, im = small_setup(seed=seed, hidden=1024, n_output=80,
                                             n_reference=80)
    ref_float = model.run(torch.from_numpy(frames).float()).matches.reference.numpy()
    ref_int, _, act = IntegerRuntime(im).run(frames)
    # measured 1.0 (seed 1) and 0.990 (seed 2, one frame of 99) on this small model
    assert np.mean(ref_int == ref_float) >= 0.98
    act_float = model.run(torch.from_numpy(frames).float()).activity.numpy()
    err = np.abs(act * 2.0 ** -im.params["state_frac"] - act_float).max()
    assert err < 0.1 * np.abs(act_float).max()  # measured 0.067 of a peak near 1


def test_bad_step_input():
    _, _, _, frames, im = small_setup()
    rt = IntegerRuntime(im)
    with pytest.raises(IntegerInputError, match="uint8"):
        rt.step(frames[:1].astype(np.int16))
    with pytest.raises(IntegerInputError, match="state"):
        rt.step(frames[:2], rt.initial_state(3))


@pytest.mark.slow
def test_default_size_model_on_real_data(corridor):
    """Default NeuralConfig fitted on the corridor reference, run on its query (real data)."""
    from torchseq.metrics import recall_at_k

    ref, query, gt = corridor.ref, corridor.query, corridor.ground_truth
    model = NeuralSeqSLAM(NeuralConfig(unit_search="off"))
    model.fit(ref, log=False)
    pool = choose_pool(tuple(query.shape[1:3]), model.config.input_size)
    assert pool == (5, 5)  # 120x160 camera frames summed in 5x5 blocks on the device
    frames = device_frames(query, model.config.input_size, pool)
    im = integer_model(model, pool)
    ref_n, conf_n, act_n = IntegerRuntime(im).run(frames)
    ref_o, conf_o, act_o = run_integer_onnx(session(build_integer_onnx(im)), frames)
    assert np.array_equal(act_n, act_o) and np.array_equal(conf_n, conf_o)
    ref_float = model.run(query).matches.reference.numpy()
    assert np.mean(ref_n == ref_float) >= 0.99  # measured 1.0 (111 of 111 frames)
    assert abs(recall_at_k(ref_n, gt) - recall_at_k(ref_float, gt)) <= 0.01

"""StreamRuntime (batched over time, int8 GEMMs) must equal IntegerRuntime.run bit for bit."""

import math

import numpy as np
import pytest
import torch
from conftest import coarse_units_expected

from torchseq.demo import make_demo
from torchseq.export import IntegerInputError
from torchseq.export.int_format import X_MAX
from torchseq.export.int_functional import input_stage, kwta_code
from torchseq.export.int_model import device_frames, integer_model
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.export.int_stream import StreamRuntime
from torchseq.neural import NeuralConfig, NeuralSeqSLAM


def fitted(**cfg):
    demo = make_demo(n_reference=70, seed=3)
    model = NeuralSeqSLAM(NeuralConfig(unit_search="off", hidden=1024, n_output=50, **cfg))
    with coarse_units_expected():  # a small model: units of several frames
        model.fit(demo.reference, log=False)
    im = integer_model(model, (1, 1))
    return im, device_frames(demo.query, model.config.input_size, (1, 1))


@pytest.mark.parametrize("grids", [True, False])
def test_stream_runtime_equals_step_by_step(grids):
    cfg = {} if grids else dict(input_steps=0, l1_levels=0, l3_levels=0)
    im, frames = fitted(**cfg)
    runtime = StreamRuntime(im, chunk=40)
    if grids and runtime.l1_int8 is None:
        pytest.skip("oneDNN's int8 GEMM is missing or inexact on this CPU")
    if not grids:
        assert runtime.l1_int8 is None  # 12-bit L1 weights: the NumPy product is used
    want = IntegerRuntime(im).run(frames)
    got = runtime.run(frames)
    for g, w in zip(got, want):
        assert g.dtype == w.dtype and np.array_equal(g, w)


def test_stream_runtime_errors():
    im, frames = fitted()
    runtime = StreamRuntime(im)
    with pytest.raises(IntegerInputError, match="uint8"):
        runtime.run(frames.astype(np.int16))
    with pytest.raises(IntegerInputError, match="uint8"):
        runtime.run(frames[:, :-1])
    with pytest.raises(IntegerInputError, match="empty"):
        runtime.run(frames[:0])


@pytest.mark.parametrize("kernel", ["numpy", "torch"])
def test_kwta_int_ties_go_to_the_lowest_index(kernel):
    g = torch.Generator().manual_seed(0)
    h = torch.randint(-4, 5, (30, 200), generator=g).numpy().astype(np.int32)
    h[2] = 7  # all tied
    win = kwta_code(h, 25, kernel=kernel)
    assert (win.sum(1) == 25).all()
    for row, w in zip(h, win):  # loop reference: sort by value, then by lower index
        order = sorted(range(200), key=lambda j: (-int(row[j]), j))[:25]
        assert set(np.flatnonzero(w)) == set(order)


def input_stage_loop(frame: np.ndarray, p: dict) -> list[int]:
    """The spec's input stage for one uint8 frame, pixel by pixel in Python integers."""
    h, w, ph, pw, s = p["height"], p["width"], p["pool_h"], p["pool_w"], p["patch"]
    pix = [[sum(int(frame[i * ph + a, j * pw + c]) for a in range(ph) for c in range(pw))
            for j in range(w)] for i in range(h)]
    n, out = s * s, [[0] * w for _ in range(h)]
    for bi in range(0, h, s):
        for bj in range(0, w, s):
            vals = [pix[i][j] for i in range(bi, bi + s) for j in range(bj, bj + s)]
            total, squares = sum(vals), sum(v * v for v in vals)
            var = n * squares - total * total
            root = max(math.isqrt(var << (2 * p["sqrt_frac"])), 1)
            for i in range(bi, bi + s):
                for j in range(bj, bj + s):
                    a = (n * pix[i][j] - total) * p["norm_const"]
                    q = (2 * abs(a) + root) // (2 * root)  # round half away from zero
                    z = q if a >= 0 else -q
                    out[i][j] = max(-X_MAX, min(X_MAX, z)) if var > 0 else 0
    return [v for row in out for v in row]


@pytest.mark.parametrize("kernel", ["numpy", "torch"])
@pytest.mark.parametrize("pool", [(1, 1), (2, 3), (5, 5)])
def test_input_stage_equals_the_spec_loop(pool, kernel):
    im, _ = fitted()
    p = dict(im.params, pool_h=pool[0], pool_w=pool[1])
    g = np.random.default_rng(sum(pool))
    size = (p["height"] * pool[0], p["width"] * pool[1])
    frames = g.integers(0, 256, (6, *size)).astype(np.uint8)
    frames[1] = 7  # flat: every block has zero variance
    frames[2] = 0
    frames[2, ::2] = 255  # extreme contrast
    frames[3] = g.integers(100, 102, size)  # tiny variance, near-ties of the rounding
    # the model's constant takes the exact float64 path; a 45-bit one the int64 path
    for x_frac, const in ((5, p["norm_const"]), (9, p["norm_const"]), (5, 2**44 + 12345)):
        q = dict(p, x_frac=x_frac, norm_const=const)
        got = input_stage(frames, q, kernel=kernel)
        for t in range(frames.shape[0]):
            assert got[t].tolist() == input_stage_loop(frames[t], q)


@pytest.mark.parametrize("scale", [1000, 2**30])
def test_ring_scan_equals_the_step_rule_with_and_without_saturation(scale):
    from torchseq.export.int_kernels import INT32_MAX, round_div

    im, _ = fitted()
    runtime = StreamRuntime(im)
    g = np.random.default_rng(scale % 97).integers(-scale, scale, (30, runtime.n_units))
    got = runtime.ring_scan(g)
    a = np.zeros(runtime.n_units, np.int64)
    for t in range(g.shape[0]):  # the step's rule, literally
        moved = (a[runtime.runtime.ring_cols] * runtime.runtime.ring_values).sum(-1)
        a = np.clip(round_div(moved, np.int64(1) << im.params["ring_frac"]) + g[t],
                    -INT32_MAX, INT32_MAX)
        assert np.array_equal(got[t], a)
    assert (np.abs(got).max() == INT32_MAX) == (scale == 2**30)  # saturation did happen

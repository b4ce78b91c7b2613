"""StreamRuntime (batched over time, int8 GEMMs) must equal IntegerRuntime.run bit for bit."""

import numpy as np
import pytest
import torch

from torchseq.demo import make_demo
from torchseq.export.int_model import device_frames, integer_model
from torchseq.export.int_runtime import IntegerRuntime, kwta_int
from torchseq.export.int_stream import StreamRuntime
from torchseq.neural import NeuralConfig, NeuralSeqSLAM


def fitted(**cfg):
    demo = make_demo(n_reference=70, seed=3)
    model = NeuralSeqSLAM(NeuralConfig(hidden=1024, n_output=50, **cfg))
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
    with pytest.raises(ValueError, match="uint8"):
        runtime.run(frames.astype(np.int16))
    with pytest.raises(ValueError, match="uint8"):
        runtime.run(frames[:, :-1])
    with pytest.raises(ValueError, match="empty"):
        runtime.run(frames[:0])


def test_kwta_int_ties_go_to_the_lowest_index():
    g = torch.Generator().manual_seed(0)
    h = torch.randint(-4, 5, (30, 200), generator=g).numpy().astype(np.int32)
    h[2] = 7  # all tied
    win = kwta_int(h, 25)
    assert (win.sum(1) == 25).all()
    for row, w in zip(h, win):  # loop reference: sort by value, then by lower index
        order = sorted(range(200), key=lambda j: (-int(row[j]), j))[:25]
        assert set(np.flatnonzero(w)) == set(order)

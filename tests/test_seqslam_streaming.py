"""StreamingSeqSLAM against an independent loop computation of the trailing-window rule."""

import numpy as np
import pytest
import torch
from conftest import DEVICES
from seqslam_oracle import oracle_difference, oracle_streaming

from torchseq.demo import make_demo
from torchseq.metrics import evaluate
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig, StreamingSeqSLAM


def route(rng, n_ref, n_query, speed, dim=64):
    ref = 127 + np.clip(np.round(rng.normal(0, 2.5, (n_ref, dim))), -8, 8)
    pos = np.minimum(np.round(np.arange(n_query) * speed).astype(int), n_ref - 1)
    return ref, np.clip(ref[pos] + np.round(rng.normal(0, 1.5, (n_query, dim))), 119, 135)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("over", [{}, dict(ds=5, vmin=0.5, vmax=1.5), dict(speed_ratio=0.7)])
def test_streaming_matches_loop_rule(over, dtype, device):
    rng = np.random.default_rng(20)
    ref, query = route(rng, 45, 40, 0.9)
    config = SeqSLAMConfig(**over)
    stream = StreamingSeqSLAM(torch.tensor(ref, dtype=dtype), config, device=device,
                              descriptors=True)
    got = stream.run(torch.tensor(query, dtype=dtype))
    vmin, vmax = config.velocity_range
    want_ref, want_uniq = oracle_streaming(oracle_difference(ref, query), config.ds, vmin, vmax,
                                           config.rwindow, config.enhance_window)
    np.testing.assert_array_equal(got.reference.numpy(), want_ref)
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    np.testing.assert_allclose(got.score.numpy(), want_uniq, rtol=tol, atol=tol)
    assert (got.reference[:config.sequence_length] == -1).all()


def test_streaming_start_equals_batch_start():
    """Column-min subtraction shifts all trajectories equally: same best start as batch."""
    rng = np.random.default_rng(21)
    ref, query = (torch.tensor(x) for x in route(rng, 50, 45, 1.0))
    batch = SeqSLAM().match_descriptors(ref, query)
    stream = StreamingSeqSLAM(ref, descriptors=True)
    for t, q in enumerate(query):
        out = stream.step(q)
        if t < 10:
            assert out.reference == -1 and np.isnan(out.score)
            continue
        centre = t - 5
        assert out.start + 5 == batch.matches.reference[centre]
        assert out.reference == min(out.start + int(np.floor(10 * out.velocity + 1e-9)), 49)


def test_streaming_frames_on_demo_and_errors():
    demo = make_demo(n_reference=80)
    stream = StreamingSeqSLAM(demo.reference)
    matches = stream.run(demo.query)
    metrics = evaluate(matches, demo.ground_truth)
    print("demo streaming", metrics)
    assert metrics["recall_at_1"] >= 0.8  # measured 0.89 with 80 reference frames
    with pytest.raises(ValueError):
        stream.step(torch.full((96, 128), float("nan")))
    with pytest.raises(ValueError):
        StreamingSeqSLAM(torch.zeros(1, 8), descriptors=True)
    with pytest.raises(ValueError):
        StreamingSeqSLAM(torch.zeros(4, 8), descriptors=True).step(torch.zeros(9))

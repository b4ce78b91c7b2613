"""StreamingSeqSLAM against an independent loop computation of the trailing-window rule.

Candidate-mode streaming is tested in test_seqslam_candidates.py (it needs FAISS)."""

import math

import numpy as np
import pytest
import torch
from conftest import DEVICES
from routes import route
from seqslam_oracle import oracle_difference, oracle_streaming

from torchseq.demo import make_demo
from torchseq.metrics import evaluate
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig, StreamingSeqSLAM


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
    state = None
    for t, q in enumerate(query):
        out, state = stream.step(q[None], state)
        assert out.reference.shape == (1,)
        if t < 10:
            assert int(out.reference[0]) == -1 and math.isnan(float(out.score[0]))
            continue
        centre = t - 5
        start, velocity = int(out.start[0]), float(out.velocity[0])
        assert start + 5 == batch.matches.reference[centre]
        assert int(out.reference[0]) == min(start + int(np.floor(10 * velocity + 1e-9)), 49)


def test_streams_in_a_batch_are_independent():
    """B streams stepped together give each stream's own decisions (and state)."""
    rng = np.random.default_rng(22)
    ref, _ = route(rng, 50, 1, 1.0)
    queries = [torch.tensor(route(np.random.default_rng(30 + i), 50, 30, speed)[1])
               for i, speed in enumerate((0.8, 1.0, 1.2))]
    stream = StreamingSeqSLAM(torch.tensor(ref), descriptors=True)
    alone = [stream.run(q) for q in queries]
    state, got = None, []
    for t in range(30):
        out, state = stream.step(torch.stack([q[t] for q in queries]), state)
        assert state.columns.shape == (3, min(t + 1, 11), 50)
        got.append(out)
    for i in range(3):
        np.testing.assert_array_equal(torch.stack([o.reference[i] for o in got]),
                                      alone[i].reference)
        np.testing.assert_allclose(torch.stack([o.score[i] for o in got]), alone[i].score)


def test_streaming_frames_on_demo_and_errors():
    demo = make_demo(n_reference=80)
    stream = StreamingSeqSLAM(demo.reference)
    matches = stream.run(demo.query)
    metrics = evaluate(matches, demo.ground_truth)
    print("demo streaming", metrics)
    assert metrics["recall_at_1"] >= 0.8  # measured 0.89 with 80 reference frames
    out, state = stream.step(demo.query[:2])  # two streams of RGB-free grey frames
    assert out.reference.tolist() == [-1, -1] and state.descriptors.shape[:2] == (2, 1)
    with pytest.raises(ValueError, match="NaN"):
        stream.step(torch.full((1, 96, 128), float("nan")))
    with pytest.raises(ValueError, match=r"looks like one frame.*frame\[None\]"):
        stream.step(demo.query[0])  # the former (H, W) call
    with pytest.raises(ValueError, match="looks like one frame"):
        stream.step(torch.zeros(96, 128, 3))
    with pytest.raises(ValueError, match="state must come from this engine"):
        stream.step(demo.query[:3], state)  # a state of 2 streams
    with pytest.raises(ValueError):
        StreamingSeqSLAM(torch.zeros(1, 8), descriptors=True)
    with pytest.raises(ValueError, match="one descriptor"):
        StreamingSeqSLAM(torch.zeros(4, 8), descriptors=True).step(torch.zeros(8))
    with pytest.raises(ValueError, match="query descriptors"):
        StreamingSeqSLAM(torch.zeros(4, 8), descriptors=True).step(torch.zeros(1, 9))

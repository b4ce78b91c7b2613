"""The compiled online step (``kernels={"step": "numba"}``, ``torchseq/neural/_step_numba.py``)
gives the stage kernels' numbers bit for bit: decisions, confidences and the new state, on the
real corridor route, on random frames and states, batched; its two helpers against NumPy's own
pairwise sum and partition. The stage kernels themselves are checked against the eager layers
(the definition) in ``tests/test_neural_step_paths.py``; which kernel ran is checked in
``tests/test_neural_dispatch.py``.
"""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchseq.layers import RingState
from torchseq.neural import NeuralConfig, NeuralError, NeuralSeqSLAM
from torchseq.neural import _step_numba as S
from torchseq.preprocess import resize

ROUTE = dict(n_reference=40, seed=11)  # the conftest ``route`` fixture's demo


_MODELS = {}


def small_model(route, **overrides):
    key = tuple(sorted(overrides.items()))
    if key not in _MODELS:
        model = NeuralSeqSLAM(NeuralConfig(hidden=512, n_output=40, **overrides))
        model.fit(route.reference, log=False)
        _MODELS[key] = model
    return _MODELS[key]


def same_bits(a: torch.Tensor, b: torch.Tensor) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.numpy().tobytes() == b.numpy().tobytes()


def stream_both(model, frames, batch=1):
    """Stream ``frames`` through the compiled step and the stages; compare every output."""
    fast, slow = model.inference({"step": "numba"}), model.inference({"step": "stages"})
    s_fast = s_slow = None
    refs = []
    with torch.inference_mode():
        for t in range(0, frames.shape[0] - batch + 1, batch):
            o1, s_fast = fast.step(frames[t:t + batch], s_fast)
            o2, s_slow = slow.step(frames[t:t + batch], s_slow)
            assert torch.equal(o1.reference, o2.reference), t
            assert same_bits(o1.confidence, o2.confidence), t
            assert same_bits(o1.activity, o2.activity) and same_bits(s_fast.activity,
                                                                     s_slow.activity), t
            refs.append(o1.reference)
    return torch.cat(refs)


def test_corridor_stream_bit_for_bit(corridor):
    """Default config fitted on the real corridor reference; its query streamed frame by frame."""
    model = NeuralSeqSLAM(NeuralConfig())
    model.fit(corridor.ref, log=False)
    assert model.inference().kernels["step"] == "stages_or_numba"
    query = resize(corridor.query, model.config.input_size)  # the stream as the step meets it
    refs = stream_both(model, query)
    assert refs.unique().numel() > 10  # the decisions move along the route
    stream_both(model, corridor.query[:12], batch=3)  # raw frames, batched: resized by the check


@pytest.mark.parametrize("rectify", [True, False])
def test_demo_stream_bit_for_bit(route, rectify):
    stream_both(small_model(route, rectify=rectify), route.query)


@settings(max_examples=40)
@given(seed=st.integers(0, 2**31 - 1), batch=st.integers(1, 4), flat=st.integers(0, 6))
def test_random_frames_and_states_bit_for_bit(route, seed, batch, flat):
    """Random frames (some blocks flat: std 0), random states, several streams at once."""
    model = small_model(route)
    if "pair" not in _MODELS:
        _MODELS["pair"] = model.inference({"step": "numba"}), model.inference({"step": "stages"})
    fast, slow = _MODELS["pair"]
    gen = torch.Generator().manual_seed(seed)
    h, w = model.config.input_size
    frames = torch.rand(batch, h, w, generator=gen) * 10 ** float(torch.randint(-2, 3, (1,),
                                                                                 generator=gen))
    p = model.config.patch_size
    for _ in range(flat):  # a constant block: z = 0 there
        r, c = (int(torch.randint(0, n // p, (1,), generator=gen)) * p for n in (h, w))
        frames[:, r:r + p, c:c + p] = float(torch.rand(1, generator=gen))
    state = RingState(torch.randn(batch, model.n_units, generator=gen).abs())
    with torch.inference_mode():
        o1, s1 = fast.step(frames, state)
        o2, s2 = slow.step(frames, state)
    assert torch.equal(o1.reference, o2.reference)
    assert same_bits(o1.confidence, o2.confidence) and same_bits(s1.activity, s2.activity)


def test_refuses_non_finite_frames_like_the_stages(route):
    model = small_model(route)
    fast = model.inference({"step": "numba"})
    frames = resize(route.query[:2], model.config.input_size).clone()
    frames[1, 3, 5] = float("nan")
    for bad in (frames, route.query[:2].clone().fill_(float("inf"))):
        with pytest.raises(NeuralError, match="frames hold NaN or infinite values"):
            fast.step(bad)
    huge = torch.full_like(frames, 3e38)  # finite, though the sums overflow: accepted
    out, _ = fast.step(huge)
    assert out.reference.shape == (2,)


def test_requirements_and_state_dtype(route):
    # several cohorts; an input grid of tenths (the float32 L1 product is not exact there)
    for other in (small_model(route, n_cohorts=2), small_model(route, input_steps=10)):
        assert other.inference().kernels["step"] == "stages"
        with pytest.raises(NeuralError, match="power of two.*one cohort"):
            other.inference({"step": "numba"})
    model = small_model(route)
    assert model.inference({"ring": "dense"}).kernels["step"] == "stages"  # a stage asked
    frames = route.query[:2]
    state = RingState(torch.zeros(2, model.n_units, dtype=torch.float64))
    with pytest.raises(NeuralError, match="float32 states"):
        model.inference({"step": "numba"}).step(frames, state)
    out, new = model.inference().step(frames, state)  # stages_or_numba: the stages take it
    assert new.activity.dtype == torch.float64


@given(n=st.integers(1, 700), scale=st.integers(-3, 3), seed=st.integers(0, 2**31 - 1))
def test_pairwise_sum_is_numpys(n, scale, seed):
    rng = np.random.default_rng(seed)
    a = (rng.standard_normal(n) * 10.0 ** rng.uniform(-3, 3, n) * 10.0 ** scale).astype(np.float32)
    want = np.add.reduce(a[None], axis=1)[0]  # as cohort_normalise_numpy reduces a row
    assert np.float32(S.pairwise_sum(a, 0, n)).tobytes() == want.tobytes()


@given(values=st.lists(st.integers(-2**31, 2**31 - 1) | st.integers(-3, 3), min_size=1,
                       max_size=300), data=st.data())
def test_kth_largest_is_partitions(values, data):
    a = np.array(values, np.int32)
    k = data.draw(st.integers(1, a.size))
    want = np.partition(a, a.size - k)[a.size - k]
    assert S.kth_largest(a, k, np.empty(256, np.int64)) == want


def test_ties_at_the_maximum_go_to_the_first_unit(route):
    """A huge uniform state: the evidence vanishes in its rounding, many units tie at the top."""
    model = small_model(route)
    state = RingState(torch.full((1, model.n_units), 1e30))
    with torch.inference_mode():
        out, new = model.inference({"step": "numba"}).step(route.query[:1], state)
        want, _ = model.inference({"step": "stages"}).step(route.query[:1], state)
    top = new.activity[0] == new.activity[0].max()
    assert int(top.sum()) > 1  # the case this test is for
    assert torch.equal(out.reference, want.reference)
    assert int(out.reference) == int(model.unit_centre[int(top.nonzero()[0])])


def test_without_numba_auto_runs_the_stages_quietly(route, monkeypatch, recwarn):
    """numba absent: auto falls back to the stage kernels with no warning; asking fails."""
    from torchseq.neural import inference as I

    monkeypatch.setattr(I, "numba_available", lambda: False)
    model = small_model(route)
    inf = model.inference()
    assert inf.kernels["step"] == "stages"
    with torch.inference_mode():
        out, _ = inf.step(route.query[:1])
    assert out.reference.shape == (1,) and len(recwarn) == 0
    with pytest.raises(NeuralError, match="needs numba"):
        model.inference({"step": "numba"})



@pytest.mark.parametrize("blocks", [0, 1])
def test_kwta_ties_go_to_the_lowest_index_like_the_stages(route, blocks):
    """Exact ties across the k-th place of the k-WTA, built with no shared data: a flat frame
    gives every L1 sum 0 (all hidden units tie, the first ``k`` win); a frame with one
    textured block gives 0 to the units that do not see it, tied across the k-th place."""
    from torchseq.preprocess import zscore_pixel_major

    model = small_model(route)
    h, w = model.config.input_size
    p = model.config.patch_size
    gen = torch.Generator().manual_seed(blocks)
    frame = torch.full((1, h, w), 0.5)
    for i in range(blocks):
        r, c = (i * 2 % (h // p)) * p, (i * 3 % (w // p)) * p
        frame[0, r:r + p, c:c + p] = torch.rand(p, p, generator=gen)
    fast, slow = model.inference({"step": "numba"}), model.inference({"step": "stages"})
    z = zscore_pixel_major(frame, p, "numpy").permute(1, 2, 0).reshape(-1).numpy()
    x = np.rint(z * np.float32(model.config.input_steps)).astype(np.int32)
    sums = fast.w1_i8.astype(np.int32) @ x  # the compiled step's integer L1 sums
    kth = np.sort(sums)[::-1][fast._k - 1]
    assert (sums > kth).sum() < fast._k < (sums >= kth).sum()  # the case this test is for
    state = RingState(torch.rand(1, model.n_units, generator=gen))
    with torch.inference_mode():
        o1, s1 = fast.step(frame, state)
        o2, s2 = slow.step(frame, state)
    assert torch.equal(o1.reference, o2.reference)
    assert same_bits(o1.confidence, o2.confidence) and same_bits(s1.activity, s2.activity)

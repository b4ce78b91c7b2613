"""Every path of the step gives the eager layers' numbers: the model's ``step`` (whatever ran
before it) and its inference module's ``step``, under ``torch.inference_mode()``, batched, and
``run`` frame by frame.

The reference here composes the ``torchseq.layers`` modules of the model by hand (the
definition in docs/guide/neural.md, "Step maths"), so no fast kernel is involved in it.
"""

import pytest
import torch

from torchseq.layers import cohort_normalise
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.neural.readout import decide

ROUTE = dict(n_reference=40, seed=6)  # the conftest ``route`` fixture's demo


def eager_step(model, frames, activity):
    """One step through the model's own layer modules, in float64 after the products."""
    with torch.no_grad():
        code = model.l2(model.l1(model.encode(frames)))
        e = cohort_normalise(model.l3(code), model.cohorts, model.config.eps)
        if model.config.rectify:
            e = e.clamp_min(0.0)
        a = model.ring.params.decay * activity @ model.ring.shift.T + model.ring.params.gain * e
    ref, conf = decide(a, model.unit_centre, model.config.uniqueness_window)
    return ref, conf, a


_MODELS = {}


def fitted(route, rectify, n_cohorts):
    key = (rectify, n_cohorts)
    if key not in _MODELS:
        model = NeuralSeqSLAM(NeuralConfig(hidden=512, n_output=40, rectify=rectify,
                                           n_cohorts=n_cohorts))
        model.fit(route.reference, log=False)
        _MODELS[key] = model
    return _MODELS[key]


def streams(route, t, batch=3):
    """Independent streams: the query, the reference backwards, then shifted queries."""
    q, r = route.query, route.reference
    frames = [q[t % len(q)], r[len(r) - 1 - t]] + [q[(t + 7 * i) % len(q)]
                                                   for i in range(1, batch - 1)]
    return torch.stack(frames[:batch])


# every (prepared, batch) with both cohort counts, and every pair of any two settings, in the
# quick run (rectify alternates); the other half of the 16 combinations in CI's slow pass
@pytest.mark.parametrize("prepared,batch,n_cohorts,rectify", [
    pytest.param(prepared, batch, n_cohorts, rectify,
                 id=f"{prepared}-{batch}-{n_cohorts}-{rectify}",
                 marks=() if rectify == ((i + (n_cohorts == 4)) % 2 == 0) else pytest.mark.slow)
    for i, (prepared, batch) in enumerate([(False, 3), (True, 1), (True, 3), (True, 20)])
    for n_cohorts in (1, 4) for rectify in (True, False)])
def test_step_after_run_under_inference_mode_equals_eager(route, rectify, n_cohorts, prepared,
                                                          batch):
    model = fitted(route, rectify, n_cohorts)
    model.run(route.query[:5])  # whatever run leaves behind must not change step's numbers
    # prepared: the inference module with its auto kernels runs the step
    stepper = model.inference() if prepared else model
    state, a_ref = None, torch.zeros(batch, model.n_units)
    for t in range(12):
        frames = streams(route, t, batch)
        with torch.inference_mode():
            out, state = stepper.step(frames, state)
        ref, conf, a_ref = eager_step(model, frames, a_ref)
        torch.testing.assert_close(out.activity, a_ref, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(out.confidence, conf, atol=1e-5, rtol=1e-5)
        assert torch.equal(out.reference, ref)
        assert float(out.activity.abs().max()) > 0  # the evidence reached the ring


@pytest.mark.parametrize("rectify", [True, False])
@pytest.mark.parametrize("n_cohorts", [1, 4])
def test_step_with_gradients_on_equals_eager(route, rectify, n_cohorts):
    model = fitted(route, rectify, n_cohorts)
    state, a_ref = None, torch.zeros(3, model.n_units)
    for t in range(6):
        frames = streams(route, t)
        out, state = model.step(frames, state)
        ref, _, a_ref = eager_step(model, frames, a_ref)
        torch.testing.assert_close(out.activity, a_ref, atol=1e-5, rtol=1e-5)
        assert torch.equal(out.reference, ref)


@pytest.mark.parametrize("n_cohorts", [1, 4])
def test_run_equals_step_frame_by_frame(route, n_cohorts):
    """run (inference module, blocked ring scan) against the eager step, frame by frame."""
    model = fitted(route, True, n_cohorts)
    q = route.query
    res = model.run(q)
    a_ref, refs = torch.zeros(1, model.n_units), []
    for t in range(len(q)):
        ref, _, a_ref = eager_step(model, q[t:t + 1], a_ref)
        refs.append(int(ref[0]))
        torch.testing.assert_close(res.activity[t], a_ref[0], atol=1e-5, rtol=1e-5)
    assert res.matches.reference.tolist() == refs


def test_prepared_step_checks_frames_at_the_input_size(route):
    from torchseq.neural import NeuralError

    inf = fitted(route, True, 1).inference()
    frame = torch.rand(1, *inf.config.input_size) * 255  # the online fast path
    for bad in (float("nan"), float("inf")):
        broken = frame.clone()
        broken[0, 3, 4] = bad
        with pytest.raises(NeuralError, match="NaN"):
            inf.step(broken)
    big = torch.full((1, *inf.config.input_size), 2.0**120)  # finite; the sum overflows
    out, _ = inf.step(big)
    assert out.reference.shape == (1,)


def test_the_model_holds_no_mode(route):
    """Building an inference module changes nothing: ``step`` is the layers whatever ran."""
    model = fitted(route, True, 1)
    frames = streams(route, 3)
    want, _ = model.step(frames)
    inf = model.inference()
    assert not any(isinstance(m, type(inf)) for m in model.modules())  # nothing kept inside
    assert not [k for k in model.state_dict() if "inference" in k]
    ran = []
    original = type(inf).step
    type(inf).step = lambda self, *a, **k: ran.append(1) or original(self, *a, **k)
    try:
        got, _ = model.step(frames)
    finally:
        type(inf).step = original
    assert ran == []  # the layers ran, not an inference module
    assert torch.equal(got.activity, want.activity)

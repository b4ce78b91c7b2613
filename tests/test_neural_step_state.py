"""``NeuralSeqSLAM.step``'s state argument: each ring takes its own state type, a fixed ring
also a VelocityState (its activity), and any other type is a NeuralError naming both."""

import pytest
import torch

from torchseq.demo import make_demo
from torchseq.layers import RingState
from torchseq.neural import NeuralConfig, NeuralError, NeuralSeqSLAM
from torchseq.neural.velocity import VelocityState


@pytest.fixture(scope="module")
def models():
    d = make_demo(n_reference=40, size=(48, 64), speed=0.8, seed=2)
    out = {}
    for name, cfg in (("fixed", NeuralConfig(hidden=256, n_output=40)),
                      ("adaptive", NeuralConfig.adaptive_velocity(hidden=256, n_output=40))):
        model = NeuralSeqSLAM(cfg)
        model.fit(d.reference, log=False)
        out[name] = model
    return out, d.query[:6]


def steppers(m, fast):
    """The models' layers, or their inference modules (both check the same way)."""
    return {name: model.inference() if fast else model for name, model in m.items()}


@pytest.mark.parametrize("fast", [False, True])
def test_a_fixed_ring_reads_a_velocity_states_activity(models, fast):
    (m, query) = models
    fixed, adaptive = steppers(m, fast).values()
    _, vstate = adaptive.step(query[:2])  # a real VelocityState, (2, 40) activity
    assert isinstance(vstate, VelocityState)
    want_step, want_state = fixed.step(query[2:4], RingState(vstate.activity))
    got_step, got_state = fixed.step(query[2:4], vstate)
    assert type(got_state) is RingState
    assert torch.equal(got_state.activity, want_state.activity)
    assert torch.equal(got_step.activity, want_step.activity)
    assert torch.equal(got_step.reference, want_step.reference)
    # the activity it read mattered: from no state the result differs
    cold, _ = fixed.step(query[2:4])
    assert not torch.equal(cold.activity, got_step.activity)


@pytest.mark.parametrize("fast", [False, True])
def test_an_adaptive_ring_refuses_a_ring_state_naming_both(models, fast):
    (m, query) = models
    m = steppers(m, fast)
    _, state = m["fixed"].step(query[:1])
    with pytest.raises(NeuralError) as err:
        m["adaptive"].step(query[1:2], state)
    assert "VelocityState" in str(err.value) and "RingState" in str(err.value)


@pytest.mark.parametrize("state", [torch.zeros(1, 40), (torch.zeros(1, 40),),
                                   RingState([[0.0] * 40])])
@pytest.mark.parametrize("fast", [False, True])
def test_a_fixed_ring_refuses_other_types_naming_both(models, state, fast):
    (m, query) = models
    m = steppers(m, fast)
    with pytest.raises(NeuralError) as err:
        m["fixed"].step(query[:1], state)
    text = str(err.value)
    assert "RingState" in text and type(state).__name__ in text


@pytest.mark.parametrize("fast", [False, True])
def test_a_velocity_state_of_the_wrong_batch_is_refused(models, fast):
    (m, query) = models
    m = steppers(m, fast)
    _, vstate = m["adaptive"].step(query[:2])
    with pytest.raises(NeuralError, match=r"state must be \(3, 40\), got \(2, 40\)"):
        m["fixed"].step(query[:3], vstate)

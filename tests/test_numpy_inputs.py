"""NeuralSeqSLAM.fit / run and SeqSLAM.match take NumPy arrays as they take tensors."""

import numpy as np
import pytest
import torch

from torchseq.demo import make_demo
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig


@pytest.fixture(scope="module")
def demo():
    return make_demo(n_reference=40)


def test_neural_fit_and_run_take_numpy(demo):
    cfg = NeuralConfig(hidden=256, n_output=40)
    from_tensor, from_numpy = NeuralSeqSLAM(cfg), NeuralSeqSLAM(cfg)
    from_tensor.fit(demo.reference, log=False)
    ref = demo.reference.numpy()
    from_numpy.fit(ref[::-1][::-1], log=False)  # a view with strides torch cannot wrap as is
    for key, value in from_tensor.state_dict().items():
        assert torch.equal(value, from_numpy.state_dict()[key]), key
    a = from_tensor.run(demo.query)
    b = from_numpy.run(demo.query.numpy())
    assert torch.equal(a.matches.reference, b.matches.reference)
    assert torch.equal(a.activity, b.activity)


def test_seqslam_match_takes_numpy(demo):
    engine = SeqSLAM(SeqSLAMConfig(ds=6))
    a = engine.match(demo.reference, demo.query)
    query = demo.query.numpy().copy()
    query.flags.writeable = False  # read-only memory is copied, not wrapped with a warning
    b = engine.match(demo.reference.numpy(), query)
    assert torch.equal(a.matches.reference, b.matches.reference)
    torch.testing.assert_close(a.matches.score, b.matches.score, rtol=0, atol=0, equal_nan=True)


@pytest.mark.parametrize("bad", ["frames.npy", np.array(["a", "b"], dtype=object)])
def test_other_inputs_are_one_clear_type_error(demo, bad):
    with pytest.raises(TypeError, match="query must"):
        SeqSLAM().match(demo.reference, bad)
    model = NeuralSeqSLAM(NeuralConfig(hidden=256, n_output=40))
    with pytest.raises(TypeError, match="reference must"):
        model.fit(bad)

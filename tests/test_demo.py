import numpy as np
import pytest
import torch

from torchseq.demo import make_demo


def test_demo_is_deterministic_and_shaped():
    a, b = make_demo(n_reference=40, seed=3), make_demo(n_reference=40, seed=3)
    assert torch.equal(a.reference, b.reference) and torch.equal(a.query, b.query)
    assert a.reference.shape == (40, 96, 128)
    assert a.query.shape[0] == 49  # floor(39 / 0.8) + 1
    assert not torch.equal(make_demo(n_reference=40, seed=4).reference, a.reference)
    assert a.reference.min() >= 0 and a.reference.max() <= 255


def test_demo_ground_truth_is_exact():
    d = make_demo(n_reference=50, speed=0.5, tolerance=1.0)
    # query j sits at reference position 0.5 j: admissible references within 1 frame
    for j in (0, 7, 20):
        expected = [i for i in range(50) if abs(i - 0.5 * j) <= 1.0]
        assert d.ground_truth[:, j].nonzero()[0].tolist() == expected
    # a query frame at an integer position equals that reference frame up to lighting and noise
    q, r = d.query[20], d.reference[10]
    corr = np.corrcoef(q.flatten().numpy(), r.flatten().numpy())[0, 1]
    assert corr > 0.8
    assert np.corrcoef(q.flatten().numpy(), d.reference[30].flatten().numpy())[0, 1] < corr


def test_demo_rejects_nonsense():
    with pytest.raises(ValueError):
        make_demo(n_reference=1)
    with pytest.raises(ValueError):
        make_demo(speed=0)

import pytest
import torch

from torchseq.demo import make_demo


def test_demo_repeat_makes_identical_stretches():
    plain = make_demo(n_reference=80, size=(24, 32), step=4.0, seed=1)
    assert torch.equal(plain.reference, make_demo(n_reference=80, size=(24, 32), step=4.0,
                                                  seed=1, repeat=1).reference)
    rep = make_demo(n_reference=80, size=(24, 32), step=4.0, seed=1, repeat=2)
    # the middle half (frames 20..60) holds two copies of a 20-frame stretch
    same = (rep.reference[25] - rep.reference[45]).abs().mean()
    neighbour = (rep.reference[25] - rep.reference[27]).abs().mean()
    assert same < 4.0 < neighbour  # copies differ only by the reference's sensor noise (2.0)
    assert torch.equal(rep.reference[:12], plain.reference[:12])  # views before the copies
    with pytest.raises(ValueError, match="repeat"):
        make_demo(repeat=0)


def test_demo_without_dense_ground_truth_is_the_same_route():
    dense = make_demo(n_reference=40, size=(24, 32), step=4.0, repeat=2)
    light = make_demo(n_reference=40, size=(24, 32), step=4.0, repeat=2,
                      dense_ground_truth=False)
    assert light.ground_truth is None
    assert torch.equal(dense.reference, light.reference)
    assert torch.equal(dense.query, light.query)
    # the positions give the same ground truth
    want = abs(light.reference_position[:, None] - light.query_position[None, :]) <= 2.0
    assert (dense.ground_truth == want).all()

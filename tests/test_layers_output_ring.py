import pytest
import torch
from conftest import DEVICES

from torchseq.layers import OutputRing, RingParams, RingState, learn_shift_matrix, ring_step

DTYPES = [torch.float32, torch.float64]


def test_shift_matrix_hand_made_order():
    # winners 0, 1, 1, 2 over 4 units; spread 2, spread_decay 0.5, stay 0.25.
    # lag 0 pairs (next, cur): (0,0) (1,1) (1,1) (2,2)               weight 0.25 each
    # lag 1 pairs: (1,0) (1,1) (2,1)                                weight 1
    # lag 2 pairs: (1,0) (2,1)                                      weight 0.5
    # raw rows: row0 = [0.25, 0, 0, 0]; row1 = [1.5, 1.5, 0, 0]; row2 = [0, 1.5, 0.25, 0]
    raw = torch.tensor([[0.25, 0, 0, 0], [1.5, 1.5, 0, 0], [0, 1.5, 0.25, 0], [0, 0, 0, 0]])
    got = learn_shift_matrix(torch.tensor([0, 1, 1, 2]), 4, spread=2, spread_decay=0.5,
                             stay=0.25, normalise=False)
    assert torch.equal(got, raw)
    expected = torch.tensor([[1.0, 0, 0, 0], [0.5, 0.5, 0, 0], [0, 1.5 / 1.75, 0.25 / 1.75, 0],
                             [0, 0, 0, 0]])
    got = learn_shift_matrix(torch.tensor([0, 1, 1, 2]), 4, spread=2, spread_decay=0.5, stay=0.25)
    torch.testing.assert_close(got, expected)


def test_shift_matrix_wrap():
    # loop 0 -> 1 -> 2 -> 0, spread 1, no stay: a cyclic permutation
    got = learn_shift_matrix(torch.tensor([0, 1, 2]), 3, spread=1, stay=0.0, wrap=True)
    assert torch.equal(got, torch.tensor([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]))
    open_route = learn_shift_matrix(torch.tensor([0, 1, 2]), 3, spread=1, stay=0.0)
    assert torch.equal(open_route, torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]))


def test_shift_matrix_errors():
    with pytest.raises(ValueError, match="non-empty"):
        learn_shift_matrix(torch.tensor([], dtype=torch.int64), 3)
    with pytest.raises(ValueError, match="lie in"):
        learn_shift_matrix(torch.tensor([0, 3]), 3)
    with pytest.raises(ValueError, match="spread"):
        learn_shift_matrix(torch.tensor([0, 1]), 3, spread=0)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_ring_step_reference_and_module(device, dtype):
    n = 6
    ring = OutputRing(n, decay=0.8, spread=1, stay=0.0, device=device, dtype=dtype)
    ring.learn(torch.arange(n))
    ev = torch.randn(5, 2, n, dtype=dtype, device=device)  # (T, B, N)
    state, ref = None, torch.zeros(2, n, dtype=dtype, device=device)
    for t in range(5):
        out, state = ring(ev[t], state)
        # independent reference: activity moves one unit along the route, old unit 0 empties
        moved = torch.zeros_like(ref)
        moved[:, 1:] = ref[:, :-1]
        ref = 0.8 * moved + 0.2 * ev[t]
        torch.testing.assert_close(out, ref)
        assert isinstance(state, RingState) and torch.equal(state.activity, out)
    assert ring.params == RingParams(0.8, 1.0 - 0.8)
    a, s = ring_step(ev[0], RingState(ref), ring.shift, ring.params)
    b, _ = ring(ev[0], RingState(ref))
    assert torch.equal(a, b) and torch.equal(s.activity, a)


def test_ring_errors():
    with pytest.raises(ValueError, match="decay"):
        OutputRing(4, decay=1.0)

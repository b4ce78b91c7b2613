"""The fast path's k-WTA tie check (one global count) against a per-row loop."""

import pytest
import torch

from torchseq.layers import kwta
from torchseq.layers.kernels import has_tie
from torchseq.layers.kernels import topk_indices as winners


def tie_loop(h: torch.Tensor, v: torch.Tensor, k: int) -> bool:
    """Independent reference: any row with a count of entries >= its threshold other than k."""
    for row, thr in zip(h.tolist(), v[:, 0].tolist()):
        if sum(1 for x in row if x >= thr) != k:
            return True
    return False


def rows(dtype: torch.dtype) -> torch.Tensor:
    h = torch.randn(6, 64, generator=torch.Generator().manual_seed(3), dtype=dtype)
    return h


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", ["none", "straddle", "all_equal", "signed_zero", "nan"])
@pytest.mark.parametrize("k", [1, 9, 64])
def test_has_tie_equals_per_row_loop(dtype, case, k):
    h = rows(dtype)
    if case == "straddle":
        h[4, :20] = h[4, 5]
    elif case == "all_equal":
        h[1] = 0.25
    elif case == "signed_zero":
        h[2, :32] = 0.0
        h[2, 32:] = -0.0
    elif case == "nan":
        h[3, 7] = float("nan")
    v = torch.topk(h, k, dim=1).values[:, -1:]
    assert has_tie(h, v, k) == tie_loop(h, v, k)


def test_has_tie_sees_a_tie_in_one_row_only():
    h = rows(torch.float32)
    h[5, :10] = 3.0  # 10 entries at the top of row 5: k = 4 ties there, nowhere else
    v = torch.topk(h, 4, dim=1).values[:, -1:]
    assert has_tie(h, v, 4) and tie_loop(h, v, 4)
    assert not has_tie(h[:5], v[:5], 4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_winners_match_kwta_code_and_topk_order_without_ties(dtype):
    h = rows(dtype)
    idx = winners(h, 9)
    assert torch.equal(idx, torch.topk(h, 9, dim=1, sorted=False).indices)  # same order
    h[0, :12] = h[0].max()
    idx = winners(h, 9)
    code = torch.zeros_like(h).scatter_(1, idx, 1.0)
    assert torch.equal(code, kwta(h, 9, binary=True))


@pytest.mark.parametrize("case", ["plain", "ties", "negative", "zeros"])
@pytest.mark.parametrize("batch", [1, 4])
def test_partition_indices_equal_kwta(case, batch):
    """kwta_partition_indices (its one-row shortcut included) against the definition."""
    from torchseq.layers.kernels import kwta_partition_indices

    g = torch.Generator().manual_seed(11)
    h = torch.randn(batch, 500, generator=g)
    if case == "ties":
        h = torch.randint(-4, 5, (batch, 500), generator=g).float()
    elif case == "negative":
        h = -h.abs() - 1.0  # the threshold is negative: the float bits do not sort
    elif case == "zeros":
        h[0] = 0.0
    idx = kwta_partition_indices(h, 37)
    want = kwta(h, 37, binary=True).nonzero()[:, 1].reshape(batch, 37)
    assert torch.equal(idx, want)

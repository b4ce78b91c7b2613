import numpy as np
import pytest
import torch
from conftest import DEVICES

from torchseq.layers import KWinnersTakeAll, kwta
from torchseq.layers.kernels import kwta_numpy

DTYPES = [torch.float32, torch.float64]


def loop_kwta(x, k, binary):
    """Independent reference: for each row, pick k winners by (value desc, index asc)."""
    out = torch.zeros_like(x)
    flat_in, flat_out = x.reshape(-1, x.shape[-1]), out.reshape(-1, x.shape[-1])
    for r in range(flat_in.shape[0]):
        row = flat_in[r].tolist()
        order = sorted(range(len(row)), key=lambda i: (-row[i], i))
        for i in order[:k]:
            flat_out[r, i] = 1.0 if binary else row[i]
    return out


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("k", [1, 3, 17, 40])
def test_matches_loop_reference(device, dtype, binary, k):
    g = torch.Generator().manual_seed(k)
    x = torch.randn(2, 5, 40, generator=g, dtype=dtype).to(device)
    x[0, 0, :10] = 0.5  # ties at the threshold too
    y = kwta(x, k, binary=binary)
    assert y.shape == x.shape and y.dtype == dtype
    assert torch.equal(y.cpu(), loop_kwta(x.cpu(), k, binary))
    assert ((y != 0).sum(-1) == k).all()


@pytest.mark.parametrize("binary", [False, True])
def test_all_equal_lowest_index_wins(binary):
    x = torch.full((3, 1000), 2.0)
    y = kwta(x, 50, binary=binary)
    expected = torch.zeros(3, 1000)
    expected[:, :50] = 1.0 if binary else 2.0
    assert torch.equal(y, expected)
    z = torch.zeros(1, 8)  # all-zero input: exactly k winners in binary mode
    assert torch.equal(kwta(z, 3, binary=True), torch.tensor([[1.0, 1, 1, 0, 0, 0, 0, 0]]))


def test_partial_ties_keep_lowest_indices():
    x = torch.tensor([[1.0, 3.0, 2.0, 3.0, 2.0, 2.0, 0.0]])
    assert torch.equal(kwta(x, 4, binary=True), torch.tensor([[0.0, 1, 1, 1, 1, 0, 0]]))


def test_gradients():
    x = torch.tensor([[0.1, 0.9, 0.5, 0.3]], requires_grad=True)
    kwta(x, 2).sum().backward()
    assert torch.equal(x.grad, torch.tensor([[0.0, 1.0, 1.0, 0.0]]))
    x.grad = None
    kwta(x, 2, binary=True, straight_through=True).mul(torch.arange(4.0)).sum().backward()
    assert torch.equal(x.grad, torch.arange(4.0)[None])
    x.grad = None
    y = kwta(x, 2, straight_through=True)
    assert torch.equal(y.detach(), torch.tensor([[0.0, 0.9, 0.5, 0.0]]))
    y.sum().backward()
    assert torch.equal(x.grad, torch.ones(1, 4))
    assert not kwta(x.detach(), 2, binary=True).requires_grad


@pytest.mark.parametrize("dtype", DTYPES)
def test_module_equals_function(dtype):
    x = torch.randn(6, 100, dtype=dtype)
    assert torch.equal(KWinnersTakeAll(k=7)(x), kwta(x, 7))
    assert torch.equal(KWinnersTakeAll(fraction=0.05, binary=True)(x), kwta(x, 5, binary=True))
    assert KWinnersTakeAll(fraction=0.001).winners(100) == 1


def test_errors():
    with pytest.raises(ValueError, match="exactly one"):
        KWinnersTakeAll()
    with pytest.raises(ValueError, match="exactly one"):
        KWinnersTakeAll(k=2, fraction=0.1)
    with pytest.raises(ValueError, match="fraction"):
        KWinnersTakeAll(fraction=0.0)
    with pytest.raises(ValueError, match="k must be"):
        kwta(torch.zeros(2, 3), 4)
    with pytest.raises(ValueError, match="k must be"):
        KWinnersTakeAll(k=5)(torch.zeros(2, 3))


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64, np.int32, np.int64])
@pytest.mark.parametrize("offset", [-10.0, 0.0, 10.0])
def test_kwta_numpy_matches_loop_reference(dtype, offset):
    """Thresholds above, at and below zero (float rows are selected on their bits)."""
    rng = np.random.default_rng(int(offset) + 20)
    x = (rng.normal(size=(12, 64)) * 4 + offset).round().astype(dtype)  # many ties
    x[0] = 0  # all tied at +0.0
    if x.dtype.kind == "f":
        x[1, ::2] = -0.0  # -0.0 == +0.0 must tie, whatever its bits
        x[1, 1::2] = 0.0
        x[2, :40] = np.linspace(-1.0, -0.01, 40)
    for k in (1, 9, 40):
        want = loop_kwta(torch.from_numpy(x.astype(np.float64)), k, binary=True)
        assert np.array_equal(kwta_numpy(x, k), want.numpy().astype(bool))

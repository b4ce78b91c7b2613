import pytest
import torch

from torchseq.layers import kwta, learn_shift_matrix
from torchseq.layers.kernels import topk_indices as winners
from torchseq.layers.ring import band_diagonals, ring_scan


def test_winners_equal_kwta_with_and_without_ties():
    h = torch.randn(4, 300, generator=torch.Generator().manual_seed(0))
    h[1, :40] = h[1, 7]  # a tie straddling the threshold in one row
    h[2] = 0.0  # all tied
    for x in (h, h[[0, 3]]):
        idx = winners(x, 15)
        dense = torch.zeros_like(x).scatter_(1, idx, 1.0)
        assert idx.shape == (x.shape[0], 15)
        assert torch.equal(dense, kwta(x, 15, binary=True))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ring_scan_band_equals_dense_and_loop(dtype):
    winners_seq = torch.arange(40).repeat_interleave(2)[:75]
    shift = learn_shift_matrix(winners_seq, 40, spread=2, stay=0.5).to(dtype)
    diag = band_diagonals(shift, 2)
    assert diag is not None and diag.shape == (3, 40)
    drive = torch.randn(25, 40, dtype=dtype)
    a0 = torch.randn(40, dtype=dtype)
    band = ring_scan(drive, a0, shift, 0.9, diag)
    dense = ring_scan(drive, a0, shift, 0.9, None)
    a, loop = a0.clone(), []
    for t in range(25):  # independent reference
        a = torch.tensor([0.9 * sum(float(shift[i, j]) * float(a[j]) for j in range(40))
                          + float(drive[t, i]) for i in range(40)], dtype=dtype)
        loop.append(a)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(band, torch.stack(loop), atol=tol, rtol=tol)
    torch.testing.assert_close(dense, torch.stack(loop), atol=tol, rtol=tol)


def test_band_diagonals_rejects_wrap():
    shift = learn_shift_matrix(torch.arange(10), 10, spread=2, wrap=True)
    assert band_diagonals(shift, 2) is None


@pytest.mark.parametrize("t_len", [1, 5, 16, 17, 100])
@pytest.mark.parametrize("block", [1, 4, 16])
@pytest.mark.parametrize("wrap", [False, True])
def test_ring_scan_blocks_equal_frame_by_frame(t_len, block, wrap):
    g = torch.Generator().manual_seed(t_len)
    shift = learn_shift_matrix(torch.arange(30), 30, spread=2, stay=0.5, wrap=wrap).double()
    diag = None if wrap else band_diagonals(shift, 2)
    drive = torch.rand(t_len, 30, generator=g, dtype=torch.float64)
    a0 = torch.rand(30, generator=g, dtype=torch.float64)
    got = ring_scan(drive, a0, shift, 0.95, diag, block=block)
    a, want = a0, []
    for t in range(t_len):  # the step's recurrence, one frame at a time
        a = 0.95 * (shift @ a) + drive[t]
        want.append(a)
    torch.testing.assert_close(got, torch.stack(want), atol=1e-12, rtol=1e-12)


@pytest.mark.parametrize("wrap", [False, True])
def test_ring_scan_tensor_path_equals_numpy_path(wrap):
    """The block steps run in NumPy on the CPU and as tensor operations elsewhere (CUDA, or
    inputs that need gradients); both give the frame-by-frame recurrence."""
    g = torch.Generator().manual_seed(7)
    shift = learn_shift_matrix(torch.arange(30), 30, spread=2, stay=0.5, wrap=wrap).double()
    diag = None if wrap else band_diagonals(shift, 2)
    drive = torch.rand(37, 30, generator=g, dtype=torch.float64)
    a0 = torch.rand(30, generator=g, dtype=torch.float64)
    via_numpy = ring_scan(drive, a0, shift, 0.95, diag, block=8)
    tracked = drive.clone().requires_grad_(True)
    via_tensors = ring_scan(tracked, a0, shift, 0.95, diag, block=8)
    torch.testing.assert_close(via_tensors.detach(), via_numpy, atol=1e-12, rtol=1e-12)
    via_tensors[-1].sum().backward()  # d a_T / d drive_t = (0.95 * shift)**(T - t), summed
    want = torch.ones(30, dtype=torch.float64)
    for t in range(36, -1, -1):
        torch.testing.assert_close(tracked.grad[t], want, atol=1e-10, rtol=1e-10)
        want = 0.95 * (shift.T @ want)

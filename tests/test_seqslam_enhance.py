"""Contrast enhancement's precision and tiling against the loop oracle (tests/seqslam_oracle.py).

The engine takes window sums from float64 cumulative sums per segment of rows; these tests
check that large common offsets, drifts, nearly flat windows and every tiling give the oracle's
two-pass result within the tolerances of the parity tests in test_seqslam_functions.py.
"""

import numpy as np
import pytest
import torch
from conftest import DEVICES
from seqslam_oracle import oracle_enhance

from torchseq.seqslam import enhance_contrast
from torchseq.seqslam.enhance import SEGMENT

DTYPES = [torch.float32, torch.float64]
TOL = {torch.float32: 2e-5, torch.float64: 1e-10}  # as test_enhance_contrast_matches_loop


def check(d: np.ndarray, dtype, device, window=10, **kwargs):
    x = torch.tensor(d, dtype=dtype, device=device)
    want = oracle_enhance(x.cpu().double().numpy(), window)  # the same (rounded) values
    got = enhance_contrast(x, window, **kwargs)
    assert got.shape == d.shape and got.dtype == dtype and got.device.type == device
    np.testing.assert_allclose(got.cpu().double().numpy(), want, rtol=TOL[dtype],
                               atol=TOL[dtype])
    return got


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_large_offset(dtype, device):
    rng = np.random.default_rng(5)
    d = 1e5 + rng.normal(0, 10, (700, 6))  # R > 2 segments, spread 1e-4 of the values
    got = check(d, dtype, device)
    assert float(got.max()) > 1.0  # real z-scores, not a collapsed matrix


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_drift_and_valley(dtype, device):
    """A steep trend (local mean far from the segment mean) and a deep narrow valley."""
    rng = np.random.default_rng(6)
    rows = np.arange(600)[:, None]
    d = 3e4 + 50.0 * rows + rng.normal(0, 2, (600, 5))
    d[300:306] -= 5e3
    check(d, dtype, device, window=7)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_nearly_flat_windows_are_exact(dtype, device):
    """Windows with a tiny spread next to a large one take the exact two-pass path."""
    rng = np.random.default_rng(7)
    d = rng.uniform(0, 1e4, (400, 4))
    d[100:130, 1] = 5000 + np.arange(30) % 3 / 1024  # spread 2e-3 among values up to 1e4
    d[200:220, 2] = 777.0  # exactly flat: z = 0 by definition
    check(d, dtype, device)
    raw = enhance_contrast(torch.tensor(d, dtype=dtype, device=device), subtract_min=False)
    assert bool((raw[205:215, 2] == 0).all())  # windows inside the flat run: exactly 0
    assert bool((raw[100:130, 1] != 0).any())  # the nearly flat run is not treated as flat


@pytest.mark.parametrize("budget", [1, 16 * 300, 16 * 5000, 2**26])
def test_every_tiling_gives_identical_results(budget):
    rng = np.random.default_rng(8)
    d = torch.tensor(rng.uniform(1000, 5000, (2 * SEGMENT + 89, 70)))  # partial last segment
    want = oracle_enhance(d.numpy(), 10)
    got = enhance_contrast(d, 10, max_chunk_elements=budget)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-10, atol=1e-10)
    np.testing.assert_array_equal(got.numpy(), enhance_contrast(d, 10).numpy())
    assert torch.equal(enhance_contrast(d.float(), 10, max_chunk_elements=budget),
                       enhance_contrast(d.float(), 10))


def test_single_column_and_short_reference():
    d = torch.tensor([[3.0], [1.0], [4.0]])
    got = enhance_contrast(d, 10, subtract_min=False)
    np.testing.assert_allclose(got.numpy(), oracle_enhance(d.numpy(), 10, False), atol=1e-6)
    with pytest.raises(ValueError, match="finite"):
        enhance_contrast(torch.tensor([[1.0, float("inf")], [2.0, 3.0]]))


def test_columns_of_very_different_scale_match_the_oracle():
    """A tile whose smallest window variance is below the tile-wide threshold though no window
    is suspect in its own column (a column of differences around 1e4 beside one around 1):
    the exact pass has nothing to do. It raised on an empty reduction (seen on nordland-b,
    summer + winter against winter + summer, exact mode at ds 20)."""
    g = torch.Generator().manual_seed(0)
    d = torch.empty(100, 2, dtype=torch.float64)
    d[:, 0] = torch.rand(100, generator=g, dtype=torch.float64) * 1e4
    d[:, 1] = torch.rand(100, generator=g, dtype=torch.float64)
    got = enhance_contrast(d, 10)
    np.testing.assert_allclose(got.numpy(), oracle_enhance(d.numpy(), 10), rtol=1e-9, atol=1e-9)

"""The one quantiser: round-trip properties (bounds, error, idempotence, sparsity, scales)."""

import numpy as np
import pytest
import torch
from conftest import DEVICES

from torchseq.export.quantise import (
    dequantise,
    fixed_point,
    fixed_point_array,
    quantise,
    round_half_away,
)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("bits", [4, 8, 12])
@pytest.mark.parametrize("per_row", [False, True])
@pytest.mark.parametrize("power_of_two", [False, True])
def test_round_trip_properties(dtype, device, bits, per_row, power_of_two):
    gen = torch.Generator().manual_seed(bits)
    w = (torch.randn(17, 33, generator=gen) * torch.rand(17, 1, generator=gen) * 3)
    w[:, ::3] = 0.0  # a sparse mask must survive
    w[5] = 0.0  # an all-zero row
    w = w.to(device=device, dtype=dtype)
    q = quantise(w, bits=bits, per_row=per_row, power_of_two=power_of_two)
    qmax = 2 ** (bits - 1) - 1
    ref = w.double().cpu().numpy()
    assert np.abs(q.values.astype(np.int64)).max() <= qmax
    assert q.scale.shape == ((17,) if per_row else ())
    back = dequantise(q)
    scale = q.scale[:, None] if per_row else q.scale
    assert np.all(np.abs(back - ref) <= scale / 2 + 1e-12)  # half a step at most
    assert np.array_equal(q.values[ref == 0], np.zeros(int((ref == 0).sum())))
    assert np.all(np.sign(q.values) * np.sign(ref) >= 0)  # never flips a sign
    again = quantise(back, bits=bits, per_row=per_row, power_of_two=power_of_two)
    assert np.array_equal(again.values, q.values) and np.allclose(again.scale, q.scale)
    if power_of_two:
        assert np.allclose(np.log2(q.scale), np.round(np.log2(q.scale)))
    else:  # the largest magnitude lands exactly on the top code
        peak = np.abs(q.values.reshape(17, -1)).max(1) if per_row else np.abs(q.values).max()
        assert np.all((peak == qmax) | (peak == 0))


def test_per_row_beats_per_tensor_on_uneven_rows():
    w = np.outer(np.array([1.0, 1e-3]), np.linspace(-1, 1, 50))
    err_row = np.abs(dequantise(quantise(w, per_row=True)) - w)[1].max()
    err_tensor = np.abs(dequantise(quantise(w)) - w)[1].max()
    assert err_row < err_tensor / 100


def test_rounding_is_half_away_from_zero():
    assert list(round_half_away(np.array([-2.5, -1.5, -0.5, 0.5, 1.5, 2.5]))) == [
        -3, -2, -1, 1, 2, 3]
    q = quantise(np.array([1.0, 0.5 / 127, -0.5 / 127]), bits=8)
    assert list(q.values) == [127, 1, -1]


def test_fixed_point():
    assert fixed_point(0.05, 28) == 13421773  # 0.05 * 2**28 = 13421772.8
    assert fixed_point(-0.75, 2) == -3
    assert list(fixed_point_array(np.array([0.25, 0.5, 0.9 * 0.25]), 15)) == [8192, 16384, 7373]
    with pytest.raises(ValueError, match="does not fit"):
        fixed_point(1.0, 40, bits=32)
    with pytest.raises(ValueError, match="do not fit"):
        fixed_point_array(np.array([1.0]), 15, bits=16)


def test_bad_input():
    with pytest.raises(ValueError, match="NaN"):
        quantise(np.array([1.0, np.nan]))
    with pytest.raises(ValueError, match="bits"):
        quantise(np.ones(3), bits=1)
    with pytest.raises(ValueError, match="finite"):
        fixed_point(float("inf"), 3)

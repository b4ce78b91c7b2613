"""The one quantiser: round-trip properties (bounds, error, idempotence, sparsity, scales)."""

import numpy as np
import pytest
import torch

from torchseq.quantise import (
    dequantise,
    fixed_point,
    fixed_point_array,
    quantise,
    round_half_away,
)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("bits", [4, 8, 12])
@pytest.mark.parametrize("per_row", [False, True])
@pytest.mark.parametrize("power_of_two", [False, True])
def test_round_trip_properties(dtype, bits, per_row, power_of_two):  # NumPy: CPU only
    gen = torch.Generator().manual_seed(bits)
    w = (torch.randn(17, 33, generator=gen) * torch.rand(17, 1, generator=gen) * 3)
    w[:, ::3] = 0.0  # a sparse mask must survive
    w[5] = 0.0  # an all-zero row
    w = w.to(dtype=dtype)
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


def test_one_quantiser_module_for_training_and_export():
    # the model's training grids and the exporter's grids are the objects of torchseq.quantise
    import torchseq.export.int_model as int_model
    import torchseq.neural.inference as inference
    import torchseq.neural.learning as learning
    import torchseq.neural.model as model
    import torchseq.quantise as one

    for mod, name in ((model, "integer_weights"), (learning, "round_rows"),
                      (inference, "factor_power_of_two"), (inference, "factor_rows"),
                      (int_model, "quantise"), (int_model, "integer_grid"),
                      (int_model, "fixed_point"), (int_model, "fixed_point_array")):
        assert getattr(mod, name) is getattr(one, name), (mod.__name__, name)


@pytest.mark.parametrize("as_tensor", [False, True])
def test_rounding_rules_are_named_and_differ_on_halves(as_tensor):
    from torchseq.quantise import HALF_AWAY, HALF_EVEN, round_to_integer

    x = np.array([0.5, 1.5, 2.5, -0.5, -2.5, 0.49, -1.51])
    arg = torch.from_numpy(x) if as_tensor else x
    even = np.asarray(round_to_integer(arg, HALF_EVEN))
    away = np.asarray(round_to_integer(arg, HALF_AWAY))
    assert even.tolist() == [0, 2, 2, 0, -2, 0, -2]
    assert away.tolist() == [1, 2, 3, -1, -3, 0, -2]
    with pytest.raises(ValueError, match="unknown rounding rule"):
        round_to_integer(arg, "nearest")


def test_training_grids_export_without_rounding():
    """What is evaluated is what is deployed: the integer file holds the training integers."""
    from export_helpers import small_setup

    from torchseq.quantise import factor_power_of_two, factor_rows

    model, *_, im = small_setup()
    n1, _ = factor_power_of_two(model.l1.folded_weight(), 64)  # the training grid's integers
    rows = np.arange(n1.shape[0])[:, None]
    assert np.array_equal(n1.numpy()[rows, im.l1.cols], im.l1.values)
    n3, scale3 = factor_rows(model.l3.folded_weight(), 127)
    assert np.array_equal(n3.numpy()[np.arange(n3.shape[0])[:, None], im.l3.cols], im.l3.values)
    ratio = scale3.double().numpy() / scale3.double().max().item()
    assert np.abs(im.l3.row_scale - ratio * 2**15).max() <= 0.5 + 1e-6

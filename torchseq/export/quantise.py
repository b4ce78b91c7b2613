"""The one quantiser of torchseq: symmetric integer quantisation and fixed-point constants.

Every integer number the exporter stores comes from :func:`quantise` (weight tensors) or
:func:`fixed_point` (scalar constants), so what the validation measures is what a device
runs. Rounding is half away from zero everywhere (as ``torchseq.preprocess.round_half_away``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch


class Quantised(NamedTuple):
    """A quantised tensor: ``real ~= values * scale`` (broadcast along rows when per-row).

    Attributes:
        values: integer array, ``|values| <= 2**(bits - 1) - 1`` (symmetric: no -128).
        scale: float64 scalar ``()`` (per tensor) or ``(rows,)`` (per row).
        bits: bit width of ``values``.
    """

    values: np.ndarray
    scale: np.ndarray
    bits: int


def _as_float64(w) -> np.ndarray:
    if isinstance(w, torch.Tensor):
        w = w.detach().cpu().to(torch.float64).numpy()
    w = np.asarray(w, dtype=np.float64)
    if not np.isfinite(w).all():
        raise ValueError("cannot quantise NaN or infinite values")
    return w


def round_half_away(x: np.ndarray) -> np.ndarray:
    """Round halves away from zero (float in, float out)."""
    return np.sign(x) * np.floor(np.abs(x) + 0.5)


def _int_dtype(bits: int) -> np.dtype:
    return np.dtype({8: np.int8, 16: np.int16, 32: np.int32}.get(bits, np.int64))


def quantise(w, bits: int = 8, per_row: bool = False, power_of_two: bool = False) -> Quantised:
    """Quantise a real tensor to signed symmetric integers.

    ``scale = max|w| / (2**(bits-1) - 1)`` over the whole tensor or over each row (axis 0
    indexes rows); with ``power_of_two`` the scale is rounded up to a power of two (a shift).
    ``values = round_half_away(w / scale)``. An all-zero tensor (or row) gets scale 1. Zeros
    stay zero, so sparse masks survive quantisation.

    Args:
        w: ``(rows, ...)`` or any shape (per-tensor) real array or tensor.
        bits: 2..32.
        per_row: one scale per row instead of one per tensor.
        power_of_two: round scales up to powers of two.

    Returns:
        :class:`Quantised` with values of the smallest NumPy int dtype holding ``bits``.
    """
    if not 2 <= bits <= 32:
        raise ValueError(f"bits must be in 2..32, got {bits}")
    w = _as_float64(w)
    qmax = 2 ** (bits - 1) - 1
    if per_row:
        if w.ndim < 1 or w.shape[0] == 0:
            raise ValueError(f"per-row quantisation needs a (rows, ...) array, got {w.shape}")
        peak = np.abs(w.reshape(w.shape[0], -1)).max(axis=1) if w.size else np.zeros(w.shape[0])
    else:
        peak = np.asarray(np.abs(w).max() if w.size else 0.0)
    scale = np.where(peak > 0, peak / qmax, 1.0)
    if power_of_two:
        scale = np.exp2(np.ceil(np.log2(scale)))
    s = scale.reshape(scale.shape + (1,) * (w.ndim - scale.ndim))
    values = np.clip(round_half_away(w / s), -qmax, qmax).astype(_int_dtype(bits))
    return Quantised(values, scale.astype(np.float64), bits)


def integer_grid(w, bits: int = 8) -> Quantised:
    """:func:`quantise`, keeping integers exactly where ``w`` already holds them.

    A tensor of small integers times one power of two keeps exactly those integers (a model
    made on integer grids exports losslessly); any other tensor goes to :func:`quantise`.

    Args:
        w: real array or tensor.
        bits: 2..32.
    """
    a = _as_float64(w)
    peak = float(np.abs(a).max()) if a.size else 0.0
    if peak > 0:
        qmax = 2 ** (bits - 1) - 1
        # the coarsest power-of-two step that leaves integers: the smallest integers
        for e in range(math.ceil(math.log2(peak)), math.ceil(math.log2(peak / qmax)) - 1, -1):
            v = a / 2.0**e
            if np.abs(v).max() <= qmax and np.array_equal(v, np.round(v)):
                return Quantised(v.astype(_int_dtype(bits)), np.float64(2.0**e), bits)
    return quantise(a, bits)


def dequantise(q: Quantised) -> np.ndarray:
    """``values * scale`` as float64 (the real numbers the integers stand for)."""
    s = q.scale.reshape(q.scale.shape + (1,) * (q.values.ndim - q.scale.ndim))
    return q.values.astype(np.float64) * s


def fixed_point(x: float, frac_bits: int, bits: int = 63) -> int:
    """A real constant as a fixed-point integer: ``round_half_away(x * 2**frac_bits)``.

    Args:
        x: the real number.
        frac_bits: fractional bits (may be negative).
        bits: the result must fit a signed integer of this width.

    Raises:
        ValueError: the constant does not fit.
    """
    if not math.isfinite(x):
        raise ValueError(f"fixed-point constant must be finite, got {x}")
    v = int(round_half_away(np.float64(x) * np.float64(2.0) ** frac_bits))
    if abs(v) > 2 ** (bits - 1) - 1:
        raise ValueError(f"fixed-point constant {x} * 2**{frac_bits} does not fit {bits} bits")
    return v


def fixed_point_array(w, frac_bits: int, bits: int = 16) -> np.ndarray:
    """A real array on the fixed grid ``2**-frac_bits``: ``round_half_away(w * 2**frac_bits)``.

    Args:
        w: real array or tensor.
        frac_bits: fractional bits.
        bits: signed width of the result (int8/16/32/64 dtype).

    Raises:
        ValueError: a value does not fit ``bits`` (no silent saturation of weights).
    """
    w = _as_float64(w)
    v = round_half_away(w * np.float64(2.0) ** frac_bits)
    qmax = 2 ** (bits - 1) - 1
    if v.size and np.abs(v).max() > qmax:
        raise ValueError(f"values up to {np.abs(w).max():.6g} * 2**{frac_bits} do not fit "
                         f"{bits} bits")
    return v.astype(_int_dtype(bits))

"""The one quantiser of torchseq: every integer grid, at training time and at export.

Two rounding rules are in use, and every function here names the one it applies:

- :data:`HALF_EVEN` (``torch.round``, ONNX ``Round``): the grids the float model is built on
  and evaluated with (:func:`integer_weights`, :func:`round_rows`, :func:`factor_rows`). The
  float model and its ONNX graph round this way, so what is trained is what is exported.
- :data:`HALF_AWAY` (halves away from zero, as the integer format's ``round_div``): the
  integers stored in the integer file (:func:`quantise`, :func:`integer_grid`,
  :func:`fixed_point`, :func:`fixed_point_array`).

A model built on the training grids (``NeuralConfig`` defaults) holds integers times powers
of two or per-row scales already, which the export grids keep exactly (:func:`integer_grid`,
and :func:`quantise` per row on an int8 row), so the rule of the export never acts on them.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

HALF_EVEN = "half_even"
HALF_AWAY = "half_away"


def round_to_integer(x, rule: str):
    """Round ``x`` (NumPy array or torch tensor, float) to integers by ``rule``.

    Args:
        x: float array or tensor.
        rule: :data:`HALF_EVEN` or :data:`HALF_AWAY`.

    Returns:
        Same type and dtype as ``x``, integer-valued.
    """
    if rule == HALF_EVEN:
        return torch.round(x) if isinstance(x, torch.Tensor) else np.round(x)
    if rule == HALF_AWAY:
        if isinstance(x, torch.Tensor):
            return torch.sign(x) * torch.floor(x.abs() + 0.5)
        return np.sign(x) * np.floor(np.abs(x) + 0.5)
    raise ValueError(f"unknown rounding rule {rule!r} (use {HALF_EVEN!r} or {HALF_AWAY!r})")


def round_half_away(x: np.ndarray) -> np.ndarray:
    """Round halves away from zero (float in, float out): :data:`HALF_AWAY`."""
    return round_to_integer(x, HALF_AWAY)


# ------------------------------------------------------------------ training-time grids
def power_of_two_scale(bound: float, levels: int) -> float:
    """The power of two nearest (in log) to ``bound / levels``: the step of an integer grid.

    The exponent is rounded :data:`HALF_EVEN` (Python's ``round``).
    """
    return 2.0 ** round(math.log2(bound / levels))


def integer_weights(w: torch.Tensor, bound: float, levels: int) -> torch.Tensor:
    """Map weights drawn uniformly in ``+-bound`` onto an integer grid.

    The grid is integers ``-levels..levels`` times a power of two
    (:func:`power_of_two_scale`), rounded :data:`HALF_EVEN`.

    Args:
        w: ``(out, in)`` float weights in ``[-bound, bound]``.
        bound: the half-width they were drawn from.
        levels: largest integer magnitude.

    Returns:
        Float tensor of the same shape whose values are ``n * 2**e`` with ``|n| <= levels``.
    """
    n = round_to_integer(w / bound * levels, HALF_EVEN).clamp(-levels, levels)
    return n * power_of_two_scale(bound, levels)


def round_rows(w: torch.Tensor, levels: int) -> torch.Tensor:
    """Round each row to integers ``-levels..levels`` times the row's own scale.

    ``scale_u = max|w_u| / levels``, rounded :data:`HALF_EVEN`; an all-zero row stays zero.

    Args:
        w: ``(rows, cols)`` float.
        levels: largest integer magnitude (127: int8).

    Returns:
        ``(rows, cols)`` float ``n * scale_u``.
    """
    scale = w.abs().amax(dim=1, keepdim=True) / levels  # (rows, 1)
    safe = torch.where(scale > 0, scale, torch.ones_like(scale))
    return round_to_integer(w / safe, HALF_EVEN).clamp(-levels, levels) * scale


def factor_power_of_two(w: torch.Tensor, levels: int) -> tuple[torch.Tensor, float] | None:
    """Recover ``(n int8, 2**e)`` with ``w == n * 2**e`` exactly and ``|n| <= levels``.

    The inverse of :func:`integer_weights`; None when ``w`` is not on such a grid (a model
    made with float weights), so callers fall back to float products.

    Args:
        w: float tensor.
        levels: largest integer magnitude accepted (at most 127).
    """
    if levels > 127 or w.numel() == 0 or not bool(torch.isfinite(w).all()):
        return None
    peak = float(w.abs().max())
    if peak == 0.0:
        return None
    step = 2.0 ** math.ceil(math.log2(peak / levels))
    n = w / step
    if bool((n.abs() <= levels).all()) and torch.equal(torch.trunc(n), n):  # exact integers
        return n.to(torch.int8), step
    return None


def factor_rows(w: torch.Tensor, levels: int,
                rtol: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Recover ``(n (rows, cols) int8, scale (rows,) float32)`` with ``w ~= n * scale``.

    The inverse of :func:`round_rows` up to float rounding (``|n * scale - w| <= rtol *
    max|w_u|`` in every row); None when some row is not on such a grid (a model made
    without integer weights), so callers fall back to float products.

    Args:
        w: ``(rows, cols)`` float.
        levels: largest integer magnitude accepted (at most 127).
        rtol: accepted error relative to each row's peak.
    """
    if w.dim() != 2 or levels > 127 or not bool(torch.isfinite(w).all()):
        return None
    peak = w.abs().amax(dim=1, keepdim=True)  # (rows, 1)
    scale = peak / levels
    n = round_to_integer(w / torch.where(scale > 0, scale, torch.ones_like(scale)), HALF_EVEN)
    if not bool(((n * scale - w).abs() <= rtol * peak).all()):
        return None
    return n.to(torch.int8), scale[:, 0].to(torch.float32)


# ------------------------------------------------------------------ export grids
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


def _int_dtype(bits: int) -> np.dtype:
    return np.dtype({8: np.int8, 16: np.int16, 32: np.int32}.get(bits, np.int64))


def quantise(w, bits: int = 8, per_row: bool = False, power_of_two: bool = False) -> Quantised:
    """Quantise a real tensor to signed symmetric integers.

    ``scale = max|w| / (2**(bits-1) - 1)`` over the whole tensor or over each row (axis 0
    indexes rows); with ``power_of_two`` the scale is rounded up to a power of two (a shift).
    ``values = round_half_away(w / scale)`` (:data:`HALF_AWAY`). An all-zero tensor (or row)
    gets scale 1. Zeros stay zero, so sparse masks survive quantisation.

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
            if np.abs(v).max() <= qmax and np.array_equal(v, np.trunc(v)):  # exact integers
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

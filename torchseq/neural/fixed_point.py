"""Integer grids of Neural SeqSLAM: quantised L1 input, integer L1 weights, int8 L3 rows.

With the defaults (``input_steps=32``, ``l1_levels=64``, ``l3_levels=127``) the model's
numbers sit on integer grids by definition, not as an approximation of a float model:

- L1 input: patch z-scores rounded to multiples of ``1 / input_steps`` (``|z| <= 3.75`` for
  4x4 patches, so ``32`` gives signed 8-bit values ``-120..120``);
- L1 weights: integers ``-l1_levels..l1_levels`` times a power of two;
- L2 -> L3 weights: each unit's row rounded to integers ``-l3_levels..l3_levels`` times a
  per-unit scale.

Every L1 product is then a small integer times a power of two, and every L1 sum (below
``2**24`` in magnitude) is exact in float32 whatever the summation order: float32 GEMMs,
int8 GEMMs (:mod:`torchseq.layers.kernels`) and the integer export all give the same L2 code.
"""

from __future__ import annotations

import math

import torch

# the input stage moved to torchseq.preprocess (one z-score); names kept for callers
from torchseq.preprocess import (  # noqa: F401
    block_order,
    in_order_sum,
    quantise_input,
    zscore_blocks,
    zscore_pixel_major,
)


def power_of_two_scale(bound: float, levels: int) -> float:
    """The power of two nearest (in log) to ``bound / levels``: the step of an integer grid."""
    return 2.0 ** round(math.log2(bound / levels))


def integer_weights(w: torch.Tensor, bound: float, levels: int) -> torch.Tensor:
    """Map weights drawn uniformly in ``+-bound`` onto an integer grid.

    The grid is integers ``-levels..levels`` times a power of two
    (:func:`power_of_two_scale`).

    Args:
        w: ``(out, in)`` float weights in ``[-bound, bound]``.
        bound: the half-width they were drawn from.
        levels: largest integer magnitude.

    Returns:
        Float tensor of the same shape whose values are ``n * 2**e`` with ``|n| <= levels``.
    """
    n = torch.round(w / bound * levels).clamp(-levels, levels)
    return n * power_of_two_scale(bound, levels)


def round_rows(w: torch.Tensor, levels: int) -> torch.Tensor:
    """Round each row to integers ``-levels..levels`` times the row's own scale.

    ``scale_u = max|w_u| / levels``; an all-zero row stays zero.

    Args:
        w: ``(rows, cols)`` float.
        levels: largest integer magnitude (127: int8).

    Returns:
        ``(rows, cols)`` float ``n * scale_u``.
    """
    scale = w.abs().amax(dim=1, keepdim=True) / levels  # (rows, 1)
    safe = torch.where(scale > 0, scale, torch.ones_like(scale))
    return torch.round(w / safe).clamp(-levels, levels) * scale


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
    if bool((n.abs() <= levels).all()) and torch.equal(torch.round(n), n):
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
    n = torch.round(w / torch.where(scale > 0, scale, torch.ones_like(scale)))
    if not bool(((n * scale - w).abs() <= rtol * peak).all()):
        return None
    return n.to(torch.int8), scale[:, 0].to(torch.float32)

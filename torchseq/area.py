"""Area reduction of a matrix for display: the one definition of its block means.

Reducing an ``(R, Q)`` matrix to ``(R', Q')``, cell ``(i, j)`` is the mean of the *finite*
entries of rows ``[floor(i R / R'), ceil((i + 1) R / R'))`` and columns
``[floor(j Q / Q'), ceil((j + 1) Q / Q'))`` (the blocks of ``adaptive_avg_pool``), NaN
where the block has none. It is computed one axis at a time, so a matrix that never exists
whole (the banded SeqSLAM engine's) reduces as its pieces arrive: :func:`reduce_rows`
pools the zero-filled values and the finite mask along the last axis (a :class:`Partial`);
:func:`finish` pools both along the other axis and divides (the block lengths cancel).
:func:`area_mean` is the two steps on a whole matrix. Sums run in float32 (a display copy).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F


class Partial(NamedTuple):
    """An area reduction along one axis: the pooled zero-filled values and finite mask.

    Both ``(n, L')``; their ratio is the mean of the finite entries of each bin.
    ``weights`` None: every entry was finite (all weights 1).
    """

    values: torch.Tensor
    weights: torch.Tensor | None


def _pool_last(x: torch.Tensor, side: int) -> torch.Tensor:
    """``(n, L)`` -> ``(n, side)``: adaptive average pooling along the last axis."""
    return F.adaptive_avg_pool1d(x[:, None, :], side)[:, 0]


def reduce_rows(x: torch.Tensor, side: int) -> Partial:
    """Reduce ``(n, L)`` along its last axis to ``min(L, side)`` bins (float32).

    Args:
        x: ``(n, L)`` values; non-finite entries are skipped.
        side: the most bins kept.

    Returns:
        :class:`Partial` of ``(n, min(L, side))`` float32 tensors (``weights`` None when
        every entry is finite).
    """
    x = x.to(torch.float32)
    side = min(x.shape[-1], side)
    pooled = _pool_last(x, side)
    if bool(torch.isfinite(pooled).all()):  # then so is every entry (NaN, inf propagate)
        return Partial(pooled, None)
    finite = torch.isfinite(x)
    return Partial(_pool_last(torch.where(finite, x, 0.0), side),
                   _pool_last(finite.to(torch.float32), side))


def finish(partial: Partial, side: int) -> torch.Tensor:
    """Reduce a :class:`Partial` ``(n, L')`` along its first axis and divide.

    Returns:
        ``(L', min(n, side))`` block means (the partial's axes swapped), NaN for blocks
        without a finite entry.
    """
    n = partial.values.shape[0]
    side = min(n, side)
    values = _pool_last(partial.values.T.contiguous(), side)
    if partial.weights is None:
        return values
    weights = _pool_last(partial.weights.T.contiguous(), side)
    return torch.where(weights > 0, values / weights.clamp_min(1e-30), torch.nan)


def area_mean(matrix: torch.Tensor, out_size: tuple[int, int]) -> torch.Tensor:
    """``(R, Q)`` -> ``(min(R, R'), min(Q, Q'))`` float32 block means of the finite entries.

    Args:
        matrix: ``(R, Q)`` dense tensor.
        out_size: ``(R', Q')`` the most cells kept on each side.
    """
    return finish(reduce_rows(matrix.T, out_size[0]), out_size[1])

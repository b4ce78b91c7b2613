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
int8 GEMMs (:mod:`torchseq.neural.fast`) and the integer export all give the same L2 code.
"""

from __future__ import annotations

import torch

# the training-time grids live in the one quantiser, beside the export grids
from torchseq.quantise import (  # noqa: F401
    factor_power_of_two,
    factor_rows,
    integer_weights,
    power_of_two_scale,
    round_rows,
)


def quantise_input(x: torch.Tensor, steps: int) -> torch.Tensor:
    """Round ``x`` to multiples of ``1 / steps`` (half to even, like ONNX ``Round``).

    Args:
        x: any float tensor.
        steps: grid steps per unit; ``0`` returns ``x`` unchanged.
    """
    if not steps:
        return x
    return torch.round(x * steps) / steps


def block_order(height: int, width: int, patch: int) -> torch.Tensor:
    """``(H * W,)`` pixel index (row-major) of each position in block-major order.

    Block-major: blocks row by row, and within a block its pixels row by row.
    """
    idx = torch.arange(height * width).reshape(height // patch, patch, width // patch, patch)
    return idx.permute(0, 2, 1, 3).reshape(-1)


def zscore_blocks(frames: torch.Tensor, patch: int) -> torch.Tensor:
    """Sample z-scores of non-overlapping ``patch x patch`` blocks, in block-major order.

    The same numbers as :func:`torchseq.preprocess.patch_normalise` in ``"zscore"`` mode up
    to float rounding (a flat block gives 0). Neural SeqSLAM uses this one definition on
    every path; :func:`zscore_pixel_major` computes it.

    Args:
        frames: ``(T, H, W)`` float, ``H`` and ``W`` multiples of ``patch``.
        patch: block side.

    Returns:
        ``(T, (H / p) * (W / p), p * p)`` (a permuted view).
    """
    return zscore_pixel_major(frames, patch).permute(1, 2, 0)


def zscore_pixel_major(frames: torch.Tensor, patch: int) -> torch.Tensor:
    """:func:`zscore_blocks` laid out ``(p * p, T, blocks)``, contiguous.

    Each pixel position of a block is one contiguous row over all frames and blocks, so the
    fixed-order sums (:func:`in_order_sum`) are whole-row additions: several times faster
    on the CPU than reductions over the strided block axes of an image, and the same
    numbers (the additions are element-wise, in the same order).

    Args:
        frames: ``(T, H, W)`` float, ``H`` and ``W`` multiples of ``patch``.
        patch: block side.

    Returns:
        ``(p * p, T, (H / p) * (W / p))``.
    """
    t, h, w = frames.shape
    n = patch * patch
    pixels = (frames.reshape(t, h // patch, patch, w // patch, patch)
              .permute(2, 4, 0, 1, 3).reshape(n, t, -1))
    dev = pixels - in_order_sum(pixels) / n
    std = (in_order_sum(dev * dev) / (n - 1)).sqrt()
    return dev / torch.where(std > 0, std, torch.ones_like(std))  # a flat block: 0 / 1


def in_order_sum(x: torch.Tensor) -> torch.Tensor:
    """Sum over the first axis, first to last: ``(n, ...) -> (...)``.

    Element-wise additions in a fixed order round the same way in PyTorch and in any ONNX
    runtime (a reduction kernel may add in another order), so the exported graph computes
    bit for bit the model's z-scores.
    """
    s = x[0]
    for i in range(1, x.shape[0]):
        s = s + x[i]
    return s

"""Fit's self-check: how well a fitted model separates its own reference, lightly disturbed.

A model whose output units do not separate the places of its own reference (units standing
for several frames that look different, a long route of look-alike stretches) collapses on
a real query without a word: measured on nordland-b (``experiments/neural_long_route.py
selfcheck``, docs/results/neural-long-routes.md) a self-check of 0.86 went with recall@1 0.25 on
1,788 frames on 555 units. :meth:`torchseq.neural.NeuralSeqSLAM.fit` computes it after
learning and warns once when it is under :data:`SELF_CHECK_FLOOR`.
"""

from __future__ import annotations

import torch

# std of the Gaussian noise added to the L1 input (patch z-scores, unit variance per patch):
# the same disturbance for camera and event frames (a light change is not: LENS's event
# counts lose their code under gamma and a brightness ramp)
SELF_CHECK_NOISE = 1.5
SELF_CHECK_TOLERANCE = 2  # frames either side of a unit's stretch that still count
# measured (experiments/neural_long_route.py selfcheck): demo, corridor, LENS >= 0.99;
# nordland-b 500 frames 0.95 (recall@1 0.93), 1,788 on 1,788 units 0.95 (0.59),
# 1,788 on 555 units 0.86 (0.25), 1,788 on 279 units 0.66 (0.12)
SELF_CHECK_FLOOR = 0.90


def disturbed(x: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """The self-check's disturbance of L1 input ``(B, n_input)``: plus N(0, noise^2) each."""
    noise = torch.randn(x.shape, generator=generator, dtype=x.dtype)
    return x + SELF_CHECK_NOISE * noise.to(x.device)


def self_recall(units: torch.Tensor, spans: torch.Tensor,
                tolerance: int = SELF_CHECK_TOLERANCE) -> float:
    """Share of reference frames whose winning unit holds them (within ``tolerance`` frames).

    Frame ``t`` is right when its winning unit ``u`` has ``f_u - tol <= t < l_u + tol`` with
    ``[f_u, l_u)`` = ``spans[u]``: with one frame per unit, ``|reported - t| <= tol``.

    Args:
        units: ``(T,)`` int64 winning unit of reference frame ``t`` (frames in route order).
        spans: ``(N, 2)`` int64 first and one-past-last reference frame of each unit.
        tolerance: frames either side.

    Returns:
        The share in ``[0, 1]``.
    """
    if units.dim() != 1 or units.numel() == 0:
        raise ValueError(f"units must be a non-empty (T,), got {tuple(units.shape)}")
    t = torch.arange(units.numel(), device=units.device)
    s = spans.to(units.device)[units]  # (T, 2)
    ok = (s[:, 0] - tolerance <= t) & (t < s[:, 1] + tolerance)
    return float(ok.to(torch.float64).mean())

"""Local learning rules of Neural SeqSLAM: recruitment, Hebbian weights, cohorts.

Pure functions. The read-out is in :mod:`torchseq.neural.readout`.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

from torchseq.neural.fixed_point import round_rows


def recruit_units(n_frames: int, n_units: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Recruit output units along the route in order, each for a contiguous stretch.

    Frame ``t`` goes to unit ``floor(t * N / T)``, so the ``N <= T`` stretches differ in
    length by at most one frame.

    Args:
        n_frames: reference frames ``T``.
        n_units: units ``N`` (``1 <= N <= T``).

    Returns:
        ``(unit_of_frame (T,) int64, spans (N, 2) int64)``: each unit's first frame and one
        past its last frame.
    """
    if not 1 <= n_units <= n_frames:
        raise ValueError(f"need 1 <= n_units <= n_frames, got {n_units} and {n_frames}")
    unit = torch.arange(n_frames, dtype=torch.int64) * n_units // n_frames  # (T,)
    start = (torch.arange(n_units, dtype=torch.int64) * n_frames + n_units - 1) // n_units
    end = torch.cat([start[1:], torch.tensor([n_frames])])
    return unit, torch.stack([start, end], 1)


def hebbian_weights(sums: torch.Tensor, counts: torch.Tensor, mean_code: torch.Tensor,
                    mask: torch.Tensor, rule: str = "mean", eps: float = 1e-6) -> torch.Tensor:
    """L2 -> L3 weights from the L2 codes a unit saw (Hebbian, within the mask).

    ``"mean"``: ``w[u] = mask[u] * mean code of u's frames``; ``"centred"``: minus the mean
    code of the whole route (a covariance rule: features every place has do not count).
    Each row is then divided by the sum of its absolute values, so a frame whose code equals
    the unit's mean code gives evidence of the same size for every unit.

    Args:
        sums: ``(N, hidden)`` sum of the binary codes of each unit's frames.
        counts: ``(N,)`` frames per unit.
        mean_code: ``(hidden,)`` mean code over the route.
        mask: ``(N, hidden)`` connection mask.
        rule: ``"mean"`` or ``"centred"``.
        eps: floor of the row norm.

    Returns:
        ``(N, hidden)`` float32 weights (zero outside the mask).
    """
    w = sums / counts.clamp_min(1.0)[:, None]
    if rule == "centred":
        w = w - mean_code[None, :]
    elif rule != "mean":
        raise ValueError(f"rule must be 'mean' or 'centred', got {rule!r}")
    w = w * mask
    return w / (w.abs().sum(1, keepdim=True) + eps)


def cohort_membership(n_units: int, n_cohorts: int) -> torch.Tensor:
    """One-hot ``(N, C)`` membership of contiguous, near-equal blocks of units.

    ``C = min(n_cohorts, N)``; unit ``u`` is in cohort ``floor(u * C / N)``.
    """
    c = max(1, min(int(n_cohorts), n_units))
    which = torch.arange(n_units) * c // n_units
    return torch.nn.functional.one_hot(which, c).to(torch.float32)


def learn_readout(codes: Iterable[tuple[int, int, torch.Tensor]], unit_of_frame: torch.Tensor,
                  spans: torch.Tensor, mask: torch.Tensor, rule: str = "centred",
                  eps: float = 1e-6, levels: int = 0) -> torch.Tensor:
    """L2 -> L3 weights from one pass over a route's binary codes.

    Accumulates each unit's codes and the route's, then applies :func:`hebbian_weights`
    and, with ``levels``, rounds each row to its integer grid
    (:func:`torchseq.neural.fixed_point.round_rows`).

    Args:
        codes: ``(lo, hi, code (hi - lo, M))`` for consecutive stretches of frames
            covering the route ``0..T`` once.
        unit_of_frame: ``(T,)`` int64 unit of each frame (:func:`recruit_units`).
        spans: ``(N, 2)`` each unit's first and one-past-last frame.
        mask: ``(N, M)`` L2 -> L3 connection mask (its device is used).
        rule: ``"mean"`` or ``"centred"``.
        eps: floor of the row norm.
        levels: integer levels per row (0: float weights).

    Returns:
        ``(N, M)`` float32 weights.
    """
    n_units, hidden = mask.shape
    dev = mask.device
    sums = torch.zeros(n_units, hidden, device=dev)
    total = torch.zeros(hidden, device=dev)
    for lo, hi, c in codes:
        sums.index_add_(0, unit_of_frame[lo:hi].to(dev), c)
        total += c.sum(0)
    counts = (spans[:, 1] - spans[:, 0]).to(dev, torch.float32)
    w = hebbian_weights(sums, counts, total / unit_of_frame.numel(), mask, rule, eps)
    return round_rows(w, levels) if levels else w

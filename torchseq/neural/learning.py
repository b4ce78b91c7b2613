"""Local learning rules of Neural SeqSLAM: recruitment, Hebbian weights, cohorts.

Pure functions. The read-out is in :mod:`torchseq.neural.readout`.
"""

from __future__ import annotations

import torch


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

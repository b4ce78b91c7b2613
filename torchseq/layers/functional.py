"""Functional core of the Neural SeqSLAM layers: pure functions, no state.

Shapes: ``B`` independent streams (batch), ``N`` units, ``T`` time steps (time-first).
Every function here uses only ops that export to ONNX (no ``kthvalue``, no sparse tensors).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F


def make_mask(
    out_features: int,
    in_features: int,
    density: float,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Draw a fixed random binary connection mask with exactly the same fan-in per row.

    Every output row gets exactly ``round(density * in_features)`` ones (at least one), so
    the whole mask holds exactly ``out_features * round(density * in_features)`` ones.

    Args:
        out_features: rows.
        in_features: columns.
        density: fraction of connections kept, in ``(0, 1]``.
        generator: CPU random generator (for determinism).

    Returns:
        ``(out_features, in_features)`` float32 mask of 0.0 and 1.0, on the CPU.
    """
    if not 0.0 < density <= 1.0:
        raise ValueError(f"density must be in (0, 1], got {density}")
    if out_features < 1 or in_features < 1:
        raise ValueError(f"need positive sizes, got ({out_features}, {in_features})")
    per_row = mask_fan_in(in_features, density)
    keys = torch.rand(out_features, in_features, generator=generator)
    cols = keys.argsort(dim=1)[:, :per_row]  # (out, per_row) distinct columns per row
    mask = torch.zeros(out_features, in_features)
    mask.scatter_(1, cols, 1.0)
    return mask


def mask_fan_in(in_features: int, density: float) -> int:
    """Connections per output row of a mask made by :func:`make_mask`."""
    return max(1, int(round(density * in_features)))


def masked_linear(
    x: torch.Tensor, weight: torch.Tensor, mask: torch.Tensor, bias: torch.Tensor | None = None
) -> torch.Tensor:
    """Linear map through a fixed connection mask: ``x @ (weight * mask).T + bias``.

    Gradients with respect to ``weight`` are zero wherever ``mask`` is zero.

    Args:
        x: ``(..., in)``.
        weight: ``(out, in)``.
        mask: ``(out, in)`` of 0 and 1.
        bias: ``(out,)`` or None.

    Returns:
        ``(..., out)``.
    """
    return F.linear(x, weight * mask, bias)


def kwta_k(n: int, k: int | None = None, fraction: float | None = None) -> int:
    """Resolve a winner count from ``k`` or ``fraction`` of ``n`` units (exactly one given)."""
    if (k is None) == (fraction is None):
        raise ValueError("give exactly one of k and fraction")
    if k is None:
        if not 0.0 < fraction <= 1.0:
            raise ValueError(f"fraction must be in (0, 1], got {fraction}")
        k = max(1, int(round(fraction * n)))
    if not 1 <= k <= n:
        raise ValueError(f"k must be in 1..{n}, got {k}")
    return int(k)


def kwta(
    x: torch.Tensor, k: int, binary: bool = False, straight_through: bool = False
) -> torch.Tensor:
    """k-winners-take-all along the last axis, with deterministic ties (lowest index wins).

    The ``k``-th largest value ``v`` comes from ``torch.topk`` (its value does not depend on
    how topk orders ties). Winners are all entries ``> v`` plus the lowest-index entries
    ``== v`` until there are exactly ``k``.

    Args:
        x: ``(..., N)``.
        k: winners per sample, ``1 <= k <= N``.
        binary: return 1.0 at winners instead of the winners' values.
        straight_through: backward pass as identity (gradient reaches every input);
            otherwise the gradient flows through the winners only (valued) or is zero (binary).

    Returns:
        ``(..., N)`` same dtype as ``x``, exactly ``k`` non-zero positions per sample
        (fewer if winners' values are themselves zero in valued mode).
    """
    n = x.shape[-1]
    if not 1 <= k <= n:
        raise ValueError(f"k must be in 1..{n}, got {k}")
    v = torch.topk(x, k, dim=-1).values[..., -1:]  # (..., 1) the k-th largest value
    greater = x > v
    equal = x == v
    room = k - greater.sum(-1, keepdim=True)  # how many tied entries still win
    win = greater | (equal & (equal.to(torch.int64).cumsum(-1) <= room))
    y = win.to(x.dtype) if binary else x * win.to(x.dtype)
    if straight_through:
        y = y.detach() + (x - x.detach())
    return y


def kwta_numpy(values: np.ndarray, k: int) -> np.ndarray:
    """The binary code of :func:`kwta` for NumPy rows ``(B, M)``, as a bool array.

    The ``k``-th largest value ``v`` of each row comes from ``numpy.partition``
    (introselect, several times faster than ``torch.topk`` on one CPU thread); the winners
    are the entries ``>= v``, except in rows with a tie at ``v``, which keep the entries
    ``> v`` and the lowest-index entries ``== v``. Any real or integer dtype, no NaN.

    Float rows are selected on their bits read as signed integers (faster to partition):
    positive floats sort like those integers and every negative float reads as a negative
    one, so the result is the same whenever each row's ``v`` is above ``+0.0``; otherwise
    the floats themselves are partitioned.
    """
    m = values.shape[1]
    keys = values
    if values.dtype.kind == "f":
        keys = values.view(np.dtype(f"i{values.itemsize}"))
    v = np.partition(keys, m - k, axis=1)[:, m - k : m - k + 1]  # (B, 1)
    if keys is not values and not bool((v > 0).all()):
        keys = values
        v = np.partition(keys, m - k, axis=1)[:, m - k : m - k + 1]
    win = keys >= v  # (B, M)
    tied = np.flatnonzero(win.view(np.uint8).sum(1, dtype=np.int32) != k)
    if tied.size:
        row, vt = keys[tied], v[tied]
        greater, equal = row > vt, row == vt
        room = k - greater.sum(1, keepdims=True, dtype=np.int32)
        win[tied] = greater | (equal & (equal.cumsum(1, dtype=np.int32) <= room))
    return win


def learn_shift_matrix(
    winners: torch.Tensor,
    n_units: int,
    spread: int = 2,
    spread_decay: float = 0.5,
    stay: float = 0.5,
    wrap: bool = False,
    normalise: bool = True,
) -> torch.Tensor:
    """Learn the ring's recurrent shift matrix from the order in which units won.

    For every time ``t`` and lag ``l``: ``W[w[t+l], w[t]] += g(l)`` with ``g(0) = stay``
    (stay in place: slower repeats) and ``g(l) = spread_decay ** (l - 1)`` for
    ``1 <= l <= spread`` (move on one or more units: normal and faster repeats). With ``wrap``
    the winner sequence is read as a loop (``t + l`` modulo ``T``). Then each row is divided
    by its sum (rows with no input stay zero).

    Args:
        winners: ``(T,)`` int64 unit index of the winner at each training step.
        n_units: ``N``.
        spread: largest lag that learns (``>= 1``).
        spread_decay: weight ratio between successive lags.
        stay: weight of lag 0 (a unit to itself).
        wrap: treat the traverse as a closed loop.
        normalise: divide rows by their sums.

    Returns:
        ``(N, N)`` float32 ``W[next, current]``.
    """
    if winners.dim() != 1 or winners.numel() == 0:
        raise ValueError(f"winners must be a non-empty (T,), got {tuple(winners.shape)}")
    if spread < 1 or spread_decay < 0 or stay < 0:
        raise ValueError("need spread >= 1, spread_decay >= 0 and stay >= 0")
    w = winners.to(torch.int64).cpu()
    if int(w.min()) < 0 or int(w.max()) >= n_units:
        raise ValueError(f"winners must lie in 0..{n_units - 1}")
    t_len = w.numel()
    shift = torch.zeros(n_units, n_units, dtype=torch.float64)
    for lag in range(spread + 1):
        g = stay if lag == 0 else spread_decay ** (lag - 1)
        if g == 0:
            continue
        if wrap:
            cur, nxt = w, torch.roll(w, -lag)
        else:
            if lag >= t_len:
                continue
            cur, nxt = w[: t_len - lag], w[lag:]
        shift.index_put_((nxt, cur), torch.full((cur.numel(),), float(g), dtype=torch.float64),
                         accumulate=True)
    if normalise:
        rows = shift.sum(1, keepdim=True)
        shift = torch.where(rows > 0, shift / torch.where(rows > 0, rows, 1.0), shift)
    return shift.to(torch.float32)


class RingState(NamedTuple):
    """State of the output ring.

    Attributes:
        activity: ``(B, N)`` activity after the last step.
    """

    activity: torch.Tensor


class RingParams(NamedTuple):
    """Ring dynamics: ``a_t = decay * (a_{t-1} @ shift.T) + gain * evidence_t``."""

    decay: float = 0.9
    gain: float = 0.1


def ring_step(
    evidence: torch.Tensor, state: RingState, shift: torch.Tensor, params: RingParams
) -> tuple[torch.Tensor, RingState]:
    """One step of the output ring: shift the old activity along the ring, add new evidence.

    ``activity = params.decay * state.activity @ shift.T + params.gain * evidence``.

    Args:
        evidence: ``(B, N)`` feed-forward evidence of the new frame.
        state: previous :class:`RingState` with ``(B, N)`` activity.
        shift: ``(N, N)`` ``W[next, current]``.
        params: :class:`RingParams`.

    Returns:
        ``(activity (B, N), new state)``.
    """
    moved = F.linear(state.activity, shift)  # (B, N): moved[b, i] = sum_j shift[i, j] a[b, j]
    activity = params.decay * moved + params.gain * evidence
    return activity, RingState(activity)


def cohort_normalise(
    evidence: torch.Tensor, membership: torch.Tensor, eps: float = 1e-6
) -> torch.Tensor:
    """Z-score evidence within cohorts of units (one cohort = global normalisation).

    Args:
        evidence: ``(B, N)``.
        membership: ``(N, C)`` one-hot: unit ``i`` belongs to cohort ``c``.
        eps: added to the std.

    Returns:
        ``(B, N)``: ``(e - mean_c) / (std_c + eps)`` with the mean and (population) std of
        each unit's cohort.
    """
    if membership.shape[1] == 1:  # one cohort: plain row statistics (fewer passes)
        dev = evidence - evidence.mean(dim=1, keepdim=True)
        return dev / ((dev * dev).mean(dim=1, keepdim=True).sqrt() + eps)
    count = membership.sum(0).clamp_min(1.0)  # (C,)
    mean = F.linear(F.linear(evidence, membership.T) / count, membership)  # (B, N)
    dev = evidence - mean
    var = F.linear(F.linear(dev * dev, membership.T) / count, membership)  # (B, N)
    return dev / (var.sqrt() + eps)

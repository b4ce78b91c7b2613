"""Functional core of the Neural SeqSLAM layers: pure functions, no state.

Shapes: ``B`` independent streams (batch), ``N`` units, ``T`` time steps (time-first).
Every function here uses only ops that export to ONNX (no ``kthvalue``, no sparse tensors).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from torchseq.layers import kernels
from torchseq.layers.ring import RingParams, RingState, ring_scan, ring_step  # noqa: F401


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


KWTA_KERNELS = ("topk", "partition")


def kwta(
    x: torch.Tensor, k: int, binary: bool = False, straight_through: bool = False,
    kernel: str = "topk",
) -> torch.Tensor:
    """k-winners-take-all along the last axis, with deterministic ties (lowest index wins).

    The ``k``-th largest value ``v`` is found; winners are all entries ``> v`` plus the
    lowest-index entries ``== v`` until there are exactly ``k``.

    Kernels (:mod:`~torchseq.layers.kernels`): ``"topk"`` takes ``v`` from ``torch.topk``
    (:func:`~torchseq.layers.kernels.kwta_topk`, any device, differentiable);
    ``"partition"`` from NumPy's introselect (:func:`~torchseq.layers.kernels.kwta_numpy`,
    several times faster on one CPU thread; CPU, no gradients, no NaN). During ONNX export
    the winners are ONNX ``TopK``'s indices, whose tie rule (TopK-11: the lower index) is
    this one, scattered into a 0/1 code.

    Args:
        x: ``(..., N)``.
        k: winners per sample, ``1 <= k <= N``.
        binary: return 1.0 at winners instead of the winners' values.
        straight_through: backward pass as identity (gradient reaches every input);
            otherwise the gradient flows through the winners only (valued) or is zero (binary).
        kernel: ``"topk"`` or ``"partition"``.

    Returns:
        ``(..., N)`` same dtype as ``x``, exactly ``k`` non-zero positions per sample
        (fewer if winners' values are themselves zero in valued mode).
    """
    n = x.shape[-1]
    if not 1 <= k <= n:
        raise ValueError(f"k must be in 1..{n}, got {k}")
    if torch.onnx.is_in_onnx_export():
        idx = torch.topk(x, k, dim=-1, sorted=False).indices  # (..., k)
        win = torch.zeros_like(x).scatter(-1, idx, torch.ones_like(idx, dtype=x.dtype))
        return win if binary else x * win
    if kernel == "partition":
        if x.device.type != "cpu" or x.requires_grad or straight_through:
            raise ValueError("kwta's partition kernel needs a CPU tensor without gradients")
        win = kernels.kwta_partition(x, k)
    elif kernel == "topk":
        win = kernels.kwta_topk(x, k)
    else:
        raise ValueError(f"kernel must be one of {KWTA_KERNELS}, got {kernel!r}")
    y = win.to(x.dtype) if binary else x * win.to(x.dtype)
    if straight_through:
        y = y.detach() + (x - x.detach())
    return y


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


def cohort_normalise(
    evidence: torch.Tensor, membership: torch.Tensor, eps: float = 1e-6, rectify: bool = False,
    kernel: str = "torch",
) -> torch.Tensor:
    """Z-score evidence within cohorts of units (one cohort = global normalisation).

    Kernels: ``"torch"`` (any device, differentiable, exportable) and ``"numpy"`` (CPU, no
    gradients, one cohort: the same statistics in NumPy with a fraction of the per-call
    overhead; several cohorts take the torch kernel). Equal up to float rounding.

    Args:
        evidence: ``(B, N)``.
        membership: ``(N, C)`` one-hot: unit ``i`` belongs to cohort ``c``.
        eps: added to the std.
        rectify: clamp the result at 0 (only above-average evidence passes).
        kernel: ``"torch"`` or ``"numpy"``.

    Returns:
        ``(B, N)``: ``(e - mean_c) / (std_c + eps)`` with the mean and (population) std of
        each unit's cohort (then ``max(., 0)`` with ``rectify``).
    """
    if kernel == "numpy" and membership.shape[1] == 1:
        return kernels.cohort_normalise_numpy(evidence, eps, rectify)
    if kernel not in ("torch", "numpy"):
        raise ValueError(f"kernel must be 'torch' or 'numpy', got {kernel!r}")
    z = _cohort_normalise(evidence, membership, eps)
    return z.clamp_min(0.0) if rectify else z


def _cohort_normalise(evidence: torch.Tensor, membership: torch.Tensor,
                      eps: float) -> torch.Tensor:
    if membership.shape[1] == 1:  # one cohort: plain row statistics (fewer passes)
        dev = evidence - evidence.mean(dim=1, keepdim=True)
        return dev / ((dev * dev).mean(dim=1, keepdim=True).sqrt() + eps)
    count = membership.sum(0).clamp_min(1.0)  # (C,)
    mean = F.linear(F.linear(evidence, membership.T) / count, membership)  # (B, N)
    dev = evidence - mean
    var = F.linear(F.linear(dev * dev, membership.T) / count, membership)  # (B, N)
    return dev / (var.sqrt() + eps)

"""Fast inference paths of Neural SeqSLAM (same maths as ``NeuralSeqSLAM.step``).

- :func:`feedforward`: preprocessing, L1 -> L2 -> L3 and cohort normalisation for a batch
  of frames with folded (dense) weights; the binary k-WTA code is never materialised: the
  L3 evidence is the sum of the ``k`` winners' columns of ``l3.weight * l3.mask``
  (``F.embedding_bag`` in sum mode).
- :func:`ring_scan`: the ring recurrence over a whole single-stream sequence; when the shift
  matrix is banded (units recruited in order, no wrap) it runs on diagonals instead of an
  ``N x N`` product per step.

Results equal the step-by-step path up to float rounding (sums in another order).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from torchseq.layers.functional import cohort_normalise

# Tie-break step for a low-precision L1 product: far below a bfloat16 ulp at the k-WTA
# threshold (|h| ~ 1, ulp 2^-7), so it only orders values that rounded to the same number.
TIE_STEP = 2.0**-24


def winners(h: torch.Tensor, k: int) -> torch.Tensor:
    """Indices ``(B, k)`` of the k-WTA winners of each row (in no particular order).

    The same winners as :func:`torchseq.layers.kwta`: the ``k``-th largest value ``v`` from
    ``torch.topk``; without a tie at ``v`` the topk indices are the winners; with one, all
    entries ``> v`` plus the lowest-index entries ``== v`` (the order of indices within a
    row does not matter to the evidence sum).

    Args:
        h: ``(B, M)`` L2 input.
        k: winners per row.
    """
    vals, idx = torch.topk(h, k, dim=1, sorted=False)
    v = vals.amin(dim=1, keepdim=True)  # (B, 1)
    if not has_tie(h, v, k):
        return idx
    greater, equal = h > v, h == v
    room = k - greater.sum(1, keepdim=True)
    win = greater | (equal & (equal.to(torch.int64).cumsum(1) <= room))
    return win.nonzero()[:, 1].reshape(h.shape[0], k)


def has_tie(h: torch.Tensor, v: torch.Tensor, k: int) -> bool:
    """Whether some row of ``h`` has more than ``k`` entries ``>= v`` (or ``v`` is NaN).

    Every row holds at least ``k`` entries ``>= v`` when ``v`` is the smallest of the row's
    ``k`` largest values (and not NaN), so one global count equal to ``B * k`` means exactly
    ``k`` per row: one ``count_nonzero`` over the whole ``(B, M)`` instead of per-row sums
    (about half the time on one CPU thread, same answer).

    Args:
        h: ``(B, M)``.
        v: ``(B, 1)`` each row's ``k``-th largest value.
        k: winners per row.
    """
    if bool(v.isnan().any()):
        return True
    return int(torch.count_nonzero(h >= v)) != h.shape[0] * k


def feedforward(x: torch.Tensor, w1_t: torch.Tensor, w3_t: torch.Tensor, k: int,
                cohorts: torch.Tensor, eps: float, rectify: bool = True) -> torch.Tensor:
    """Normalised L3 evidence of preprocessed frames.

    Args:
        x: ``(B, D)`` L1 activity (after patch normalisation).
        w1_t: ``(D, M)`` ``(l1.weight * l1.mask).T``, contiguous (in ``x``'s dtype for the
            exact step; a lower-precision copy makes the L1 product approximate).
        w3_t: ``(M, N)`` ``(l3.weight * l3.mask).T``, contiguous.
        k: L2 winners.
        cohorts: ``(N, C)`` membership.
        eps: normalisation floor.
        rectify: clamp the z-scores at 0 (only above-average evidence drives the ring).

    Returns:
        ``(B, N)`` z-scored (and rectified) evidence.
    """
    if w1_t.dtype == x.dtype:
        h = x @ w1_t  # (B, M)
    else:  # approximate: low-precision product; its many exact ties go to the lowest index
        h = (x.to(w1_t.dtype) @ w1_t).to(x.dtype)
        h = h - torch.arange(h.shape[1], device=h.device, dtype=h.dtype) * TIE_STEP
    idx = winners(h, k)  # (B, k)
    # sum the k winners' rows of w3_t: k * N reads per frame instead of M * N
    e = F.embedding_bag(idx, w3_t, mode="sum")  # (B, N)
    z = cohort_normalise(e, cohorts, eps)
    return z.clamp_min(0.0) if rectify else z


def band_diagonals(shift: torch.Tensor, max_lag: int) -> torch.Tensor | None:
    """Diagonals ``(L + 1, N)`` of a banded shift matrix, or None when it is not banded.

    ``d[l, i] = shift[i, i - l]``; None unless every non-zero entry has a lag
    ``0 <= i - j <= max_lag``.
    """
    n = shift.shape[0]
    i = torch.arange(n, device=shift.device)
    lag = i[:, None] - i[None, :]  # (N, N) next - current
    if bool((shift[(lag < 0) | (lag > max_lag)] != 0).any()):
        return None
    d = torch.zeros(max_lag + 1, n, dtype=shift.dtype, device=shift.device)
    for m in range(max_lag + 1):
        d[m, m:] = torch.diagonal(shift, -m)
    return d


def ring_scan(drive: torch.Tensor, activity: torch.Tensor, shift: torch.Tensor, decay: float,
              diagonals: torch.Tensor | None = None) -> torch.Tensor:
    """Run ``a_t = decay * a_{t-1} @ shift.T + drive_t`` over a single stream.

    Args:
        drive: ``(T, N)`` ``gain * evidence``.
        activity: ``(N,)`` activity before the first step.
        shift: ``(N, N)``.
        decay: ring decay.
        diagonals: output of :func:`band_diagonals` (None: dense products).

    Returns:
        ``(T, N)`` activity after each step.
    """
    out = torch.empty_like(drive)
    a = activity
    if diagonals is None:
        for t in range(drive.shape[0]):
            a = torch.addmv(drive[t], shift, a, alpha=decay)
            out[t] = a
        return out
    d = diagonals * decay  # (L + 1, N)
    lags = range(1, d.shape[0])
    for t in range(drive.shape[0]):
        m = torch.addcmul(drive[t], d[0], a)
        for lag in lags:
            m[lag:].addcmul_(d[lag, lag:], a[:-lag])
        a = m
        out[t] = a
    return out

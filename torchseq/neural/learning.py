"""Local learning rules of Neural SeqSLAM: recruitment, Hebbian weights, cohorts.

Pure functions. The read-out is in :mod:`torchseq.neural.readout`.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch

from torchseq.quantise import round_rows


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


BISECTION_STEPS = 60  # halvings of the threshold interval (float64 has 53 bits)


def novelty_starts(winners: np.ndarray, threshold: float) -> np.ndarray:
    """First frame of each unit when a new unit starts where the current one stops matching.

    Walks the route in order. The current unit holds frames ``s..t-1``; frame ``t`` starts
    a new unit when its code's overlap with the unit's mean code,
    ``o_t = sum_{j=s}^{t-1} |c_t & c_j| / (k (t - s))`` (1 when every frame of the unit has
    ``t``'s code, 0 when none shares a winner with it), is below ``threshold``; else it
    joins the unit. Frame 0 starts the first unit. ``threshold <= 0``: one unit;
    ``threshold > 1``: one unit per frame.

    Args:
        winners: ``(T, k)`` integer indices of each frame's ``k`` active L2 units (the binary
            k-WTA code; distinct within a row).
        threshold: the overlap below which a new unit starts.

    Returns:
        ``(U,)`` int64 ascending first frames, starting with 0.
    """
    n_frames, k = winners.shape
    if winners.size and int(winners.max()) >= winners.size:  # sparse labels: bound the sums
        winners = np.unique(winners, return_inverse=True)[1].reshape(n_frames, k)
    hidden = int(winners.max()) + 1 if winners.size else 1
    hits = np.zeros(hidden, np.int64)  # sum of the current unit's codes
    starts = [0]
    held = 0  # frames in the current unit
    # o_t < p / q  <=>  dot * q < p * k * held, in integers: exact at ties
    p, q = float(threshold).as_integer_ratio()
    for t in range(n_frames):
        row = winners[t]
        if held and int(hits[row].sum()) * q < p * k * held:
            starts.append(t)
            hits[:] = 0
            held = 0
        hits[row] += 1
        held += 1
    return np.asarray(starts, np.int64)


def recruit_by_novelty(winners: torch.Tensor | np.ndarray,
                       n_units: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Recruit exactly ``n_units`` units along the route where the codes change.

    The units are :func:`novelty_starts`'s stretches at the threshold found by bisection
    on ``[0, 2]`` (:data:`BISECTION_STEPS` halvings, stopping early at exactly ``n_units``
    stretches): the largest threshold tried that gives at most ``n_units`` stretches. If
    that is fewer (the count need not grow monotonically with the threshold, and it can
    jump: a route of identical frames is one stretch for every threshold up to 1), the
    longest stretch ``[a, b)`` (the earliest on ties) is cut in two until there are
    ``n_units``: before the frame ``t`` in ``a+1 .. b-1`` whose code shares the fewest
    winners with the previous frame's, ``|c_t & c_{t-1}|`` (the sharpest change; ties: the
    ``t`` nearest ``a + (b - a) // 2``, then the earliest). With ``n_units == T`` every
    unit is one frame, exactly as :func:`recruit_units`.

    Args:
        winners: ``(T, k)`` integer indices of each frame's active L2 units.
        n_units: units ``N`` (``1 <= N <= T``).

    Returns:
        ``(unit_of_frame (T,) int64, spans (N, 2) int64)`` as :func:`recruit_units`.
    """
    w = winners.detach().cpu().numpy() if isinstance(winners, torch.Tensor) else winners
    w = np.asarray(w)
    if w.ndim != 2 or w.shape[1] == 0 or not np.issubdtype(w.dtype, np.integer):
        raise ValueError(f"winners must be a (T, k) integer array, got {w.dtype} {w.shape}")
    n_frames = w.shape[0]
    if not 1 <= n_units <= n_frames:
        raise ValueError(f"need 1 <= n_units <= n_frames, got {n_units} and {n_frames}")
    if w.min() < 0:
        raise ValueError("winners must be non-negative unit indices")
    if (np.diff(np.sort(w, axis=1), axis=1) == 0).any():
        raise ValueError("each row of winners must hold distinct unit indices")
    if n_units == n_frames:
        return recruit_units(n_frames, n_units)
    best, _, _ = novelty_search(w, n_units)
    if best.size < n_units:
        best = _split_longest(best, _shared_with_previous(w), n_units)
    return _spans_from_starts(best, n_frames)


def novelty_search(winners: np.ndarray, n_units: int) -> tuple[np.ndarray, float, int]:
    """The bisection of :func:`recruit_by_novelty`, before any cut.

    Args:
        winners: ``(T, k)`` integer indices of each frame's active L2 units.
        n_units: most stretches ``N``.

    Returns:
        ``(starts, threshold, walks)``: :func:`novelty_starts` at the largest threshold
        tried that gives at most ``N`` stretches, that threshold, and how many walks over
        the route the search made.
    """
    best, lo, hi, walks = novelty_starts(winners, 0.0), 0.0, 2.0, 1  # one stretch at 0
    for _ in range(BISECTION_STEPS):  # count(lo) <= N < count(hi): 2.0 gives T stretches
        if best.size == n_units:
            break
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        starts = novelty_starts(winners, mid)
        walks += 1
        if starts.size <= n_units:
            lo, best = mid, starts
        else:
            hi = mid
    return best, lo, walks


def _shared_with_previous(winners: np.ndarray, chunk: int = 1024) -> np.ndarray:
    """``(T,)`` int64 ``|c_t & c_{t-1}|`` (``shared[0] = k``), in chunks of dense codes."""
    n_frames, k = winners.shape
    labels, flat = np.unique(winners, return_inverse=True)
    idx = flat.reshape(n_frames, k)
    shared = np.full(n_frames, k, np.int64)
    for lo in range(1, n_frames, chunk):
        hi = min(lo + chunk, n_frames)
        code = np.zeros((hi - lo + 1, labels.size), bool)
        np.put_along_axis(code, idx[lo - 1:hi], True, axis=1)
        shared[lo:hi] = (code[1:] & code[:-1]).sum(1)
    return shared


def _split_longest(starts: np.ndarray, shared: np.ndarray, n_units: int) -> np.ndarray:
    """Cut the longest stretch at its sharpest code change until there are ``n_units``.

    See :func:`recruit_by_novelty`.
    """
    bounds = list(starts.tolist()) + [shared.size]
    while len(bounds) - 1 < n_units:
        i = int(np.diff(bounds).argmax())  # first index on ties
        a, b = bounds[i], bounds[i + 1]
        t = np.arange(a + 1, b)
        order = np.lexsort((t, np.abs(t - (a + (b - a) // 2)), shared[a + 1:b]))
        bounds.insert(i + 1, int(t[order[0]]))
    return np.asarray(bounds[:-1], np.int64)


def _spans_from_starts(starts: np.ndarray, n_frames: int) -> tuple[torch.Tensor, torch.Tensor]:
    start = torch.from_numpy(starts)
    end = torch.cat([start[1:], torch.tensor([n_frames])])
    unit = torch.repeat_interleave(torch.arange(start.numel()), end - start)
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
    (:func:`torchseq.quantise.round_rows`).

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

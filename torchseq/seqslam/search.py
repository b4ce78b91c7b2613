"""Sequence search: score every straight trajectory through the enhanced difference matrix.

For query centre ``N`` the trajectory of start ``s`` and velocity ``v`` visits reference row
``min(s + floor(k v), R)`` at query column ``N - ds/2 + k``, ``k = 0..ds``; row ``R`` is an
appended row of ``+inf`` (OpenSeqSLAM), so trajectories that run off the reference score
``inf``. Tensorised as shifted slices: for a block of queries, velocity ``v`` and step ``k``
the costs of all starts of all queries are one slice ``D'^T[cols + k, off_k : off_k + L]``
of the query-major matrix, summed over ``k`` (no gather, no Python loop over frames or
references; only the handful of velocities and the ``ds + 1`` steps are looped).
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from tqdm import tqdm

from torchseq._checks import check_not_empty, check_shape
from torchseq.seqslam._parallel import run_blocks

_EPS = 1e-9
# Score blocks on CPU are kept about this size (elements) so they stay in the L2 cache.
CPU_BLOCK_ELEMENTS = 2**18
MAX_VELOCITIES = 4096  # trajectories per start: counted before any is enumerated


def velocities(ds: int, vmin: float = 0.8, vmax: float = 1.2) -> list[float]:
    """Trajectory velocities ``m / ds`` for every integer ``m`` in ``[vmin ds, vmax ds]``.

    Args:
        ds: sequence length (already even).
        vmin: slowest velocity, reference frames per query frame.
        vmax: fastest velocity.

    Returns:
        Increasing list of velocities (``0.8*10`` counts as 8 thanks to a small epsilon).

    Raises:
        ValueError: no velocity in the range, or more than ``MAX_VELOCITIES``.
    """
    if (ds < 1 or not vmin > 0 or not vmax >= vmin
            or not (math.isfinite(vmin) and math.isfinite(vmax))):
        raise ValueError(f"need ds >= 1 and 0 < vmin <= vmax, got ds={ds}, [{vmin}, {vmax}]")
    lo, hi = math.ceil(vmin * ds - _EPS), math.floor(vmax * ds + _EPS)
    if hi < lo:
        raise ValueError(f"no velocity m/{ds} lies in [{vmin}, {vmax}]: widen the range")
    if hi - lo >= MAX_VELOCITIES:
        raise ValueError(f"ds={ds} and velocities [{vmin}, {vmax}] make {hi - lo + 1} "
                         f"trajectories per start, more than {MAX_VELOCITIES}: narrow them")
    return [m / ds for m in range(lo, hi + 1)]


def trajectory_offsets(ds: int, speeds: Sequence[float]) -> list[list[int]]:
    """``floor(k v)`` for ``k = 0..ds``, one list per velocity."""
    return [[math.floor(k * v + _EPS) for k in range(ds + 1)] for v in speeds]


def trajectory_scores(
    d_t: torch.Tensor, first: int, last: int, ds: int, offsets: list[list[int]],
    with_velocity: bool = False,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Best (over velocities) score of every start for query centres ``first .. last - 1``.

    Args:
        d_t: ``(Q, R)`` query-major enhanced difference matrix.
        first: first query centre (``>= ds / 2``).
        last: one past the last centre (``<= Q - ds / 2``).
        ds: even sequence length.
        offsets: per velocity, the row offsets of the ``ds + 1`` steps.
        with_velocity: also return the index of the best velocity (ties -> slowest).

    Returns:
        ``(C, R + 1)`` scores (start ``R`` is the appended inf row) and ``(C, R + 1)`` int64
        velocity indices or None.
    """
    n_ref = d_t.shape[1]
    rows = last - first
    base = first - ds // 2
    best = torch.full((rows, n_ref + 1), math.inf, dtype=d_t.dtype, device=d_t.device)
    best_v = None
    if with_velocity:
        best_v = torch.zeros(best.shape, dtype=torch.int64, device=d_t.device)
    acc = torch.empty_like(best)
    for vi, off in enumerate(offsets):
        width = max(0, n_ref - off[-1])  # starts whose whole trajectory stays inside
        acc.fill_(math.inf)
        if width:
            head = acc[:, :width]
            head.copy_(d_t[base:base + rows, off[0]:off[0] + width])
            for k in range(1, ds + 1):
                head += d_t[base + k:base + k + rows, off[k]:off[k] + width]
        if with_velocity:
            best_v.masked_fill_(acc < best, vi)
        torch.minimum(best, acc, out=best)
    return best, best_v


def start_velocity(d_t: torch.Tensor, first: int, ds: int, offsets: list[list[int]],
                   starts: torch.Tensor) -> torch.Tensor:
    """Best velocity index of chosen starts only (ties -> slowest).

    The same sums in the same order as ``trajectory_scores(..., with_velocity=True)``, so
    the same index, at the cost of the chosen starts instead of all ``R + 1``.

    Args:
        d_t: ``(Q, R)`` query-major enhanced difference matrix.
        first: query centre of row 0 of ``starts``.
        ds: even sequence length.
        offsets: per velocity, the row offsets of the ``ds + 1`` steps.
        starts: ``(C, m)`` int64 starts of centres ``first .. first + C - 1`` (``R``: the
            inf row).

    Returns:
        ``(C, m)`` int64 velocity indices (0 where every velocity runs off the reference).
    """
    n_ref = d_t.shape[1]
    cols = (first - ds // 2 + torch.arange(len(starts), device=d_t.device))[:, None]
    best = torch.full(starts.shape, math.inf, dtype=d_t.dtype, device=d_t.device)
    best_v = torch.zeros_like(starts)
    for vi, off in enumerate(offsets):
        width = n_ref - off[-1]  # starts whose whole trajectory stays inside
        if width <= 0:
            continue
        inside = starts < width
        s = starts.clamp_max(width - 1)
        acc = d_t[cols, s + off[0]]
        for k in range(1, ds + 1):
            acc += d_t[cols + k, s + off[k]]
        acc.masked_fill_(~inside, math.inf)
        best_v.masked_fill_(acc < best, vi)
        torch.minimum(best, acc, out=best)
    return best_v


def uniqueness_ratio(best: torch.Tensor, second: torch.Tensor,
                     shift: float = 0.0) -> torch.Tensor:
    """OpenSeqSLAM's uniqueness: ``(best + shift) / (second + shift)``, elementwise.

    ``second`` is the best score outside the exclusion window; ``shift`` a constant added to
    every finite trajectory score (0 for scores taken as they are). 0 when ``second`` is inf,
    1 when both are 0 (nothing is distinctive), NaN when ``best`` is inf.
    """
    best, second = best + shift, second + shift
    ratio = torch.where(second > 0, best / torch.where(second > 0, second, 1.0),
                        torch.ones_like(best))  # 0 / 0: nothing is distinctive -> 1
    return torch.where(torch.isfinite(best), ratio, torch.full_like(ratio, math.nan))


def _lowest_tied(scores: torch.Tensor, cand: torch.Tensor, vals: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Top-K ``(C, K)`` starts whose ties with the K-th score are the lowest starts.

    ``topk`` keeps *some* of the starts tied with the K-th smallest score; where it left out
    a lower one, the row is redone: every start below the K-th score, then the lowest tied
    starts until K (the rule of a stable sort, as the loop oracle ranks). Only rows with a
    finite K-th score tied beyond the kept ones are touched (inf starts report -1 anyway).
    """
    kth = vals[:, -1:]
    fix = (((scores == kth).sum(1) > (vals == kth).sum(1)) & torch.isfinite(kth[:, 0]))
    rows = fix.nonzero()[:, 0]
    if len(rows) == 0:
        return cand, vals
    s, t, k = scores[rows], kth[rows], cand.shape[1]
    below, tied = s < t, s == t
    take = below | (tied & (tied.cumsum(1) <= k - below.sum(1, keepdim=True)))
    cand, vals = cand.clone(), vals.clone()
    cand[rows] = take.nonzero()[:, 1].view(-1, k)  # exactly K per row, in start order
    vals[rows] = s.gather(1, cand[rows])
    return cand, vals


def _offsets_of(centre, starts: torch.Tensor, ds: int) -> torch.Tensor:
    """``(C, m)`` offsets from ``(C, m)`` starts to the reference they report.

    ``centre``: None (``ds / 2``), a ``(C, R + 1)`` tensor, or a function of the starts.
    """
    if centre is None:
        return torch.full_like(starts, ds // 2)
    return centre(starts) if callable(centre) else centre.gather(1, starts)


def _rank(
    scores: torch.Tensor, ds: int, n_ref: int, rwindow: int, top_k: int,
    centre=None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`rank_scores` with the best score outside the window in place of the ratio.

    ``centre`` may also be a function of ``(C, m)`` starts (see :func:`_offsets_of`).
    A fifth result: ``(C, top_k)`` the ranked references' scores (their best start's; NaN
    where the reference is ``-1``).
    """
    rows, n_starts = scores.shape
    start = scores.argmin(dim=1)  # first minimum: ties -> lowest start
    best = scores.gather(1, start[:, None])[:, 0]
    idx = torch.arange(n_starts, device=scores.device)
    half = rwindow // 2
    inside = (idx[None] >= (start - half)[:, None]) & (idx[None] <= (start + half)[:, None])
    second = scores.masked_fill(inside, math.inf).min(dim=1).values
    m = min(2 * top_k, n_starts)
    while True:  # widen the prefix until it holds top_k distinct places (or all of them)
        cand, vals = _top_starts(scores, m)
        shift = _offsets_of(centre, cand, ds)
        place = torch.where(torch.isfinite(vals), (cand + shift).clamp_max(n_ref - 1), -1)
        ranked, found, ranked_vals = _first_distinct(place, top_k, vals)
        if m == n_starts or bool(((found >= top_k) | (place[:, -1] < 0)).all()):
            return start, best, second, ranked, ranked_vals
        m = min(2 * m, n_starts)


def _top_starts(scores: torch.Tensor, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(C, m)`` starts and scores: the first ``m`` of a stable sort by score."""
    vals, cand = torch.topk(scores, m, dim=1, largest=False, sorted=True)
    cand, vals = _lowest_tied(scores, cand, vals)
    order = cand.argsort(dim=1)  # make ties come out lowest start first
    cand, vals = cand.gather(1, order), vals.gather(1, order)
    order = vals.argsort(dim=1, stable=True)
    return cand.gather(1, order), vals.gather(1, order)


def _first_distinct(place: torch.Tensor, k: int, vals: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per row, the first ``k`` distinct places ``>= 0`` in order, and how many it holds.

    Returns ``(C, k)`` places (``-1`` padded), ``(C,)`` counts of distinct places and
    ``(C, k)`` the ``vals`` of the places kept (NaN padded).
    Starts that report the same place (``match_at="trajectory"``: ``s + floor(v ds/2)`` with
    each start's own velocity, or clamped to ``R - 1``) count once, at their best-ranked
    start; without this a top-10 list repeats places (corridor: 7 distinct of 10).
    """
    rows, m = place.shape
    by_place, pos = place.sort(dim=1, stable=True)  # equal places keep their rank order
    first = torch.ones_like(by_place, dtype=torch.bool)
    first[:, 1:] = by_place[:, 1:] != by_place[:, :-1]
    keep = torch.zeros_like(first).scatter_(1, pos, first) & (place >= 0)
    rank = keep.cumsum(1) - 1
    sel = keep & (rank < k)
    out = place.new_full((rows, k), -1)
    out_vals = vals.new_full((rows, k), math.nan)
    r, c = sel.nonzero(as_tuple=True)
    out[r, rank[r, c]] = place[r, c]
    out_vals[r, rank[r, c]] = vals[r, c]
    return out, keep.sum(1), out_vals


def rank_scores(
    scores: torch.Tensor, ds: int, n_ref: int, rwindow: int, top_k: int,
    centre: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Best start, uniqueness ratio and top-K candidates from ``(C, R + 1)`` start scores.

    Args:
        scores: ``(C, R + 1)`` best score of each start.
        ds: even sequence length.
        n_ref: reference frames ``R``.
        rwindow: uniqueness exclusion window.
        top_k: candidates kept.
        centre: ``(C, R + 1)`` int64 offset from each start to the reference it reports
            (None: ``ds / 2`` for all, OpenSeqSLAM).

    Returns:
        ``(C,)`` best start, ``(C,)`` best score, ``(C,)`` uniqueness
        (:func:`uniqueness_ratio` of the best and the best outside ``start +- rwindow // 2``)
        and ``(C, top_k)`` ranked references (``start + ds / 2`` clamped to ``R - 1``, ``-1``
        for inf scores or when fewer remain), each reference once, at the rank of its best
        start. Ties go to the lower start: the best start is the first minimum, and the
        ranking is a stable sort's, also where ties straddle the K-th place.
    """
    start, best, second, ranked, _ = _rank(scores, ds, n_ref, rwindow, top_k, centre)
    return start, best, uniqueness_ratio(best, second), ranked


def search(
    enhanced: torch.Tensor,
    ds: int,
    speeds: Sequence[float],
    rwindow: int = 10,
    top_k: int = 10,
    max_chunk_elements: int = 2**26,
    progress: bool = False,
    match_at: str = "start",
    threads: int = 1,
    edges: bool = False,
    ranked_score: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Match every query by its best trajectory (OpenSeqSLAM's ``findMatches``).

    Args:
        enhanced: ``(R, Q)`` contrast-enhanced difference matrix.
        ds: sequence length; odd values are rounded up to even.
        speeds: trajectory velocities (see :func:`velocities`).
        rwindow: uniqueness exclusion window.
        top_k: ranked candidates per query.
        max_chunk_elements: bound on the elements of each ``(C, R + 1)`` score block.
        progress: show a progress bar over query blocks.
        match_at: ``"start"``: a start ``s`` reports ``s + ds/2`` (OpenSeqSLAM);
            ``"trajectory"``: ``s + floor(v ds/2)`` with ``v`` its best velocity (ties ->
            slowest), the row its trajectory crosses at the query centre.
        threads: CPU worker threads, each taking whole blocks of queries.
        edges: also match the first and last ``ds/2`` queries (no centred window covers
            them): query ``N < ds/2`` from its leading window (columns ``N .. N + ds``),
            reporting the start row ``s``; query ``N > Q - 1 - ds/2`` from its trailing
            window (``N - ds .. N``), reporting the end row ``s + floor(ds v_best)``; both
            clamped to ``R - 1``.
        ranked_score: a ``(Q, top_k)`` tensor that receives each ranked reference's
            trajectory score (the best start reporting it; NaN where ``ranked`` is ``-1``),
            for recall@K with ties (:func:`torchseq.metrics.recall_at_ks`); None: not kept.

    Returns:
        ``match (Q,)`` int64 reference (``-1`` when unscored or no finite trajectory),
        ``best_score (Q,)`` (NaN when unscored), ``uniqueness (Q,)`` (NaN when no match) and
        ``ranked (Q, top_k)`` int64 (``-1`` when none), all on the input's device.
    """
    match, best, second, ranked = search_scores(enhanced, ds, speeds, rwindow, top_k,
                                                max_chunk_elements, progress, match_at,
                                                threads, edges, ranked_score)
    return match, best, uniqueness_ratio(best, second), ranked


def search_scores(
    enhanced: torch.Tensor,
    ds: int,
    speeds: Sequence[float],
    rwindow: int = 10,
    top_k: int = 10,
    max_chunk_elements: int = 2**26,
    progress: bool = False,
    match_at: str = "start",
    threads: int = 1,
    edges: bool = False,
    ranked_score: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`search`, returning the best score outside the exclusion window instead of the ratio.

    Same arguments as :func:`search`. For callers that add a constant to every trajectory
    score afterwards (:func:`uniqueness_ratio` takes it).

    Returns:
        ``match (Q,)``, ``best_score (Q,)``, ``second (Q,)`` (the best score outside
        ``start +- rwindow // 2``; NaN when unscored) and ``ranked (Q, top_k)``.
    """
    check_shape(enhanced, ("R", "Q"), "enhanced difference matrix")
    check_not_empty(enhanced, "enhanced difference matrix")
    if len(speeds) == 0 or min(speeds) <= 0:
        raise ValueError("speeds must be a non-empty list of positive velocities")
    if match_at not in ("start", "trajectory"):
        raise ValueError(f"match_at must be 'start' or 'trajectory', got {match_at!r}")
    ds = int(ds) + int(ds) % 2
    n_ref, n_query = enhanced.shape
    if n_query < ds + 1:
        raise ValueError(f"need at least ds + 1 = {ds + 1} query frames, got {n_query}")
    d_t = enhanced.T.contiguous()  # (Q, R); free when the input is a transposed view
    offsets = trajectory_offsets(ds, speeds)
    by_velocity = match_at == "trajectory"
    half = torch.tensor([off[ds // 2] for off in offsets], device=enhanced.device)
    dev, dtype = enhanced.device, enhanced.dtype
    match = torch.full((n_query,), -1, dtype=torch.int64, device=dev)
    best_score = torch.full((n_query,), math.nan, dtype=dtype, device=dev)
    second_score = torch.full((n_query,), math.nan, dtype=dtype, device=dev)
    ranked = torch.full((n_query, top_k), -1, dtype=torch.int64, device=dev)
    if ranked_score is not None:
        if tuple(ranked_score.shape) != (n_query, top_k):
            raise ValueError(f"ranked_score must be ({n_query}, {top_k}), got "
                             f"{tuple(ranked_score.shape)}")
        ranked_score.fill_(math.nan)
    budget = max_chunk_elements
    if dev.type != "cuda":
        budget = min(budget, CPU_BLOCK_ELEMENTS)
    rows = max(1, budget // (n_ref + 1))
    first, stop = ds // 2, n_query - ds // 2
    bar = tqdm(total=max(0, stop - first), desc="sequence search", disable=not progress,
               leave=False)

    def block(c0: int) -> None:
        c1 = min(c0 + rows, stop)
        scores, _ = trajectory_scores(d_t, c0, c1, ds, offsets)
        centre = None  # offset to report: ds/2, or that of each ranked start's best velocity
        if by_velocity:
            def centre(starts):
                return half[start_velocity(d_t, c0, ds, offsets, starts)]
        start, best, second, rank, rank_vals = _rank(scores, ds, n_ref, rwindow, top_k,
                                                     centre)
        ok = torch.isfinite(best)
        shift = _offsets_of(centre, start[:, None], ds)[:, 0]
        match[c0:c1] = torch.where(ok, (start + shift).clamp_max(n_ref - 1), -1)
        best_score[c0:c1] = best
        second_score[c0:c1] = second
        ranked[c0:c1] = rank
        if ranked_score is not None:
            ranked_score[c0:c1] = rank_vals.to(ranked_score)
        bar.update(c1 - c0)

    run_blocks(block, range(first, stop, rows), threads, dev)
    bar.close()
    if edges:
        ends = torch.tensor([off[-1] for off in offsets], device=dev)
        # the leading window of query N (N < ds/2, N + ds < Q) is the centred window of
        # N + ds/2; the trailing window of N (N >= Q - ds/2, N >= ds) that of N - ds/2
        lead = range(0, min(first, n_query - ds))
        trail = range(max(stop, ds), n_query)
        for queries, shift_c, end in ((lead, first, False), (trail, -first, True)):
            if len(queries) == 0:
                continue
            centres = range(queries[0] + shift_c, queries[-1] + 1 + shift_c)
            scores, best_v = trajectory_scores(d_t, centres[0], centres[-1] + 1, ds, offsets,
                                               with_velocity=True)
            centre = ends[best_v] if end else torch.zeros_like(best_v)
            start, best, second, rank, rank_vals = _rank(scores, ds, n_ref, rwindow, top_k,
                                                         centre)
            if ranked_score is not None:
                ranked_score[queries[0]:queries[-1] + 1] = rank_vals.to(ranked_score)
            q = torch.arange(queries[0], queries[-1] + 1, device=dev)
            shift = centre.gather(1, start[:, None])[:, 0]
            match[q] = torch.where(torch.isfinite(best), (start + shift).clamp_max(n_ref - 1), -1)
            best_score[q], second_score[q], ranked[q] = best, second, rank
    return match, best_score, second_score, ranked

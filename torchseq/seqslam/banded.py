"""SeqSLAM without the full matrices: bands of query columns, difference -> enhance -> search.

Every stage works along the reference axis of each query column (contrast enhancement) or
over ``ds + 1`` neighbouring columns (search), so a band of ``B`` query centres needs only the
``B + ds`` columns around it: memory is O(B R), not O(R Q). The L1 kernel is chosen once for
the whole ``R x Q`` run (``difference.l1_choice``) and the reference's codes (thermometer, or
uint8 for ``"sad"``) are built once and reused by every band.

OpenSeqSLAM subtracts the *global* minimum ``m`` of the enhanced matrix, unknown until the
last band. Every trajectory takes exactly ``ds + 1`` entries, so the subtraction shifts every
finite trajectory score by ``-(ds + 1) m``: best starts, velocities and rankings do not
depend on it. Scores are summed in float64 without the shift, and the shift is applied at
the end to the best score and to the uniqueness ratio (:func:`uniqueness_ratio`).
"""

from __future__ import annotations

import math

import torch

from torchseq.area import Partial, area_mean, finish, reduce_rows
from torchseq.seqslam._parallel import resolve_threads
from torchseq.seqslam.config import SeqSLAMConfig
from torchseq.seqslam.difference import (
    _l1_sad,
    _l1_thermometer,
    difference_with_kernel,
    l1_choice,
    sad_codes,
    thermometer_codes,
    thermometer_levels,
)
from torchseq.seqslam.enhance import enhance_contrast
from torchseq.seqslam.search import search_scores, uniqueness_ratio

PREVIEW_SIDE = 1024  # the reduced copy of the enhanced matrix is at most this on a side


def preview(enhanced: torch.Tensor) -> torch.Tensor:
    """``(R, Q)`` -> ``(min(R, PREVIEW_SIDE), min(Q, PREVIEW_SIDE))`` float32 reduced copy.

    The block means of :func:`torchseq.area.area_mean` (non-finite entries skipped).
    """
    return area_mean(enhanced, (PREVIEW_SIDE, PREVIEW_SIDE))


def band_centres(n_ref: int, config: SeqSLAMConfig) -> int:
    """Query centres per band, so a band's float64 temporaries stay near the chunk budget."""
    per_column = 8 * n_ref * 3  # bytes: float64 scores and about two float32 copies
    return max(1, (4 * config.max_chunk_elements) // per_column)


def match_banded(reference: torch.Tensor, query: torch.Tensor, config: SeqSLAMConfig,
                 speeds: list[float], progress: bool = False) -> dict:
    """All of :class:`SeqSLAM`'s outputs except the full matrices, band by band.

    Args:
        reference: ``(R, D)`` descriptors (working dtype and device).
        query: ``(Q, D)`` descriptors, ``Q >= ds + 1``.
        config: validated configuration.
        speeds: trajectory velocities.
        progress: unused per band (kept for the signature of the full path).

    Returns:
        dict with ``match``, ``best``, ``ratio`` ``(Q,)``, ``ranked``, ``ranked_score (Q, top_k)``,
        ``preview`` ``(R', Q')``, ``kernel``, ``threads`` and ``seconds``.
    """
    import time

    c = config
    ds, half = c.sequence_length, c.sequence_length // 2
    n_ref, n_query = reference.shape[0], query.shape[0]
    budget = c.max_chunk_elements
    workers = resolve_threads(c.threads)
    seconds = {"difference": 0.0, "enhance": 0.0, "search": 0.0}
    t = time.perf_counter()
    levels = thermometer_levels(reference, query, budget) if c.metric == "l1" else None
    if levels is not None and levels[0].numel() == 0:
        levels = None  # every value equal: the general path gives the zero matrix
    # the kernel for the whole run (l1_choice's size rule on R x Q x D), the reference's
    # codes built once
    kernel = lo = None
    if c.metric == "l1":
        kernel, lo = l1_choice(reference, query, levels, budget)
    per_band = kernel if kernel == "cdist" else None  # else (l2, cosine) the bands' own
    codes = weights = None
    if kernel == "sad":
        codes = sad_codes(reference, lo, max(1, budget // reference.shape[1]))
    elif levels is not None:
        weights = levels[1].to(reference.device) if levels[1] is not None else None
        codes = thermometer_codes(reference, levels[0], weights)
    seconds["difference"] += time.perf_counter() - t

    def enhanced_columns(q0: int, q1: int) -> torch.Tensor:
        """``(R, q1 - q0)`` enhanced columns of queries ``q0 .. q1 - 1``, no min subtraction."""
        nonlocal kernel
        t = time.perf_counter()
        if kernel in ("sad", "thermometer"):
            d_t = torch.empty(q1 - q0, n_ref, dtype=reference.dtype, device=reference.device)
            if kernel == "sad":
                _l1_sad(reference, query[q0:q1], d_t, lo, budget, workers, codes)
            else:
                _l1_thermometer(reference, query[q0:q1], d_t, levels[0], weights, budget,
                                workers, codes)
            d = d_t.T
        else:
            d, kernel = difference_with_kernel(reference, query[q0:q1], c.metric, budget,
                                               workers, per_band)
        seconds["difference"] += time.perf_counter() - t
        t = time.perf_counter()
        e = enhance_contrast(d, c.enhance_window, False, budget, workers)
        seconds["enhance"] += time.perf_counter() - t
        return e

    dev = reference.device
    match = torch.full((n_query,), -1, dtype=torch.int64, device=dev)
    best = torch.full((n_query,), math.nan, dtype=torch.float64, device=dev)
    second = torch.full((n_query,), math.nan, dtype=torch.float64, device=dev)
    ranked = torch.full((n_query, c.top_k), -1, dtype=torch.int64, device=dev)
    ranked_score = torch.full((n_query, c.top_k), math.nan, dtype=torch.float64, device=dev)
    # the preview reduced along R band by band (torchseq.area); the finite counts are kept
    # only once a band holds a non-finite entry (until then every weight is 1)
    rows = torch.empty(n_query, min(n_ref, PREVIEW_SIDE), dtype=torch.float32, device=dev)
    weights = None
    low = math.inf
    step = band_centres(n_ref, c)
    args = (ds, speeds, c.rwindow, c.top_k, budget, False, c.match_rule, workers)
    for c0 in range(half, n_query - half, step):
        c1 = min(c0 + step, n_query - half)
        e = enhanced_columns(c0 - half, c1 + half)
        low = min(low, float(e.min()))
        part = reduce_rows(e.T, PREVIEW_SIDE)
        rows[c0 - half:c1 + half] = part.values
        if weights is None and part.weights is not None:
            weights = torch.ones_like(rows)
        if weights is not None:
            weights[c0 - half:c1 + half] = 1.0 if part.weights is None else part.weights
        t = time.perf_counter()
        rs = torch.empty(e.shape[1], c.top_k, dtype=torch.float64, device=dev)
        m, b, s, r = search_scores(e.double(), *args, ranked_score=rs)
        own = slice(half, half + c1 - c0)
        match[c0:c1], best[c0:c1], second[c0:c1], ranked[c0:c1] = m[own], b[own], s[own], r[own]
        ranked_score[c0:c1] = rs[own]
        seconds["search"] += time.perf_counter() - t
    shift = -(ds + 1) * low
    if c.edges:  # the first and last 3 ds / 2 columns again, shifted as the full path does
        n_edge = min(n_query, ds + half)
        for q0, take in ((0, slice(0, half)), (n_query - n_edge, slice(n_edge - half, n_edge))):
            e = enhanced_columns(q0, q0 + n_edge) - low
            t = time.perf_counter()
            rs = torch.empty(e.shape[1], c.top_k, dtype=torch.float64, device=dev)
            m, b, s, r = search_scores(e.double(), *args[:-1], workers, True, rs)
            q = slice(q0 + take.start, q0 + take.stop)
            match[q], ranked[q] = m[take], r[take]
            ranked_score[q] = rs[take] - shift  # undone below
            best[q], second[q] = b[take] - shift, s[take] - shift  # undone below
            seconds["search"] += time.perf_counter() - t
    return {"match": match, "best": best + shift, "ratio": uniqueness_ratio(best, second, shift),
            "ranked": ranked, "ranked_score": ranked_score + shift,
            "preview": finish(Partial(rows, weights), PREVIEW_SIDE) - low,
            "kernel": kernel, "threads": workers, "seconds": seconds}

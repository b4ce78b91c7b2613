"""A plain, loop-based SeqSLAM written from the OpenSeqSLAM description (NumPy, float64).

Independent of ``torchseq.seqslam`` on purpose (it must not import it): it mirrors the MATLAB
structure (loop over queries, then starts, then velocities) and serves as the tests' oracle
and the benchmark's "loop" baseline.
"""

from __future__ import annotations

import math

import numpy as np


def oracle_difference(ref: np.ndarray, query: np.ndarray, metric: str = "l1") -> np.ndarray:
    """(R, D), (Q, D) -> (R, Q) distances, one pair at a time."""
    ref = np.asarray(ref, np.float64)
    query = np.asarray(query, np.float64)
    out = np.zeros((len(ref), len(query)))
    for i in range(len(ref)):
        for j in range(len(query)):
            a, b = ref[i], query[j]
            if metric == "l1":
                out[i, j] = np.sum(np.abs(a - b))
            elif metric == "l2":
                out[i, j] = math.sqrt(np.sum((a - b) ** 2))
            elif metric == "cosine":
                na, nb = np.linalg.norm(a), np.linalg.norm(b)
                out[i, j] = 1.0 - (float(a @ b) / (na * nb) if na > 0 and nb > 0 else 0.0)
            else:
                raise ValueError(metric)
    return out


def oracle_enhance(d: np.ndarray, window: int = 10, subtract_min: bool = True) -> np.ndarray:
    """Local contrast enhancement, one entry at a time (std 0 -> 0)."""
    d = np.asarray(d, np.float64)
    n_ref, n_query = d.shape
    out = np.zeros_like(d)
    half = window // 2
    for i in range(n_ref):
        a, b = max(0, i - half), min(n_ref - 1, i + half)
        for j in range(n_query):
            vals = d[a:b + 1, j]
            mean = vals.sum() / len(vals)
            std = math.sqrt(((vals - mean) ** 2).sum() / (len(vals) - 1))
            out[i, j] = 0.0 if std == 0 else (d[i, j] - mean) / std
    if subtract_min:
        out = out - out.min()
    return out


def oracle_velocities(ds: int, vmin: float, vmax: float) -> list[tuple[int, int]]:
    """Velocities as exact fractions ``(m, ds)``, m from ceil(vmin ds) to floor(vmax ds)."""
    lo = math.ceil(round(vmin * ds, 6))
    hi = math.floor(round(vmax * ds, 6))
    return [(m, ds) for m in range(lo, hi + 1)]


def _scores_for_window(dext: np.ndarray, col0: int, ds: int, vels):
    """Scores of every start 0..R (dext has the inf row R) and the best velocity index."""
    n_rows = dext.shape[0]  # R + 1
    score = np.full(n_rows, np.inf)
    best_v = np.zeros(n_rows, dtype=int)
    for s in range(n_rows):
        for vi, (m, den) in enumerate(vels):
            cost = 0.0
            for k in range(ds + 1):
                row = min(s + (k * m) // den, n_rows - 1)
                cost += dext[row, col0 + k]
            if cost < score[s]:
                score[s], best_v[s] = cost, vi
    return score, best_v


def _uniqueness(score: np.ndarray, s: int, rwindow: int) -> float:
    half = rwindow // 2
    outside = [score[x] for x in range(len(score)) if not (s - half <= x <= s + half)]
    second = min(outside) if outside else np.inf
    if second == 0:
        return 1.0
    return float(score[s] / second)


def rank_places(score: np.ndarray, report, top_k: int) -> np.ndarray:
    """Starts in a stable sort by score, each reporting ``report(start)``; a place already
    listed is skipped (its best start listed it); the first ``top_k`` places, -1 padded."""
    out = []
    for x in np.argsort(score, kind="stable"):
        if len(out) == top_k or not np.isfinite(score[x]):
            break
        if report(x) not in out:
            out.append(report(x))
    return np.array(out + [-1] * (top_k - len(out)))


def oracle_seqslam(enhanced: np.ndarray, ds: int = 10, vmin: float = 0.8, vmax: float = 1.2,
                   rwindow: int = 10, top_k: int = 10, match_at: str = "start",
                   edges: bool = False):
    """OpenSeqSLAM's findMatches with loops. Returns match, best score, uniqueness, ranked.

    ``match_at="trajectory"`` reports, for a start ``s`` with best velocity ``m/ds``, the row
    its trajectory crosses at the centre column, ``s + (ds/2 * m) // ds``. ``edges=True``
    also scores the first ds/2 queries from the window that starts at them (reporting ``s``)
    and the last ds/2 from the window that ends at them (reporting ``s + (ds m) // ds``).
    Ranked candidates are distinct places (:func:`rank_places`).
    """
    ds = ds + ds % 2
    n_ref, n_query = enhanced.shape
    dext = np.vstack([np.asarray(enhanced, np.float64), np.full((1, n_query), np.inf)])
    vels = oracle_velocities(ds, vmin, vmax)
    match = np.full(n_query, -1)
    best = np.full(n_query, np.nan)
    uniq = np.full(n_query, np.nan)
    ranked = np.full((n_query, top_k), -1)
    for n in range(n_query):
        if ds // 2 <= n < n_query - ds // 2:
            col0, at = n - ds // 2, match_at  # the centred window
        elif not edges:
            continue
        elif n < ds // 2 and n + ds <= n_query - 1:
            col0, at = n, "first"  # leading window: the query is its first column
        elif n >= n_query - ds // 2 and n - ds >= 0:
            col0, at = n - ds, "last"  # trailing window: the query is its last column
        else:
            continue  # too few query frames for a whole window on that side
        score, best_v = _scores_for_window(dext, col0, ds, vels)

        def report(x):
            if at == "start":
                return min(x + ds // 2, n_ref - 1)
            step = {"trajectory": ds // 2, "first": 0, "last": ds}[at]
            m, den = vels[best_v[x]]
            return min(x + (step * m) // den, n_ref - 1)

        s = int(np.argmin(score))
        best[n] = score[s]
        ranked[n] = rank_places(score, report, top_k)
        if not np.isfinite(score[s]):
            continue
        match[n] = report(s)
        uniq[n] = _uniqueness(score, s, rwindow)
    return match, best, uniq, ranked


# MATLAB's rgb2gray weights, written out again here (the oracle imports nothing from torchseq)
_RGB2GRAY = (0.298936021293775, 0.587043074451121, 0.114020904255103)


def _round(v: float) -> float:
    """MATLAB's round: halves away from zero (NaN stays NaN)."""
    if math.isnan(v):
        return v
    return math.floor(abs(v) + 0.5) * (1 if v >= 0 else -1)


def _uint8(v: float) -> int:
    """MATLAB's assignment of a double to uint8: NaN -> 0, round halves away, saturate."""
    if math.isnan(v):
        return 0
    return int(min(255, max(0, _round(v))))


def oracle_openseqslam_descriptors(frames: np.ndarray, patch: int = 8) -> np.ndarray:
    """OpenSeqSLAM's preprocessing of frames already at the working size, pixel by pixel.

    ``frames`` (T, H, W) grey or (T, H, W, 3) RGB with uint8 values. Grey: rgb2gray on
    uint8 (weights above, stored as uint8); then per ``patch`` block
    ``127 + round((p - mean) / std)`` with the sample std, stored as uint8 (std 0 gives
    0/0 = NaN, stored as 0). Returns (T, H * W) float64.
    """
    frames = np.asarray(frames, np.float64)
    t, h, w = frames.shape[:3]
    out = np.zeros((t, h, w))
    for f in range(t):
        grey = np.zeros((h, w))
        for y in range(h):
            for x in range(w):
                if frames.ndim == 4:
                    r, g, b = frames[f, y, x]
                    grey[y, x] = _uint8(_RGB2GRAY[0] * r + _RGB2GRAY[1] * g + _RGB2GRAY[2] * b)
                else:
                    grey[y, x] = _uint8(frames[f, y, x])
        for by in range(0, h, patch):
            for bx in range(0, w, patch):
                pp = [grey[y, x] for y in range(by, by + patch) for x in range(bx, bx + patch)]
                mean = sum(pp) / len(pp)
                std = math.sqrt(sum((p - mean) ** 2 for p in pp) / (len(pp) - 1))
                for y in range(by, by + patch):
                    for x in range(bx, bx + patch):
                        z = (grey[y, x] - mean) / std if std > 0 else math.nan
                        out[f, y, x] = _uint8(127 + _round(z))
    return out.reshape(t, -1)


def oracle_streaming(difference: np.ndarray, ds: int = 10, vmin: float = 0.8,
                     vmax: float = 1.2, rwindow: int = 10, window: int = 10):
    """Trailing-window rule: enhancement per column, column-minimum subtraction, and the
    reference at the trajectory end. Returns (Q,) reference and uniqueness."""
    ds = ds + ds % 2
    e = oracle_enhance(difference, window, subtract_min=False)
    e = e - e.min(axis=0, keepdims=True)
    n_ref, n_query = e.shape
    dext = np.vstack([e, np.full((1, n_query), np.inf)])
    vels = oracle_velocities(ds, vmin, vmax)
    ref = np.full(n_query, -1)
    uniq = np.full(n_query, np.nan)
    for t in range(ds, n_query):
        score, best_v = _scores_for_window(dext, t - ds, ds, vels)
        s = int(np.argmin(score))
        if not np.isfinite(score[s]):
            continue
        m, den = vels[best_v[s]]
        ref[t] = min(s + (ds * m) // den, n_ref - 1)
        uniq[t] = _uniqueness(score, s, rwindow)
    return ref, uniq

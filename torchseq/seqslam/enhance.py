"""Local contrast enhancement of a difference matrix (OpenSeqSLAM's ``enhanceContrast``).

Window sums come from cumulative sums (float64) restarted every ``SEGMENT`` reference rows
(segments overlap by the window), each segment centred on its own mean, so rounding depends on
the segment and the local spread, not on R or on a large common offset. The matrix is walked in
tiles of ``(columns, rows)``: on CPU a band of about 64 query columns (so reading the row-major
input transposed stays cheap) by as many whole segments as fit in the cache.
"""

from __future__ import annotations

import torch

from torchseq._checks import check_finite, check_not_empty, check_shape
from torchseq.seqslam._parallel import run_blocks

SEGMENT = 256  # rows per cumulative-sum segment
# On CPU a tile holds about this many float64 elements per temporary (cache-sized) and is
# CPU_COLUMNS query columns wide (measured at N = 5000: 2**16 0.48 s, 2**15 0.61 s, 2**17
# 0.53 s, 2**18 0.91 s).
CPU_BLOCK_ELEMENTS = 2**16
CPU_COLUMNS = 64
# A window whose sum of squared deviations falls below this fraction of the cumulative sum of
# squares it came from is recomputed exactly (two-pass; a flat window gives exactly 0).
SUSPECT_RTOL = 1e-6


def _exact(x: torch.Tensor, r: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor):
    """Two-pass mean and sample variance of the windows ``x[r, lo..hi]`` (float64).

    A window of equal values gets variance exactly 0. Memory is O(number of entries).
    """
    n = (hi - lo + 1).to(torch.float64)
    total = torch.zeros_like(n)
    vmax = vmin = x[r, lo]
    for s in range(int((hi - lo).max()) + 1):
        ok = lo + s <= hi
        v = x[r, torch.minimum(lo + s, hi)]
        total += torch.where(ok, v, 0.0)
        vmax, vmin = torch.maximum(vmax, v), torch.minimum(vmin, v)  # v is a window value
    mean = total / n
    ss = torch.zeros_like(n)
    for s in range(int((hi - lo).max()) + 1):
        dev = x[r, torch.minimum(lo + s, hi)] - mean
        ss += torch.where(lo + s <= hi, dev * dev, 0.0)
    return mean, torch.where(vmax == vmin, 0.0, ss / (n - 1))


def _enhance_tile(d: torch.Tensor, q0: int, q1: int, r0: int, n_seg: int, seg: int,
                  half: int) -> torch.Tensor:
    """Z-scores of rows ``r0 .. r0 + n_seg seg - 1`` (clipped to R) of columns ``q0 .. q1 - 1``.

    Args:
        d: ``(R, Q)`` difference matrix.
        q0: first query column.
        q1: one past the last query column.
        r0: first reference row, a multiple of ``seg``.
        n_seg: segments in the tile.
        seg: rows per segment.
        half: half window; the window of row ``i`` is ``i - half .. i + half`` clipped.

    Returns:
        ``(q1 - q0, rows)`` z-scores in ``d``'s dtype (0 where the window's std is 0).
    """
    n_ref = d.shape[0]
    n_cols, w = q1 - q0, 2 * half + 1
    rows = min(n_seg * seg, n_ref - r0)
    base = r0 - half - 1  # buffer position p holds row base + p; zeros outside 0 .. R - 1
    size = n_seg * seg + w
    x = torch.empty(n_cols, size, dtype=torch.float64, device=d.device)
    a, b = max(0, base), min(n_ref, base + size)
    x[:, :a - base] = 0
    x[:, a - base:b - base] = d[a:b, q0:q1].T
    x[:, b - base:] = 0
    # centre each segment on the mean of its own rows
    own = x[:, half + 1:half + 1 + n_seg * seg].view(n_cols, n_seg, seg)
    count = (rows - torch.arange(n_seg, device=d.device) * seg).clamp(max=seg)
    offset = own.sum(-1, keepdim=True) / count[:, None]  # (C, n_seg, 1)
    y = x.unfold(-1, seg + w, seg) - offset  # (C, n_seg, seg + w), materialised
    if a > base or b < base + size:  # padding must count as nothing
        pos = base + torch.arange(size, device=d.device)
        mask = ((pos >= 0) & (pos < n_ref)).to(torch.float64).unfold(0, seg + w, seg)
        y *= mask
    c1 = y.cumsum(-1)
    c2 = (y * y).cumsum_(-1)
    s1 = c1[..., w:] - c1[..., :seg]  # (C, n_seg, seg) window sums
    s2 = c2[..., w:] - c2[..., :seg]
    i = r0 + torch.arange(n_seg * seg, device=d.device)  # global rows (junk past R)
    lo, hi = (i - half).clamp(min=0), (i + half).clamp(max=n_ref - 1)
    n = (hi - lo + 1).clamp(min=2).to(torch.float64).view(n_seg, seg)
    mean_y = s1 / n
    sq_dev = torch.addcmul(s2, s1, mean_y, value=-1)  # (n - 1) var, one pass
    num = y[..., half + 1:half + 1 + seg] - mean_y  # D - window mean
    # rounding in sq_dev is about eps * (segment length) * (segment's sum of squares); one
    # cheap reduction rules out suspect windows in the whole tile first
    sq_rows, total = sq_dev.view(n_cols, -1)[:, :rows], c2[..., -1:]
    if bool(sq_rows.amin() <= SUSPECT_RTOL * total.amax()):  # rare: (nearly) flat windows
        suspect = (sq_dev <= SUSPECT_RTOL * total).view(n_cols, -1)[:, :rows]
        r, t = torch.nonzero(suspect, as_tuple=True)
        if r.numel():  # the tile-wide test can pass with no window suspect in its own column
            mean, var = _exact(x, r, lo[t] - base, hi[t] - base)
            flat = var == 0  # std 0 is defined as 0: num 0 over any positive sq_dev
            k, t_seg = t // seg, t % seg
            num[r, k, t_seg] = torch.where(flat, 0.0, x[r, t + half + 1] - mean)
            sq_dev[r, k, t_seg] = torch.where(flat, 1.0, var * (n[k, t_seg] - 1))
    z = num.to(d.dtype) * sq_dev.to(d.dtype).rsqrt_()
    z *= (n - 1).sqrt().to(d.dtype)
    return z.view(n_cols, -1)[:, :rows]


def _tiles(n_ref: int, n_query: int, half: int, budget: int, cpu: bool):
    """``(columns, segments)`` per tile and the segment length for a budget of elements."""
    seg = min(SEGMENT, n_ref)
    n_seg_all = -(-n_ref // seg)
    segs = max(1, budget // (seg + 2 * half + 1))  # segments (of all columns) per tile
    if cpu:  # a band of columns wide enough for cheap transposed reads, rows to fill it
        # columns of one segment or less (candidate mode's tiles): as many as the budget
        # holds (each column's values do not depend on its band; 64 a call made the
        # per-call overhead 10x the arithmetic on 42-row tiles)
        wide = segs if n_seg_all == 1 else CPU_COLUMNS
        cols = max(1, min(n_query, wide, segs))
        return cols, max(1, min(n_seg_all, segs // cols)), seg
    n_seg = min(n_seg_all, segs)  # whole columns first
    return max(1, min(n_query, segs // n_seg)), n_seg, seg


def enhance_contrast(
    difference: torch.Tensor,
    window: int = 10,
    subtract_min: bool = True,
    max_chunk_elements: int = 2**26,
    threads: int = 1,
) -> torch.Tensor:
    """Normalise each entry by the mean and sample std of its local window of reference rows.

    ``D'[i, j] = (D[i, j] - mean(D[a:b+1, j])) / std(D[a:b+1, j])`` with
    ``a = max(0, i - window // 2)``, ``b = min(R - 1, i + window // 2)`` and the sample
    (N - 1) std; entries whose window has std 0 become 0. With ``subtract_min`` the global
    minimum is then subtracted so every entry is >= 0 (OpenSeqSLAM). Sums are taken in
    float64 whatever the input dtype.

    Args:
        difference: ``(R, Q)`` difference matrix.
        window: window length R in rows (OpenSeqSLAM: 10); 0 returns the input unchanged
            apart from the minimum subtraction.
        subtract_min: subtract the global minimum afterwards.
        max_chunk_elements: bound on the elements of each temporary block.
        threads: CPU worker threads, each taking whole bands of query columns.

    Returns:
        ``(R, Q)`` enhanced matrix, same dtype and device (transposed view of a ``(Q, R)``
        buffer).
    """
    check_shape(difference, ("R", "Q"), "difference matrix")
    check_not_empty(difference, "difference matrix")
    if not bool(torch.isfinite(difference.sum())):  # cheap first: finite sum, finite entries
        check_finite(difference, "difference matrix")
    if window < 0 or window == 1:
        raise ValueError(f"window must be 0 (off) or >= 2, got {window}")
    n_ref, n_query = difference.shape
    if window and n_ref < 2:
        raise ValueError(f"contrast enhancement needs >= 2 reference rows, got {n_ref}")
    out_t = torch.empty(n_query, n_ref, dtype=difference.dtype, device=difference.device)
    if window:
        half = window // 2
        # about eight float64 temporaries of a tile's size live at once (16 float32-sized
        # elements each); on CPU tiles are kept cache-sized
        cpu = difference.device.type != "cuda"
        budget = max_chunk_elements // 16
        if cpu:
            budget = min(budget, CPU_BLOCK_ELEMENTS)
        cols, n_seg, seg = _tiles(n_ref, n_query, half, budget, cpu)

        def band(q0: int) -> None:
            q1 = min(n_query, q0 + cols)
            for r0 in range(0, n_ref, n_seg * seg):
                z = _enhance_tile(difference, q0, q1, r0, n_seg, seg, half)
                out_t[q0:q1, r0:r0 + z.shape[1]] = z

        run_blocks(band, range(0, n_query, cols), threads, difference.device)
    else:
        out_t.copy_(difference.T)
    if subtract_min:
        out_t -= out_t.min()
    return out_t.T

"""SeqSLAM candidate mode: only trajectories through K indexed candidates per query are scored.

An index proposes K references per query; the differences of the pairs those trajectories
need are computed exactly, and no R x Q matrix is made. Definitions (``ds`` even, offsets
``floor(k v)`` of :func:`~torchseq.seqslam.search.trajectory_offsets`, ``M`` = the largest
offset ``floor(ds vmax)``):

- ``cand(j)``: the K references the index (:class:`~torchseq.seqslam.ann_index.CandidateIndex`)
  returns for query ``j``.
- Candidate starts of the window of query centre ``N`` (columns ``N - ds/2 .. N + ds/2``): every
  start ``0 <= s < R`` whose trajectory at some velocity passes through a candidate of its
  column, ``s + floor(k v) in cand(N - ds/2 + k)``. Each candidate start is scored over *all*
  velocities, exactly as the exact search scores it; other starts count as unscored (inf).
- The entries this needs are the window's columns by the band rows ``s .. s + M`` of its
  candidate starts. Their differences are computed with the engine's metric, and their
  contrast enhancement over the true window of ``enhance_window`` reference rows (the rows
  around them are computed too), so every enhanced value is the exact mode's value.
- OpenSeqSLAM subtracts the global minimum of the enhanced matrix. Candidate mode subtracts
  the minimum over the entries it evaluated (all band entries of all windows). Every
  trajectory takes one entry per column, so the constant moves all scores of a window equally:
  matches and rankings do not depend on it, only the uniqueness value does. With ``K >= R``
  every entry is evaluated and the result is the exact mode's (tested against the engine and
  the loop oracle).

Implementation (``layout="shared"``, the default): consecutive windows share ``ds`` of their
``ds + 1`` columns, so a block of up to :data:`CENTRES_PER_BLOCK` consecutive centres is laid
out over one compact reference axis (:func:`shared_layout`): every row within ``M`` of a
candidate of the block's columns, in order, with runs farther apart than ``G`` separated by
``G`` empty (inf) positions, ``G > M`` and ``G > rwindow / 2`` (so a trajectory from a
candidate start stays inside its run, and starts closer than the uniqueness window keep their
true distance). Each column's values are looked up once per block, each difference tile and
its enhancement are computed once for every window that needs them (:class:`TileTable`), the
candidate starts of all windows are marked by one scatter, and
:func:`~torchseq.seqslam.search.trajectory_scores` scores every window of the block as the
exact mode scores its centres (shifted slices of the query-major block), then
:func:`~torchseq.seqslam.search.rank_scores` ranks them (its ``centre`` argument maps compact
positions back to reference rows): the score, velocity, tie, uniqueness and top-K rules are
the exact mode's own code. A block whose rows exceed :data:`SHARE_RATIO` times its middle
window's (scattered proposals) is halved, down to one window. ``layout="per-window"`` gives
each window its own band layout (the first implementation); both give the same results bit
for bit (tested).
"""

from __future__ import annotations

import math
import time
import warnings
from typing import NamedTuple

import torch
import torch.nn.functional as F
from tqdm import tqdm

from torchseq._checks import check_finite, check_not_empty, check_shape
from torchseq.matches import Matches
from torchseq.seqslam.ann_index import CandidateIndex
from torchseq.seqslam.config import SeqSLAMConfig
from torchseq.seqslam.difference import (
    _l1_sad,
    check_magnitude,
    l1_choice,
    l1_kernel,
    thermometer_levels,
)
from torchseq.seqslam.enhance import enhance_contrast
from torchseq.seqslam.result import SeqSLAMResult
from torchseq.seqslam.search import rank_scores, trajectory_offsets, trajectory_scores, velocities

# Above this many reference x query pairs, ``candidates=None`` switches to candidate mode (with
# a warning): 2**31 pairs are 16 GB for the exact mode's two float32 matrices, and above the
# 35,768 x 35,768 full Nordland route (1.28e9 pairs) that the exact mode is meant to handle.
EXACT_MAX_PAIRS = 2**31
# K used when ``candidates=None`` switches to candidate mode above EXACT_MAX_PAIRS.
DEFAULT_CANDIDATES = 20
# Enhanced values are computed in tiles of this many reference rows of one query column.
TILE_ROWS = 32
# Elements of the working dtype in one block of gathered reference rows: cache-sized (at
# 2**22 the L1 differences took 8.5 us per 2048-dim pair, at 2**16 .. 2**20 about 1.9 us).
PAIR_BLOCK_ELEMENTS = 2**19
# Query centres whose bands are laid out and scored together.
CENTRES_PER_BLOCK = 64
# A tile needed by at least this many query columns has its reference rows converted once
# and met by all of them (no per-key gather of D-dimensional rows).
TILE_SHARED_COLUMNS = 8
# Reference rows per block of a dense column's differences (see :class:`TileTable`).
DENSE_BLOCK_ROWS = 64
# Most elements of one chunk of dense columns' differences held at once (64 MB of float32).
DENSE_CHUNK_ELEMENTS = 2**24
# Layouts of candidate mode's search (``CandidateSeqSLAM(layout=...)``): "shared" lays the
# windows of consecutive centres over one compact axis (each difference tile, enhanced value
# and candidate position computed once for all windows that use it); "per-window" gives
# every window its own band layout (the first implementation, kept as the reference).
LAYOUTS = ("shared", "per-window")
# A block of consecutive centres shares one layout while its rows number at most this many
# times those of one window (its middle one); wider blocks are halved. Windows whose
# candidates agree (a matched route) share almost all rows; scattered proposals do not.
SHARE_RATIO = 4


def resolve_candidates(config: SeqSLAMConfig, n_ref: int, n_query: int) -> int:
    """Candidates per query for a run of ``n_ref x n_query``; 0 = exact mode.

    ``config.candidates``: None = exact up to :data:`EXACT_MAX_PAIRS` pairs, else
    :data:`DEFAULT_CANDIDATES` with a warning; 0 = always exact; ``K >= 1`` = candidate mode.
    """
    k = config.candidates
    if k is not None:
        return int(k)
    if n_ref * n_query <= EXACT_MAX_PAIRS:
        return 0
    warnings.warn(
        f"SeqSLAM: {n_ref} x {n_query} pairs exceed the exact mode's limit of "
        f"{EXACT_MAX_PAIRS} (two float32 matrices of {8 * n_ref * n_query / 1e9:.0f} GB): "
        f"using candidate mode with candidates={DEFAULT_CANDIDATES}. Set "
        f"SeqSLAMConfig(candidates=K) to choose K, or candidates=0 to force the exact mode.",
        stacklevel=3)
    return DEFAULT_CANDIDATES


def pair_differences(reference: torch.Tensor, query: torch.Tensor, metric: str) -> torch.Tensor:
    """Distances of matched rows: ``(..., D)`` against ``(..., D)`` -> ``(...)``.

    The definitions of :func:`~torchseq.seqslam.difference.difference_matrix` (``l1`` sum of
    absolute differences, ``l2`` Euclidean, ``cosine`` 1 - cosine similarity with a zero vector
    at similarity 0), evaluated pair by pair (the all-pairs function is tested equal to it).
    """
    if metric == "l1":
        return (reference - query).abs_().sum(-1)
    if metric == "l2":
        diff = reference - query
        return (diff * diff).sum(-1).sqrt_()
    tiny = torch.finfo(reference.dtype).tiny
    ref_n = reference / reference.norm(dim=-1, keepdim=True).clamp_min(tiny)
    query_n = query / query.norm(dim=-1, keepdim=True).clamp_min(tiny)
    return 1.0 - (ref_n * query_n).sum(-1)


def _unique_rows(x: torch.Tensor, fill: int) -> torch.Tensor:
    """Sort each row and replace repeats by ``fill`` (larger than every value), sorted again."""
    x = x.sort(dim=1).values
    if x.shape[1] > 1:
        dup = torch.zeros_like(x, dtype=torch.bool)
        dup[:, 1:] = x[:, 1:] == x[:, :-1]
        x = x.masked_fill(dup, fill).sort(dim=1).values
    keep = int((x < fill).sum(1).max()) if x.numel() else 0
    return x[:, :max(keep, 1)].contiguous()


def candidate_starts(cand: torch.Tensor, offsets: list[list[int]], n_ref: int) -> torch.Tensor:
    """Starts whose trajectories pass through a candidate of their window.

    Args:
        cand: ``(C, ds + 1, K)`` int64 candidates of each window's columns (``-1``: none).
        offsets: per velocity, the row offsets of the ``ds + 1`` steps.
        n_ref: reference frames ``R``.

    Returns:
        ``(C, P)`` int64 sorted distinct starts in ``0 .. R - 1``, padded with ``R``.
    """
    off = torch.tensor(offsets, device=cand.device).T  # (ds + 1, V)
    s = cand[:, :, None, :] - off[None, :, :, None]  # (C, ds + 1, V, K)
    s = s.masked_fill((cand < 0)[:, :, None, :] | (s < 0), n_ref).clamp_max(n_ref)
    return _unique_rows(s.reshape(cand.shape[0], -1), n_ref)


def compact_bands(starts: torch.Tensor, n_ref: int, span: int,
                  gap: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Band rows ``s .. s + span - 1`` of every start, in compact coordinates.

    Args:
        starts: ``(C, P)`` sorted distinct starts, padded with ``n_ref``.
        n_ref: reference frames ``R``.
        span: rows per start (``M + 1``).
        gap: the longest run of empty positions between band rows, also appended at the end.

    Returns:
        ``rows (C, W)`` int64 reference row at each position (``-1`` for empty positions) and
        ``is_start (C, W)`` bool, True at the positions of the starts.
    """
    n_c = starts.shape[0]
    rows = (starts[:, :, None] + torch.arange(span, device=starts.device)).reshape(n_c, -1)
    rows = _unique_rows(rows.clamp_max(n_ref), n_ref)  # (C, N) sorted, padded with n_ref
    valid = rows < n_ref
    step = (rows[:, 1:] - rows[:, :-1]).clamp(max=gap)
    pos = torch.cat([torch.zeros_like(rows[:, :1]), step.cumsum(1)], 1)
    width = int(pos.masked_fill(~valid, -1).max()) + 1 + gap
    pos = pos.masked_fill(~valid, width)  # dump column, dropped below
    grid = rows.new_full((n_c, width + 1), -1).scatter_(1, pos, rows.masked_fill(~valid, -1))
    at = torch.searchsorted(rows, starts).clamp_max(rows.shape[1] - 1)
    start_pos = torch.where(starts < n_ref, pos.gather(1, at), width)
    is_start = torch.zeros(n_c, width + 1, dtype=torch.bool, device=starts.device)
    is_start.scatter_(1, start_pos, True)
    return grid[:, :width], is_start[:, :width]


class TileTable:
    """Enhanced (and raw) differences of whole tiles of ``TILE_ROWS`` rows of query columns.

    Each tile is enhanced over its window of ``L = TILE_ROWS + 2 (window // 2)`` reference rows
    (clipped to the reference), so its values are the exact mode's. The window's differences
    come from one of two kernels, both :func:`pair_differences` (the same values):

    - ``"tiles"``: each key's ``L`` rows against its column (a tile that many columns need has
      its rows converted once and met by all of them; the rest are gathered per key).
    - ``"dense"``: a column that needs so many tiles that its tiles' windows hold at least
      ``R`` rows (``tiles * L >= R``, the halos of neighbouring tiles counted again) has its
      whole column computed once, reference block by block (each block met by all such
      columns), and every tile window is a slice of it: no row is computed twice. Only for a
      plain tensor reference (a shard's rows do not hold whole columns) with ``dense=True``.
      The whole columns are a difference matrix of those columns against the reference, so
      for ``l1`` they go through the exact mode's ``"sad"`` kernel where its rule
      (:func:`~torchseq.seqslam.difference.l1_kernel`, for the reference against the dense
      columns) chooses it, else :func:`pair_differences` (:meth:`dense_kernel_for`): the same
      values, integer sums being exact in float32 below ``2**24``.

    ``kernels`` counts the keys each kernel computed; ``dense_kernel`` is the whole columns'
    kernel (``"sad"`` or ``"pairs"``; None when no column was dense).

    Args:
        reference: ``(R, D)`` reference descriptors (any real dtype; rows are converted to
            ``dtype`` as they are gathered).
        columns: ``(C, D)`` query descriptors, one per column id, in ``dtype``.
        keys: ``(n,)`` int64 distinct tile keys ``column * n_tiles + tile``.
        metric: the engine's metric.
        window: contrast enhancement window (0 = off).
        dense: allow the ``"dense"`` kernel (False: every key by ``"tiles"``).
    """

    def __init__(self, reference: torch.Tensor, columns: torch.Tensor, keys: torch.Tensor,
                 metric: str, window: int, dense: bool = True) -> None:
        n_ref, dim = reference.shape
        self.n_tiles = -(-n_ref // TILE_ROWS)
        self.keys = keys.sort().values
        half = window // 2 if window else 0
        length = min(n_ref, TILE_ROWS + 2 * half)
        col, tile = self.keys // self.n_tiles, self.keys % self.n_tiles
        out_rows = tile[:, None] * TILE_ROWS + torch.arange(TILE_ROWS, device=keys.device)
        lo = (tile * TILE_ROWS - half).clamp(min=0, max=n_ref - length)
        local = (out_rows - lo[:, None]).clamp_max(length - 1)
        outside = out_rows >= n_ref
        dtype = columns.dtype
        self.values = torch.empty(len(keys), TILE_ROWS, dtype=dtype, device=keys.device)
        self.difference = torch.empty_like(self.values)
        self.seconds = {"difference": 0.0, "enhance": 0.0}
        t = time.perf_counter()
        d = torch.empty(len(keys), length, dtype=dtype, device=keys.device)  # (n, L)
        # columns whose tiles' windows hold at least R rows: whole columns, once
        per_column = torch.bincount(col, minlength=len(columns))
        whole = per_column[col] * length >= n_ref
        if not (dense and isinstance(reference, torch.Tensor)):
            whole = torch.zeros_like(whole)
        self.dense_kernel = None
        if bool(whole.any()):
            self.dense_kernel = self._dense(reference, columns, col, lo, whole, d, metric)
        self.kernels = {"dense": int(whole.sum()), "tiles": len(keys) - int(whole.sum())}
        # tiles that many columns need: their rows are converted once and met by every column
        # (a slice, no gather); the rest: their rows gathered per key
        count = torch.bincount(tile[~whole], minlength=self.n_tiles)
        shared = (count[tile] >= TILE_SHARED_COLUMNS) & ~whole
        if bool(shared.any()):
            at = shared.nonzero()[:, 0]
            at = at[torch.sort(tile[at], stable=True).indices]  # grouped by tile
            runs = torch.unique_consecutive(tile[at], return_counts=True)
            block = max(1, PAIR_BLOCK_ELEMENTS // (length * dim))
            i0 = 0
            for tl, n in zip(runs[0].tolist(), runs[1].tolist()):
                r0 = int(lo[at[i0]])
                ref = reference[r0:r0 + length].to(dtype)[None]  # (1, L, D)
                for b0 in range(i0, i0 + n, block):
                    idx = at[b0:min(b0 + block, i0 + n)]
                    d[idx] = pair_differences(ref, columns[col[idx]][:, None, :], metric)
                i0 += n
        rest = (~shared & ~whole).nonzero()[:, 0]
        block = max(1, PAIR_BLOCK_ELEMENTS // (length * dim))
        for t0 in range(0, len(rest), block):  # cache-sized blocks of gathered rows
            idx = rest[t0:t0 + block]
            rows = lo[idx, None] + torch.arange(length, device=keys.device)  # (c, L)
            ref = reference[rows.reshape(-1)].to(dtype).view(-1, length, dim)
            d[idx] = pair_differences(ref, columns[col[idx]][:, None, :], metric)
        self.seconds["difference"] += time.perf_counter() - t
        t = time.perf_counter()
        if len(keys):  # one call: every tile is a column of its own (L, n) matrix
            e = enhance_contrast(d.T, window, False).T if window else d
            self.values = e.gather(1, local).masked_fill_(outside, math.inf)
            self.difference = d.gather(1, local).masked_fill_(outside, math.inf)
        self.seconds["enhance"] += time.perf_counter() - t

    @staticmethod
    def dense_kernel_for(reference: torch.Tensor, columns: torch.Tensor,
                         metric: str) -> tuple[str, float | None]:
        """The kernel of whole columns ``columns (m, D)`` against ``reference (R, D)``.

        ``("sad", lo)`` where the exact mode's rule
        (:func:`~torchseq.seqslam.difference.l1_kernel`) picks ``"sad"`` for this difference
        matrix (``lo``: the minimum it subtracts), else ``("pairs", None)``
        (:func:`pair_differences`). The rule is asked first without thermometer levels, which
        answers ``"sad"`` only when the size, device and values allow it; only then are the
        levels scanned (they decide between ``"sad"`` and the thermometer's int8 product).
        """
        if metric != "l1" or l1_kernel(reference, columns, None) != "sad":
            return "pairs", None
        # a uint8 reference is scanned as it is (no float copy of the whole reference)
        levels = thermometer_levels(reference, columns)
        if levels is not None and levels[0].numel() == 0:
            return "pairs", None  # all values equal: no work worth numba's start-up
        kernel, lo = l1_choice(reference, columns, levels)
        return (kernel, lo) if kernel == "sad" else ("pairs", None)

    @staticmethod
    def _dense(reference: torch.Tensor, columns: torch.Tensor, col: torch.Tensor,
               lo: torch.Tensor, whole: torch.Tensor, d: torch.Tensor, metric: str) -> str:
        """Fill the windows ``d[whole]`` from whole columns, each pair computed once.

        Args:
            reference: ``(R, D)`` reference descriptors.
            columns: ``(C, D)`` query descriptors in the working dtype.
            col: ``(n,)`` column id of each key.
            lo: ``(n,)`` first reference row of each key's window.
            whole: ``(n,)`` bool, the keys of dense columns.
            d: ``(n, L)`` windows, written at ``whole``.
            metric: the engine's metric.

        Returns:
            The kernel that computed the columns (:meth:`dense_kernel_for`).
        """
        n_ref, dim = reference.shape
        length = d.shape[1]
        at = whole.nonzero()[:, 0]
        ids, slot = torch.unique(col[at], return_inverse=True)  # dense columns, each key's
        kernel, offset = TileTable.dense_kernel_for(reference, columns[ids], metric)
        per_chunk = max(1, DENSE_CHUNK_ELEMENTS // n_ref)
        block = max(1, PAIR_BLOCK_ELEMENTS // (DENSE_BLOCK_ROWS * dim))
        for c0 in range(0, len(ids), per_chunk):
            chunk = ids[c0:c0 + per_chunk]
            full = torch.empty(len(chunk), n_ref, dtype=d.dtype, device=d.device)  # (m, R)
            if kernel == "sad":  # (m, R) is the difference matrix's query-major buffer
                _l1_sad(reference, columns[chunk], full, offset, DENSE_CHUNK_ELEMENTS, 1)
            else:
                for r0 in range(0, n_ref, DENSE_BLOCK_ROWS):  # rows converted once per block
                    ref = reference[r0:r0 + DENSE_BLOCK_ROWS].to(d.dtype)[None]  # (1, b, D)
                    for b0 in range(0, len(chunk), block):
                        q = columns[chunk[b0:b0 + block]][:, None, :]  # (c, 1, D)
                        full[b0:b0 + block, r0:r0 + DENSE_BLOCK_ROWS] = pair_differences(
                            ref, q, metric)
            mine = (slot >= c0) & (slot < c0 + len(chunk))
            k = at[mine]
            rows = lo[k, None] + torch.arange(length, device=d.device)  # (k, L)
            d[k] = full[(slot[mine] - c0)[:, None], rows]
        return kernel

    @classmethod
    def from_values(cls, keys: torch.Tensor, values: torch.Tensor, n_tiles: int) -> TileTable:
        """A table of already computed enhanced tiles (``keys`` sorted, ``values (n, 32)``).

        Its ``difference`` is None: only :meth:`lookup` and :meth:`block_values` use it.
        """
        table = cls.__new__(cls)
        table.keys, table.values, table.n_tiles = keys, values, n_tiles
        table.difference, table.seconds = None, {"difference": 0.0, "enhance": 0.0}
        table.kernels, table.dense_kernel = {"dense": 0, "tiles": 0}, None
        return table

    def lookup(self, column: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """Enhanced values at ``(column, row)`` (broadcast); ``inf`` where ``row < 0``.

        Raises:
            RuntimeError: a looked-up tile was never computed (an internal error).
        """
        r = rows.clamp_min(0)
        if len(self.keys) == 0:
            return torch.full(torch.broadcast_shapes(column.shape, rows.shape), math.inf,
                              dtype=self.values.dtype, device=self.values.device)
        key = (column * self.n_tiles + r // TILE_ROWS).contiguous()
        slot = torch.searchsorted(self.keys, key).clamp_max(len(self.keys) - 1)
        missing = (self.keys[slot] != key) & (rows >= 0)
        if bool(missing.any()):
            raise RuntimeError("candidate mode looked up a tile it did not compute")
        val = self.values[slot, r % TILE_ROWS]
        return val.masked_fill_(rows < 0, math.inf)

    def block_values(self, columns: torch.Tensor, block: SharedBlock) -> torch.Tensor:
        """Enhanced values of ``columns (n,)`` at the positions of ``block``: ``(n, W)``.

        ``inf`` wherever ``block.needed`` is False (those tiles may not be computed).

        Raises:
            RuntimeError: a needed tile was never computed (an internal error).
        """
        n, width = len(columns), len(block.rows)
        if len(self.keys) == 0 or width == 0:
            return torch.full((n, width), math.inf, dtype=self.values.dtype,
                              device=self.values.device)
        key = columns[:, None] * self.n_tiles + block.tiles[None]  # (n, T)
        slot = torch.searchsorted(self.keys, key).clamp_max(len(self.keys) - 1)
        slot = torch.where(self.keys[slot] == key, slot, -1)
        slot = F.pad(slot, (0, 1), value=-1)[:, block.tile_of]  # (n, W)
        if bool((block.needed & (slot < 0)).any()):
            raise RuntimeError("candidate mode looked up a tile it did not compute")
        val = self.values[slot.clamp_min(0), block.rows.clamp_min(0) % TILE_ROWS]
        return val.masked_fill_(~block.needed, math.inf)


def shared_tile_keys(columns: torch.Tensor, block: SharedBlock, n_tiles: int) -> torch.Tensor:
    """Distinct keys ``column * n_tiles + tile`` of the entries a :class:`SharedBlock` needs.

    Args:
        columns: ``(C + ds,)`` int64 column id of each of the block's columns.
        block: the layout.
        n_tiles: tiles of the reference.
    """
    n_t = len(block.tiles)
    hit = torch.zeros(len(columns), n_t + 1, dtype=torch.int32, device=columns.device)
    hit.index_add_(1, block.tile_of, block.needed.to(torch.int32))
    col, t = hit[:, :n_t].nonzero(as_tuple=True)
    return (columns[col] * n_tiles + block.tiles[t]).unique()


def band_tile_keys(rows: torch.Tensor, columns: torch.Tensor, n_tiles: int) -> torch.Tensor:
    """Distinct tile keys of the band rows ``(C, W)`` in each window's columns ``(C, ds + 1)``."""
    tiles = torch.where(rows >= 0, rows // TILE_ROWS, n_tiles)
    tiles = _unique_rows(tiles, n_tiles)  # (C, n) distinct tiles per window
    keys = columns[:, :, None] * n_tiles + tiles[:, None, :]
    keep = (tiles < n_tiles)[:, None, :].expand_as(keys)
    return keys[keep].unique()


def score_bands(values: torch.Tensor, rows: torch.Tensor, is_start: torch.Tensor, ds: int,
                offsets: list[list[int]], n_ref: int, rwindow: int, top_k: int,
                report: str) -> tuple[torch.Tensor, ...]:
    """Score the candidate starts of ``C`` windows laid out as compact bands.

    Args:
        values: ``(ds + 1, C, W)`` enhanced values of each window's columns at its band rows
            (``inf`` at empty positions).
        rows: ``(C, W)`` reference row of each position (``-1`` empty).
        is_start: ``(C, W)`` True at candidate starts.
        ds: even sequence length.
        offsets: per velocity, the row offsets of the ``ds + 1`` steps.
        n_ref: reference frames ``R``.
        rwindow: uniqueness exclusion window.
        top_k: ranked candidates kept.
        report: which row a start reports: ``"start"`` (``s + ds/2``), ``"trajectory"``
            (``s + floor(v ds/2)``) or ``"end"`` (``s + floor(ds v)``, streaming).

    Returns:
        ``match (C,)``, ``best (C,)``, ``uniqueness (C,)``, ``ranked (C, top_k)``, best start
        ``(C,)`` (reference row, ``-1`` if none) and best velocity index ``(C,)``.
    """
    n_c, width = rows.shape
    scores, best_v = trajectory_scores(values.reshape(ds + 1, n_c * width), ds // 2,
                                       ds // 2 + 1, ds, offsets, with_velocity=True)
    scores = scores[0, :-1].view(n_c, width)
    best_v = best_v[0, :-1].view(n_c, width)
    return rank_bands(scores, best_v, rows, is_start, ds, offsets, n_ref, rwindow, top_k,
                      report)


def rank_bands(scores: torch.Tensor, best_v: torch.Tensor, rows: torch.Tensor,
               is_start: torch.Tensor, ds: int, offsets: list[list[int]], n_ref: int,
               rwindow: int, top_k: int, report: str) -> tuple[torch.Tensor, ...]:
    """Rank the scored positions of ``C`` compact layouts.

    The second half of :func:`score_bands`, shared with :func:`score_shared`.

    Args:
        scores: ``(C, W)`` best trajectory score of each position (any value where not
            ``is_start``: it is set to inf).
        best_v: ``(C, W)`` int64 index of each position's best velocity.
        rows: ``(C, W)`` (or ``(W,)``, one layout for all) reference row per position.
        is_start: ``(C, W)`` True at candidate starts.
        ds: even sequence length.
        offsets: per velocity, the row offsets of the ``ds + 1`` steps.
        n_ref: reference frames ``R``.
        rwindow: uniqueness exclusion window.
        top_k: ranked candidates kept.
        report: ``"start"``, ``"trajectory"`` or ``"end"`` (see :func:`score_bands`).

    Returns:
        As :func:`score_bands`.
    """
    n_c, width = scores.shape
    rows = rows.expand(n_c, width)
    scores = scores.masked_fill(~is_start, math.inf)
    if report == "start":
        offset = torch.full_like(rows, ds // 2)
    else:
        step = ds // 2 if report == "trajectory" else ds
        offset = torch.tensor([off[step] for off in offsets], device=rows.device)[best_v]
    # position p reports rows[p] + offset[p]: rank_scores adds ``centre`` to the position
    shift = rows + offset - torch.arange(width, device=rows.device)
    start, best, ratio, ranked = rank_scores(scores, ds, n_ref, rwindow, top_k, shift)
    ok = torch.isfinite(best)
    match = torch.where(ok, (start + shift.gather(1, start[:, None])[:, 0]).clamp_max(n_ref - 1),
                        -1)
    first = torch.where(ok, rows.gather(1, start[:, None])[:, 0], -1)
    return match, best, ratio, ranked, first, best_v.gather(1, start[:, None])[:, 0]


class SharedBlock(NamedTuple):
    """``C`` consecutive windows laid out over one compact reference axis.

    Made by :func:`shared_layout`.

    Attributes:
        rows: ``(W,)`` int64 reference row of each position (``-1``: empty).
        is_start: ``(C, W)`` bool, the candidate starts of each window.
        needed: ``(C + ds, W)`` bool, the entries some window of the block uses: column ``j``
            at the band rows of the windows that contain it.
        tiles: ``(T,)`` int64 distinct reference tiles of the layout's rows, increasing.
        tile_of: ``(W,)`` int64 index into ``tiles`` of each position (``T`` where empty).
    """

    rows: torch.Tensor
    is_start: torch.Tensor
    needed: torch.Tensor
    tiles: torch.Tensor
    tile_of: torch.Tensor


def union_rows(cand: torch.Tensor, n_ref: int, reach: int) -> torch.Tensor:
    """Sorted distinct rows ``r + d`` in ``0 .. R - 1``, ``r`` a candidate, ``|d| <= reach``."""
    c = cand[cand >= 0].unique()
    r = (c[:, None] + torch.arange(-reach, reach + 1, device=cand.device)).reshape(-1)
    return r[(r >= 0) & (r < n_ref)].unique()


def shared_layout(cand: torch.Tensor, offsets: list[list[int]], n_ref: int, span: int,
                  gap: int) -> SharedBlock:
    """One compact layout for the windows of ``C`` consecutive centres.

    The layout holds every row within ``M = span - 1`` of a candidate of the block's columns
    (a superset of every window's band: a start ``s = r - floor(k v)`` of candidate ``r`` has
    its band ``s .. s + M`` inside ``r - M .. r + M``), in increasing order, with ``gap``
    empty positions before the first row, between runs of rows farther apart than ``gap``,
    and after the last. Since every band lies inside one run, a trajectory from a true start
    moves along positions exactly as along rows, and ``is_start`` marks, per window, the
    positions ``pos(r) - floor(k v)`` of its candidates (a start below row 0 lands in the
    leading gap, which is empty). Distances up to ``gap`` are kept, longer ones stay
    ``>= gap`` (so ``gap > rwindow / 2`` keeps the uniqueness window exact).

    Args:
        cand: ``(C + ds, K)`` int64 candidates of the block's columns (``-1``: none).
        offsets: per velocity, the row offsets of the ``ds + 1`` steps.
        n_ref: reference frames ``R``.
        span: rows per start (``M + 1``).
        gap: empty positions between runs (``> M`` and ``> rwindow / 2``).

    Returns:
        :class:`SharedBlock`.
    """
    dev = cand.device
    ds = len(offsets[0]) - 1
    n_c = cand.shape[0] - ds
    rows_u = union_rows(cand, n_ref, span - 1)  # (N,)
    if len(rows_u) == 0:
        empty = torch.zeros(n_c, 0, dtype=torch.bool, device=dev)
        none = torch.zeros(0, dtype=torch.int64, device=dev)
        return SharedBlock(none, empty, torch.zeros(n_c + ds, 0, dtype=torch.bool,
                                                    device=dev), none, none)
    step = (rows_u[1:] - rows_u[:-1]).clamp(max=gap)
    pos = gap + torch.cat([torch.zeros_like(rows_u[:1]), step.cumsum(0)])
    width = int(pos[-1]) + 1 + gap
    rows = torch.full((width,), -1, dtype=torch.int64, device=dev)
    rows[pos] = rows_u
    ok = cand >= 0
    cpos = pos[torch.searchsorted(rows_u, cand.clamp_min(0))]  # (C + ds, K)
    off = torch.tensor(offsets, device=dev).T  # (ds + 1, V)
    win = cpos.unfold(0, ds + 1, 1).permute(0, 2, 1)  # (C, ds + 1, K)
    win_ok = ok.unfold(0, ds + 1, 1).permute(0, 2, 1)
    s = win[:, :, None, :] - off[None, :, :, None]  # (C, ds + 1, V, K), all >= gap - M > 0
    s = s.masked_fill(~win_ok[:, :, None, :], width).reshape(n_c, -1)
    is_start = torch.zeros(n_c, width + 1, dtype=torch.bool, device=dev)
    is_start.scatter_(1, s, True)
    is_start = is_start[:, :width] & (rows >= 0)
    # band: positions p with a start in p - M .. p; needed: column j in windows j - ds .. j
    cs = F.pad(is_start.to(torch.int32).cumsum(1), (span, 0))
    band = (cs[:, span:] - cs[:, :-span]) > 0  # (C, W)
    cb = F.pad(band.to(torch.int32).cumsum(0), (0, 0, 1, 0))  # (C + 1, W)
    j = torch.arange(n_c + ds, device=dev)
    needed = (cb[j.clamp(max=n_c - 1) + 1] - cb[(j - ds).clamp(min=0)]) > 0
    needed &= rows >= 0
    tile = torch.where(rows >= 0, rows // TILE_ROWS, -1)
    tiles = tile[tile >= 0].unique()
    tile_of = torch.where(rows >= 0, torch.searchsorted(tiles, tile.clamp_min(0)), len(tiles))
    return SharedBlock(rows, is_start, needed, tiles, tile_of)


def score_shared(values: torch.Tensor, block: SharedBlock, ds: int, offsets: list[list[int]],
                 n_ref: int, rwindow: int, top_k: int, report: str) -> tuple[torch.Tensor, ...]:
    """Score and rank the windows of a :class:`SharedBlock`.

    Args:
        values: ``(C + ds, W)`` enhanced values of the block's columns at its positions
            (``inf`` where not ``block.needed``).
        block: the layout.
        ds: even sequence length.
        offsets: per velocity, the row offsets of the ``ds + 1`` steps.
        n_ref: reference frames ``R``.
        rwindow: uniqueness exclusion window.
        top_k: ranked candidates kept.
        report: ``"start"``, ``"trajectory"`` or ``"end"`` (see :func:`score_bands`).

    Returns:
        As :func:`score_bands`, one entry per window.
    """
    n_c = block.is_start.shape[0]
    scores, best_v = trajectory_scores(values, ds // 2, ds // 2 + n_c, ds, offsets,
                                       with_velocity=True)
    return rank_bands(scores[:, :-1], best_v[:, :-1], block.rows, block.is_start, ds,
                      offsets, n_ref, rwindow, top_k, report)


class CandidateSeqSLAM:
    """SeqSLAM in candidate mode over a fixed reference traverse (the index is built once).

    Args:
        reference: ``(R, D)`` reference descriptors; integer-valued descriptors may be kept
            as uint8 (4x less memory at 10^6 references; converted as rows are used).
        config: parameters; ``config.candidates`` is K unless ``candidates`` is given.
        candidates: K, overriding ``config.candidates`` (the one used must be >= 1).
        index: index kind (:data:`~torchseq.seqslam.ann_index.INDEX_KINDS`) or a built
            :class:`~torchseq.seqslam.ann_index.CandidateIndex` over the same reference.
        device: where to compute (the index itself runs on CPU).
        dtype: working float dtype (None: float64 for float64 references, else float32).
        index_options: keyword arguments of :class:`CandidateIndex`.
        refine: an approximate index proposes ``refine * K`` references, re-ranked exactly
            (see :meth:`search`); 1 = take its K as they are.
        layout: ``"shared"`` (default) or ``"per-window"``, see :data:`LAYOUTS`; both give
            the same results (tested), ``result.kernels["layout"]`` says which ran.
        dense: let columns that need most tiles be computed whole (:class:`TileTable`'s
            ``"dense"`` kernel); False computes every tile's window on its own. Both give the
            same results (tested).
    """

    def __init__(self, reference: torch.Tensor, config: SeqSLAMConfig | None = None,
                 candidates: int | None = None, index: str | CandidateIndex = "auto",
                 device: torch.device | str | None = None, dtype: torch.dtype | None = None,
                 index_options: dict | None = None, refine: int = 4,
                 layout: str = "shared", dense: bool = True) -> None:
        self.config = (config or SeqSLAMConfig()).validate()
        if layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
        self.layout = layout
        self.dense = bool(dense)
        k = candidates if candidates is not None else self.config.candidates
        if k is None or isinstance(k, bool) or int(k) < 1:
            raise ValueError(f"candidate mode needs candidates K >= 1, got {k!r}")
        self.k = int(k)
        if isinstance(refine, bool) or int(refine) < 1:
            raise ValueError(f"refine must be an integer >= 1, got {refine!r}")
        self.refine = int(refine)
        reference = torch.as_tensor(reference)
        check_not_empty(reference, "reference descriptors")
        check_shape(reference, ("R", "D"), "reference descriptors")
        check_finite(reference, "reference descriptors")
        check_magnitude(reference, "reference descriptors")
        if reference.shape[0] < 2:
            raise ValueError(f"need at least 2 reference frames, got {reference.shape[0]}")
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.dtype = dtype or (torch.float64 if reference.dtype == torch.float64
                               else torch.float32)
        t = time.perf_counter()
        if isinstance(index, CandidateIndex):
            if index.size != reference.shape[0] or index.dim != reference.shape[1]:
                raise ValueError(f"index holds ({index.size}, {index.dim}) descriptors, the "
                                 f"reference is {tuple(reference.shape)}")
            self.index = index
        else:
            self.index = CandidateIndex(reference, self.config.metric, index,
                                        **(index_options or {}))
        self.index_seconds = time.perf_counter() - t
        self.reference = reference.to(self.device)
        c = self.config
        self.ds = c.sequence_length
        self.speeds = velocities(self.ds, *c.velocity_range)
        self.offsets = trajectory_offsets(self.ds, self.speeds)
        self.span = max(off[-1] for off in self.offsets) + 1
        self.gap = max(self.span, c.rwindow // 2 + 1)

    @property
    def n_ref(self) -> int:
        """Reference frames ``R``."""
        return self.reference.shape[0]

    def search(self, query: torch.Tensor) -> torch.Tensor:
        """``(Q, D)`` descriptors -> ``(Q, K)`` candidate references on the device.

        A flat index gives the exact top K under the metric. An approximate one (IVF, HNSW)
        is asked for ``refine * K`` and those are re-ranked by their exact distance (the
        metric on the stored descriptors; ties -> lower reference), keeping K: the far-off
        proposals an approximate index makes at 10^6 references would each cost a band.
        """
        query = torch.as_tensor(query)
        if self.index.kind == "flat" or self.refine <= 1:
            return self.index.search(query, self.k).to(self.device)
        cand = self.index.search(query, self.refine * self.k).to(self.device)  # (Q, K')
        k = min(self.k, cand.shape[1])
        out = torch.empty(cand.shape[0], k, dtype=torch.int64, device=self.device)
        rows = max(1, PAIR_BLOCK_ELEMENTS // (cand.shape[1] * query.shape[1]))
        for q0 in range(0, cand.shape[0], rows):
            c = cand[q0:q0 + rows]
            ok = c >= 0
            ref = self.reference[c.clamp_min(0)].to(self.dtype)  # (q, K', D)
            q = query[q0:q0 + rows].to(self.device, self.dtype)[:, None, :]
            d = pair_differences(ref, q, self.config.metric).masked_fill_(~ok, math.inf)
            # order by (distance, reference): sort by reference first, then stably by distance
            by_ref = c.masked_fill(~ok, self.n_ref).argsort(dim=1)
            d, c = d.gather(1, by_ref), c.gather(1, by_ref)
            order = d.argsort(dim=1, stable=True)[:, :k]
            out[q0:q0 + rows] = torch.where(d.gather(1, order).isfinite(), c.gather(1, order),
                                            -1)
        return out

    def bands(self, cand: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(C, ds + 1, K)`` window candidates -> band ``rows (C, W)``, ``is_start (C, W)``."""
        starts = candidate_starts(cand, self.offsets, self.n_ref)
        return compact_bands(starts, self.n_ref, self.span, self.gap)

    def table(self, columns: torch.Tensor, keys: torch.Tensor) -> TileTable:
        """Enhanced values of the tiles ``keys`` of the query ``columns (C, D)``."""
        return TileTable(self.reference, columns, keys, self.config.metric,
                         self.config.enhance_window, self.dense)

    def _blocks(self, cand: torch.Tensor, rows_per_block: int):
        """Yield ``(c0, c1, columns (C, ds+1), rows, is_start)`` per block of centres."""
        ds = self.ds
        windows = cand.unfold(0, ds + 1, 1).permute(0, 2, 1)  # (Q - ds, ds + 1, K)
        for c0 in range(0, windows.shape[0], rows_per_block):
            c1 = min(c0 + rows_per_block, windows.shape[0])
            rows, is_start = self.bands(windows[c0:c1])
            cols = torch.arange(c0, c1, device=cand.device)[:, None] + torch.arange(
                ds + 1, device=cand.device)
            yield c0, c1, cols, rows, is_start

    def shared_blocks(self, cand: torch.Tensor, c0: int = 0, c1: int | None = None):
        """Yield ``(c0, c1, SharedBlock)`` for the windows of consecutive centres.

        Window ``i`` holds columns ``i .. i + ds`` of ``cand (Q, K)``; windows ``c0 .. c1 - 1``
        are split into blocks of at most :data:`CENTRES_PER_BLOCK`, halved while a block's
        rows exceed :data:`SHARE_RATIO` times its middle window's (down to one window).
        """
        ds = self.ds
        c1 = cand.shape[0] - ds if c1 is None else c1
        todo = [(b0, min(b0 + CENTRES_PER_BLOCK, c1))
                for b0 in range(c0, c1, CENTRES_PER_BLOCK)][::-1]
        reach = self.span - 1
        while todo:
            b0, b1 = todo.pop()
            part = cand[b0:b1 + ds]
            if b1 - b0 > 1:
                mid = (b0 + b1) // 2
                one = len(union_rows(cand[mid:mid + ds + 1], self.n_ref, reach))
                if len(union_rows(part, self.n_ref, reach)) > SHARE_RATIO * max(one, 1):
                    half = (b0 + b1) // 2
                    todo += [(half, b1), (b0, half)]
                    continue
            yield b0, b1, shared_layout(part, self.offsets, self.n_ref, self.span, self.gap)

    def match_descriptors(self, query: torch.Tensor, progress: bool = False):
        """Match ``(Q, D)`` query descriptors (as :meth:`SeqSLAM.match_descriptors`).

        Returns:
            :class:`~torchseq.seqslam.result.SeqSLAMResult` whose ``difference`` and
            ``enhanced`` are sparse ``(R, Q)`` COO tensors of the evaluated entries (whole
            tiles of :data:`TILE_ROWS` rows around the bands); ``seconds`` adds ``"index"``
            (building it, not in ``"total"``), ``"candidates"`` (querying it) and ``"bands"``;
            ``kernels["layout"]`` is the layout that ran, ``kernels["dense_keys"]`` and
            ``kernels["tile_keys"]`` the tiles whose differences came from whole columns and
            from their own windows (:class:`TileTable`), ``kernels["dense_difference"]`` the
            whole columns' kernel (``"sad"``, ``"pairs"``, None: no whole column).
        """
        c = self.config
        query = torch.as_tensor(query)
        check_not_empty(query, "query descriptors")
        check_shape(query, ("Q", self.reference.shape[1]), "query descriptors")
        check_finite(query, "query descriptors")
        check_magnitude(query, "query descriptors")
        n_query = query.shape[0]
        if n_query < self.ds + 1:
            raise ValueError(f"need at least ds + 1 = {self.ds + 1} query frames for ds = "
                             f"{c.ds}, got {n_query}")
        if self.layout == "per-window":
            return self._match_per_window(query, progress)

        ds = self.ds
        seconds = {"index": self.index_seconds}
        t0 = t = time.perf_counter()
        cand = self.search(query)
        seconds["candidates"] = time.perf_counter() - t
        t = time.perf_counter()
        n_tiles = -(-self.n_ref // TILE_ROWS)
        blocks, keys = [], []
        for b0, b1, block in self.shared_blocks(cand):
            cols = torch.arange(b0, b1 + ds, device=cand.device)
            blocks.append((b0, b1, cols, block))
            keys.append(shared_tile_keys(cols, block, n_tiles))
        seconds["bands"] = time.perf_counter() - t
        query = query.to(self.device, self.dtype)
        table = self.table(query, torch.cat(keys).unique())
        seconds.update(table.seconds)
        t = time.perf_counter()
        floor = math.inf  # minimum over the evaluated band entries (OpenSeqSLAM's global min)
        for _, _, cols, block in blocks:
            if bool(block.needed.any()):
                floor = min(floor, float(table.block_values(cols, block).min()))
        floor = floor if math.isfinite(floor) else 0.0  # nothing evaluated: no match anywhere
        match, best_score, uniqueness, ranked = self._outputs(n_query)
        for b0, b1, cols, block in tqdm(blocks, desc="candidate search", disable=not progress,
                                        leave=False):
            if len(block.rows) == 0:
                continue
            vals = table.block_values(cols, block) - floor
            out = score_shared(vals, block, ds, self.offsets, self.n_ref, c.rwindow, c.top_k,
                               c.match_rule)
            sl = slice(b0 + ds // 2, b1 + ds // 2)
            match[sl], best_score[sl], uniqueness[sl], ranked[sl] = out[:4]
        seconds["search"] = time.perf_counter() - t
        seconds["total"] = time.perf_counter() - t0
        return self._result(table, floor, (match, best_score, uniqueness, ranked), seconds,
                            {"layout": "shared", "blocks": len(blocks),
                             "dense_keys": table.kernels["dense"],
                             "tile_keys": table.kernels["tiles"],
                             "dense_difference": table.dense_kernel})

    def _match_per_window(self, query: torch.Tensor, progress: bool):
        """:meth:`match_descriptors` with every window in its own layout (checked query)."""
        c, ds = self.config, self.ds
        n_query = query.shape[0]
        seconds = {"index": self.index_seconds}
        t0 = t = time.perf_counter()
        cand = self.search(query)
        seconds["candidates"] = time.perf_counter() - t
        t = time.perf_counter()
        block = CENTRES_PER_BLOCK
        keys = [band_tile_keys(rows, cols, -(-self.n_ref // TILE_ROWS))
                for _, _, cols, rows, _ in self._blocks(cand, block)]
        seconds["bands"] = time.perf_counter() - t
        query = query.to(self.device, self.dtype)
        table = self.table(query, torch.cat(keys).unique())
        seconds.update(table.seconds)
        t = time.perf_counter()
        floor = math.inf  # minimum over the evaluated band entries (OpenSeqSLAM's global min)
        for _, _, cols, rows, _ in self._blocks(cand, block):
            vals = table.lookup(cols.T[:, :, None], rows[None])
            floor = min(floor, float(vals.min()))
        floor = floor if math.isfinite(floor) else 0.0  # nothing evaluated: no match anywhere
        match, best_score, uniqueness, ranked = self._outputs(n_query)
        report = c.match_rule
        blocks = self._blocks(cand, block)
        for c0, c1, cols, rows, is_start in tqdm(blocks, total=-(-(n_query - ds) // block),
                                                 desc="candidate search", disable=not progress,
                                                 leave=False):
            vals = table.lookup(cols.T[:, :, None], rows[None]) - floor
            out = score_bands(vals, rows, is_start, ds, self.offsets, self.n_ref, c.rwindow,
                              c.top_k, report)
            sl = slice(c0 + ds // 2, c1 + ds // 2)
            match[sl], best_score[sl], uniqueness[sl], ranked[sl] = out[:4]
        seconds["search"] = time.perf_counter() - t
        seconds["total"] = time.perf_counter() - t0
        return self._result(table, floor, (match, best_score, uniqueness, ranked), seconds,
                            {"layout": "per-window", "dense_keys": table.kernels["dense"],
                             "tile_keys": table.kernels["tiles"],
                             "dense_difference": table.dense_kernel})

    def _outputs(self, n_query: int) -> tuple[torch.Tensor, ...]:
        """Empty ``match (Q,)``, ``best_score (Q,)``, ``uniqueness (Q,)``, ``ranked (Q, K)``."""
        dev = self.device
        match = torch.full((n_query,), -1, dtype=torch.int64, device=dev)
        best_score = torch.full((n_query,), math.nan, dtype=self.dtype, device=dev)
        ranked = torch.full((n_query, self.config.top_k), -1, dtype=torch.int64, device=dev)
        return match, best_score, torch.full_like(best_score, math.nan), ranked

    def _result(self, table: TileTable, floor: float, outputs: tuple, seconds: dict,
                kernels: dict):
        """The search's :class:`SeqSLAMResult`, its sparse matrices less the minimum ``floor``."""
        match, best_score, uniqueness, ranked = outputs
        table.values -= floor
        difference, enhanced = self._sparse(table, ranked.shape[0])
        return SeqSLAMResult(
            matches=Matches(match.cpu(), uniqueness.cpu(), lower_is_better=True),
            difference=difference, enhanced=enhanced, ranked=ranked.cpu(),
            best_score=best_score.cpu(), seconds=seconds, kernels=kernels)

    def _sparse(self, table: TileTable, n_query: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The table's entries as sparse ``(R, Q)`` COO tensors on CPU (raw, enhanced)."""
        col = (table.keys // table.n_tiles)[:, None].expand(-1, TILE_ROWS)
        row = (table.keys % table.n_tiles)[:, None] * TILE_ROWS + torch.arange(
            TILE_ROWS, device=table.keys.device)
        keep = row < self.n_ref
        row, col = row[keep], col[keep]
        order = (row * n_query + col).argsort()  # distinct entries: sorted is coalesced
        idx = torch.stack([row[order], col[order]]).cpu()
        size = (self.n_ref, n_query)
        return tuple(torch.sparse_coo_tensor(idx, v[keep][order].cpu(), size,
                                             check_invariants=False, is_coalesced=True)
                     for v in (table.difference, table.values))

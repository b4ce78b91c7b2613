"""SeqSLAM candidate mode over a reference map split between workers (Ray actors).

Each worker (:class:`ShardWorker`) holds the places ``start .. stop - 1`` of a
:class:`~torchseq.maps.ReferenceMap` plus its *edge rows*: the rows a trajectory from one of
its starts reaches (``M = floor(ds vmax)`` further) and the contrast-enhancement window
around them (``enhance_window / 2``, rounded out to whole tiles of
:data:`~torchseq.seqslam.candidates.TILE_ROWS` rows as the tile table computes them). A worker
scores exactly the candidate starts that fall in its range, with the one-machine mode's
functions (:func:`~torchseq.seqslam.candidates.candidate_starts`,
:func:`~torchseq.seqslam.candidates.compact_bands`,
:class:`~torchseq.seqslam.candidates.TileTable`,
:func:`~torchseq.seqslam.search.trajectory_scores`) on its rows, addressed by their place
numbers in the whole map, so a trajectory that runs over a shard boundary gets the same
enhanced values, sums and velocity as on one machine.

The driver (:class:`ShardedSeqSLAM`) holds the map's index and proposes the K candidates of
every query (for an approximate index the shards return the exact distances of the
proposals, and the driver keeps the K nearest by ``(distance, place)`` as
:meth:`CandidateSeqSLAM.search` does). A run has two rounds per batch of query centres:

1. every shard evaluates the band entries of its starts and returns their minimum; the
   driver takes the minimum over shards and batches (OpenSeqSLAM's global minimum, as the
   one-machine candidate mode evaluates it);
2. every shard returns, per query centre, its candidate starts with their exact sequence
   scores (minimum removed) and best velocities; the driver lays all shards' starts out as
   the one-machine mode does (:func:`~torchseq.seqslam.candidates.compact_bands`) and ranks
   them with the exact mode's :func:`~torchseq.seqslam.search.rank_scores`.

Matches, scores and rankings are those of :class:`CandidateSeqSLAM` on the whole map
(tested equal, value for value). A shard's work in round 1 is kept for round 2; a restarted
actor (killed, its node lost) reloads its shard from the map and recomputes it, so no query
is lost.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict
from typing import NamedTuple

import torch

from torchseq._checks import check_finite, check_not_empty, check_shape
from torchseq.maps.format import MapError, ReferenceMap
from torchseq.matches import Matches
from torchseq.seqslam.candidates import (
    CENTRES_PER_BLOCK,
    PAIR_BLOCK_ELEMENTS,
    TILE_ROWS,
    TileTable,
    band_tile_keys,
    candidate_starts,
    compact_bands,
    pair_differences,
    rank_bands,
)
from torchseq.seqslam.config import SeqSLAMConfig
from torchseq.seqslam.difference import check_magnitude
from torchseq.seqslam.result import SeqSLAMResult
from torchseq.seqslam.search import (
    trajectory_offsets,
    trajectory_scores,
    velocities,
)
from torchseq.seqslam.streaming import StreamingMatch

DEFAULT_BATCH = 4 * CENTRES_PER_BLOCK  # query centres per task


class ShardedStreamState(NamedTuple):
    """The trailing windows of ``B`` streams (``n <= ds + 1`` frames so far).

    Attributes:
        descriptors: ``(B, n, D)`` query descriptors.
        candidates: ``(B, n, K)`` int64 their candidates.
    """

    descriptors: torch.Tensor
    candidates: torch.Tensor


def band_geometry(config: SeqSLAMConfig) -> tuple[list[list[int]], int, int]:
    """``(offsets, span, gap)`` of candidate mode's bands (as :class:`CandidateSeqSLAM`)."""
    ds = config.sequence_length
    offsets = trajectory_offsets(ds, velocities(ds, *config.velocity_range))
    span = max(off[-1] for off in offsets) + 1
    return offsets, span, max(span, config.rwindow // 2 + 1)


def edge_rows(start: int, stop: int, n_ref: int, span: int, window: int) -> tuple[int, int]:
    """Rows ``lo .. hi - 1`` a shard of starts ``start .. stop - 1`` reads (with edge rows).

    Band rows reach ``stop + span - 2``. The tile table computes whole tiles of ``TILE_ROWS``
    rows, each from ``length = min(R, TILE_ROWS + 2 (window // 2))`` rows starting at
    ``clamp(tile * TILE_ROWS - window // 2, 0, R - length)``; these are the rows of the
    first and last tile's.
    """
    half = window // 2 if window else 0
    length = min(n_ref, TILE_ROWS + 2 * half)
    first, last = start // TILE_ROWS, min(stop + span - 2, n_ref - 1) // TILE_ROWS
    lo = min(max(0, first * TILE_ROWS - half), n_ref - length)
    hi = max(min(n_ref - length, max(0, last * TILE_ROWS - half)), 0) + length
    return lo, hi


def shard_ranges(ref_map: ReferenceMap, n_shards: int) -> list[tuple[int, int]]:
    """Places of each of ``n_shards`` workers: whole shard files, as even as they divide."""
    files = ref_map.shards
    if not 1 <= n_shards <= len(files):
        raise ValueError(f"the map has {len(files)} shard file(s) of {ref_map.shard_size} "
                         f"places: --shards must be 1 .. {len(files)}, got {n_shards} (build "
                         f"the map with a smaller --shard-size for more)")
    cuts = [round(i * len(files) / n_shards) for i in range(n_shards + 1)]
    return [(files[a].start, files[b - 1].stop) for a, b in zip(cuts, cuts[1:])]


class GlobalRows:
    """Rows ``offset .. offset + len(local) - 1`` of an ``(R, D)`` reference, by place number.

    Presents the whole reference's ``shape`` to the tile table, which indexes rows by place;
    a row outside the held ones is an internal error (the edge rows were too few).
    """

    def __init__(self, local: torch.Tensor, offset: int, n_ref: int) -> None:
        self.local, self.offset = local, int(offset)
        self.shape = torch.Size((int(n_ref), local.shape[1]))
        self.dtype, self.device = local.dtype, local.device

    def __getitem__(self, rows: torch.Tensor | slice) -> torch.Tensor:
        if isinstance(rows, slice):  # the tile table reads a block of rows at once
            rows = torch.arange(*rows.indices(self.shape[0]))
        rows = torch.as_tensor(rows)
        local = rows - self.offset
        if local.numel() and (int(local.min()) < 0 or int(local.max()) >= len(self.local)):
            raise RuntimeError(f"shard rows {self.offset}..{self.offset + len(self.local) - 1} "
                               f"do not hold rows {int(rows.min())}..{int(rows.max())}")
        return self.local[local]


class ShardWorker:
    """One shard of a map: its places, edge rows, and the scoring of its candidate starts.

    Runs in-process or as a Ray actor (:class:`ShardedSeqSLAM`). A map file that cannot be
    read does not raise here: :meth:`ready` reports it, so the driver can name the shard.

    Args:
        map_path: the map folder.
        shard: this worker's number (for messages).
        start: first place it owns.
        stop: one past the last.
        config: the run's :class:`SeqSLAMConfig` as a dict.
        dtype: working dtype name (``"float32"`` or ``"float64"``).
    """

    def __init__(self, map_path: str, shard: int, start: int, stop: int, config: dict,
                 dtype: str = "float32") -> None:
        torch.set_num_threads(1)
        self.shard, self.start, self.stop = shard, start, stop
        fields = dict(config)
        fields["image_size"] = tuple(fields["image_size"])
        self.config = SeqSLAMConfig(**fields).validate()
        self.dtype = getattr(torch, dtype)
        self.offsets, self.span, self.gap = band_geometry(self.config)
        self.ds = self.config.sequence_length
        self.cache: dict = {}
        self.error = None
        t = time.perf_counter()
        try:
            m = ReferenceMap(map_path)
            self.n_ref = m.n_places
            lo, hi = edge_rows(start, stop, self.n_ref, self.span, self.config.enhance_window)
            self.lo, self.hi = lo, hi
            self.reference = GlobalRows(m.rows(lo, hi), lo, self.n_ref)
        except (MapError, OSError, ValueError) as err:
            self.error = f"shard {shard} (places {start}..{stop - 1}) could not load: {err}"
        self.load_seconds = time.perf_counter() - t

    def _check(self) -> None:
        if self.error is not None:
            raise MapError(self.error)

    def ready(self) -> dict:
        """``{"error": message or None, "pid", "rows": held rows, "load_seconds"}``."""
        rows = 0 if self.error else self.hi - self.lo
        return {"error": self.error, "pid": os.getpid(), "rows": rows,
                "load_seconds": self.load_seconds}

    def memory(self) -> dict:
        """Bytes held: descriptor rows, cached tables, and the process's resident set."""
        held = 0 if self.error else self.reference.local.numel() * \
            self.reference.local.element_size()
        cached = sum(t.values.numel() * t.values.element_size() * 2
                     for _, _, _, t, _ in self.cache.values())
        rss = 0
        try:
            with open("/proc/self/statm") as f:
                rss = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, ValueError):  # pragma: no cover - not Linux
            pass
        return {"rows_bytes": held, "cache_bytes": cached, "rss_bytes": rss}

    def distances(self, query: torch.Tensor, proposals: torch.Tensor) -> torch.Tensor:
        """Exact distances of ``(Q, K')`` proposals this shard owns (``inf`` for the rest)."""
        self._check()
        own = (proposals >= self.start) & (proposals < self.stop)
        rows = torch.where(own, proposals, self.start)
        out = torch.empty(proposals.shape, dtype=self.dtype)
        step = max(1, PAIR_BLOCK_ELEMENTS // max(1, proposals.shape[1] * query.shape[1]))
        for q0 in range(0, len(query), step):
            ref = self.reference[rows[q0:q0 + step]].to(self.dtype)
            q = query[q0:q0 + step].to(self.dtype)[:, None, :]
            out[q0:q0 + step] = pair_differences(ref, q, self.config.metric)
        return out.masked_fill_(~own, math.inf)

    def _table(self, key, columns: torch.Tensor, windows: torch.Tensor, col_ids: torch.Tensor):
        """This shard's starts, bands and tile table of ``C`` windows (kept under ``key``).

        Args:
            key: the work's name.
            columns: ``(n, D)`` query descriptors, one per column id.
            windows: ``(C, ds + 1, K)`` candidates of each window's columns.
            col_ids: ``(C, ds + 1)`` column id of each window's columns.
        """
        if key in self.cache:
            return self.cache[key]
        n_ref = self.n_ref
        starts = candidate_starts(windows, self.offsets, n_ref)  # (C, P), padded with R
        own = (starts >= self.start) & (starts < self.stop)
        starts = starts.masked_fill(~own, n_ref).sort(dim=1).values
        starts = starts[:, :max(1, int(own.sum(1).max()))].contiguous()
        rows, is_start = compact_bands(starts, n_ref, self.span, self.gap)
        keys = band_tile_keys(rows, col_ids, -(-n_ref // TILE_ROWS))
        table = TileTable(self.reference, columns.to(self.dtype), keys, self.config.metric,
                          self.config.enhance_window)
        self.cache[key] = (starts, rows, is_start, table, col_ids)
        return self.cache[key]

    @staticmethod
    def _values(entry) -> torch.Tensor:
        """``(ds + 1, C, W)`` enhanced values of the windows' columns at their band rows."""
        _, rows, _, table, col_ids = entry
        return table.lookup(col_ids.T[:, :, None], rows[None])

    def _batch(self, key, query: torch.Tensor, cand: torch.Tensor):
        windows = cand.unfold(0, self.ds + 1, 1).permute(0, 2, 1)  # (C, ds + 1, K)
        col_ids = torch.arange(len(windows))[:, None] + torch.arange(self.ds + 1)
        return self._table(key, query, windows, col_ids)

    def _stream(self, key, descs: torch.Tensor, cands: torch.Tensor):
        b, n = descs.shape[:2]
        return self._table(key, descs.reshape(b * n, -1), cands,
                           torch.arange(b * n).view(b, n))

    def floor(self, key, query: torch.Tensor, cand: torch.Tensor) -> float:
        """Minimum enhanced value over this shard's band entries of a batch (inf if none).

        Args:
            key: the batch's name (its work is kept for :meth:`scores`).
            query: ``(C + ds, D)`` query descriptors of the batch's window columns.
            cand: ``(C + ds, K)`` their candidates (``-1``: none).
        """
        self._check()
        values = self._values(self._batch(key, query, cand))
        return float(values.min()) if values.numel() else math.inf

    def stream_floor(self, key, descs: torch.Tensor, cands: torch.Tensor) -> torch.Tensor:
        """``(ds + 1, B)`` minimum of each stream's window column over this shard's band rows.

        Args:
            key: the step's name (its work is kept for :meth:`stream_scores`).
            descs: ``(B, ds + 1, D)`` each stream's trailing window of descriptors.
            cands: ``(B, ds + 1, K)`` their candidates.
        """
        self._check()
        return self._values(self._stream(key, descs, cands)).amin(dim=2)

    def _scores(self, entry, floor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        starts, rows, is_start, _, _ = entry
        n_c, width = rows.shape
        ds = self.ds
        values = self._values(entry) - floor
        scores, best_v = trajectory_scores(values.reshape(ds + 1, n_c * width), ds // 2,
                                           ds // 2 + 1, ds, self.offsets, with_velocity=True)
        valid = starts < self.n_ref
        out = torch.full(starts.shape, math.inf, dtype=scores.dtype)
        vel = torch.zeros(starts.shape, dtype=torch.int64)
        out[valid] = scores[0, :-1].view(n_c, width)[is_start]
        vel[valid] = best_v[0, :-1].view(n_c, width)[is_start]
        return starts, out, vel

    def scores(self, key, query: torch.Tensor, cand: torch.Tensor, floor: float
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Exact scores of this shard's candidate starts of a batch, ``floor`` removed.

        A batch whose round-1 work is gone (a restarted actor) is recomputed.

        Returns:
            ``starts (C, P)`` int64 (sorted, padded with ``R``), ``scores (C, P)`` and
            ``velocity (C, P)`` int64 best velocity index (ties -> slowest).
        """
        self._check()
        entry = self._batch(key, query, cand)
        self.cache.pop(key)
        return self._scores(entry, floor)

    def stream_scores(self, key, descs: torch.Tensor, cands: torch.Tensor,
                      floor: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`scores` of ``B`` streams' windows, each column's ``(ds + 1, B)`` floor removed."""
        self._check()
        entry = self._stream(key, descs, cands)
        self.cache.pop(key)
        return self._scores(entry, floor[:, :, None])


def rank_merged(starts: torch.Tensor, scores: torch.Tensor, vel: torch.Tensor, n_ref: int,
                config: SeqSLAMConfig, offsets: list[list[int]], span: int, gap: int,
                report: str | None = None, top_k: int | None = None):
    """Rank every shard's candidate starts of ``C`` centres as one machine ranks its bands.

    The starts are laid out as one machine lays them out (:func:`compact_bands`) and ranked
    by the same function (:func:`~torchseq.seqslam.candidates.rank_bands`).

    Args:
        starts: ``(C, P)`` int64 starts of all shards (padded with ``R``), any order.
        scores: ``(C, P)`` their exact scores.
        vel: ``(C, P)`` their best velocity indices.
        n_ref: reference places ``R``.
        config: the run's config.
        offsets: per velocity, the row offsets of the ``ds + 1`` steps.
        span: rows per start's band.
        gap: the compact layout's gap.
        report: ``"start"``, ``"trajectory"`` or ``"end"`` (streaming); None:
            ``config.match_rule``.
        top_k: ranked places kept (None: ``config.top_k``).

    Returns:
        As :func:`~torchseq.seqslam.candidates.score_bands`: ``match (C,)``, ``best (C,)``,
        ``uniqueness (C,)``, ``ranked (C, top_k)``, best start ``(C,)`` (``-1`` if none) and
        its velocity index ``(C,)``.
    """
    order = starts.argsort(dim=1)
    starts, scores, vel = (x.gather(1, order) for x in (starts, scores, vel))
    rows, is_start = compact_bands(starts, n_ref, span, gap)  # the one-machine layout
    valid = starts < n_ref
    grid = torch.full(rows.shape, math.inf, dtype=scores.dtype)
    grid[is_start] = scores[valid]
    best_v = torch.zeros(rows.shape, dtype=torch.int64)
    best_v[is_start] = vel[valid]
    return rank_bands(grid, best_v, rows, is_start, config.sequence_length, offsets, n_ref,
                      config.rwindow, top_k or config.top_k, report or config.match_rule)


class _Local:
    """A worker called in-process, with the call style of a Ray actor handle."""

    class _Method:
        def __init__(self, fn):
            self.fn = fn

        def remote(self, *args):
            return self.fn(*args)

    def __init__(self, worker: ShardWorker) -> None:
        self.worker = worker

    def __getattr__(self, name):
        return self._Method(getattr(self.worker, name))


class ShardedSeqSLAM:
    """Candidate-mode SeqSLAM against a reference map spread over ``shards`` workers.

    Args:
        ref_map: a :class:`~torchseq.maps.ReferenceMap` or its folder.
        config: parameters (``candidates`` K >= 1, unless ``candidates`` is given).
        shards: workers, each holding whole shard files of the map.
        candidates: K, overriding ``config.candidates``.
        address: Ray cluster address (None: the running one, or a local cluster started now
            and stopped by :meth:`close`); ignored with ``use_ray=False``.
        use_ray: False runs the workers in this process (same results; for tests and
            debugging).
        batch: query centres per task.
        refine: as :class:`CandidateSeqSLAM`: an approximate index proposes ``refine * K``.
        max_restarts: times a killed actor is restarted (it reloads its shard).
        actor_options: more ``ray.remote`` options of the actors (default ``num_cpus=0``).
        dtype: working dtype (None: float64 for float64 maps, else float32).
    """

    def __init__(self, ref_map: ReferenceMap | str, config: SeqSLAMConfig | None = None,
                 shards: int = 1, candidates: int | None = None, address: str | None = None,
                 use_ray: bool = True, batch: int = DEFAULT_BATCH, refine: int = 4,
                 max_restarts: int = 3, actor_options: dict | None = None,
                 dtype: torch.dtype | None = None) -> None:
        self.map = ref_map if isinstance(ref_map, ReferenceMap) else ReferenceMap(ref_map)
        self.config = (config or SeqSLAMConfig()).validate()
        k = candidates if candidates is not None else self.config.candidates
        if k is None or isinstance(k, bool) or int(k) < 1:
            raise ValueError(f"sharded matching runs candidate mode: it needs candidates "
                             f"K >= 1, got {k!r}")
        if isinstance(batch, bool) or int(batch) < 1:
            raise ValueError(f"batch must be an integer >= 1, got {batch!r}")
        if isinstance(refine, bool) or int(refine) < 1:
            raise ValueError(f"refine must be an integer >= 1, got {refine!r}")
        self.k, self.batch, self.refine = int(k), int(batch), int(refine)
        self.dtype = dtype or (torch.float64 if self.map.dtype == "float64" else torch.float32)
        self.offsets, self.span, self.gap = band_geometry(self.config)
        self.ranges = shard_ranges(self.map, int(shards))
        self.index = self.map.index()
        self.use_ray = bool(use_ray)
        self._started_ray = False
        self._on_round = None  # tests: called with the round's name once its tasks are out
        self.workers = []
        cfg = asdict(self.config)
        dtype_name = str(self.dtype).replace("torch.", "")
        args = [(str(self.map.path), i, a, b, cfg, dtype_name)
                for i, (a, b) in enumerate(self.ranges)]
        if not self.use_ray:
            self.workers = [_Local(ShardWorker(*a)) for a in args]
        else:
            ray = _import_ray()
            if not ray.is_initialized():
                try:
                    ray.init(address=address, include_dashboard=False, log_to_driver=False)
                except Exception as err:  # noqa: BLE001 - Ray raises plain Exception here
                    where = f"the Ray cluster at {address}" if address else \
                        "a local Ray cluster"
                    first = str(err).splitlines()[0] if str(err) else type(err).__name__
                    raise RuntimeError(f"could not start or reach {where}: {first} (start "
                                       f"one with 'ray start --head' and pass its address "
                                       f"as --ray-address / address=)") from err
                self._started_ray = True
            options = {"num_cpus": 0, **(actor_options or {}),
                       "max_restarts": int(max_restarts), "max_task_retries": int(max_restarts)}
            actor = ray.remote(ShardWorker).options(**options)
            self.workers = [actor.remote(*a) for a in args]
        self.status = self._get([w.ready.remote() for w in self.workers])
        for state in self.status:
            if state["error"]:
                self.close()
                raise MapError(state["error"])

    def _get(self, refs):
        if not self.use_ray:
            return refs
        return _import_ray().get(refs)

    def _put(self, value):
        return _import_ray().put(value) if self.use_ray else value

    def search(self, query: torch.Tensor) -> torch.Tensor:
        """``(Q, D)`` -> ``(Q, K)`` candidates, as :meth:`CandidateSeqSLAM.search` gives them.

        A flat index gives its top K; an approximate one proposes ``refine * K``, the shards
        return the exact distances of those they hold, and the K nearest are kept by
        ``(distance, place)`` (``-1`` where fewer are finite).
        """
        if self.index.kind == "flat" or self.refine <= 1:
            return self.index.search(query, self.k)
        cand = self.index.search(query, self.refine * self.k)  # (Q, K')
        parts = self._get([w.distances.remote(query, cand) for w in self.workers])
        d = torch.stack(parts).amin(0).masked_fill_(cand < 0, math.inf)
        by_ref = cand.masked_fill(cand < 0, self.map.n_places).argsort(dim=1)
        d, cand = d.gather(1, by_ref), cand.gather(1, by_ref)
        order = d.argsort(dim=1, stable=True)[:, :min(self.k, cand.shape[1])]
        return torch.where(d.gather(1, order).isfinite(), cand.gather(1, order), -1)

    def match_descriptors(self, query: torch.Tensor):
        """Match ``(Q, D)`` query descriptors (as :meth:`CandidateSeqSLAM.match_descriptors`).

        Returns:
            :class:`~torchseq.seqslam.result.SeqSLAMResult` without matrices; ``seconds``:
            ``"candidates"``, ``"floor"`` (round 1), ``"scores"`` (round 2), ``"merge"``
            (the driver's layout and ranking) and ``"total"``; ``kernels["shards"]``.
        """
        c, ds = self.config, self.config.sequence_length
        query = torch.as_tensor(query)
        check_not_empty(query, "query descriptors")
        check_shape(query, ("Q", self.map.dim), "query descriptors")
        check_finite(query, "query descriptors")
        check_magnitude(query, "query descriptors")
        n_query, n_ref = query.shape[0], self.map.n_places
        if n_query < ds + 1:
            raise ValueError(f"need at least ds + 1 = {ds + 1} query frames for ds = {c.ds}, "
                             f"got {n_query}")
        query = query.to("cpu", self.dtype)  # the workers compute on their CPUs
        seconds = {}
        t0 = t = time.perf_counter()
        cand = self.search(query)
        seconds["candidates"] = time.perf_counter() - t
        t = time.perf_counter()
        run = f"{os.getpid()}-{time.monotonic_ns()}"
        batches = []
        for c0 in range(0, n_query - ds, self.batch):
            c1 = min(c0 + self.batch, n_query - ds)
            batches.append((c0, c1, (run, c0), self._put(query[c0:c1 + ds]),
                            self._put(cand[c0:c1 + ds])))
        refs = [[w.floor.remote(key, q, k) for w in self.workers] for _, _, key, q, k in batches]
        if self._on_round is not None:
            self._on_round("floor")
        floors = self._get([r for row in refs for r in row])
        floor = min(floors) if floors else math.inf
        floor = floor if math.isfinite(floor) else 0.0  # nothing evaluated: no match anywhere
        seconds["floor"] = time.perf_counter() - t
        t = time.perf_counter()
        refs = [[w.scores.remote(key, q, k, floor) for w in self.workers]
                for _, _, key, q, k in batches]
        if self._on_round is not None:
            self._on_round("scores")
        parts = self._get([r for row in refs for r in row])
        seconds["scores"] = time.perf_counter() - t
        t = time.perf_counter()
        match = torch.full((n_query,), -1, dtype=torch.int64)
        best_score = torch.full((n_query,), math.nan, dtype=self.dtype)
        uniqueness = torch.full_like(best_score, math.nan)
        ranked = torch.full((n_query, c.top_k), -1, dtype=torch.int64)
        n_w = len(self.workers)
        for b, (c0, c1, *_rest) in enumerate(batches):
            got = parts[b * n_w:(b + 1) * n_w]
            starts, scores, vel = (torch.cat([g[i] for g in got], 1) for i in range(3))
            out = rank_merged(starts, scores, vel, n_ref, c, self.offsets, self.span, self.gap)
            sl = slice(c0 + ds // 2, c1 + ds // 2)
            match[sl], best_score[sl], uniqueness[sl], ranked[sl] = out[:4]
        seconds["merge"] = time.perf_counter() - t
        seconds["total"] = time.perf_counter() - t0
        return SeqSLAMResult(
            matches=Matches(match, uniqueness, lower_is_better=True), difference=None,
            enhanced=None, ranked=ranked, best_score=best_score, seconds=seconds,
            kernels={"shards": n_w, "ray": self.use_ray})

    def initial_state(self, batch: int) -> ShardedStreamState:
        """The state of ``batch`` streams that have seen no frame."""
        return ShardedStreamState(torch.zeros(batch, 0, self.map.dim, dtype=self.dtype),
                                  torch.zeros(batch, 0, self.k, dtype=torch.int64))

    def step(self, desc: torch.Tensor, state: ShardedStreamState | None = None
             ) -> tuple[StreamingMatch, ShardedStreamState]:
        """One step of ``B`` independent streams (robots), as :meth:`StreamingSeqSLAM.step`.

        Each stream's trailing window of ``ds + 1`` frames is scored on the shards (two
        rounds: each column's minimum over the window's band rows, then the starts' exact
        scores); the decisions are :class:`StreamingSeqSLAM`'s in candidate mode.

        Args:
            desc: ``(B, D)`` one new query descriptor per stream.
            state: from the previous step (None: the streams start now).

        Returns:
            ``(StreamingMatch, new state)``.
        """
        desc = torch.as_tensor(desc)
        check_shape(desc, ("B", self.map.dim), "query descriptors")
        check_not_empty(desc, "query descriptors")
        check_finite(desc, "query descriptors")
        check_magnitude(desc, "query descriptors")
        b, ds = desc.shape[0], self.config.sequence_length
        state = self.initial_state(b) if state is None else state
        if (not isinstance(state, ShardedStreamState) or state.descriptors.shape[0] != b
                or state.descriptors.shape[2] != desc.shape[1]):
            raise ValueError(f"state must come from this object's step for {b} streams")
        desc = desc.to("cpu", self.dtype)
        descs = torch.cat([state.descriptors[:, -ds:], desc[:, None]], 1)
        cands = torch.cat([state.candidates[:, -ds:], self.search(desc)[:, None]], 1)
        state = ShardedStreamState(descs, cands)
        if descs.shape[1] < ds + 1:
            none = torch.full((b,), -1, dtype=torch.int64)
            nan = torch.full((b,), math.nan, dtype=torch.float64)
            return StreamingMatch(none, nan, none.clone(), nan.clone()), state
        key = ("step", os.getpid(), time.monotonic_ns())
        d_ref, c_ref = self._put(descs), self._put(cands)
        floors = self._get([w.stream_floor.remote(key, d_ref, c_ref) for w in self.workers])
        floor = torch.stack(floors).amin(0)  # (ds + 1, B)
        floor = torch.where(torch.isfinite(floor), floor, 0.0)
        parts = self._get([w.stream_scores.remote(key, d_ref, c_ref, floor)
                           for w in self.workers])
        starts, scores, vel = (torch.cat([g[i] for g in parts], 1) for i in range(3))
        match, _, ratio, _, first, vel = rank_merged(
            starts, scores, vel, self.map.n_places, self.config, self.offsets, self.span,
            self.gap, report="end", top_k=1)
        speeds = torch.tensor(velocities(ds, *self.config.velocity_range), dtype=torch.float64)
        velocity = torch.where(match >= 0, speeds[vel], math.nan)
        return StreamingMatch(match, ratio.double(), first, velocity), state

    def memory(self) -> list[dict]:
        """Per worker: bytes of rows held, cached work and the process's resident set."""
        return self._get([w.memory.remote() for w in self.workers])

    def restarted(self) -> list[int]:
        """The shards whose actor was restarted since they started (a new process id)."""
        now = self._get([w.ready.remote() for w in self.workers])
        return [i for i, (a, b) in enumerate(zip(self.status, now)) if a["pid"] != b["pid"]]

    def close(self) -> None:
        """Stop the actors (and the local Ray cluster this object started)."""
        if self.use_ray and self.workers:
            ray = _import_ray()
            for w in self.workers:
                ray.kill(w, no_restart=True)
        self.workers = []
        if self._started_ray:
            _import_ray().shutdown()
            self._started_ray = False

    def __enter__(self) -> ShardedSeqSLAM:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _import_ray():
    """The ``ray`` module, or an ``ImportError`` that says how to install it."""
    try:
        import ray
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError("sharded matching runs on Ray: pip install 'torchseq[ray]'") from err
    return ray


__all__ = ["ShardWorker", "ShardedSeqSLAM", "ShardedStreamState", "edge_rows", "rank_merged",
           "shard_ranges"]

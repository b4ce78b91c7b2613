"""Streaming SeqSLAM: match each newly arriving query frame with its trailing window.

At time ``t`` (``t >= ds``) the trajectories span the trailing query frames ``t - ds .. t``,
i.e. the batch engine's query centre ``t - ds/2``. Every step is causal:

- the difference column of frame ``t`` needs only the (fixed) reference;
- contrast enhancement runs along the reference axis of that one column, so it is causal;
- OpenSeqSLAM's subtraction of the *global* minimum needs the future; instead each column's
  own minimum is subtracted. Every trajectory takes exactly one entry per column, so this
  shifts all trajectory costs of a window by the same constant: the best start and velocity
  are exactly the batch ones; only the uniqueness ratio's value changes (both rules keep all
  entries >= 0, so the ratio stays in 0..1 and lower = more distinctive).

The reported place is the reference at the trajectory's END, ``s + floor(ds v)`` (clamped
to ``R - 1``): where the robot is now, not ``ds/2`` frames ago.

Candidate mode (``config.candidates >= 1``, see :mod:`torchseq.seqslam.candidates`): the
state keeps the trailing window's descriptors and their K candidates; each step scores the
candidate starts of the window from the enhanced values of its band rows, and subtracts from
each column the minimum over those rows (with ``K >= R`` that is the column's minimum, and
the decisions are the exact streaming ones).

Like :meth:`torchseq.neural.NeuralSeqSLAM.step`, :meth:`StreamingSeqSLAM.step` takes a batch
of independent streams and an explicit state: ``step(frames (B, H, W), state) -> (match,
state)``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import nn

from torchseq._checks import check_finite, check_shape
from torchseq.matches import Matches
from torchseq.seqslam.candidates import (
    TILE_ROWS,
    CandidateSeqSLAM,
    TileTable,
    band_tile_keys,
    score_bands,
)
from torchseq.seqslam.config import SeqSLAMConfig
from torchseq.seqslam.difference import check_magnitude, difference_matrix
from torchseq.seqslam.engine import SeqSLAM
from torchseq.seqslam.enhance import enhance_contrast
from torchseq.seqslam.search import trajectory_offsets


class StreamingMatch(NamedTuple):
    """One streaming decision per stream, ``(B,)`` each.

    Attributes:
        reference: int64 reference at the trajectory's end; ``-1`` until ``ds + 1`` frames
            and where no trajectory is finite.
        score: float64 uniqueness ratio (lower = more distinctive; NaN without a match).
        start: int64 start of the best trajectory (``-1`` without a match).
        velocity: float64 its velocity (NaN without a match).
    """

    reference: torch.Tensor
    score: torch.Tensor
    start: torch.Tensor
    velocity: torch.Tensor


class TileCache(NamedTuple):
    """Candidate mode: the enhanced tiles already computed for the trailing frames.

    An enhanced tile (``TILE_ROWS`` reference rows of one query frame) depends only on that
    frame's descriptor, so each is computed once and reused by the next ``ds`` steps.

    Attributes:
        keys: ``(N,)`` int64 sorted ``(serial * B + stream) * n_tiles + tile``.
        values: ``(N, TILE_ROWS)`` enhanced values (no minimum subtracted).
        serial: frames seen per stream (the serial the next frame gets).
    """

    keys: torch.Tensor
    values: torch.Tensor
    serial: int


class StreamingState(NamedTuple):
    """The trailing window of ``B`` streams (``n <= ds + 1`` frames seen so far, capped).

    Attributes:
        descriptors: ``(B, n, D)`` query descriptors.
        columns: ``(B, n, R)`` enhanced, column-min-subtracted difference columns (exact
            mode); ``(B, n, 0)`` in candidate mode.
        candidates: ``(B, n, K)`` int64 candidate references (candidate mode); ``(B, n, 0)``
            in exact mode.
        tiles: candidate mode's :class:`TileCache` (None: none computed yet, or exact mode).
    """

    descriptors: torch.Tensor
    columns: torch.Tensor
    candidates: torch.Tensor
    tiles: TileCache | None = None


class StreamingSeqSLAM(nn.Module):
    """Match query frames of ``B`` streams one step at a time against a fixed reference.

    Args:
        reference: ``(R, H, W)`` frames, or ``(R, D)`` descriptors with ``descriptors=True``.
        config: parameters (defaults: OpenSeqSLAM's); ``candidates >= 1`` = candidate mode.
        device: where to compute.
        dtype: working dtype (None: float64 stays float64, else float32).
        descriptors: ``reference`` (and every ``step`` input) are already descriptors.
        index: candidate mode's index kind (see
            :class:`~torchseq.seqslam.ann_index.CandidateIndex`).
    """

    def __init__(self, reference: torch.Tensor, config: SeqSLAMConfig | None = None,
                 device: torch.device | str | None = None, dtype: torch.dtype | None = None,
                 descriptors: bool = False, index: str = "auto") -> None:
        super().__init__()
        self.engine = SeqSLAM(config, device, dtype)
        self.config = self.engine.config
        self.from_descriptors = descriptors
        reference = torch.as_tensor(reference)
        if descriptors:
            check_shape(reference, ("R", "D"), "reference descriptors")
            check_finite(reference, "reference descriptors")
            check_magnitude(reference, "reference descriptors")
            ref = reference.to(self.engine.device, self.engine._working_dtype(reference))
        else:
            ref = self.engine.descriptors(reference)
        if ref.shape[0] < 2:
            raise ValueError(f"need at least 2 reference frames, got {ref.shape[0]}")
        self.register_buffer("reference", ref, persistent=False)
        self.candidate = None
        if self.config.candidates:  # None and 0: exact (a stream has no size to judge by)
            self.candidate = CandidateSeqSLAM(ref, self.config, index=index,
                                              device=ref.device, dtype=ref.dtype)
        self.ds = self.config.sequence_length
        self.speeds = self.engine.speeds
        self.offsets = trajectory_offsets(self.ds, self.speeds)
        self.gap = max(max(off[-1] for off in self.offsets) + 1, self.config.rwindow // 2 + 1)

    def initial_state(self, batch: int) -> StreamingState:
        """The state of ``batch`` streams that have seen no frame."""
        ref = self.reference
        k = self.candidate.k if self.candidate else 0
        return StreamingState(ref.new_zeros(batch, 0, ref.shape[1]),
                              ref.new_zeros(batch, 0, 0 if self.candidate else ref.shape[0]),
                              torch.zeros(batch, 0, k, dtype=torch.int64, device=ref.device))

    def _descriptors(self, frames: torch.Tensor) -> torch.Tensor:
        """``(B, H, W)`` frames (or ``(B, D)`` descriptors) -> ``(B, D)`` descriptors."""
        frames = torch.as_tensor(frames)
        ref = self.reference
        if self.from_descriptors:
            if frames.dim() == 1:
                raise ValueError(
                    f"step takes a batch of descriptors (B, {ref.shape[1]}) and a state, got "
                    f"one descriptor {tuple(frames.shape)}: call step(desc[None], state) and "
                    f"keep the state it returns")
            check_shape(frames, ("B", ref.shape[1]), "query descriptors")
            desc = frames.to(ref.device, ref.dtype)
        else:
            if frames.dim() == 2 or (frames.dim() == 3 and frames.shape[-1] == 3):
                raise ValueError(
                    f"step takes a batch of frames (B, H, W) or (B, H, W, 3) and a state, got "
                    f"{tuple(frames.shape)}, which looks like one frame: call "
                    f"step(frame[None], state) and keep the state it returns")
            if frames.dim() not in (3, 4) or frames.shape[0] == 0:
                raise ValueError(f"frames must be a non-empty (B, H, W) or (B, H, W, 3) batch, "
                                 f"got {tuple(frames.shape)}")
            check_finite(frames, "query frames")
            desc = self.engine.descriptors(frames).to(ref.dtype)
        if desc.shape[0] == 0:
            raise ValueError("the batch holds no stream (B = 0)")
        check_finite(desc, "query descriptors")
        check_magnitude(desc, "query descriptors")
        return desc

    def _exact_columns(self, desc: torch.Tensor) -> torch.Tensor:
        """``(B, D)`` descriptors -> ``(B, R)`` enhanced, column-min-subtracted differences."""
        c = self.config
        d = difference_matrix(self.reference, desc, c.metric, c.max_chunk_elements)
        e = enhance_contrast(d, c.enhance_window, False, c.max_chunk_elements).T  # (B, R)
        return e - e.min(dim=1, keepdim=True).values

    def step(self, frames: torch.Tensor,
             state: StreamingState | None = None) -> tuple[StreamingMatch, StreamingState]:
        """One step of ``B`` independent streams.

        Args:
            frames: ``(B, H, W)`` (or ``(B, H, W, 3)``) one new frame per stream, or ``(B, D)``
                descriptors with ``descriptors=True``.
            state: from the previous step (None: the streams start now).

        Returns:
            ``(StreamingMatch, new state)``.
        """
        desc = self._descriptors(frames)
        b = desc.shape[0]
        state = self.initial_state(b) if state is None else state
        if (not isinstance(state, StreamingState) or state.descriptors.shape[0] != b
                or state.descriptors.shape[2] != desc.shape[1]):
            got = getattr(getattr(state, "descriptors", None), "shape", None)
            raise ValueError(f"state must come from this engine's step for {b} streams "
                             f"(descriptors ({b}, n, {desc.shape[1]})), got {got}")
        keep = self.ds  # the new frame makes ds + 1
        descs = torch.cat([state.descriptors[:, -keep:], desc[:, None]], 1)
        if self.candidate is None:
            cols = torch.cat([state.columns[:, -keep:], self._exact_columns(desc)[:, None]], 1)
            cands = state.candidates[:, -keep:]
        else:
            cols = state.columns[:, -keep:]
            new = self.candidate.search(desc)[:, None]
            cands = torch.cat([state.candidates[:, -keep:], new], 1)
        tiles = state.tiles
        if self.candidate is not None:
            tiles = tiles or TileCache(torch.zeros(0, dtype=torch.int64, device=desc.device),
                                       desc.new_zeros(0, TILE_ROWS), 0)
            tiles = tiles._replace(serial=tiles.serial + 1)  # the new frame's serial + 1
        state = StreamingState(descs, cols, cands, tiles)
        if descs.shape[1] < self.ds + 1:
            none = torch.full((b,), -1, dtype=torch.int64)
            nan = torch.full((b,), math.nan, dtype=torch.float64)
            return StreamingMatch(none, nan, none.clone(), nan.clone()), state
        if self.candidate is None:
            out = self._score_exact(cols)
        else:
            out, tiles = self._score_candidates(descs, cands, tiles)
            state = state._replace(tiles=tiles)
        match, _, ratio, _, first, vel = out
        speeds = torch.tensor(self.speeds, dtype=torch.float64)
        ok = match >= 0
        velocity = torch.where(ok.cpu(), speeds[vel.cpu()], math.nan)
        return StreamingMatch(match.cpu(), ratio.cpu().double(), first.cpu(), velocity), state

    def _score_exact(self, cols: torch.Tensor):
        """Score ``(B, ds + 1, R)`` windows: each stream's starts laid out with an inf gap."""
        b, _, n_ref = cols.shape
        width = n_ref + self.gap
        values = cols.new_full((self.ds + 1, b, width), math.inf)
        values[:, :, :n_ref] = cols.permute(1, 0, 2)
        rows = torch.full((b, width), -1, dtype=torch.int64, device=cols.device)
        rows[:, :n_ref] = torch.arange(n_ref, device=cols.device)
        return score_bands(values, rows, rows >= 0, self.ds, self.offsets, n_ref,
                           self.config.rwindow, 1, "end")

    def _score_candidates(self, descs: torch.Tensor, cands: torch.Tensor,
                          cache: TileCache) -> tuple[tuple, TileCache]:
        """Score ``B`` windows of candidates ``(B, ds + 1, K)`` from their band values.

        Tiles of earlier frames come from ``cache`` (computed by earlier steps); only the
        missing ones are computed. Returns the scores and the cache for the next step (the
        tiles of the frames still in its window).
        """
        cand = self.candidate
        b, n = descs.shape[:2]
        n_tiles = -(-cand.n_ref // TILE_ROWS)
        rows, is_start = cand.bands(cands)
        column_ids = torch.arange(b * n, device=descs.device).view(b, n)
        keys = band_tile_keys(rows, column_ids, n_tiles)  # sorted, (b * n + i) * n_tiles + t
        col, tile = keys // n_tiles, keys % n_tiles
        first = cache.serial - n  # serial of the window's first frame
        serial_keys = ((first + col % n) * b + col // n) * n_tiles + tile
        values = descs.new_empty(len(keys), TILE_ROWS)
        hit = torch.zeros(len(keys), dtype=torch.bool, device=keys.device)
        if len(cache.keys):
            slot = torch.searchsorted(cache.keys, serial_keys).clamp_max(len(cache.keys) - 1)
            hit = cache.keys[slot] == serial_keys
            values[hit] = cache.values[slot[hit]]
        if bool((~hit).any()):
            table: TileTable = cand.table(descs.reshape(b * n, -1), keys[~hit])
            values[~hit] = table.values
        table = TileTable.from_values(keys, values, n_tiles)
        vals = table.lookup(column_ids.T[:, :, None], rows[None])  # (ds + 1, B, W)
        floor = vals.amin(dim=2, keepdim=True)  # each column's minimum over the band rows
        vals = vals - torch.where(torch.isfinite(floor), floor, 0.0)
        out = score_bands(vals, rows, is_start, self.ds, self.offsets, cand.n_ref,
                          self.config.rwindow, 1, "end")
        # keep the tiles of frames the next window still holds (serials >= serial - ds)
        all_keys = torch.cat([cache.keys, serial_keys[~hit]])
        all_values = torch.cat([cache.values, values[~hit]])
        keep = all_keys // (b * n_tiles) >= cache.serial - self.ds
        order = all_keys[keep].argsort()
        return out, TileCache(all_keys[keep][order], all_values[keep][order], cache.serial)

    def run(self, query: torch.Tensor) -> Matches:
        """Stream a whole traverse ``(Q, H, W)`` (or ``(Q, D)`` descriptors) as one stream."""
        state, refs, scores = None, [], []
        for q in torch.as_tensor(query):
            out, state = self.step(q[None], state)
            refs.append(out.reference)
            scores.append(out.score)
        return Matches(torch.cat(refs), torch.cat(scores), lower_is_better=True)

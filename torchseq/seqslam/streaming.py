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
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import nn

from torchseq._checks import check_finite, check_shape
from torchseq.matches import Matches
from torchseq.seqslam.config import SeqSLAMConfig
from torchseq.seqslam.difference import difference_matrix
from torchseq.seqslam.engine import SeqSLAM
from torchseq.seqslam.enhance import enhance_contrast
from torchseq.seqslam.search import rank_scores, trajectory_offsets, trajectory_scores


class StreamingMatch(NamedTuple):
    """One streaming decision: ``reference`` -1 and ``score`` NaN until ``ds + 1`` frames."""

    reference: int
    score: float
    start: int
    velocity: float


class StreamingSeqSLAM(nn.Module):
    """Match query frames one at a time against a fixed reference traverse.

    Args:
        reference: ``(R, H, W)`` frames, or ``(R, D)`` descriptors with ``descriptors=True``.
        config: parameters (defaults: OpenSeqSLAM's).
        device: where to compute.
        dtype: working dtype (None: float64 stays float64, else float32).
        descriptors: ``reference`` (and every ``step`` input) are already descriptors.
    """

    def __init__(self, reference: torch.Tensor, config: SeqSLAMConfig | None = None,
                 device: torch.device | str | None = None, dtype: torch.dtype | None = None,
                 descriptors: bool = False) -> None:
        super().__init__()
        self.engine = SeqSLAM(config, device, dtype)
        self.config = self.engine.config
        self.from_descriptors = descriptors
        reference = torch.as_tensor(reference)
        if descriptors:
            check_shape(reference, ("R", "D"), "reference descriptors")
            check_finite(reference, "reference descriptors")
            ref = reference.to(self.engine.device, self.engine._working_dtype(reference))
        else:
            ref = self.engine.descriptors(reference)
        if ref.shape[0] < 2:
            raise ValueError(f"need at least 2 reference frames, got {ref.shape[0]}")
        self.register_buffer("reference", ref, persistent=False)
        self.ds = self.config.sequence_length
        self.speeds = self.engine.speeds
        self.offsets = trajectory_offsets(self.ds, self.speeds)
        self.reset()

    def reset(self) -> None:
        """Forget the query frames seen so far."""
        self.window = self.reference.new_zeros(0, self.reference.shape[0])

    def column(self, desc: torch.Tensor) -> torch.Tensor:
        """``(D,)`` query descriptor -> ``(R,)`` enhanced, column-min-subtracted differences."""
        c = self.config
        d = difference_matrix(self.reference, desc[None], c.metric, c.max_chunk_elements)
        e = enhance_contrast(d, c.enhance_window, False, c.max_chunk_elements)[:, 0]
        return e - e.min()

    def step_descriptor(self, desc: torch.Tensor) -> StreamingMatch:
        """Take the next ``(D,)`` query descriptor and return the current decision."""
        desc = torch.as_tensor(desc).to(self.reference.device, self.reference.dtype)
        check_shape(desc, (self.reference.shape[1],), "query descriptor")
        check_finite(desc, "query descriptor")
        col = self.column(desc)
        self.window = torch.cat([self.window[-self.ds:], col[None]])  # (<= ds + 1, R)
        if self.window.shape[0] < self.ds + 1:
            return StreamingMatch(-1, math.nan, -1, math.nan)
        half = self.ds // 2
        scores, vel = trajectory_scores(self.window, half, half + 1, self.ds, self.offsets,
                                        with_velocity=True)
        start, best, ratio, _ = rank_scores(scores, self.ds, self.reference.shape[0],
                                            self.config.rwindow, 1)
        s = int(start[0])
        if not math.isfinite(float(best[0])):
            return StreamingMatch(-1, math.nan, -1, math.nan)
        v = int(vel[0, s])
        end = min(s + self.offsets[v][-1], self.reference.shape[0] - 1)
        return StreamingMatch(end, float(ratio[0]), s, self.speeds[v])

    def step(self, frame: torch.Tensor) -> StreamingMatch:
        """Take the next query frame ``(H, W)`` (or descriptor ``(D,)``) and decide."""
        frame = torch.as_tensor(frame)
        if self.from_descriptors:
            return self.step_descriptor(frame)
        return self.step_descriptor(self.engine.descriptors(frame[None])[0])

    def run(self, query: torch.Tensor) -> Matches:
        """Stream a whole traverse ``(Q, H, W)`` (or ``(Q, D)`` descriptors) from a reset state."""
        self.reset()
        out = [self.step(q) for q in torch.as_tensor(query)]
        return Matches(torch.tensor([o.reference for o in out], dtype=torch.int64),
                       torch.tensor([o.score for o in out], dtype=torch.float64),
                       lower_is_better=True)

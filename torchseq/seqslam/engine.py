"""The classic SeqSLAM engine: descriptors -> difference matrix -> enhancement -> search."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import torch
from torch import nn

from torchseq._checks import check_not_empty
from torchseq.matches import Matches
from torchseq.preprocess import preprocess
from torchseq.seqslam.candidates import CandidateSeqSLAM, resolve_candidates
from torchseq.seqslam.config import SeqSLAMConfig
from torchseq.seqslam.difference import check_descriptors, difference_matrix
from torchseq.seqslam.enhance import enhance_contrast
from torchseq.seqslam.search import search, velocities


@dataclass
class SeqSLAMResult:
    """What one SeqSLAM run produces.

    Attributes:
        matches: per query, the matched reference (``-1`` for the first and last ``ds/2``
            queries and where no trajectory is finite) and its uniqueness ratio
            (``lower_is_better=True``; NaN without a match).
        difference: ``(R, Q)`` difference matrix on CPU.
        enhanced: ``(R, Q)`` contrast-enhanced difference matrix on CPU.
        ranked: ``(Q, top_k)`` int64 candidate references, best first, ``-1`` for none.
        best_score: ``(Q,)`` best trajectory cost (NaN where unscored).
        seconds: wall time of ``"difference"``, ``"enhance"``, ``"search"`` and ``"total"``.
    """

    matches: Matches
    difference: torch.Tensor
    enhanced: torch.Tensor
    ranked: torch.Tensor
    best_score: torch.Tensor
    seconds: dict = field(default_factory=dict)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class SeqSLAM(nn.Module):
    """OpenSeqSLAM-compatible sequence matcher on CPU or CUDA (no learnable parameters).

    Args:
        config: parameters (defaults: OpenSeqSLAM's).
        device: where to compute (default: CPU); results come back on CPU.
        dtype: working float dtype; None keeps float64 inputs float64 and uses float32
            otherwise.
    """

    def __init__(self, config: SeqSLAMConfig | None = None,
                 device: torch.device | str | None = None,
                 dtype: torch.dtype | None = None) -> None:
        super().__init__()
        self.config = (config or SeqSLAMConfig()).validate()
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.dtype = dtype

    @property
    def speeds(self) -> list[float]:
        """Trajectory velocities the search uses."""
        return velocities(self.config.sequence_length, *self.config.velocity_range)

    def _working_dtype(self, x: torch.Tensor) -> torch.dtype:
        if self.dtype is not None:
            return self.dtype
        return torch.float64 if x.dtype == torch.float64 else torch.float32

    def descriptors(self, frames: torch.Tensor) -> torch.Tensor:
        """Grey, resize and patch-normalise frames.

        Args:
            frames: ``(T, H, W)`` or ``(T, H, W, 3)``.

        Returns:
            ``(T, h * w)`` descriptors on the engine's device.
        """
        c = self.config
        frames = torch.as_tensor(frames)
        desc = preprocess(frames.to(self.device), c.image_size, c.patch_size, mode="seqslam")
        return desc.to(self._working_dtype(frames))

    def match(self, reference: torch.Tensor, query: torch.Tensor,
              progress: bool = False) -> SeqSLAMResult:
        """Match a query traverse of frames against a reference traverse.

        Args:
            reference: ``(R, H, W)`` (or RGB ``(R, H, W, 3)``) frames.
            query: ``(Q, H, W)`` frames.
            progress: show a progress bar during the search.
        """
        check_not_empty(torch.as_tensor(reference), "reference frames")
        check_not_empty(torch.as_tensor(query), "query frames")
        return self.match_descriptors(self.descriptors(reference), self.descriptors(query),
                                      progress=progress)

    def match_descriptors(self, reference: torch.Tensor, query: torch.Tensor,
                          progress: bool = False) -> SeqSLAMResult:
        """Match ``(Q, D)`` query descriptors against ``(R, D)`` reference descriptors."""
        c = self.config
        reference, query = torch.as_tensor(reference), torch.as_tensor(query)
        check_descriptors(reference, query)
        ds = c.sequence_length
        if reference.shape[0] < 2:
            raise ValueError(f"need at least 2 reference frames, got {reference.shape[0]}")
        if query.shape[0] < ds + 1:
            raise ValueError(
                f"need at least ds + 1 = {ds + 1} query frames for ds = {c.ds}, "
                f"got {query.shape[0]}")
        dtype = self._working_dtype(reference)
        reference = reference.to(self.device, dtype)
        query = query.to(self.device, dtype)
        k = resolve_candidates(c, reference.shape[0], query.shape[0])
        if k:  # candidate mode: an index proposes K references per query (candidates.py)
            result = CandidateSeqSLAM(reference, c, k, device=self.device,
                                      dtype=dtype).match_descriptors(query, progress)
            result.seconds["total"] += result.seconds["index"]  # built for this call
            return result
        seconds = {}
        t0 = t = time.perf_counter()
        diff = difference_matrix(reference, query, c.metric, c.max_chunk_elements)
        _sync(self.device)
        seconds["difference"] = time.perf_counter() - t
        t = time.perf_counter()
        enhanced = enhance_contrast(diff, c.enhance_window, True, c.max_chunk_elements)
        _sync(self.device)
        seconds["enhance"] = time.perf_counter() - t
        t = time.perf_counter()
        match, best, ratio, ranked = search(enhanced, ds, self.speeds, c.rwindow, c.top_k,
                                            c.max_chunk_elements, progress, c.match_rule)
        _sync(self.device)
        seconds["search"] = time.perf_counter() - t
        seconds["total"] = time.perf_counter() - t0
        return SeqSLAMResult(
            matches=Matches(match.cpu(), ratio.cpu(), lower_is_better=True),
            difference=diff.cpu(), enhanced=enhanced.cpu(), ranked=ranked.cpu(),
            best_score=best.cpu(), seconds=seconds)

    def forward(self, reference: torch.Tensor, query: torch.Tensor) -> SeqSLAMResult:
        """Same as :meth:`match`."""
        return self.match(reference, query)

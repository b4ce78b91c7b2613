"""The classic SeqSLAM engine: descriptors -> difference matrix -> enhancement -> search."""

from __future__ import annotations

import time

import torch
from torch import nn

from torchseq._checks import as_frames, check_not_empty
from torchseq.matches import Matches
from torchseq.preprocess import preprocess, preprocess_openseqslam
from torchseq.seqslam._parallel import map_rows, resolve_threads, single_threaded_ops
from torchseq.seqslam.banded import match_banded, preview
from torchseq.seqslam.candidates import CandidateSeqSLAM, resolve_candidates
from torchseq.seqslam.config import SeqSLAMConfig
from torchseq.seqslam.difference import (
    check_descriptors,
    difference_with_kernel,
    thermometer_product,
)
from torchseq.seqslam.enhance import enhance_contrast
from torchseq.seqslam.result import SeqSLAMResult
from torchseq.seqslam.search import search, velocities


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
        if config is not None and not isinstance(config, SeqSLAMConfig):
            raise TypeError(f"config must be a SeqSLAMConfig or None, got "
                            f"{type(config).__name__} (StreamingSeqSLAM takes the reference "
                            f"first: StreamingSeqSLAM(reference, config))")
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

        def describe(block: torch.Tensor) -> torch.Tensor:
            if c.preprocessing == "openseqslam":
                return preprocess_openseqslam(block, c.image_size, c.patch_size)
            return preprocess(block, c.image_size, c.patch_size, mode="seqslam")

        # frame by frame work: blocks of frames on the stages' worker threads (_parallel.py)
        desc = map_rows(describe, frames.to(self.device), c.threads)
        return desc.to(self._working_dtype(frames))

    def match(self, reference: torch.Tensor, query: torch.Tensor,
              progress: bool = False) -> SeqSLAMResult:
        """Match a query traverse of frames against a reference traverse.

        Args:
            reference: ``(R, H, W)`` (or RGB ``(R, H, W, 3)``) frames, a tensor or a NumPy
                array.
            query: ``(Q, H, W)`` frames, likewise.
            progress: show a progress bar during the search.
        """
        reference, query = as_frames(reference, "reference"), as_frames(query, "query")
        check_not_empty(reference, "reference frames")
        check_not_empty(query, "query frames")
        return self.match_descriptors(self.descriptors(reference), self.descriptors(query),
                                      progress=progress)

    def match_descriptors(self, reference: torch.Tensor, query: torch.Tensor,
                          progress: bool = False) -> SeqSLAMResult:
        """Match ``(Q, D)`` query descriptors against ``(R, D)`` reference descriptors.

        On CPU every op runs on one intra-op thread; the stages spread whole blocks over
        worker threads instead (``config.threads``, see ``seqslam/_parallel.py``).
        """
        if self.device.type == "cuda":
            return self._match_descriptors(reference, query, progress)
        with single_threaded_ops():
            return self._match_descriptors(reference, query, progress)

    def _match_descriptors(self, reference: torch.Tensor, query: torch.Tensor,
                           progress: bool) -> SeqSLAMResult:
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
        if not c.keeps_matrices(reference.shape[0], query.shape[0]):
            t0 = time.perf_counter()
            out = match_banded(reference, query, c, self.speeds, progress)
            _sync(self.device)
            seconds = {**out["seconds"], "total": time.perf_counter() - t0}
            return SeqSLAMResult(
                matches=Matches(out["match"].cpu(), out["ratio"].to(dtype).cpu(),
                                lower_is_better=True),
                difference=None, enhanced=None, ranked=out["ranked"].cpu(),
                best_score=out["best"].to(dtype).cpu(), seconds=seconds,
                kernels={"difference": out["kernel"], "threads": out["threads"],
                         "matrices": "banded", **_product(out["kernel"], self.device)},
                preview=out["preview"].cpu(),
                ranked_score=out["ranked_score"].to(dtype).cpu())
        seconds = {}
        threads = {}
        t0 = t = time.perf_counter()
        threads["difference"] = resolve_threads(c.threads)  # per stage: the load changes
        diff, kernel = difference_with_kernel(reference, query, c.metric, c.max_chunk_elements,
                                              threads["difference"])
        _sync(self.device)
        seconds["difference"] = time.perf_counter() - t
        t = time.perf_counter()
        threads["enhance"] = resolve_threads(c.threads)
        enhanced = enhance_contrast(diff, c.enhance_window, True, c.max_chunk_elements,
                                    threads["enhance"])
        _sync(self.device)
        seconds["enhance"] = time.perf_counter() - t
        t = time.perf_counter()
        threads["search"] = resolve_threads(c.threads)
        ranked_score = torch.empty(query.shape[0], c.top_k, dtype=enhanced.dtype,
                                   device=self.device)
        match, best, ratio, ranked = search(enhanced, ds, self.speeds, c.rwindow, c.top_k,
                                            c.max_chunk_elements, progress, c.match_rule,
                                            threads["search"], c.edges, ranked_score)
        _sync(self.device)
        seconds["search"] = time.perf_counter() - t
        seconds["total"] = time.perf_counter() - t0
        return SeqSLAMResult(
            matches=Matches(match.cpu(), ratio.cpu(), lower_is_better=True),
            difference=diff.cpu(), enhanced=enhanced.cpu(), ranked=ranked.cpu(),
            best_score=best.cpu(), seconds=seconds,
            kernels={"difference": kernel, "threads": threads, "matrices": "full",
                     **_product(kernel, self.device)},
            preview=preview(enhanced).cpu(), ranked_score=ranked_score.cpu())

    def forward(self, reference: torch.Tensor, query: torch.Tensor) -> SeqSLAMResult:
        """Same as :meth:`match`."""
        return self.match(reference, query)


def _product(kernel: str, device) -> dict:
    """``{"product": "int8" | "float32"}`` when the thermometer kernel ran (else empty)."""
    return {"product": thermometer_product(device)} if kernel == "thermometer" else {}

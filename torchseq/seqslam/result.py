"""The result type of the SeqSLAM engines, in a module of its own.

The exact engine (:mod:`torchseq.seqslam.engine`), the candidate mode
(:mod:`torchseq.seqslam.candidates`) and the sharded driver all return it; it lives here so
that none of them imports another for it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from torchseq.matches import Matches


@dataclass
class SeqSLAMResult:
    """What one SeqSLAM run produces.

    Attributes:
        matches: per query, the matched reference (``-1`` for the first and last ``ds/2``
            queries unless ``config.edges``, and where no trajectory is finite) and its
            uniqueness ratio (``lower_is_better=True``; NaN without a match).
        difference: ``(R, Q)`` difference matrix on CPU (None when the config does not keep
            the full matrices, see ``SeqSLAMConfig.keep_matrices``).
        enhanced: ``(R, Q)`` contrast-enhanced difference matrix on CPU (or None, as above).
        ranked: ``(Q, top_k)`` int64 candidate references, best first, ``-1`` for none.
        best_score: ``(Q,)`` best trajectory cost (NaN where unscored).
        seconds: wall time of ``"difference"``, ``"enhance"``, ``"search"`` and ``"total"``.
        kernels: which kernel ran per stage, e.g. ``{"difference": "thermometer"}``,
            ``"threads"``: the worker threads each stage used, ``"matrices"``: ``"full"`` or
            ``"banded"``.
        preview: ``(R', Q')`` reduced copy of the enhanced matrix on CPU (area averages,
            at most 1024 on a side) for plots, or None.
        ranked_score: ``(Q, top_k)`` trajectory score of each ranked reference (lower is
            better, NaN where ``ranked`` is ``-1``) for recall@K with ties
            (:func:`torchseq.metrics.recall_at_ks`); None where the run does not keep it
            (candidate runs).
    """

    matches: Matches
    difference: torch.Tensor | None
    enhanced: torch.Tensor | None
    ranked: torch.Tensor
    best_score: torch.Tensor
    seconds: dict = field(default_factory=dict)
    kernels: dict = field(default_factory=dict)
    preview: torch.Tensor | None = None
    ranked_score: torch.Tensor | None = None

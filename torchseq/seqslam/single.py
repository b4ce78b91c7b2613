"""Single-frame matching: each query's nearest references, no sequence (``ds = 1``).

The baseline that says what sequence matching adds: the same descriptors and the same
difference (:func:`~torchseq.seqslam.difference.difference_matrix`, ``l1``, ``l2`` or
``cosine``), no contrast enhancement, no trajectory; every query gets its nearest reference.
Computed in blocks of queries, so memory stays ``O(R x block)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchseq.matches import Matches
from torchseq.seqslam.difference import check_descriptors, difference_matrix


@dataclass
class SingleFrameResult:
    """Nearest references of every query.

    Attributes:
        matches: the nearest reference and its distance (``lower_is_better=True``).
        ranked: ``(Q, top_k)`` int64 references, nearest first (ties: lower index first).
        ranked_score: ``(Q, top_k)`` their distances.
    """

    matches: Matches
    ranked: torch.Tensor
    ranked_score: torch.Tensor


def single_frame(reference: torch.Tensor, query: torch.Tensor, metric: str = "l1",
                 top_k: int = 21, max_chunk_elements: int = 2**26) -> SingleFrameResult:
    """Match every query descriptor to its nearest reference descriptors.

    Args:
        reference: ``(R, D)`` descriptors.
        query: ``(Q, D)`` descriptors.
        metric: ``"l1"``, ``"l2"`` or ``"cosine"`` (as :class:`SeqSLAMConfig.metric`).
        top_k: references ranked per query (at most ``R``).
        max_chunk_elements: bound on each block's difference matrix.

    Returns:
        :class:`SingleFrameResult` on CPU.
    """
    reference, query = torch.as_tensor(reference), torch.as_tensor(query)
    check_descriptors(reference, query)
    if top_k < 1:
        raise ValueError(f"top_k must be >= 1, got {top_k}")
    k = min(top_k, reference.shape[0])
    rows = max(1, max_chunk_elements // reference.shape[0])
    ranked, scores = [], []
    for q0 in range(0, query.shape[0], rows):
        d_t = difference_matrix(reference, query[q0:q0 + rows], metric,
                                max_chunk_elements).T  # (block, R)
        order = torch.argsort(d_t, dim=1, stable=True)[:, :k]  # ties: lower index first
        ranked.append(order)
        scores.append(d_t.gather(1, order))
    ranked_t, score_t = torch.cat(ranked).cpu(), torch.cat(scores).cpu()
    if k < top_k:
        pad = top_k - k
        ranked_t = torch.cat([ranked_t, ranked_t.new_full((len(ranked_t), pad), -1)], 1)
        score_t = torch.cat([score_t, score_t.new_full((len(score_t), pad), float("nan"))], 1)
    return SingleFrameResult(Matches(ranked_t[:, 0].clone(), score_t[:, 0].clone(), True),
                             ranked_t, score_t)

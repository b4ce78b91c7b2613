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
    rows = max(1, max_chunk_elements // reference.shape[0])
    blocks = (difference_matrix(reference, query[q0:q0 + rows], metric, max_chunk_elements)
              for q0 in range(0, query.shape[0], rows))
    return _ranked(blocks, reference.shape[0], top_k)


def single_frame_from_difference(difference: torch.Tensor, top_k: int = 21,
                                 max_chunk_elements: int = 2**26) -> SingleFrameResult:
    """:func:`single_frame` from a difference matrix already computed (nothing computed twice).

    The SeqSLAM engine keeps its raw difference matrix (``SeqSLAMResult.difference``, the
    same :func:`~torchseq.seqslam.difference.difference_matrix` of the same descriptors), so
    the baseline only ranks it.

    Args:
        difference: ``(R, Q)`` distances, reference rows by query columns.
        top_k: references ranked per query (at most ``R``).
        max_chunk_elements: bound on each block of queries ranked at once.

    Returns:
        :class:`SingleFrameResult` on CPU, equal to :func:`single_frame` of the descriptors
        the matrix was computed from.
    """
    difference = torch.as_tensor(difference)
    if difference.layout != torch.strided:  # a candidate run's: only some entries are there
        raise ValueError("need the whole dense (R, Q) difference matrix, got a sparse one "
                         "(candidate mode keeps only its candidates' entries)")
    if difference.ndim != 2 or 0 in difference.shape:
        raise ValueError(f"need a non-empty (R, Q) difference matrix, got "
                         f"{tuple(difference.shape)}")
    if top_k < 1:
        raise ValueError(f"top_k must be >= 1, got {top_k}")
    rows = max(1, max_chunk_elements // difference.shape[0])
    blocks = (difference[:, q0:q0 + rows] for q0 in range(0, difference.shape[1], rows))
    return _ranked(blocks, difference.shape[0], top_k)


def smallest(d: torch.Tensor, k: int) -> torch.Tensor:
    """Indices of the ``k`` smallest of each row, ascending, ties: lower index first.

    ``torch.argsort(d, dim=1, stable=True)[:, :k]``, to the index, without sorting whole rows:
    a top-k selection of ``2k`` per row holds every entry up to the k-th value (the k smallest
    and each tie of the k-th) when its largest value is above the k-th; then only the
    selection is sorted, by index and then by value (stable). Rows where it may not (ties of
    the k-th reaching the selection's edge, NaN) are sorted whole.

    Args:
        d: ``(B, R)`` values.
        k: ``1 <= k <= R``.

    Returns:
        ``(B, k)`` int64 column indices.
    """
    wide = 2 * k
    if wide >= d.shape[1] or d.shape[0] == 0:
        return torch.argsort(d, dim=1, stable=True)[:, :k]
    values, index = torch.topk(d, wide, dim=1, largest=False, sorted=False)  # (B, wide)
    kth = torch.kthvalue(values, k, dim=1, keepdim=True).values
    by_index = torch.argsort(index, dim=1)
    index, values = index.gather(1, by_index), values.gather(1, by_index)
    out = index.gather(1, torch.argsort(values, dim=1, stable=True)[:, :k])
    whole = ~(values.amax(1) > kth[:, 0])  # a tie of the k-th may be left outside
    if bool(whole.any()):
        out[whole] = torch.argsort(d[whole], dim=1, stable=True)[:, :k]
    return out


def _ranked(blocks, n_ref: int, top_k: int) -> SingleFrameResult:
    """Rank the references of each query from ``(R, block)`` difference blocks."""
    k = min(top_k, n_ref)
    ranked, scores = [], []
    for block in blocks:
        d_t = block.T  # (block, R)
        order = smallest(d_t, k)  # ties: lower index first
        ranked.append(order)
        scores.append(d_t.gather(1, order))
    ranked_t, score_t = torch.cat(ranked).cpu(), torch.cat(scores).cpu()
    if k < top_k:
        pad = top_k - k
        ranked_t = torch.cat([ranked_t, ranked_t.new_full((len(ranked_t), pad), -1)], 1)
        score_t = torch.cat([score_t, score_t.new_full((len(score_t), pad), float("nan"))], 1)
    return SingleFrameResult(Matches(ranked_t[:, 0].clone(), score_t[:, 0].clone(), True),
                             ranked_t, score_t)

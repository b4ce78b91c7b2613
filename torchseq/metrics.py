"""Place-recognition metrics: recall@K, precision-recall, AUC, recall at 100% precision, coverage.

Conventions (the usual ones in visual place recognition):

- Only queries with at least one admissible reference in the ground truth count towards
  recall ("positives"). A query without a match (reference ``-1``) is never accepted.
- A match is accepted when its confidence is at or above the threshold; it is a true
  positive when the ground truth admits it, else a false positive.
- Precision = TP / (TP + FP), recall = TP / positives, swept over every threshold.
- AUC is the area under the precision-recall curve by step integration (average precision).

Ground truth ``gt`` is a ``(R, Q)`` bool array or the sparse
:class:`torchseq.ground_truth.GroundTruthRanges` (long routes); both give the same metrics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from torchseq.ground_truth import GroundTruthRanges, admits, positives
from torchseq.matches import Matches

GroundTruth = np.ndarray | GroundTruthRanges


def _as_numpy(matches: Matches) -> tuple[np.ndarray, np.ndarray]:
    return matches.reference.cpu().numpy().astype(np.int64), matches.confidence.cpu().numpy()


def _check_gt(gt: GroundTruth, n_query: int) -> GroundTruth:
    if not isinstance(gt, GroundTruthRanges):
        gt = np.asarray(gt, dtype=bool)
    if len(gt.shape) != 2 or gt.shape[1] != n_query:
        raise ValueError(f"ground truth must be (R, {n_query}), got {gt.shape}")
    return gt


def correct(matches: Matches, gt: GroundTruth) -> np.ndarray:
    """``(Q,)`` bool: the query got a match and the ground truth admits it."""
    ref, _ = _as_numpy(matches)
    gt = _check_gt(gt, len(ref))
    ok = (ref >= 0) & (ref < gt.shape[0])
    out = np.zeros(len(ref), dtype=bool)
    out[ok] = admits(gt, ref[ok], np.nonzero(ok)[0])
    return out


def recall_at_k(ranked: np.ndarray | torch.Tensor, gt: GroundTruth, k: int = 1) -> float:
    """Fraction of positive queries with an admissible reference among their top ``k``.

    Args:
        ranked: ``(Q, K')`` candidate reference indices per query, best first, ``-1`` for none
            (a ``(Q,)`` vector is read as ``K' = 1``).
        gt: ``(R, Q)`` bool ground truth (or :class:`GroundTruthRanges`).
        k: how many candidates count.

    Returns:
        Recall in 0..1 (NaN when no query has a positive).
    """
    ranked = np.asarray(torch.as_tensor(ranked).cpu())
    if ranked.ndim == 1:
        ranked = ranked[:, None]
    gt = _check_gt(gt, ranked.shape[0])
    positive = positives(gt)
    if not positive.any():
        return float("nan")
    top = ranked[:, :k]
    valid = (top >= 0) & (top < gt.shape[0])
    hit = np.zeros(top.shape, dtype=bool)
    q = np.broadcast_to(np.arange(top.shape[0])[:, None], top.shape)
    hit[valid] = admits(gt, top[valid], q[valid])
    return float(hit.any(1)[positive].mean())


@dataclass
class PRCurve:
    """Precision and recall at each distinct confidence threshold, by decreasing threshold."""

    precision: np.ndarray
    recall: np.ndarray
    thresholds: np.ndarray


def precision_recall_curve(matches: Matches, gt: GroundTruth) -> PRCurve:
    """Sweep the acceptance threshold over every match confidence."""
    ref, conf = _as_numpy(matches)
    gt = _check_gt(gt, len(ref))
    n_positive = int(positives(gt).sum())
    ok = correct(matches, gt)
    has = ref >= 0
    order = np.argsort(-conf[has], kind="stable")
    c, t = conf[has][order], ok[has][order]
    tp, fp = np.cumsum(t), np.cumsum(~t)
    last = np.r_[np.nonzero(np.diff(c))[0], len(c) - 1] if len(c) else np.array([], int)
    tp, fp = tp[last], fp[last]
    precision = np.where(tp + fp > 0, tp / np.maximum(tp + fp, 1), 1.0)
    recall = tp / n_positive if n_positive else np.zeros_like(tp, dtype=float)
    return PRCurve(precision.astype(float), recall.astype(float), c[last])


def auc(curve: PRCurve) -> float:
    """Area under the precision-recall curve (average precision, step integration)."""
    if len(curve.recall) == 0:
        return 0.0
    r = np.r_[0.0, curve.recall]
    return float(np.sum(np.diff(r) * curve.precision))


def recall_at_100_precision(curve: PRCurve) -> float:
    """Highest recall reached with no false positive accepted."""
    perfect = curve.precision >= 1.0
    # only the prefix before the first false positive counts
    if not len(perfect) or not perfect[0]:
        return 0.0
    first_bad = np.argmin(perfect) if not perfect.all() else len(perfect)
    return float(curve.recall[first_bad - 1])


def operating_point(matches: Matches, gt: GroundTruth, precision: float = 0.99) -> dict:
    """The acceptance threshold that reaches ``precision`` with the most recall.

    As OpenSeqSLAM2.0 tunes its match threshold: among the thresholds of the PR sweep whose
    precision is at least ``precision``, the one with the highest recall (the lowest such
    threshold). ``score_threshold`` is in the engine's own score units (accept a match when
    its score is ``<=`` it for lower-is-better scores, ``>=`` otherwise).

    Args:
        matches: the engine's matches.
        gt: ``(R, Q)`` bool ground truth (or :class:`GroundTruthRanges`).
        precision: the precision to reach, 0..1.

    Returns:
        ``{"precision_target", "precision", "recall", "score_threshold", "n_accepted"}``;
        ``score_threshold`` None (and recall 0) when no threshold reaches ``precision``.
    """
    if not 0.0 <= precision <= 1.0:
        raise ValueError(f"precision must be in 0..1, got {precision}")
    curve = precision_recall_curve(matches, gt)
    ok = np.nonzero(curve.precision >= precision)[0]
    out = {"precision_target": float(precision), "precision": None, "recall": 0.0,
           "score_threshold": None, "n_accepted": 0}
    if len(ok) == 0:
        return out
    i = ok[np.argmax(curve.recall[ok])]
    conf = float(curve.thresholds[i])
    _, all_conf = _as_numpy(matches)
    out.update(precision=float(curve.precision[i]), recall=float(curve.recall[i]),
               score_threshold=-conf if matches.lower_is_better else conf,
               n_accepted=int((all_conf >= conf).sum()))
    return out


def coverage(matches: Matches, gt: GroundTruth | None = None) -> float:
    """Fraction of query frames that get a match; with ``gt``, a correct match."""
    ref, _ = _as_numpy(matches)
    if len(ref) == 0:
        return float("nan")
    return float((correct(matches, gt) if gt is not None else ref >= 0).mean())


def evaluate(matches: Matches, gt: GroundTruth, ranked: np.ndarray | None = None) -> dict:
    """All headline metrics of one engine on one query traverse, as a JSON-ready dict."""
    curve = precision_recall_curve(matches, gt)
    out = {
        "recall_at_1": recall_at_k(matches.reference, gt, 1),
        "auc": auc(curve),
        "recall_at_100_precision": recall_at_100_precision(curve),
        "coverage": coverage(matches),
        "correct_coverage": coverage(matches, gt),
        "n_queries": len(matches),
        "n_matched": int((matches.reference >= 0).sum()),
        "n_positive_queries": int(positives(_check_gt(gt, len(matches))).sum()),
    }
    if ranked is not None:
        for k in (5, 10):
            out[f"recall_at_{k}"] = recall_at_k(ranked, gt, k)
    return out

"""Place-recognition metrics: recall@K, precision-recall, AUC, recall at 100% precision, coverage.

Conventions (the usual ones in visual place recognition):

- Only queries with at least one admissible reference in the ground truth count towards
  recall ("positives"). A query without a match (reference ``-1``) is never accepted.
- A match is accepted when its confidence is at or above the threshold; it is a true
  positive when the ground truth admits it, else a false positive.
- Precision = TP / (TP + FP), recall = TP / positives, swept over every threshold.
- AUC is the area under the precision-recall curve by step integration (average precision).

recall@K with ties (:func:`recall_at_ks`, the field's convention; docs/reference/metrics.md):
a query is a hit at ``K`` when fewer than ``K`` candidates score strictly better than its best
admissible candidate (ties counted *for* the method) or when fewer than ``K`` candidates score
better than or equal to it, admissible ones aside (ties counted *against*), as Event-LAB's
``utils/metrics.py`` does. The two bracket every tie-breaking rule. Both denominators are
given: the queries with a true match (Event-LAB, and this module's other recalls) and all
queries (VPR-methods-evaluation's ``main.py``).

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


RECALL_KS = (1, 5, 10, 20)
DENOMINATORS = {
    "queries_with_a_true_match": "queries with at least one admissible reference (Event-LAB)",
    "all_queries": "every query; one without an admissible reference is a miss "
                   "(VPR-methods-evaluation)",
}


@dataclass
class RecallAtK:
    """recall@K with ties counted both ways, over a named denominator.

    Attributes:
        ks: the K values.
        ties_for: ``{K: recall}``, a tie between an admissible and another candidate counts as
            retrieved (Event-LAB's ``"optimistic"``).
        ties_against: ``{K: recall}``, such a tie counts as missed (``"pessimistic"``).
        denominator: ``"queries_with_a_true_match"`` or ``"all_queries"``.
        n_queries: queries in the denominator.
        unresolved: ``{K: queries}`` whose candidate list ends inside a tie that reaches
            rank ``K`` (a longer list could change them; 0 when the lists hold every
            reference or end past the ties).
    """

    ks: tuple[int, ...]
    ties_for: dict
    ties_against: dict
    denominator: str
    n_queries: int
    unresolved: dict

    def to_dict(self) -> dict:
        """JSON-ready: string keys ``"1"``, ``"5"``, ... and the denominator's meaning."""
        return {"denominator": self.denominator,
                "denominator_means": DENOMINATORS[self.denominator],
                "n_queries": self.n_queries,
                "ties_for": {str(k): v for k, v in self.ties_for.items()},
                "ties_against": {str(k): v for k, v in self.ties_against.items()},
                "unresolved": {str(k): v for k, v in self.unresolved.items()}}


def tie_ranks(ranked: np.ndarray | torch.Tensor, scores: np.ndarray | torch.Tensor,
              gt: GroundTruth, lower_is_better: bool
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per query, how many candidates beat its best admissible candidate (the tie rule).

    Args:
        ranked: ``(Q, M)`` distinct candidate references per query (any order), ``-1`` for
            none; ``M = R`` with every reference listed is a full score matrix.
        scores: ``(Q, M)`` each candidate's score (NaN where ``ranked`` is ``-1``).
        gt: ``(R, Q)`` bool ground truth (or :class:`GroundTruthRanges`).
        lower_is_better: True for distances and costs, False for similarities.

    Returns:
        ``found (Q,)`` bool (an admissible candidate is listed), ``better (Q,)`` (candidates
        scoring strictly better than the best admissible one), ``tied (Q,)`` (inadmissible
        candidates scoring equal to it) and ``last (Q,)``: ``-1`` where the list settles the
        counts (it holds every candidate the engine has: padded with ``-1``, or ``M >= R``;
        or its best admissible candidate scores above the list's worst score), else the
        number of listed candidates scoring strictly better than that worst score (where a
        longer list could add tied candidates).
    """
    ranked = np.asarray(torch.as_tensor(ranked).cpu(), dtype=np.int64)
    conf = np.asarray(torch.as_tensor(scores).cpu(), dtype=np.float64)
    if ranked.ndim != 2 or conf.shape != ranked.shape:
        raise ValueError(f"ranked and scores must both be (Q, M), got {ranked.shape} and "
                         f"{conf.shape}")
    gt = _check_gt(gt, ranked.shape[0])
    if lower_is_better:
        conf = -conf
    valid = (ranked >= 0) & (ranked < gt.shape[0]) & ~np.isnan(conf)
    conf = np.where(valid, conf, -np.inf)
    ok = np.zeros(ranked.shape, dtype=bool)
    q = np.broadcast_to(np.arange(ranked.shape[0])[:, None], ranked.shape)
    ok[valid] = admits(gt, ranked[valid], q[valid])
    found = ok.any(1)
    best = np.where(ok, conf, -np.inf).max(1, initial=-np.inf)[:, None]
    better = (valid & (conf > best)).sum(1)
    tied = (valid & ~ok & (conf == best)).sum(1)
    full = ~valid.all(1) | (ranked.shape[1] >= gt.shape[0])
    worst = np.where(valid, conf, np.inf).min(1, initial=np.inf)[:, None]
    settled = full | (found & (best[:, 0] > worst[:, 0]))  # ties above the list's end
    last = np.where(settled, -1, (valid & (conf > worst)).sum(1))
    return found, better, tied, last


def recall_at_ks(ranked: np.ndarray | torch.Tensor, scores: np.ndarray | torch.Tensor,
                 gt: GroundTruth, lower_is_better: bool, ks=RECALL_KS,
                 denominator: str = "queries_with_a_true_match") -> RecallAtK:
    """recall@K for every K, ties counted for and against the method (the one definition).

    A query is a hit at ``K`` (ties for) when an admissible candidate is listed and fewer
    than ``K`` candidates score strictly better than the best admissible one; (ties against)
    when fewer than ``K`` candidates score better than or equal to it, admissible ones
    aside. On a full ``(R, Q)`` score matrix this is Event-LAB's ``recall_at_k`` with
    ``tie_policy`` ``"optimistic"`` and ``"pessimistic"``; without ties both equal
    VPR-methods-evaluation's "an admissible reference among the first K predictions".

    Args:
        ranked: ``(Q, M)`` candidate references (see :func:`tie_ranks`).
        scores: ``(Q, M)`` their scores.
        gt: ``(R, Q)`` bool ground truth (or :class:`GroundTruthRanges`).
        lower_is_better: True for distances and costs.
        ks: the K values.
        denominator: ``"queries_with_a_true_match"`` (Event-LAB) or ``"all_queries"``
            (VPR-methods-evaluation).

    Returns:
        :class:`RecallAtK` (NaN recalls when the denominator is empty).
    """
    if denominator not in DENOMINATORS:
        raise ValueError(f"denominator must be one of {', '.join(DENOMINATORS)}, got "
                         f"{denominator!r}")
    ks = tuple(int(k) for k in ks)
    if not ks or min(ks) < 1:
        raise ValueError(f"every K must be >= 1, got {ks}")
    found, better, tied, last = tie_ranks(ranked, scores, gt, lower_is_better)
    gt = _check_gt(gt, len(found))
    counted = positives(gt) if denominator == "queries_with_a_true_match" else \
        np.ones(len(found), dtype=bool)
    n = int(counted.sum())
    out_for, out_against, unresolved = {}, {}, {}
    for k in ks:
        hit_for = found & (better < k)
        hit_against = found & (better + tied < k)
        out_for[k] = float(hit_for[counted].mean()) if n else float("nan")
        out_against[k] = float(hit_against[counted].mean()) if n else float("nan")
        # the list ends inside a tie group that starts before rank K: a longer list could
        # hold more tied (or better-placed admissible) candidates
        unresolved[k] = int((counted & (last >= 0) & (last < k)).sum())
    return RecallAtK(ks, out_for, out_against, denominator, n, unresolved)


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


def recall_table(ranked, scores, gt: GroundTruth, lower_is_better: bool,
                 ks=RECALL_KS) -> dict:
    """metrics.json's ``"recall"``: :func:`recall_at_ks` over both denominators."""
    return {"k": list(ks), **{d: recall_at_ks(ranked, scores, gt, lower_is_better, ks,
                                              d).to_dict() for d in DENOMINATORS}}


def sequence_vs_single(sequence: Matches, single: Matches, gt: GroundTruth) -> dict:
    """What sequence matching does to each query, against single-frame matching.

    Over the queries with a true match: ``made_worse`` is the share whose single-frame
    match is correct and whose sequence match is not (wrong, or no match at all, e.g. the
    first and last ``ds/2`` queries); ``made_better`` the reverse; both the engines' own
    decisions (top-1).

    Returns:
        ``{"single_frame_recall_at_1", "sequence_recall_at_1", "made_worse", "made_better",
        "n_made_worse", "n_made_better", "n_without_sequence_match", "denominator",
        "n_queries"}`` (shares NaN
        without positives).
    """
    gt = _check_gt(gt, len(sequence))
    if len(single) != len(sequence):
        raise ValueError(f"single-frame and sequence matches must cover the same queries, "
                         f"got {len(single)} and {len(sequence)}")
    counted = positives(gt)
    n = int(counted.sum())
    seq_ok, one_ok = correct(sequence, gt)[counted], correct(single, gt)[counted]
    worse, better = int((one_ok & ~seq_ok).sum()), int((seq_ok & ~one_ok).sum())

    def share(x: float) -> float:
        return x / n if n else float("nan")

    return {"single_frame_recall_at_1": share(int(one_ok.sum())),
            "sequence_recall_at_1": share(int(seq_ok.sum())),
            "made_worse": share(worse), "made_better": share(better),
            "n_made_worse": worse, "n_made_better": better,
            "n_without_sequence_match": int((sequence.reference.cpu().numpy() < 0)[counted].sum()),
            "denominator": "queries_with_a_true_match", "n_queries": n}


def evaluate(matches: Matches, gt: GroundTruth, ranked: np.ndarray | None = None,
             ranked_score: np.ndarray | torch.Tensor | None = None) -> dict:
    """All headline metrics of one engine on one query traverse, as a JSON-ready dict.

    ``recall_at_1`` (and ``recall_at_5``, ``recall_at_10`` from ``ranked``) count the
    engine's own decisions in its own order over the queries with a true match; with
    ``ranked_score`` (the candidates' scores, in ``matches``' score units) ``"recall"``
    adds recall@1/5/10/20 with ties counted both ways over both denominators
    (:func:`recall_table`).
    """
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
        if ranked_score is not None:
            out["recall"] = recall_table(ranked, ranked_score, gt, matches.lower_is_better)
    return out


@dataclass
class MatchLine:
    """The straight line ``reference = offset + scale * query`` most matches lie near.

    Attributes:
        offset: reference index of query 0 on the line.
        scale: reference frames per query frame.
        band: how far (reference frames) a match may lie from the line and count.
        share: the share of matched queries within ``band`` of the line.
        correct: the share of matched queries the ground truth admits.
    """

    offset: float
    scale: float
    band: float
    share: float
    correct: float

    def disagrees(self) -> bool:
        """Most matches follow a line the ground truth does not admit (it looks misaligned)."""
        return self.share >= 0.5 and self.share - self.correct >= 0.25


def match_line(matches: Matches, gt: GroundTruth, tries: int = 256,
               seed: int = 0) -> MatchLine | None:
    """What an engine's own matches suggest, against the ground truth's verdict on them.

    A line through two random matches, ``tries`` times (RANSAC); the one most matches lie
    within ``band`` of wins, ``band`` half the median number of admissible references per
    query (at least 1). A route matched well lies on such a line (any speed ratio, any
    start), so ``share`` far above ``correct`` says the ground truth is misaligned (a query
    stretched over a longer reference, a shifted or mis-based file), not the matching.

    Returns:
        :class:`MatchLine`, or None with fewer than 10 matched queries.
    """
    gt = _check_gt(gt, len(matches))
    ref, _ = _as_numpy(matches)
    q = np.nonzero(ref >= 0)[0]
    if len(q) < 10:
        return None
    r = ref[q].astype(np.float64)
    width = (gt.hi - gt.lo) if isinstance(gt, GroundTruthRanges) else gt.sum(0)
    width = width[width > 0]
    band = max(1.0, (float(np.median(width)) - 1) / 2) if len(width) else 1.0
    rng = np.random.default_rng(seed)
    i, j = rng.integers(0, len(q), (2, tries))
    keep = np.abs(q[i] - q[j]) >= max(1, (q[-1] - q[0]) // 10)  # far apart: a steady slope
    i, j = i[keep], j[keep]
    if not len(i):
        return None
    scale = (r[j] - r[i]) / (q[j] - q[i])
    offset = r[i] - scale * q[i]
    best, hits = 0, -1
    for k in range(len(i)):  # (tries,) lines over (M,) matches: O(tries M), no (tries, M)
        n = int((np.abs(r - (offset[k] + scale[k] * q)) <= band).sum())
        if n > hits:
            best, hits = k, n
    a, b = float(offset[best]), float(scale[best])
    inside = np.abs(r - (a + b * q)) <= band
    b2, a2 = np.polyfit(q[inside], r[inside], 1)  # least squares on the line's matches
    if (np.abs(r - (a2 + b2 * q)) <= band).sum() >= hits:
        a, b = float(a2), float(b2)
        hits = int((np.abs(r - (a + b * q)) <= band).sum())
    ok = correct(matches, gt)[q]
    return MatchLine(a, b, band, hits / len(q), float(ok.mean()))

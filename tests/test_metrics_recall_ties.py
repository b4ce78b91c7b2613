"""recall@K with ties counted both ways, checked against the two tools' published formulas.

- Event-LAB, ``utils/metrics.py`` (``recall_at_k``, ``_chunk_counts``): on a ``(R, Q)``
  similarity matrix ``S`` (a distance matrix ``D`` enters as ``D.max() - D``,
  ``EventBaselineLab.run_metrics``), keep the queries with a ground-truth match; ``best`` is
  the highest similarity among a query's admissible rows, ``n_better`` the rows scoring
  strictly above it, ``n_tied`` the inadmissible rows equal to it; hit at K when
  ``n_better < K`` ("optimistic") or ``n_better + n_tied < K`` ("pessimistic"); divide by the
  kept queries.
- VPR-methods-evaluation, ``main.py``: predictions are the K nearest references (faiss L2);
  a query is a hit at ``n`` when ``np.in1d(preds[:n], positives)`` has any; recalls are
  divided by ``num_queries`` (every query).

Both are re-implemented here as plain loops, independently of torchseq.metrics.
"""

import numpy as np
import pytest
import torch

from torchseq import metrics
from torchseq.ground_truth import alignment_ranges
from torchseq.matches import Matches

KS = (1, 2, 5, 10, 20)


def eventlab_recall(S, GT, k, policy):
    """Event-LAB's formula, one query column at a time (similarity: higher is better)."""
    kept = hits = 0
    for q in range(S.shape[1]):
        rows = [r for r in range(S.shape[0]) if GT[r, q]]
        if not rows:
            continue
        kept += 1
        best = max(S[r, q] for r in rows)
        n_better = sum(1 for r in range(S.shape[0]) if S[r, q] > best)
        n_tied = sum(1 for r in range(S.shape[0]) if S[r, q] == best and not GT[r, q])
        n = n_better + (n_tied if policy == "pessimistic" else 0)
        hits += n < k
    return hits / kept if kept else float("nan")


def vpr_methods_recall(D, GT, k, order_seed=None):
    """VPR-methods-evaluation's formula: sorted predictions, every query in the denominator.

    ``order_seed`` breaks ties between equal distances in a random order (faiss gives some
    order; any order must fall within the tie bracket).
    """
    hits = 0
    rng = np.random.default_rng(order_seed)
    for q in range(D.shape[1]):
        col = D[:, q]
        tie_break = rng.random(len(col)) if order_seed is not None else np.arange(len(col))
        preds = sorted(range(len(col)), key=lambda r: (col[r], tie_break[r]))
        positives = [r for r in range(D.shape[0]) if GT[r, q]]
        hits += any(p in positives for p in preds[:k])
    return hits / D.shape[1]


def random_case(seed, n_ref=40, n_query=30, levels=None):
    rng = np.random.default_rng(seed)
    gt = np.zeros((n_ref, n_query), bool)
    for q in range(n_query):
        if q % 6:  # some queries have no true match
            c = rng.integers(0, n_ref)
            gt[max(0, c - 1):c + 2, q] = True
    d = rng.random((n_ref, n_query))
    if levels:  # quantised distances: many ties, as event matrices have
        d = np.round(d * levels) / levels
    for q in range(n_query):  # make the truth often close
        d[gt[:, q], q] *= rng.choice([0.2, 1.0])
    if levels:
        d = np.round(d * levels) / levels
    return d, gt


def full_lists(d):
    """Every reference as a candidate of every query, in a shuffled order."""
    n_ref, n_query = d.shape
    rng = np.random.default_rng(1)
    ranked = np.stack([rng.permutation(n_ref) for _ in range(n_query)])
    return ranked, d.T[np.arange(n_query)[:, None], ranked]


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("levels", [None, 4, 10])
def test_full_matrix_equals_eventlab(seed, levels):
    d, gt = random_case(seed, levels=levels)
    ranked, score = full_lists(d)
    got = metrics.recall_at_ks(ranked, score, gt, lower_is_better=True, ks=KS)
    s = d.max() - d  # Event-LAB's distance -> similarity
    assert got.denominator == "queries_with_a_true_match"
    assert got.n_queries == int(gt.any(0).sum())
    for k in KS:
        assert got.ties_for[k] == pytest.approx(eventlab_recall(s, gt, k, "optimistic"))
        assert got.ties_against[k] == pytest.approx(eventlab_recall(s, gt, k, "pessimistic"))
        assert got.unresolved[k] == 0
    # a similarity matrix given as it is (higher is better) gives the same numbers
    sim = metrics.recall_at_ks(ranked, s.T[np.arange(d.shape[1])[:, None], ranked], gt,
                               lower_is_better=False, ks=KS)
    assert sim.ties_for == got.ties_for and sim.ties_against == got.ties_against


def test_ties_bracket_differs_when_ties_decide():
    d, gt = random_case(0, levels=4)
    ranked, score = full_lists(d)
    got = metrics.recall_at_ks(ranked, score, gt, lower_is_better=True, ks=KS)
    assert any(got.ties_for[k] > got.ties_against[k] for k in KS)  # the case is not trivial


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("levels", [None, 5])
def test_all_queries_equals_vpr_methods_evaluation(seed, levels):
    d, gt = random_case(seed, levels=levels)
    ranked, score = full_lists(d)
    got = metrics.recall_at_ks(ranked, score, gt, lower_is_better=True, ks=KS,
                               denominator="all_queries")
    assert got.n_queries == d.shape[1]
    for k in KS:
        if levels is None:  # no ties: one value, theirs
            assert got.ties_for[k] == pytest.approx(vpr_methods_recall(d, gt, k))
            assert got.ties_against[k] == pytest.approx(vpr_methods_recall(d, gt, k))
        for order in range(5):  # any tie order lies within the bracket
            theirs = vpr_methods_recall(d, gt, k, order_seed=order)
            assert got.ties_against[k] - 1e-12 <= theirs <= got.ties_for[k] + 1e-12


@pytest.mark.parametrize("levels", [None, 6])
def test_top_m_lists_equal_the_full_matrix(levels):
    """A top-M list (as the engines return) gives the full matrix's numbers for K < M."""
    d, gt = random_case(5, n_ref=60, levels=levels)
    ranked_all, score_all = full_lists(d)
    full = metrics.recall_at_ks(ranked_all, score_all, gt, True, KS)
    order = np.argsort(d, axis=0, kind="stable").T  # (Q, R) best first
    m = 25
    top = order[:, :m]
    part = metrics.recall_at_ks(top, d.T[np.arange(d.shape[1])[:, None], top], gt, True, KS)
    for k in KS:
        if part.unresolved[k] == 0:
            assert part.ties_for[k] == full.ties_for[k]
            assert part.ties_against[k] == full.ties_against[k]
    if levels is None:
        assert all(v == 0 for v in part.unresolved.values())


def test_unresolved_when_the_list_ends_in_a_tie():
    gt = np.zeros((10, 1), bool)
    gt[7, 0] = True
    # listed: refs 0, 1, 2 with scores 0.1, 0.5, 0.5; ref 7 (true) is not listed
    ranked = np.array([[0, 1, 2]])
    score = np.array([[0.1, 0.5, 0.5]])
    got = metrics.recall_at_ks(ranked, score, gt, True, (1, 2, 5))
    assert got.unresolved == {1: 0, 2: 1, 5: 1}  # ref 7 could score 0.5 too
    assert got.ties_for == {1: 0.0, 2: 0.0, 5: 0.0}
    # padded with -1: the engine listed all it had, nothing is open
    padded = metrics.recall_at_ks(np.array([[0, 1, 2, -1]]),
                                  np.array([[0.1, 0.5, 0.5, np.nan]]), gt, True, (1, 2, 5))
    assert padded.unresolved == {1: 0, 2: 0, 5: 0}


def test_hand_case_ties_and_denominators():
    # 3 references, 3 queries; query 2 has no true match
    gt = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 0]], bool)
    ranked = np.array([[0, 1, 2], [0, 1, 2], [0, 1, 2]])
    score = np.array([[0.2, 0.2, 0.9],   # true ref 0 tied with ref 1 at the top
                      [0.1, 0.3, 0.3],   # true ref 1 second, tied with ref 2
                      [0.1, 0.2, 0.3]])
    r = metrics.recall_at_ks(ranked, score, gt, True, (1, 2, 3))
    assert r.ties_for == {1: 0.5, 2: 1.0, 3: 1.0}
    assert r.ties_against == {1: 0.0, 2: 0.5, 3: 1.0}
    a = metrics.recall_at_ks(ranked, score, gt, True, (1, 2, 3), "all_queries")
    assert a.n_queries == 3 and a.ties_for == {1: 0.5 * 2 / 3, 2: 2 / 3, 3: 2 / 3}


def test_sparse_ground_truth_gives_the_same():
    rng = np.random.default_rng(0)
    ranges = alignment_ranges(50, 40, 2.0)
    d = np.round(rng.random((50, 40)) * 8) / 8
    ranked, score = full_lists(d)
    a = metrics.recall_at_ks(ranked, score, ranges, True, KS)
    b = metrics.recall_at_ks(ranked, score, ranges.dense(), True, KS)
    assert a == b


def test_engine_order_lies_in_the_bracket_and_evaluate_reports_it():
    d, gt = random_case(2, levels=5)
    order = np.argsort(d, axis=0, kind="stable").T[:, :21]
    score = d.T[np.arange(d.shape[1])[:, None], order]
    m = Matches(torch.as_tensor(order[:, 0]), torch.as_tensor(score[:, 0]), True)
    out = metrics.evaluate(m, gt, order, score)
    rec = out["recall"]["queries_with_a_true_match"]
    assert rec["denominator_means"].startswith("queries with at least one")
    for k in (1, 5, 10):
        assert rec["ties_against"][str(k)] <= out[f"recall_at_{k}"] <= rec["ties_for"][str(k)]
    assert out["recall"]["all_queries"]["n_queries"] == d.shape[1]
    assert out["recall"]["k"] == [1, 5, 10, 20]


def test_errors():
    gt = np.eye(3, dtype=bool)
    with pytest.raises(ValueError, match="denominator"):
        metrics.recall_at_ks(np.zeros((3, 1), int), np.zeros((3, 1)), gt, True, (1,), "some")
    with pytest.raises(ValueError, match="K must be"):
        metrics.recall_at_ks(np.zeros((3, 1), int), np.zeros((3, 1)), gt, True, (0,))
    with pytest.raises(ValueError, match=r"\(Q, M\)"):
        metrics.recall_at_ks(np.zeros((3, 1), int), np.zeros((3, 2)), gt, True, (1,))

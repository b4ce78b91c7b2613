import numpy as np
import pytest
import torch

from torchseq import metrics
from torchseq.matches import Matches


def brute_force_pr(ref, conf, gt):
    """Precision/recall by trying every threshold with plain loops (independent reference)."""
    positives = sum(1 for q in range(gt.shape[1]) if gt[:, q].any())
    points = []
    for thr in sorted({c for r, c in zip(ref, conf) if r >= 0}, reverse=True):
        tp = fp = 0
        for q, (r, c) in enumerate(zip(ref, conf)):
            if r >= 0 and c >= thr:
                if gt[r, q]:
                    tp += 1
                else:
                    fp += 1
        points.append((tp / (tp + fp), tp / positives))
    return points


def random_case(seed, n_ref=30, n_query=40):
    rng = np.random.default_rng(seed)
    gt = np.zeros((n_ref, n_query), bool)
    for q in range(n_query):
        if q % 7:  # some queries have no admissible reference
            c = rng.integers(0, n_ref)
            gt[max(0, c - 1):c + 2, q] = True
    ref = np.where(rng.random(n_query) < 0.1, -1, rng.integers(0, n_ref, n_query))
    ref = np.where(rng.random(n_query) < 0.5, gt.argmax(0), ref)  # half of them right
    ref[0] = -1
    score = rng.random(n_query).round(2)  # ties in the score on purpose
    return ref, score, gt


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("lower", [True, False])
def test_pr_curve_matches_brute_force(seed, lower):
    ref, score, gt = random_case(seed)
    m = Matches(torch.tensor(ref), torch.tensor(score), lower_is_better=lower)
    curve = metrics.precision_recall_curve(m, gt)
    conf = -score if lower else score
    expected = brute_force_pr(ref, conf, gt)
    assert len(curve.precision) == len(expected)
    np.testing.assert_allclose(curve.precision, [p for p, _ in expected])
    np.testing.assert_allclose(curve.recall, [r for _, r in expected])
    # AUC by step integration of the brute-force points
    area, prev = 0.0, 0.0
    for p, r in expected:
        area += (r - prev) * p
        prev = r
    assert metrics.auc(curve) == pytest.approx(area)
    # recall at 100% precision: the largest recall among the leading perfect points
    r100 = 0.0
    for p, r in expected:
        if p < 1:
            break
        r100 = r
    assert metrics.recall_at_100_precision(curve) == pytest.approx(r100)


def test_recall_at_k_and_coverage():
    gt = np.eye(4, dtype=bool)
    ranked = np.array([[0, 1], [0, 1], [3, -1], [-1, -1]])
    assert metrics.recall_at_k(ranked, gt, 1) == pytest.approx(1 / 4)
    assert metrics.recall_at_k(ranked, gt, 2) == pytest.approx(2 / 4)
    m = Matches(torch.tensor([0, 0, 3, -1]), torch.tensor([0.1, 0.2, 0.3, float("nan")]), True)
    assert metrics.coverage(m) == pytest.approx(0.75)
    assert metrics.coverage(m, gt) == pytest.approx(0.25)
    out = metrics.evaluate(m, gt, ranked)
    assert out["recall_at_1"] == pytest.approx(0.25)
    assert out["recall_at_5"] == pytest.approx(0.5)
    assert out["n_matched"] == 3
    with pytest.raises(ValueError):
        metrics.evaluate(m, np.eye(4, 5, dtype=bool))


def test_perfect_matches_give_unit_scores():
    gt = np.eye(6, dtype=bool)
    m = Matches(torch.arange(6), torch.linspace(0.1, 0.6, 6), lower_is_better=True)
    out = metrics.evaluate(m, gt)
    assert out["recall_at_1"] == 1.0 and out["auc"] == 1.0
    assert out["recall_at_100_precision"] == 1.0


def test_matches_shape_check():
    with pytest.raises(ValueError):
        Matches(torch.zeros(3, dtype=torch.long), torch.zeros(4), True)


def test_operating_point_against_a_plain_sweep():
    from torchseq.metrics import operating_point

    rng = np.random.default_rng(3)
    for _ in range(20):
        q, r = 40, 30
        gt = np.zeros((r, q), bool)
        truth = rng.integers(0, r, q)
        gt[truth, np.arange(q)] = True
        ref = np.where(rng.random(q) < 0.7, truth, rng.integers(0, r, q))
        ref[rng.random(q) < 0.1] = -1
        score = rng.random(q).round(2)  # ties on purpose
        m = Matches(torch.as_tensor(ref), torch.as_tensor(score), lower_is_better=True)
        for target in (0.5, 0.9, 1.0):
            op = operating_point(m, gt, target)
            # the plain definition: every threshold t, accept score <= t
            best = (0.0, None)
            for t in sorted(set(score[ref >= 0])):
                acc = (ref >= 0) & (score <= t)
                tp = int(gt[ref[acc], np.nonzero(acc)[0]].sum())
                prec = tp / acc.sum()
                rec = tp / q
                if prec >= target and rec > best[0]:
                    best = (rec, t)
            assert op["recall"] == pytest.approx(best[0])
            if best[1] is not None:
                assert op["score_threshold"] == pytest.approx(best[1])
                assert op["precision"] >= target


def loop_alignment(n_ref, n_query, tol, offset=0.0):
    """Index-alignment ground truth by plain loops (the documented rule, independently)."""
    scale = (n_ref - 1 - offset) / (n_query - 1) if n_query > 1 else 0.0
    gt = np.zeros((n_ref, n_query), bool)
    for j in range(n_query):
        for r in range(n_ref):
            gt[r, j] = abs(r - (offset + j * scale)) <= tol + 1e-9
    return gt


ALIGNMENT_CASES = [(11, 21, 1.0, 0.0), (21, 11, 1.0, 0.0), (37, 23, 0.0, 0.0),
                   (37, 23, 0.4, 3.5), (50, 50, 2.0, 0.0), (17, 40, 0.5, 0.0),
                   (9, 1, 2.0, 4.0), (1, 5, 3.0, 0.0), (64, 29, 100.0, 10.0),
                   (100, 33, 2.999999999, 7.25), (30, 7, 1e-10, 29.0)]


@pytest.mark.parametrize("n_ref,n_query,tol,offset", ALIGNMENT_CASES)
def test_alignment_ranges_equal_the_dense_matrix(n_ref, n_query, tol, offset):
    from torchseq.ground_truth import alignment_ground_truth, alignment_ranges

    ranges = alignment_ranges(n_ref, n_query, tol, offset)
    loop = loop_alignment(n_ref, n_query, tol, offset)
    assert ranges.shape == (n_ref, n_query)
    assert np.array_equal(ranges.dense(), loop)
    assert np.array_equal(alignment_ground_truth(n_ref, n_query, tol, offset), loop)


def test_ranges_selection_equals_dense_selection():
    from torchseq.ground_truth import alignment_ranges

    ranges = alignment_ranges(100, 77, 3.0, 5.0)
    for rows, cols in ((range(3, 100, 4), range(2, 77, 3)), (range(0, 60), range(10, 11)),
                       ([0, 7, 8, 50, 99], [76, 0, 5])):
        want = ranges.dense()[np.ix_(list(rows), list(cols))]
        assert np.array_equal(ranges.take(rows, cols).dense(), want)


def test_ranges_need_no_dense_allocation():
    from torchseq.ground_truth import GroundTruthError, alignment_ranges

    n = 100_000  # 10^10 cells dense: far above MAX_CELLS, a few MB as ranges
    ranges = alignment_ranges(n, n, 2.0)
    assert ranges.lo.nbytes + ranges.hi.nbytes == 16 * n
    assert ranges.lo[5000] == 4998 and ranges.hi[5000] == 5003
    with pytest.raises(GroundTruthError, match="larger than"):
        ranges.dense()


@pytest.mark.parametrize("seed", range(4))
def test_metrics_from_ranges_equal_the_dense_metrics(seed):
    from torchseq.ground_truth import alignment_ranges

    rng = np.random.default_rng(seed)
    n_ref, n_query = int(rng.integers(20, 60)), int(rng.integers(20, 60))
    ranges = alignment_ranges(n_ref, n_query, float(rng.choice([0.0, 1.0, 2.5])),
                              float(rng.integers(0, 5)))
    dense = ranges.dense()
    truth = dense.argmax(0)
    ref = np.where(rng.random(n_query) < 0.5, truth, rng.integers(0, n_ref, n_query))
    ref = np.where(rng.random(n_query) < 0.1, -1, ref)
    ref[: 3] = [n_ref - 1, 0, -1]  # the ends of the reference
    score = rng.random(n_query).round(2)
    m = Matches(torch.as_tensor(ref), torch.as_tensor(score), lower_is_better=False)
    ranked = np.stack([ref] + [rng.integers(-1, n_ref, n_query) for _ in range(9)], 1)
    sparse_out = metrics.evaluate(m, ranges, ranked)
    dense_out = metrics.evaluate(m, dense, ranked)
    assert sparse_out == dense_out
    assert np.array_equal(metrics.correct(m, ranges), metrics.correct(m, dense))
    assert metrics.operating_point(m, ranges, 0.9) == metrics.operating_point(m, dense, 0.9)
    # and the dense metrics themselves against the plain loops
    points = brute_force_pr(ref, score, dense)
    curve = metrics.precision_recall_curve(m, ranges)
    assert np.allclose(curve.precision, [p for p, _ in points])
    assert np.allclose(curve.recall, [r for _, r in points])


@pytest.mark.parametrize("extra", [[], ["--frame-step", "3", "--start", "2"],
                                   ["--no-keep-matrices"]])
def test_eval_metrics_with_sparse_ground_truth_equal_the_dense_ones(tmp_path, extra):
    """eval.py's index-alignment ground truth is ranges; its metrics equal the dense form's."""
    import json

    import torchseq.cli.eval as cli_eval
    from torchseq.demo import make_demo
    from torchseq.ground_truth import alignment_ground_truth

    demo = make_demo(n_reference=90, speed=1.3, size=(32, 64), seed=3)
    ref, query = tmp_path / "ref.npy", tmp_path / "query.npy"
    np.save(ref, demo.reference.numpy())
    np.save(query, demo.query.numpy())
    out = tmp_path / "out"
    assert cli_eval.main(["--engine", "seqslam", "--reference", str(ref), "--query", str(query),
                          "--tolerance", "2", "--gt-offset", "1.5", "--ds", "6", "--out",
                          str(out), "--no-progress", "--no-tensorboard", *extra]) == 0
    got = json.loads((out / "metrics.json").read_text())["seqslam"]
    assert (out / "seqslam_difference_matrix.png").stat().st_size > 0
    kept = json.loads((out / "config.json").read_text())["seqslam"]["keep_matrices"]
    assert kept is (False if "--no-keep-matrices" in extra else None)  # banded run too
    rows = list(csv_rows(out / "matches.csv"))
    r_idx = np.arange(90)[2::3] if extra[:1] == ["--frame-step"] else np.arange(90)
    q_idx = np.arange(len(demo.query))[2::3] if extra[:1] == ["--frame-step"] else \
        np.arange(len(demo.query))
    dense = alignment_ground_truth(90, len(demo.query), 2.0, offset=1.5)[np.ix_(r_idx, q_idx)]
    reference = np.array([int(r["reference"]) if r["reference"] else -1 for r in rows])
    score = np.array([float(r["score"]) if r["score"] else np.nan for r in rows])
    m = Matches(torch.as_tensor(reference), torch.as_tensor(score), lower_is_better=True)
    assert got["n_positive_queries"] == int(dense.any(0).sum())
    want = metrics.evaluate(m, dense)
    for key in ("recall_at_1", "correct_coverage", "n_matched"):
        assert got[key] == pytest.approx(want[key])


def csv_rows(path):
    import csv

    with open(path, newline="") as f:
        yield from csv.DictReader(f)

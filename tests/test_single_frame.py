"""Single frame against sequence: the nearest-neighbour baseline and the queries made worse."""

import json

import numpy as np
import pytest
import torch
from conftest import shared_data
from seqslam_oracle import oracle_difference

import torchseq.cli.eval as cli_eval
from torchseq import metrics
from torchseq.cli.runs import run_main
from torchseq.matches import Matches
from torchseq.seqslam.difference import difference_matrix
from torchseq.seqslam.single import single_frame, single_frame_from_difference


@pytest.mark.parametrize("metric", ["l1", "l2", "cosine"])
def test_single_frame_equals_a_loop(metric):
    rng = np.random.default_rng(0)
    ref = rng.integers(0, 4, (30, 6)).astype(np.float64)  # ties between references
    query = rng.integers(0, 4, (17, 6)).astype(np.float64)
    if metric == "cosine":  # exact ties would hang on the last bit of a division
        ref, query = ref + rng.random(ref.shape), query + rng.random(query.shape)
    d = oracle_difference(ref, query, metric)
    got = single_frame(torch.tensor(ref), torch.tensor(query), metric, top_k=5,
                       max_chunk_elements=64)  # several blocks of queries
    for q in range(17):
        order = sorted(range(30), key=lambda r: (d[r, q], r))[:5]  # ties: lower index
        assert got.ranked[q].tolist() == order
        np.testing.assert_allclose(got.ranked_score[q].numpy(), d[order, q], atol=1e-9)
        assert int(got.matches.reference[q]) == order[0]
    short = single_frame(torch.tensor(ref[:3]), torch.tensor(query), metric, top_k=5)
    assert (short.ranked[:, 3:] == -1).all() and short.ranked_score[:, 3:].isnan().all()


def test_sequence_vs_single_equals_a_loop():
    rng = np.random.default_rng(1)
    gt = np.zeros((20, 40), bool)
    for q in range(40):
        if q % 5:
            gt[q // 2, q] = True
    seq = np.where(rng.random(40) < 0.6, np.arange(40) // 2, rng.integers(0, 20, 40))
    seq[:3] = -1
    one = np.where(rng.random(40) < 0.5, np.arange(40) // 2, rng.integers(0, 20, 40))
    out = metrics.sequence_vs_single(Matches(torch.tensor(seq), torch.rand(40), True),
                                     Matches(torch.tensor(one), torch.rand(40), True), gt)
    pos = [q for q in range(40) if gt[:, q].any()]
    ok = lambda m, q: m[q] >= 0 and gt[m[q], q]  # noqa: E731
    worse = sum(1 for q in pos if ok(one, q) and not ok(seq, q))
    better = sum(1 for q in pos if ok(seq, q) and not ok(one, q))
    assert out["n_made_worse"] == worse and out["n_made_better"] == better
    assert out["made_worse"] == pytest.approx(worse / len(pos))
    assert out["single_frame_recall_at_1"] == pytest.approx(
        sum(ok(one, q) for q in pos) / len(pos))
    assert out["n_without_sequence_match"] == sum(1 for q in pos if seq[q] < 0)
    assert out["n_queries"] == len(pos) and worse > 0 and better > 0


@pytest.mark.slow
def test_eval_reports_single_frame_beside_the_sequence(tmp_path, capsys):
    root = shared_data("corridor")
    out = tmp_path / "o"
    assert run_main(cli_eval.main, "eval.py", [
        "--reference", str(root / "ref"), "--query", str(root / "query"), "--engine",
        "seqslam", "--ground-truth", str(root / "ground_truth.csv"), "--out", str(out),
        "--no-tensorboard", "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    from torchseq import load_traverse
    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig

    engine = SeqSLAM(SeqSLAMConfig())
    size = SeqSLAMConfig().image_size
    r = engine.descriptors(load_traverse(root / "ref", progress=False, size=size)).numpy()
    q = engine.descriptors(load_traverse(root / "query", progress=False, size=size)).numpy()
    d = oracle_difference(r, q, "l1")
    nearest = d.argmin(0)
    gt = np.zeros((111, 111), bool)
    for j in range(111):
        gt[max(0, j - 2):j + 3, j] = True
    want = float(np.mean(gt[nearest, np.arange(111)]))
    assert m["single_frame"]["recall_at_1"] == pytest.approx(want)
    vs = m["seqslam"]["versus_single_frame"]
    assert vs["single_frame_recall_at_1"] == pytest.approx(want)
    seq = np.array([int(x["reference"]) if x["reference"] else -1 for x in
                    __import__("csv").DictReader(open(out / "matches.csv"))])
    worse = sum(1 for j in range(111) if gt[nearest[j], j] and not (seq[j] >= 0 and
                                                                    gt[seq[j], j]))
    assert vs["n_made_worse"] == worse
    line = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("seqslam:")][0]
    assert f"single frame {want:.3f}, made worse {100 * worse / 111:.1f}%" in line


@pytest.mark.parametrize("metric", ["l1", "l2", "cosine"])
def test_single_frame_from_difference_equals_single_frame(metric):
    rng = np.random.default_rng(2)
    ref = torch.tensor(rng.integers(0, 4, (30, 6)).astype(np.float32))  # ties
    query = torch.tensor(rng.integers(0, 4, (17, 6)).astype(np.float32))
    want = single_frame(ref, query, metric, top_k=5)
    for chunk in (64, 2**26):  # several blocks of queries, one block
        got = single_frame_from_difference(difference_matrix(ref, query, metric), 5, chunk)
        assert torch.equal(got.ranked, want.ranked)
        assert torch.equal(got.ranked_score, want.ranked_score)
        assert torch.equal(got.matches.reference, want.matches.reference)
    short = single_frame_from_difference(difference_matrix(ref[:3], query, metric), 5)
    assert (short.ranked[:, 3:] == -1).all() and short.ranked_score[:, 3:].isnan().all()
    with pytest.raises(ValueError, match="top_k"):
        single_frame_from_difference(difference_matrix(ref, query, metric), 0)


def test_eval_baseline_ranks_the_engines_difference_matrix(tmp_path, monkeypatch):
    """The eval computes the difference matrix once: the baseline ranks the engine's."""
    import torchseq.seqslam.single as single

    root = shared_data("corridor")
    args = ["--reference", str(root / "ref"), "--query", str(root / "query"), "--engine",
            "seqslam", "--ground-truth", str(root / "ground_truth.csv"), "--no-tensorboard",
            "--no-progress"]
    assert run_main(cli_eval.main, "eval.py", [*args, "--out", str(tmp_path / "a")]) == 0

    def fail(*a, **k):
        raise AssertionError("the baseline computed the difference matrix again")

    monkeypatch.setattr(single, "single_frame", fail)
    assert run_main(cli_eval.main, "eval.py", [*args, "--out", str(tmp_path / "b")]) == 0
    a, b = (json.loads((tmp_path / f / "metrics.json").read_text()) for f in "ab")
    assert a["single_frame"] == b["single_frame"] and "recall_at_1" in a["single_frame"]


def test_a_sparse_difference_matrix_is_refused():
    """A candidate run keeps only its candidates' entries: ranking them would be wrong."""
    dense = torch.rand(6, 4)
    with pytest.raises(ValueError, match="sparse"):
        single_frame_from_difference(dense.to_sparse())
    assert single_frame_from_difference(dense).matches.reference.shape == (4,)


def test_smallest_is_the_stable_argsort_to_the_index():
    # the baseline's top-k selection ranks as a whole stable sort (ties: lower index first):
    # ties inside the selection (fast path), ties reaching its edge, NaN, inf, few columns
    from torchseq.seqslam.single import smallest

    g = torch.Generator().manual_seed(0)
    seen_fast = seen_whole = 0
    for trial in range(400):
        rows, cols = int(torch.randint(1, 30, (1,), generator=g)), int(
            torch.randint(1, 300, (1,), generator=g))
        k = int(torch.randint(1, min(cols, 25) + 1, (1,), generator=g))
        span = (2, 8, 60, 10**6)[trial % 4]
        d = torch.randint(0, span, (rows, cols), generator=g).float()
        if trial % 5 == 0:
            d[torch.rand(rows, cols, generator=g) < 0.05] = float("nan")
        if trial % 7 == 0:
            d[torch.rand(rows, cols, generator=g) < 0.05] = float("inf")
        if trial % 3 == 0:
            d = d.T.contiguous().T  # a transposed view, as the engine's blocks may be
        expect = torch.argsort(d, dim=1, stable=True)[:, :k]
        assert torch.equal(smallest(d, k), expect), (trial, rows, cols, k, span)
        if 2 * k < cols:
            v, _ = torch.topk(d, 2 * k, dim=1, largest=False)
            fast = v[:, -1] > v[:, k - 1]
            seen_fast += int(fast.sum())
            seen_whole += int((~fast).sum())
    assert seen_fast > 1000 and seen_whole > 100  # both paths were taken, many times


@pytest.mark.slow  # 1,788 x 1,788 places: descriptors and the whole difference matrix
def test_single_frame_ranks_nordland_as_a_whole_stable_sort():
    # real distances (integer L1 of patch-normalised frames: many ties): the top-k selection
    # ranks exactly as the full stable argsort it replaced
    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
    from torchseq.sources import load_traverse

    root = shared_data("nordland-b")
    s = SeqSLAM(SeqSLAMConfig.openseqslam(threads=1))
    ref = s.descriptors(load_traverse(root / "summer", progress=False))
    query = s.descriptors(load_traverse(root / "winter", progress=False))
    d = difference_matrix(ref, query, "l1")
    got = single_frame_from_difference(d, top_k=21)
    expect = torch.argsort(d.T, dim=1, stable=True)[:, :21]
    assert torch.equal(got.ranked, expect)
    assert torch.equal(got.ranked_score, d.T.gather(1, expect))
    # the distances do tie at the 21st place, so the tie rule is exercised
    kth = d.T.gather(1, expect[:, -1:])
    assert int(((d.T == kth).sum(1) > 1).sum()) > 0

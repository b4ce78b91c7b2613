"""The tensorised engine against the loop oracle (tests/seqslam_oracle.py), then real data."""

import numpy as np
import pytest
import torch
from conftest import DEVICES
from routes import route
from seqslam_oracle import oracle_difference, oracle_enhance, oracle_seqslam

from torchseq.demo import make_demo
from torchseq.metrics import evaluate
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig, search, velocities


def assert_parity(result, want, exact_scores):
    match, best, uniq, ranked = want
    np.testing.assert_array_equal(result.matches.reference.numpy(), match)
    np.testing.assert_array_equal(result.ranked.numpy(), ranked)
    tol = 1e-10 if exact_scores else 1e-4
    np.testing.assert_allclose(result.matches.score.double().numpy(), uniq, rtol=tol, atol=tol)
    np.testing.assert_allclose(result.best_score.double().numpy(), best, rtol=tol, atol=tol)


CASES = [  # (R, Q, query speed, config overrides)
    (40, 30, 1.0, {}),
    (25, 60, 0.4, dict(ds=7, vmin=0.3, vmax=0.6)),  # odd ds rounds up to 8
    (60, 24, 2.0, dict(ds=6, speed_ratio=2.0, speed_tolerance=0.25)),
    (33, 33, 1.0, dict(ds=4, rwindow=6, top_k=40)),  # top_k > R + 1: padded with -1
    (12, 40, 0.3, dict(ds=12, vmin=0.5, vmax=1.5)),  # most trajectories run off the end
    (25, 60, 0.4, dict(ds=8, vmin=0.3, vmax=0.6, match_at="trajectory")),
    (60, 24, 2.0, dict(ds=6, speed_ratio=2.0, match_at="start")),  # parity rule forced
]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", range(len(CASES)))
def test_engine_matches_oracle_on_random_routes(case, dtype):
    n_ref, n_query, speed, over = CASES[case]
    rng = np.random.default_rng(10 + case)
    ref, query = route(rng, n_ref, n_query, speed)
    config = SeqSLAMConfig(**over)
    vmin, vmax = config.velocity_range
    result = SeqSLAM(config).match_descriptors(torch.tensor(ref, dtype=dtype),
                                               torch.tensor(query, dtype=dtype))
    d = oracle_difference(ref, query)
    np.testing.assert_array_equal(result.difference.double().numpy(), d)
    e = oracle_enhance(d, config.enhance_window)
    np.testing.assert_allclose(result.enhanced.double().numpy(), e, atol=1e-4, rtol=1e-5)
    want = oracle_seqslam(e, config.ds, vmin, vmax, config.rwindow, config.top_k,
                          config.match_rule)
    assert_parity(result, want, exact_scores=dtype == torch.float64)
    assert result.ranked.shape == (n_query, config.top_k)
    assert result.matches.lower_is_better and result.difference.dtype == dtype
    assert set(result.seconds) == {"difference", "enhance", "search", "total"}


@pytest.mark.parametrize("speed", [0.4, 2.0])
def test_trajectory_rule_reports_the_true_place_at_speeds_far_from_one(speed):
    # OpenSeqSLAM's start + ds/2 is right only at velocity 1; the trajectory rule reports the
    # row the best trajectory crosses at the query centre.
    rng = np.random.default_rng(5)
    n_query = 60 if speed < 1 else 30
    ref, query = route(rng, 70, n_query, speed, noise=0.5)
    truth = np.minimum(np.round(np.arange(n_query) * speed), 69)
    errors = {}
    for rule in ("start", "trajectory"):
        cfg = SeqSLAMConfig(ds=10, speed_ratio=speed, speed_tolerance=0.3, match_at=rule)
        m = SeqSLAM(cfg).match_descriptors(torch.tensor(ref), torch.tensor(query)).matches
        ok = m.reference.numpy() >= 0
        errors[rule] = np.abs(m.reference.numpy()[ok] - truth[ok]).max()
    assert errors["trajectory"] <= 1
    assert errors["start"] >= 3


@pytest.mark.parametrize("metric", ["l2", "cosine"])
def test_engine_matches_oracle_with_other_metrics(metric):
    rng = np.random.default_rng(5)
    ref, query = route(rng, 30, 30, 1.0)
    result = SeqSLAM(SeqSLAMConfig(metric=metric)).match_descriptors(
        torch.tensor(ref), torch.tensor(query))
    e = oracle_enhance(oracle_difference(ref, query, metric), 10)
    np.testing.assert_allclose(result.enhanced.numpy(), e, atol=1e-8)
    assert_parity(result, oracle_seqslam(e, match_at="trajectory"), exact_scores=False)


def test_search_is_identical_for_any_chunk_budget():
    rng = np.random.default_rng(6)
    e = torch.tensor(rng.uniform(0, 5, (50, 45)), dtype=torch.float32)
    speeds = velocities(10, 0.8, 1.2)
    outs = [search(e, 10, speeds, max_chunk_elements=b) for b in (1, 51, 200, 2**26)]
    for out in outs[1:]:
        for a, b in zip(outs[0], out):
            assert torch.equal(a.nan_to_num(-1), b.nan_to_num(-1))
    small = SeqSLAM(SeqSLAMConfig(max_chunk_elements=7))
    ref, query = route(rng, 40, 30, 1.0)
    a = small.match_descriptors(torch.tensor(ref), torch.tensor(query))
    b = SeqSLAM().match_descriptors(torch.tensor(ref), torch.tensor(query))
    assert torch.equal(a.matches.reference, b.matches.reference)
    assert torch.equal(a.enhanced, b.enhanced) and torch.equal(a.ranked, b.ranked)


@pytest.mark.parametrize("device", DEVICES)
def test_device_param_gives_the_cpu_answer(device):
    rng = np.random.default_rng(7)
    ref, query = (torch.tensor(x, dtype=torch.float32) for x in route(rng, 40, 35, 1.0))
    cpu = SeqSLAM().match_descriptors(ref, query)
    dev = SeqSLAM(device=device).match_descriptors(ref, query)
    assert dev.matches.reference.device.type == "cpu"
    assert torch.equal(dev.matches.reference, cpu.matches.reference)
    assert torch.allclose(dev.matches.score.nan_to_num(-1), cpu.matches.score.nan_to_num(-1),
                          atol=1e-5)


def test_uniqueness_edge_rules():
    e = torch.zeros(20, 11, dtype=torch.float64)  # everything 0: ratio 0 / 0 -> 1
    _, _, uniq, _ = search(e, 10, [1.0], rwindow=10)
    assert uniq[5] == 1.0 and torch.isnan(uniq[:5]).all() and torch.isnan(uniq[6:]).all()
    e = torch.rand(30, 11, dtype=torch.float64)  # rwindow covers all starts: outside = inf -> 0
    match, _, uniq, _ = search(e, 10, [1.0], rwindow=100)
    assert uniq[5] == 0.0 and match[5] >= 0
    match, best, uniq, ranked = search(e[:5], 10, [1.0])  # every trajectory runs off: no match
    assert match[5] == -1 and torch.isinf(best[5]) and torch.isnan(uniq[5])
    assert (ranked == -1).all()


@pytest.mark.slow
def test_corridor_matches_oracle_and_recall(corridor):
    ref, query, gt = corridor.ref, corridor.query, corridor.ground_truth
    engine = SeqSLAM()
    result = engine.match(ref, query)
    rd, qd = engine.descriptors(ref).double().numpy(), engine.descriptors(query).double().numpy()
    d = oracle_difference(rd, qd)
    np.testing.assert_array_equal(result.difference.double().numpy(), d)
    e = oracle_enhance(d)
    np.testing.assert_allclose(result.enhanced.double().numpy(), e, atol=1e-4)
    assert_parity(result, oracle_seqslam(e, match_at="trajectory"), exact_scores=False)
    metrics = evaluate(result.matches, gt, result.ranked.numpy())
    print("corridor", metrics)
    # measured with OpenSeqSLAM's parameters: recall@1 = 0.441 (49/111) reporting where the
    # best trajectory crosses the query (the default), 0.378 with OpenSeqSLAM's start + ds/2
    # (same starts); this fisheye corridor is hard for 64x32 patch-normalised frames
    # (contrast enhancement off gives 0.586, ds=20 gives 0.450, see docs/guide/seqslam.md).
    assert metrics["recall_at_1"] >= 0.42


def test_demo_recall():
    demo = make_demo()
    result = SeqSLAM().match(demo.reference, demo.query)
    metrics = evaluate(result.matches, demo.ground_truth, result.ranked.numpy())
    print("demo", metrics)
    # measured: recall@1 = 0.952 (237/249; the first and last ds/2 queries are unscored)
    assert metrics["recall_at_1"] >= 0.9
    assert metrics["recall_at_10"] >= metrics["recall_at_1"]

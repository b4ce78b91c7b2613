"""Building blocks of torchseq.seqslam against the loop oracle (tests/seqslam_oracle.py)."""

import math

import numpy as np
import pytest
import torch
from conftest import DEVICES
from seqslam_oracle import oracle_difference, oracle_enhance, oracle_velocities

from torchseq.seqslam import SeqSLAMConfig, difference_matrix, enhance_contrast, velocities
from torchseq.seqslam.difference import thermometer_levels

DTYPES = [torch.float32, torch.float64]


def seqslam_like(rng, n, dim=96):
    """Integer descriptors in 119..135, like OpenSeqSLAM's patch-normalised pixels."""
    return (127 + np.clip(np.round(rng.normal(0, 2.5, (n, dim))), -8, 8)).astype(np.float64)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("metric", ["l1", "l2", "cosine"])
@pytest.mark.parametrize("kind", ["integer", "float"])
def test_difference_matrix_matches_loop(metric, kind, dtype, device):
    rng = np.random.default_rng(1)
    if kind == "integer":
        ref, query = seqslam_like(rng, 23), seqslam_like(rng, 17)
    else:
        ref, query = rng.normal(0, 3, (23, 40)), rng.normal(0, 3, (17, 40))
    want = oracle_difference(ref, query, metric)
    got = difference_matrix(torch.tensor(ref, dtype=dtype, device=device),
                            torch.tensor(query, dtype=dtype, device=device), metric)
    assert got.shape == (23, 17) and got.dtype == dtype and got.device.type == device
    tol = 1e-5 if dtype == torch.float32 else 1e-10
    np.testing.assert_allclose(got.cpu().double().numpy(), want, rtol=tol, atol=tol)
    if kind == "integer" and metric == "l1":  # the thermometer path is exact
        assert thermometer_levels(torch.tensor(ref), torch.tensor(query)) is not None
        np.testing.assert_array_equal(got.cpu().double().numpy(), want)


@pytest.mark.parametrize("budget", [1, 100, 2**26])
def test_difference_matrix_chunking_is_exact(budget):
    rng = np.random.default_rng(2)
    ref, query = torch.tensor(seqslam_like(rng, 37)), torch.tensor(seqslam_like(rng, 29))
    full = difference_matrix(ref, query, "l1")
    np.testing.assert_array_equal(difference_matrix(ref, query, "l1", budget).numpy(),
                                  full.numpy())
    # the general cdist path (half-integer values leave the thermometer path) agrees
    np.testing.assert_allclose(difference_matrix(ref + 0.5, query, "l1", budget).numpy(),
                               oracle_difference(ref.numpy() + 0.5, query.numpy()), rtol=1e-12)


def test_difference_matrix_constant_inputs_give_zero():
    x = torch.full((4, 8), 127.0)
    assert torch.equal(difference_matrix(x, x[:3]), torch.zeros(4, 3, dtype=x.dtype))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("window", [10, 4, 7, 0])
def test_enhance_contrast_matches_loop(window, dtype, device):
    rng = np.random.default_rng(3)
    d = rng.uniform(1000, 5000, (31, 13))
    d[:, 4] = 2500.0  # a constant column: std 0 everywhere -> 0 by definition
    d[10:15, 6] = 7.0  # a flat run shorter than the window
    got = enhance_contrast(torch.tensor(d, dtype=dtype, device=device), window)
    want = oracle_enhance(d, window) if window else d - d.min()
    assert got.shape == d.shape and got.dtype == dtype
    tol = 2e-5 if dtype == torch.float32 else 1e-10
    np.testing.assert_allclose(got.cpu().double().numpy(), want, rtol=tol, atol=tol)
    assert float(got.min()) == 0.0 and bool(torch.isfinite(got).all())


def test_enhance_contrast_without_min_and_chunked():
    rng = np.random.default_rng(4)
    d = torch.tensor(rng.uniform(0, 100, (20, 9)))
    raw = enhance_contrast(d, 10, subtract_min=False)
    np.testing.assert_allclose(raw.numpy(), oracle_enhance(d.numpy(), 10, False), atol=1e-12)
    assert float(raw.min()) < 0  # z-scores go negative before the subtraction
    np.testing.assert_array_equal(enhance_contrast(d, 10, max_chunk_elements=1).numpy(),
                                  enhance_contrast(d, 10).numpy())


@pytest.mark.parametrize("ds,vmin,vmax,want", [
    (10, 0.8, 1.2, [0.8, 0.9, 1.0, 1.1, 1.2]),
    (4, 0.8, 1.2, [1.0]),
    (20, 0.9, 1.1, [0.9, 0.95, 1.0, 1.05, 1.1]),
    (10, 1.0, 1.0, [1.0]),
    (100, 0.7 * 0.8, 0.7 * 1.2, [m / 100 for m in range(56, 85)]),
])
def test_velocities(ds, vmin, vmax, want):
    got = velocities(ds, vmin, vmax)
    assert got == pytest.approx(want, abs=1e-12)
    assert [m / d for m, d in oracle_velocities(ds, vmin, vmax)] == pytest.approx(got)


def test_velocities_empty_range_raises():
    with pytest.raises(ValueError, match="no velocity"):
        velocities(10, 0.81, 0.89)


@pytest.mark.parametrize("bad", [
    dict(ds=1), dict(vmin=1.3), dict(vmin=0.0), dict(metric="hamming"),
    dict(enhance_window=1), dict(rwindow=-1), dict(top_k=0), dict(max_chunk_elements=0),
    dict(speed_ratio=-1.0), dict(speed_ratio=2.0, speed_tolerance=1.5), dict(patch_size=7),
    dict(image_size=(0, 64)), dict(vmin=math.nan), dict(vmin=0.81, vmax=0.89),
])
def test_config_rejects_nonsense(bad):
    with pytest.raises(ValueError):
        SeqSLAMConfig(**bad).validate()


def test_config_speed_ratio_and_rounding():
    c = SeqSLAMConfig(ds=9, speed_ratio=2.0, speed_tolerance=0.1).validate()
    assert c.sequence_length == 10
    assert c.velocity_range == pytest.approx((1.8, 2.2))
    from dataclasses import asdict
    assert asdict(c)["speed_ratio"] == 2.0 and asdict(c)["metric"] == "l1"


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("n,k", [(8, 3), (40, 10), (300, 10),
                                 pytest.param(3000, 5, marks=pytest.mark.slow)])
def test_rank_scores_ties_go_to_the_lower_start(n, k, device):
    # integer scores: many ties, also across the K-th place, where topk keeps any of them
    from torchseq.seqslam.search import rank_scores

    rng = np.random.default_rng(n)
    s = rng.integers(0, 4, (64, n)).astype(np.float64)
    s[::7, : n // 2] = np.inf  # unscored starts
    s[3] = 1.0  # a row of one value
    start, best, _, ranked = rank_scores(torch.tensor(s, device=device), 4, n - 1, 4, k)
    for r in range(64):
        order = sorted(range(n), key=lambda i: (s[r, i], i))  # stable: lower start first
        want = []  # each place once (starts past n - 4 all report the clamped n - 2)
        for i in order:
            if np.isfinite(s[r, i]) and min(i + 2, n - 2) not in want:
                want.append(min(i + 2, n - 2))
        want = want[:k]
        assert ranked[r].tolist() == want + [-1] * (k - len(want)), r
        assert int(start[r]) == order[0] and float(best[r]) == s[r, order[0]]


def test_search_with_tied_scores_matches_oracle():
    from seqslam_oracle import oracle_seqslam

    from torchseq.seqslam import search

    rng = np.random.default_rng(5)
    e = rng.integers(0, 2, (400, 16)).astype(np.float64)  # an enhanced matrix full of ties
    speeds = velocities(4, 0.8, 1.2)
    match, best, _, ranked = search(torch.tensor(e), 4, speeds, rwindow=4, top_k=10)
    w_match, w_best, _, w_ranked = oracle_seqslam(e, 4, 0.8, 1.2, 4, 10)
    np.testing.assert_array_equal(ranked.numpy(), w_ranked)
    np.testing.assert_array_equal(match.numpy(), w_match)
    np.testing.assert_allclose(best.numpy(), w_best, rtol=1e-12)


def test_rank_scores_lists_each_place_once_however_many_starts_report_it():
    """Starts 0..29 (the best 30) all report place 50 through ``centre``; the rest report
    start + 2. The ranking lists 50 once and then the next places, however deep it must go."""
    from torchseq.seqslam.search import rank_scores

    n, k = 80, 4
    scores = torch.arange(n, dtype=torch.float64)[None].repeat(2, 1)
    centre = torch.full((2, n), 2, dtype=torch.int64)
    centre[:, :30] = 50 - torch.arange(30)
    scores[1, 31] = math.inf  # an unscored start is skipped
    start, best, _, ranked = rank_scores(scores, 4, 100, 4, k, centre)
    assert ranked[0].tolist() == [50, 32, 33, 34]
    assert ranked[1].tolist() == [50, 32, 34, 35]
    assert start.tolist() == [0, 0] and best.tolist() == [0.0, 0.0]
    few = scores.clone()
    few[:, 31:] = math.inf  # only two distinct places hold finite scores
    assert rank_scores(few, 4, 100, 4, k, centre)[3].tolist() == [[50, 32, -1, -1]] * 2


@pytest.mark.parametrize("integer", [False, True])
def test_start_velocity_equals_the_full_velocity_map(integer):
    """The trajectory rule's velocities, computed for chosen starts only, are those of
    ``trajectory_scores(with_velocity=True)`` for every start (inf row and ties included)."""
    from torchseq.seqslam.search import start_velocity, trajectory_offsets, trajectory_scores

    rng = np.random.default_rng(11)
    e = rng.integers(0, 3, (60, 40)) if integer else rng.uniform(0, 5, (60, 40))
    d_t = torch.tensor(e, dtype=torch.float32).T.contiguous()
    ds = 10
    offsets = trajectory_offsets(ds, velocities(ds, 0.8, 1.2))
    _, full = trajectory_scores(d_t, 5, 35, ds, offsets, with_velocity=True)
    starts = torch.arange(61).repeat(30, 1)
    assert torch.equal(start_velocity(d_t, 5, ds, offsets, starts), full)
    some = torch.tensor(rng.integers(0, 61, (30, 7)))
    assert torch.equal(start_velocity(d_t, 5, ds, offsets, some), full.gather(1, some))

"""The ranked references' trajectory scores (recall@K with ties needs them) against loops."""

import numpy as np
import pytest
import torch
from seqslam_oracle import _scores_for_window, oracle_seqslam, oracle_velocities

from torchseq.seqslam import SeqSLAM, SeqSLAMConfig, search, velocities


def loop_place_scores(e, ds, vmin, vmax, ranked, edges):
    """Per query, each ranked place's score: the lowest score of the starts reporting it."""
    n_ref, n_query = e.shape
    dext = np.vstack([e, np.full((1, n_query), np.inf)])
    vels = oracle_velocities(ds, vmin, vmax)
    out = np.full(ranked.shape, np.nan)
    for n in range(n_query):
        if ds // 2 <= n < n_query - ds // 2:
            col0, step = n - ds // 2, None
        elif edges and n < ds // 2:
            col0, step = n, 0
        elif edges and n >= n_query - ds // 2:
            col0, step = n - ds, ds
        else:
            continue
        score, best_v = _scores_for_window(dext, col0, ds, vels)
        for i, place in enumerate(ranked[n]):
            if place < 0:
                continue
            reps = []
            for x in range(n_ref + 1):
                if step is None:
                    rep = min(x + ds // 2, n_ref - 1)
                else:
                    m, den = vels[best_v[x]]
                    rep = min(x + (step * m) // den, n_ref - 1)
                if rep == place:
                    reps.append(score[x])
            out[n, i] = min(reps)
    return out


@pytest.mark.parametrize("edges", [False, True])
@pytest.mark.parametrize("ties", [False, True])
def test_ranked_scores_equal_the_loop(edges, ties):
    rng = np.random.default_rng(3)
    e = rng.random((60, 20))
    if ties:
        e = rng.integers(0, 2, (60, 20)).astype(np.float64)
    speeds = velocities(4, 0.8, 1.2)
    got = torch.empty(20, 10, dtype=torch.float64)
    _, _, _, ranked = search(torch.tensor(e), 4, speeds, rwindow=4, top_k=10, edges=edges,
                             ranked_score=got)
    want_ranked = oracle_seqslam(e, 4, 0.8, 1.2, 4, 10, edges=edges)[3]
    np.testing.assert_array_equal(ranked.numpy(), want_ranked)
    want = loop_place_scores(e, 4, 0.8, 1.2, ranked.numpy(), edges)
    np.testing.assert_array_equal(np.isnan(got.numpy()), np.isnan(want))
    np.testing.assert_allclose(got.numpy()[~np.isnan(want)], want[~np.isnan(want)], rtol=1e-12)


def test_engine_keeps_ranked_scores_in_order():
    rng = np.random.default_rng(0)
    ref, query = rng.random((40, 16)), rng.random((30, 16))
    res = SeqSLAM(SeqSLAMConfig(ds=6)).match_descriptors(ref, query)
    s = res.ranked_score.numpy()
    listed = res.ranked.numpy() >= 0
    assert np.array_equal(listed, ~np.isnan(s))
    rows = listed.all(1)
    assert (np.diff(s[rows], axis=1) >= 0).all()  # best first
    ok = res.matches.reference.numpy() >= 0
    np.testing.assert_allclose(s[ok, 0], res.best_score.numpy()[ok])


@pytest.mark.parametrize("edges", [False, True])
def test_banded_runs_keep_the_same_ranked_scores(edges):
    """A long route's banded run (no full matrices) ranks with the full run's scores."""
    rng = np.random.default_rng(2)
    ref, query = rng.random((90, 12)), rng.random((70, 12))
    full = SeqSLAM(SeqSLAMConfig(ds=6, edges=edges, keep_matrices=True)).match_descriptors(
        ref, query)
    band = SeqSLAM(SeqSLAMConfig(ds=6, edges=edges, keep_matrices=False,
                                 max_chunk_elements=3000)).match_descriptors(ref, query)
    assert band.kernels["matrices"] == "banded"
    np.testing.assert_array_equal(band.ranked.numpy(), full.ranked.numpy())
    np.testing.assert_allclose(band.ranked_score.numpy(), full.ranked_score.numpy(),
                               rtol=1e-9, atol=1e-9)

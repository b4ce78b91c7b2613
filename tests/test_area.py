"""The one area reduction (torchseq.area) against a plain-loop block mean; its two users."""

import numpy as np
import pytest
import torch

import torchseq.cli.plots as plots
from torchseq.area import Partial, area_mean, finish, reduce_rows
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
from torchseq.seqslam import banded as banded_module


def loop_block_mean(m, out_h, out_w):
    """Mean of the finite entries of each adaptive-pooling block, by plain loops."""
    n_r, n_q = m.shape
    out_h, out_w = min(out_h, n_r), min(out_w, n_q)
    out = np.full((out_h, out_w), np.nan)
    for i in range(out_h):
        r0, r1 = (i * n_r) // out_h, -((-(i + 1) * n_r) // out_h)
        for j in range(out_w):
            c0, c1 = (j * n_q) // out_w, -((-(j + 1) * n_q) // out_w)
            vals = [float(v) for v in m[r0:r1, c0:c1].ravel() if np.isfinite(v)]
            if vals:
                out[i, j] = sum(vals) / len(vals)
    return out


def assert_same(got, want):
    got = np.asarray(got, np.float64)
    assert got.shape == want.shape
    assert np.array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got[~np.isnan(got)], want[~np.isnan(want)], rtol=1e-5)


def matrix(shape, seed=0, holes=True):
    m = np.random.default_rng(seed).random(shape) * 10 - 3
    if holes:
        m[1, 2] = np.nan
        m[3:, 0] = np.inf  # whole blocks without a finite entry become NaN
        m[0, -1] = -np.inf
    return m


@pytest.mark.parametrize("shape,out", [((12, 8), (4, 4)), ((37, 23), (5, 7)),
                                       ((6, 50), (7, 3)), ((9, 9), (9, 9))])
def test_area_mean_is_the_loop_block_mean(shape, out):
    m = matrix(shape)
    assert_same(area_mean(torch.tensor(m), out), loop_block_mean(m, *out))
    # plots.reduce_matrix is the same definition (square side)
    side = min(out)
    if side < max(shape):
        assert np.array_equal(plots.reduce_matrix(m, side),
                              area_mean(torch.tensor(m), (side, side)).double().numpy(),
                              equal_nan=True)


def test_reduction_in_column_bands_equals_whole():
    # as the banded engine does: reduce query columns band by band (overlapping), finish once
    m = matrix((30, 41), seed=1)  # (R, Q)
    rows = torch.empty(41, 6)
    weights = torch.empty(41, 6)
    seen_all_finite = False
    for q0 in range(0, 41, 9):
        q1 = min(q0 + 13, 41)  # overlapping bands rewrite the same columns
        part = reduce_rows(torch.tensor(m[:, q0:q1]).T, 6)
        seen_all_finite |= part.weights is None
        rows[q0:q1] = part.values
        weights[q0:q1] = 1.0 if part.weights is None else part.weights
    assert seen_all_finite  # a band without holes takes the one-pooling branch
    got = finish(Partial(rows, weights), 4)
    assert_same(got, loop_block_mean(m, 6, 4))
    assert torch.equal(torch.isnan(got), torch.isnan(area_mean(torch.tensor(m), (6, 4))))
    finite = matrix((30, 41), seed=1, holes=False)
    part = reduce_rows(torch.tensor(finite).T, 6)
    assert part.weights is None
    assert_same(finish(part, 4), loop_block_mean(finite, 6, 4))


@pytest.mark.parametrize("over", [{}, dict(metric="l2", edges=True)])
def test_banded_preview_is_the_block_mean(monkeypatch, over):
    monkeypatch.setattr(banded_module, "PREVIEW_SIDE", 5)  # reduce a small matrix
    rng = np.random.default_rng(3)
    ref = rng.normal(0, 1, (33, 24))
    query = ref[np.minimum(np.arange(29), 32)] + rng.normal(0, 0.3, (29, 24))
    cfg = SeqSLAMConfig(**{"keep_matrices": False, "max_chunk_elements": 2**9, "ds": 6,
                           **over})
    banded = SeqSLAM(cfg).match_descriptors(torch.tensor(ref), torch.tensor(query))
    full = SeqSLAM(SeqSLAMConfig(**{**cfg.__dict__, "keep_matrices": True})).match_descriptors(
        torch.tensor(ref), torch.tensor(query))
    assert banded.kernels["matrices"] == "banded" and full.kernels["matrices"] == "full"
    want = loop_block_mean(full.enhanced.numpy(), 5, 5)
    assert_same(banded.preview, want)
    assert_same(full.preview, want)

"""Difference-matrix plots of long routes: a reduced copy, overlays in full coordinates."""

import numpy as np
import pytest
import torch

import torchseq.cli.plots as plots
from torchseq.cli.report_images import GREEN, RED, draw_difference_matrix
from torchseq.ground_truth import alignment_ranges
from torchseq.matches import Matches


def loop_block_mean(m, out_h, out_w):
    """Mean of the finite entries of each adaptive-pooling block, by plain loops."""
    n_r, n_q = m.shape
    out = np.full((out_h, out_w), np.nan)
    for i in range(out_h):
        r0, r1 = (i * n_r) // out_h, -((-(i + 1) * n_r) // out_h)
        for j in range(out_w):
            c0, c1 = (j * n_q) // out_w, -((-(j + 1) * n_q) // out_w)
            vals = [v for v in m[r0:r1, c0:c1].ravel() if np.isfinite(v)]
            if vals:
                out[i, j] = sum(vals) / len(vals)
    return out


@pytest.mark.parametrize("shape,side", [((12, 8), 4), ((37, 23), 5), ((6, 50), 7)])
def test_reduce_matrix_is_the_block_mean(shape, side):
    rng = np.random.default_rng(0)
    m = rng.random(shape)
    m[1, 2] = np.nan
    m[3:, 0] = np.inf  # whole blocks without a finite entry become NaN
    got = plots.reduce_matrix(m, side)
    want = loop_block_mean(m, min(shape[0], side), min(shape[1], side))
    assert got.shape == want.shape
    assert np.array_equal(np.isnan(got), np.isnan(want))
    assert np.allclose(got[~np.isnan(got)], want[~np.isnan(want)], rtol=1e-5)
    small = rng.random((3, 4))
    assert np.array_equal(plots.reduce_matrix(small, side), small)  # small ones untouched


def _case(n_ref, n_query, seed=0):
    rng = np.random.default_rng(seed)
    gt = alignment_ranges(n_ref, n_query, 2.0)
    ref = np.round(np.arange(n_query) * (n_ref - 1) / (n_query - 1)).astype(np.int64)
    wrong = rng.random(n_query) < 0.2
    ref[wrong] = rng.integers(0, n_ref, int(wrong.sum()))
    ref[5] = -1
    m = Matches(torch.as_tensor(ref), torch.as_tensor(rng.random(n_query)),
                lower_is_better=False)
    return gt, ref, m


def test_engine_preview_is_stretched_over_the_full_matrix():
    n_ref, n_query = 3000, 2000
    gt, ref, m = _case(n_ref, n_query)
    preview = np.random.default_rng(2).random((1024, 1024))
    img = draw_difference_matrix(preview, m, gt, shape=(n_ref, n_query))
    full = draw_difference_matrix(np.zeros((n_ref, n_query), np.float32), m, gt)
    for colour in (GREEN, RED):  # the match dots where the full matrix puts them
        dots = (img == colour).all(-1)
        assert dots[:, 62:590].sum() > 100
        assert np.array_equal(dots, (full == colour).all(-1))
    with pytest.raises(ValueError, match="reduce"):
        draw_difference_matrix(preview, m, gt, shape=(100, n_query))
    with pytest.raises(ValueError, match="ground truth"):
        draw_difference_matrix(preview, m, gt, shape=(n_ref + 1, n_query))


def test_save_image_writes_the_drawn_figure(tmp_path):
    import cv2

    fig = plots.plot_matrix(np.random.default_rng(4).random((40, 30)), "t")
    image = plots.figure_to_array(fig)
    plots.save_image(image, tmp_path / "a.png")
    back = cv2.imread(str(tmp_path / "a.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(back[..., ::-1], image)  # RGB kept, pixel for pixel
    plots.save_figure(fig, tmp_path / "b.png")  # the figure's own PNG: same size
    assert cv2.imread(str(tmp_path / "b.png")).shape == back.shape
    assert [p.name for p in tmp_path.iterdir()] != [] and not list(tmp_path.glob(".*tmp*"))
    with pytest.raises(ValueError, match="uint8"):
        plots.save_image(image.astype(np.float32), tmp_path / "c.png")


def test_activity_raster_of_a_long_run_is_reduced_in_frame_coordinates():
    activity = np.random.default_rng(5).random((3000, 40))
    fig = plots.plot_activity_raster(activity)
    ax = fig.axes[0]
    image = ax.get_images()[0]
    assert image.get_array().shape == (40, plots.PLOT_SIDE)
    assert tuple(image.get_extent()) == (-0.5, 2999.5, -0.5, 39.5)
    line = ax.get_lines()[0]
    assert np.array_equal(line.get_ydata(), activity.argmax(1))  # winners, every frame
    assert np.array_equal(line.get_xdata(), np.arange(3000))


@pytest.mark.parametrize("shape,side", [((12, 8), 4), ((37, 23), 5), ((600, 530), 512),
                                        ((30, 20), 512)])
def test_sparse_matrix_reduces_as_its_dense_form_with_blanks(shape, side):
    rng = np.random.default_rng(6)
    dense = np.full(shape, np.nan)
    keep = rng.random(shape) < 0.2  # candidate mode: a few evaluated entries per column
    dense[keep] = rng.random(int(keep.sum()))
    rows, cols = np.nonzero(keep)
    sparse = torch.sparse_coo_tensor(np.stack([rows, cols]), dense[keep], shape,
                                     check_invariants=True)
    got = plots.reduce_matrix(sparse, side)
    want = loop_block_mean(dense, min(shape[0], side), min(shape[1], side)) \
        if shape[0] < 100 else plots.reduce_matrix(dense, side)
    assert got.shape == want.shape
    assert np.array_equal(np.isnan(got), np.isnan(want))
    assert np.allclose(got[~np.isnan(got)], want[~np.isnan(want)], rtol=1e-5)


def test_true_units_follow_a_plain_loop_and_the_raster_draws_them():
    """issue 23 item 14: the neural raster shows the ground truth as the units standing for an
    admissible reference frame of each query (spans past the reference are clipped)."""
    from torchseq.cli.plots import plot_activity_raster, true_units
    from torchseq.ground_truth import alignment_ground_truth

    rng = np.random.default_rng(0)
    gt = (rng.random((23, 17)) < 0.15).astype(np.uint8)  # (R, Q)
    spans = np.array([[0, 3], [3, 5], [5, 9], [9, 10], [10, 16], [16, 23], [20, 30]])
    want = np.array([[any(gt[r, q] for r in range(f, min(e, 23))) for f, e in spans]
                     for q in range(17)])
    got = true_units(gt, torch.tensor(spans), 17)
    assert got.shape == (17, 7) and np.array_equal(got, want)
    ranges = alignment_ground_truth(40, 30, 2)
    dense = np.asarray(ranges.dense() if hasattr(ranges, "dense") else ranges)
    spans2 = np.stack([np.arange(0, 40, 4), np.arange(4, 44, 4)], 1)
    assert np.array_equal(true_units(ranges, spans2, 30), true_units(dense, spans2, 30))
    assert true_units(gt, spans, 17, max_elements=100) is None
    fig = plot_activity_raster(rng.random((17, 7)), truth=got)
    lines = {line.get_label(): line for line in fig.axes[0].lines}
    frames, units = np.nonzero(want)
    assert np.array_equal(lines["ground truth"].get_xdata(), frames)
    assert np.array_equal(lines["ground truth"].get_ydata(), units)
    plain = plot_activity_raster(rng.random((17, 7))).axes[0].lines
    assert "ground truth" not in {line.get_label() for line in plain}

"""The eval report's figures drawn with NumPy/OpenCV (torchseq.cli.report_images).

Each figure is checked against what it must show, read back from its pixels: the matrix's
grey levels, the ground-truth band, the matches' colours at their coordinates, the frames of
the matched pairs, the PR curve's line.
"""

import numpy as np
import pytest
import torch

import torchseq.cli.report_images as report_images
from torchseq import metrics
from torchseq.ground_truth import alignment_ranges
from torchseq.matches import Matches

GREEN, RED, BLUE = report_images.GREEN, report_images.RED, report_images.BLUE


def _axes(n_ref, n_query):
    """The plot area of draw_difference_matrix (its fixed layout)."""
    return report_images._Axes(None, (62, 30, 590, 448), (-0.5, n_query - 0.5),
                               (n_ref - 0.5, -0.5))


def test_difference_matrix_shows_the_matrix_band_and_matches():
    n = 40
    rng = np.random.default_rng(0)
    matrix = rng.random((n, n))
    ref = np.arange(n)
    ref[5] = 30  # one wrong match
    ref[7] = -1  # one query without a match
    m = Matches(torch.tensor(ref), torch.rand(n), True)
    gt = alignment_ranges(n, n, 1.0)
    img = report_images.draw_difference_matrix(matrix, m, gt, "t")
    assert img.shape == (500, 600, 3) and img.dtype == np.uint8
    ax = _axes(n, n)
    lo, hi = np.percentile(matrix, [1, 99])
    want = np.clip((matrix - lo) / (hi - lo), 0, 1) * 255  # the grey scale, row r = ref r
    # a cell far from the band and from every dot: its grey level, as the matrix says
    for r, q in ((30, 2), (2, 30), (20, 35)):
        u, v = (int(round(float(c))) for c in ax.px(q, r))
        assert np.abs(img[v, u].astype(int) - int(want[r, q])).max() <= 1, (r, q)
    # every match is a dot of its colour at (query, reference); the wrong one red
    for q in (0, 5, 20, 39):
        u, v = (int(round(float(c))) for c in ax.px(q, ref[q]))
        assert tuple(img[v, u]) == (RED if q == 5 else GREEN), q
    u, v = (int(round(float(c))) for c in ax.px(7, 7))  # no match at query 7: band only
    grey = want[7, 7]
    assert np.allclose(img[v, u], 0.75 * grey + 0.25 * np.array(BLUE), atol=2)
    # the band: tinted inside the admissible references, untinted just outside
    u, v = (int(round(float(c))) for c in ax.px(7, 9))  # reference 9: outside +-1 of 7
    assert np.abs(img[v, u].astype(int) - int(want[9, 7])).max() <= 1


def test_difference_matrix_dense_ground_truth_and_reduction():
    n_ref, n_query = 1500, 1100  # reduced to 512 a side before drawing
    matrix = np.add.outer(np.arange(n_ref) / n_ref, np.zeros(n_query))  # rows get brighter
    gt = np.zeros((n_ref, n_query), bool)
    img = report_images.draw_difference_matrix(matrix, None, gt, "t")
    ax = _axes(n_ref, n_query)
    column = [img[int(round(float(ax.px(500, r)[1]))), int(round(float(ax.px(500, r)[0])))][0]
              for r in range(0, n_ref, 100)]
    assert all(a <= b for a, b in zip(column, column[1:])) and column[-1] > column[0] + 200
    with pytest.raises(ValueError, match="does not fit"):
        report_images.draw_difference_matrix(matrix, None, gt[:10], "t")
    with pytest.raises(ValueError, match="matches for a matrix"):
        report_images.draw_difference_matrix(matrix, Matches(torch.zeros(3, dtype=torch.long),
                                                             torch.zeros(3), True))


def test_matched_pairs_show_the_frames_and_the_verdict():
    n = 12
    frames = np.stack([np.full((16, 32), 10.0 * i + 100) for i in range(n)])  # camera levels
    ref = np.arange(n)
    ref[11] = 0  # the last pick is wrong
    m = Matches(torch.tensor(ref), torch.ones(n), True)
    gt = alignment_ranges(n, n, 0.0)
    img = report_images.draw_matched_pairs(frames, frames, m, gt, n=4, title="t")
    assert img.shape == (420, 800, 3)
    picks = [0, 4, 7, 11]  # np.linspace(0, 11, 4).round()
    for col, q in enumerate(picks):
        # the frame panels: 184 x 160 boxes, the 32x16 frame scaled 5.75x, centred
        y_q, y_r, x = 50 + 80, 235 + 80, col * 200 + 100
        assert tuple(img[y_q, x]) == (int(10 * q + 100),) * 3
        assert tuple(img[y_r, x]) == (int(10 * ref[q] + 100),) * 3
    label = img[250:268, 3 * 200:4 * 200]  # "reference 0" above the last, wrong pair
    assert ((label[..., 0] > 200) & (label[..., 1] < 80)).any()  # red text
    ok = img[250:268, 0:200]
    assert ((ok[..., 1] > 100) & (ok[..., 0] < 60)).any()  # green text


def test_pr_curve_draws_each_engine_in_its_colour():
    n = 50
    ref = torch.arange(n)
    ref[::3] = 0
    m = Matches(ref, torch.linspace(0, 1, n), True)
    gt = alignment_ranges(n, n, 0.0)
    curve = metrics.precision_recall_curve(m, gt)
    img = report_images.draw_pr_curves({"seqslam": curve})
    assert img.shape == (400, 500, 3)
    ax = report_images._Axes(None, (58, 30, 488, 348), (0.0, 1.0), (0.0, 1.02))
    u, v = ax.px(curve.recall[len(curve.recall) // 2], curve.precision[len(curve.recall) // 2])
    patch = img[int(v) - 2:int(v) + 3, int(u) - 2:int(u) + 3].reshape(-1, 3).astype(int)
    assert (np.abs(patch - np.array(BLUE)).sum(1) < 60).any()  # the first engine's colour


def test_nice_ticks():
    assert report_images.nice_ticks(-0.5, 3575.5).tolist() == [0, 500, 1000, 1500, 2000, 2500,
                                                               3000, 3500]
    assert np.allclose(report_images.nice_ticks(0, 1.02), [0, 0.2, 0.4, 0.6, 0.8, 1.0])


def test_tensorboard_holds_the_report_images_and_scalars(tmp_path):
    """The event file's images are the PNG files' pixels (written once, not re-encoded)."""
    import json

    import cv2
    from conftest import shared_data
    from tensorboard.backend.event_processing.event_file_loader import LegacyEventFileLoader

    import torchseq.cli.eval as cli_eval
    from torchseq.cli.runs import run_main

    root = shared_data("corridor")
    out = tmp_path / "o"
    assert run_main(cli_eval.main, "eval.py", [
        "--reference", str(root / "ref"), "--query", str(root / "query"), "--engine", "seqslam",
        "--ground-truth", str(root / "ground_truth.csv"), "--no-progress", "--out",
        str(out)]) == 0
    events = sorted((out / "tensorboard").glob("events.out.tfevents.*"))[0]
    images, scalars = {}, {}
    for event in LegacyEventFileLoader(str(events)).Load():  # as written, not migrated
        for v in event.summary.value:
            if v.HasField("image"):
                images[v.tag] = v.image
            elif v.HasField("simple_value"):
                scalars[v.tag] = v.simple_value
    names = {"seqslam_difference_matrix", "seqslam_matched_pairs", "pr_curve"}
    assert set(images) == names
    for name in names:
        png = cv2.imread(str(out / f"{name}.png"), cv2.IMREAD_COLOR)
        got = cv2.imdecode(np.frombuffer(images[name].encoded_image_string, np.uint8),
                           cv2.IMREAD_COLOR)
        assert np.array_equal(got, png)
        assert (images[name].height, images[name].width, images[name].colorspace) == \
            (*png.shape[:2], 3)
    m = json.loads((out / "metrics.json").read_text())["seqslam"]
    assert scalars["seqslam/recall_at_1"] == pytest.approx(m["recall_at_1"])

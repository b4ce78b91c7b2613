"""What an eval run leaves and says (issue 23): plots for a checkpoint of a longer route,
a start past the end, interrupted runs, matches.csv columns, plot labels."""

import json
import shutil

import numpy as np
import pytest
import torch
from conftest import shared_data

from torchseq import cli_eval, cli_train, plots
from torchseq.frontend import run_main
from torchseq.matches import Matches


def run_eval(tmp_path, capsys, *args, out="o"):
    code = run_main(cli_eval.main, "eval.py", [*args, "--no-progress", "--no-tensorboard",
                                               "--out", str(tmp_path / out)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.fixture(scope="module")
def lens_checkpoint(tmp_path_factory):
    """A neural checkpoint learnt on LENS's 100 reference frames."""
    ref = shared_data("lens-davis128", "example-reference")
    out = tmp_path_factory.mktemp("train")
    code = run_main(cli_train.main, "train.py", [
        "--reference", str(ref), "--no-progress", "--no-tensorboard", "--out", str(out / "t")])
    assert code == 0
    return out / "t" / "model.pt"


def test_matched_pairs_past_the_reference_are_left_out_and_said():
    ref = np.zeros((40, 8, 8), np.uint8)
    qry = np.zeros((100, 8, 8), np.uint8)
    m = Matches(torch.arange(100), torch.ones(100), lower_is_better=False)
    fig = plots.plot_matched_pairs(ref, qry, m, title="t")
    assert "60 of 100 matches point past the 40 reference frames: not shown" in \
        fig._suptitle.get_text()
    titles = [ax.get_title() for ax in fig.axes if ax.get_title().startswith("reference")]
    assert titles and all(int(t.split()[1]) < 40 for t in titles)


def test_checkpoint_of_a_longer_route_on_a_shorter_one_writes_its_plots(
        tmp_path, capsys, lens_checkpoint):
    lens = shared_data("lens-davis128")
    short = tmp_path / "short"
    short.mkdir()
    for i in range(40):
        shutil.copy(lens / "example-reference" / f"image_{i:04d}.png", short)
    code, out, err = run_eval(tmp_path, capsys, "--engine", "neural", "--checkpoint",
                              str(lens_checkpoint), "--reference", str(short), "--query",
                              str(lens / "example-query"))
    assert code == 0, err
    assert "Traceback" not in err and "IndexError" not in err
    assert "it learnt 100 reference frames, this reference has 40" in err
    assert (tmp_path / "o" / "neural_matched_pairs.png").stat().st_size > 1000
    assert (tmp_path / "o" / "neural_activity.png").stat().st_size > 1000


@pytest.mark.parametrize("kind", ["folder", "array", "events", "video"])
def test_start_past_the_end_says_how_many_frames_the_route_has(tmp_path, capsys, kind):
    corridor = shared_data("corridor")
    if kind == "folder":
        src, n = corridor / "ref", 111
    elif kind == "array":
        src, n = tmp_path / "f.npy", 7
        np.save(src, np.zeros((7, 4, 5), np.uint8))
    elif kind == "events":
        src, n = shared_data("events", "evt3_sample.raw"), 1
    else:
        import cv2

        src, n = tmp_path / "v.avi", 12
        writer = cv2.VideoWriter(str(src), cv2.VideoWriter_fourcc(*"MJPG"), 10, (32, 24))
        for i in range(n):
            writer.write(np.full((24, 32, 3), 20 * i, np.uint8))
        writer.release()
    code, _, err = run_eval(tmp_path, capsys, "--engine", "seqslam", "--reference", str(src),
                            "--query", str(src), "--start", "500")
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert f"reference traverse {src}: no frame selected: the traverse has {n} frame" in lines[0]
    assert f"must be below {n}" in lines[0] and "TensorList" not in lines[0]


def test_ctrl_c_while_plotting_leaves_a_run_marked_incomplete(tmp_path, capsys, monkeypatch):
    corridor = shared_data("corridor")
    args = ["--engine", "seqslam", "--reference", str(corridor / "ref"), "--query",
            str(corridor / "query"), "--ground-truth", str(corridor / "ground_truth.csv")]

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(plots, "plot_matched_pairs", interrupted)
        code, _, err = run_eval(tmp_path, capsys, *args)
    assert code == 130 and "interrupted" in err
    out = tmp_path / "o"
    assert (out / "matches.csv").exists() and (out / "config.json").exists()
    assert (out / "INCOMPLETE").is_file()
    assert "stopped before it finished" in (out / "INCOMPLETE").read_text()
    assert json.loads((out / "metrics.json").read_text())["status"] == "incomplete"
    # the same folder is taken back with --overwrite, and a finished run is marked so
    code, _, err = run_eval(tmp_path, capsys, *args, "--overwrite")
    assert code == 0, err
    assert not (out / "INCOMPLETE").exists()
    assert json.loads((out / "metrics.json").read_text())["status"] == "complete"

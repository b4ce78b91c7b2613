"""What an eval run leaves and says (issue 23): plots for a checkpoint of a longer route,
a start past the end, interrupted runs, matches.csv columns, plot labels."""

import csv
import json
import shutil

import numpy as np
import pytest
import torch
from conftest import shared_data

import torchseq.cli.eval as cli_eval
import torchseq.cli.plots as plots
import torchseq.cli.report_images as report_images
import torchseq.cli.train as cli_train
from torchseq.cli.runs import run_main
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
    idx = np.arange(100)
    pick, title = plots.pick_pairs(idx, 40, 6, "t")
    assert "60 of 100 matches point past the 40 reference frames: not shown" in title
    assert len(pick) and all(idx[pick] < 40)


@pytest.mark.slow
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


@pytest.mark.slow
def test_ctrl_c_while_plotting_leaves_a_run_marked_incomplete(tmp_path, capsys, monkeypatch):
    corridor = shared_data("corridor")
    args = ["--engine", "seqslam", "--reference", str(corridor / "ref"), "--query",
            str(corridor / "query"), "--ground-truth", str(corridor / "ground_truth.csv")]

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(report_images, "draw_matched_pairs", interrupted)
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


def corridor_truth(corridor):
    """query -> admissible references, read from ground_truth.csv by hand."""
    rows = csv.reader(open(corridor / "ground_truth.csv"))
    next(rows)
    return {int(q): {int(r) for r in refs.split()} for q, refs in rows}


@pytest.mark.slow
def test_matches_csv_has_correct_and_top_k_and_the_run_its_labels(tmp_path, capsys):
    corridor = shared_data("corridor")
    out = tmp_path / "o"
    code = run_main(cli_eval.main, "eval.py", [
        "--engine", "seqslam", "--reference", str(corridor / "ref"), "--query",
        str(corridor / "query"), "--ground-truth", str(corridor / "ground_truth.csv"),
        "--no-progress", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    truth = corridor_truth(corridor)
    rows = list(csv.DictReader(open(out / "matches.csv")))
    assert list(rows[0]) == ["engine", "query", "reference", "score", "correct", "candidates"]
    assert len(rows) == 111
    for row in rows:
        q = int(row["query"])
        expected = row["reference"] != "" and int(row["reference"]) in truth[q]
        assert row["correct"] == str(int(expected))
        cands = [int(c) for c in row["candidates"].split()]
        assert len(cands) <= 5 and len(set(cands)) == len(cands)
        if row["reference"] != "":
            assert len(cands) == 5 and cands[0] == int(row["reference"])
    m = json.loads((out / "metrics.json").read_text())
    assert sum(int(r["correct"]) for r in rows) / 111 == pytest.approx(
        m["seqslam"]["recall_at_1"])
    # recall@5 from the candidates column equals metrics.json's
    hit5 = [any(c in truth[int(r["query"])] for c in map(int, r["candidates"].split()))
            for r in rows]
    assert sum(hit5) / 111 == pytest.approx(m["seqslam"]["recall_at_5"])
    # the HParams tab: a sub-run per engine holding the hparams summary
    sub = out / "tensorboard" / "seqslam"
    assert sub.is_dir() and any(b"hparams" in f.read_bytes() for f in sub.iterdir())
    # a smaller K, and no correct column without ground truth
    code = run_main(cli_eval.main, "eval.py", [
        "--engine", "seqslam", "--reference", str(corridor / "ref"), "--query",
        str(corridor / "query"), "--matches-top-k", "2", "--no-progress", "--no-tensorboard",
        "--out", str(tmp_path / "k2")])
    assert code == 0
    rows = list(csv.DictReader(open(tmp_path / "k2" / "matches.csv")))
    assert "correct" not in rows[0] and max(len(r["candidates"].split()) for r in rows) == 2


def test_the_ring_matrix_has_its_axes():
    fig = plots.plot_matrix(np.eye(4), "ring", xlabel="from output unit",
                            ylabel="to output unit")
    assert fig.axes[0].get_xlabel() == "from output unit"
    assert fig.axes[0].get_ylabel() == "to output unit"
    import inspect

    import torchseq.cli.report as report

    source = inspect.getsource(report.log_training)
    assert 'xlabel="from output unit (the current winner)"' in source


def test_matches_csv_rows_equal_a_plain_writer():
    """matches.csv against rows written here one field at a time (scores as %.6g of the
    float32 value, the reference and score empty without a match, candidates past -1 cut)."""
    from torchseq.cli.report import matches_csv
    from torchseq.cli.results import EngineRun

    score = torch.tensor([0.123456789, 1.5e-7, 2.0, 7.25], dtype=torch.float32)
    m = Matches(torch.tensor([3, -1, 0, 2]), score, lower_is_better=True)
    ranked = torch.tensor([[3, 1, 2], [-1, -1, -1], [0, 2, -1], [2, 3, 0]])
    run = EngineRun(m, ranked, None, 0.0, {})
    gt = np.zeros((4, 4), bool)
    gt[3, 0] = gt[0, 2] = True  # query 0 -> 3 admitted; query 2 -> 0 admitted; 3 -> 2 not
    want = ["engine,query,reference,score,correct,candidates",
            "e,0,3,0.123457,1,3 1", "e,1,,,0,", "e,2,0,2,1,0 2", "e,3,2,7.25,0,2 3"]
    assert matches_csv({"e": run}, gt, top_k=2).splitlines() == want
    assert matches_csv({"e": run}, None, top_k=3).splitlines()[1:3] == ["e,0,3,0.123457,3 1 2",
                                                                       "e,1,,,"]

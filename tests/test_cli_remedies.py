"""Error messages that state the problem and the remedy (issue 23, item 12)."""

import json
import warnings

import numpy as np
import pytest
from conftest import shared_data

import torchseq.cli.eval as cli_eval
from torchseq.cli.engines import transposed_size
from torchseq.cli.runs import run_main
from torchseq.ground_truth import GroundTruthError, load_ground_truth


def eval_error(tmp_path, capsys, *args):
    code = run_main(cli_eval.main, "eval.py", [
        "--engine", "seqslam", *args, "--no-progress", "--no-tensorboard",
        "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    return err[0]


def test_transposed_ground_truth_asks_whether_reference_and_query_were_swapped(tmp_path):
    np.save(tmp_path / "gt.npy", np.eye(30, 100, dtype=np.uint8))  # (reference 30, query 100)
    with pytest.raises(GroundTruthError, match="were --reference and --query swapped"):
        load_ground_truth(tmp_path / "gt.npy", 100, 30)
    with pytest.raises(GroundTruthError) as err:  # a square mismatch is not called swapped
        load_ground_truth(tmp_path / "gt.npy", 40, 100)
    assert "swapped" not in str(err.value)


def test_one_based_ground_truth_is_flagged(tmp_path):
    path = tmp_path / "gt.csv"
    path.write_text("query,references\n" + "".join(f"{i},{i}\n" for i in range(1, 6)))
    with pytest.raises(GroundTruthError, match="never uses index 0: if it counts from 1, "
                                               "subtract 1 from every index"):
        load_ground_truth(path, 5, 5)
    # every query must be covered, so a CSV that never uses 0 always fails: with the hint
    path.write_text("query,references\n" + "".join(f"{i},{i}\n" for i in range(1, 5)))
    with pytest.raises(GroundTruthError, match="covers 4 queries but the query has 5; "
                                               "indices are 0-based"):
        load_ground_truth(path, 5, 5)
    # a file that uses 0 says nothing
    path.write_text("query,references\n" + "".join(f"{i},{i}\n" for i in range(5)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_ground_truth(path, 5, 5)


def test_text_file_named_mp4_is_not_a_video(tmp_path, capsys):
    corridor = shared_data("corridor")
    fake = tmp_path / "fake.mp4"
    fake.write_text("hello\n")
    err = eval_error(tmp_path, capsys, "--reference", str(corridor / "ref"), "--query",
                     str(fake))
    assert err.endswith(f"query traverse {fake}: a text file, not a video (it starts 'hello')")
    fake.write_bytes(b"")
    assert "an empty file, not a video" in eval_error(
        tmp_path, capsys, "--reference", str(corridor / "ref"), "--query", str(fake))


def test_ground_truth_folder_sweep_typo_and_metrics_json_as_config(tmp_path, capsys):
    corridor = shared_data("corridor")
    both = ["--reference", str(corridor / "ref"), "--query", str(corridor / "query")]
    err = eval_error(tmp_path, capsys, *both, "--ground-truth", str(corridor))
    assert f"{corridor} is a folder; --ground-truth takes a file" in err
    err = eval_error(tmp_path, capsys, *both, "--sweep", "dss=5,10")
    assert err.endswith("'dss' is not a setting of this script; did you mean ds?")
    metrics = tmp_path / "run" / "metrics.json"
    metrics.parent.mkdir()
    metrics.write_text(json.dumps({"inputs": {}, "warnings": [], "seqslam": {}}))
    err = eval_error(tmp_path, capsys, "--config", str(metrics))
    assert "this is a run's metrics.json, not a config; give the config.json beside it" in err
    assert str(metrics.with_name("config.json")) in err


def test_evt3_recording_shorter_than_one_window_suggests_the_flags(tmp_path, capsys):
    raw = shared_data("events", "evt3_sample.raw")
    err = eval_error(tmp_path, capsys, "--reference", str(raw), "--query", str(raw))
    assert "shorter than one 10 ms window" in err
    assert "--window-ms" in err and "--event-count" in err


@pytest.mark.slow
def test_transposed_image_size_is_warned_once(tmp_path, capsys):
    corridor = shared_data("corridor")
    args = ["--engine", "seqslam", "--reference", str(corridor / "ref"), "--query",
            str(corridor / "query"), "--no-progress", "--no-tensorboard"]
    code = run_main(cli_eval.main, "eval.py", [*args, "--image-size", "64x32",
                                               "--out", str(tmp_path / "t")])
    err = capsys.readouterr().err
    assert code == 0
    want = ("--image-size 64x32 is height x width (64 high, 32 wide), the transposed shape of "
            "these 120x160 frames (landscape); give --image-size 32x64")
    assert err.count(want) == 1, err
    assert any(want in w for w in json.loads(
        (tmp_path / "t" / "metrics.json").read_text())["warnings"])
    code = run_main(cli_eval.main, "eval.py", [*args, "--out", str(tmp_path / "d")])
    assert code == 0 and "--image-size" not in capsys.readouterr().err
    assert transposed_size((32, 32), (120, 160)) is None  # square: no orientation
    assert transposed_size((24, 32), (120, 160)) is None
    assert transposed_size((64, 32), (160, 120)) is None  # portrait frames

"""A number a user reads is right, or the run says why not (issue 36)."""

import json
import warnings

import numpy as np
import pytest
import torch
from conftest import shared_data

import torchseq.cli.eval as cli_eval
from torchseq.cli.runs import run_main
from torchseq.ground_truth import (
    GroundTruthError,
    alignment_ground_truth,
    alignment_ranges,
    load_ground_truth,
)
from torchseq.matches import Matches
from torchseq.metrics import match_line


def read_csv(tmp_path, text: str, n_reference=3, n_query=3, encoding="utf-8"):
    path = tmp_path / "gt.csv"
    path.write_bytes(text.encode(encoding))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gt = load_ground_truth(path, n_reference, n_query)
    return gt, [str(w.message) for w in caught]


def test_csv_with_a_byte_order_mark_reads_as_without(tmp_path):
    plain, _ = read_csv(tmp_path, "query,references\n0,0\n1,1 2\n2,2\n")
    bom, said = read_csv(tmp_path, "query,references\n0,0\n1,1 2\n2,2\n", encoding="utf-8-sig")
    assert (bom == plain).all() and plain[:, 1].tolist() == [False, True, True] and not said


@pytest.mark.parametrize("row", ["1,1,2", "1,1 2,7"])
def test_csv_row_with_extra_fields_is_refused_with_the_form_expected(tmp_path, row):
    with pytest.raises(GroundTruthError, match=r"gt.csv:3: 3 fields, expected 2 \(query, then "
                                               r"its references separated by spaces: '1,"):
        read_csv(tmp_path, f"query,references\n0,0\n{row}\n2,2\n")


def test_csv_header_with_extra_columns_is_refused(tmp_path):
    with pytest.raises(GroundTruthError, match="gt.csv:1: expected the header "
                                               "'query,references'.*'query,references,d'"):
        read_csv(tmp_path, "query,references,d\n0,0,1\n1,1,1\n2,2,1\n")


def test_nordland_headerless_one_based_table_is_read_and_said(tmp_path):
    # the layout of TimQuelch/seqslam's datasets/nordland_trimmed_resized/sample_ground_truth.csv
    gt, said = read_csv(tmp_path, "".join(f"{i},{i},15\n" for i in range(1, 6)), 5, 5)
    assert (gt == np.eye(5, dtype=bool)).all()
    assert said == [f"{tmp_path / 'gt.csv'}: read as headerless 1-based query,reference pairs "
                    f"(third column not used)"]
    gt, said = read_csv(tmp_path, "0,0\n1,1\n1,2\n2,2\n")  # 0-based, a query on two rows
    assert gt[:, 1].tolist() == [False, True, True] and "0-based" in said[0]


@pytest.mark.parametrize("text", ["0,0\n1,1\n", "2,2\n3,3\n4,4\n", "0,0\n1,1\n2,x\n",
                                  "0,0,1,2\n1,1,1,2\n2,2,1,2\n"])
def test_ambiguous_headerless_table_is_refused(tmp_path, text):
    with pytest.raises(GroundTruthError, match="gt.csv"):
        read_csv(tmp_path, text)


def test_alignment_with_a_scale_admits_the_query_at_its_own_pace():
    dense = alignment_ground_truth(20, 10, 1, offset=3, scale=1.0)
    ranges = alignment_ranges(20, 10, 1, offset=3, scale=1.0)
    assert (ranges.dense() == dense).all()
    assert [np.nonzero(dense[:, j])[0].tolist() for j in (0, 9)] == [[2, 3, 4], [11, 12, 13]]
    stretched = alignment_ground_truth(20, 10, 0)  # default: query j at reference j * 19/9
    assert np.nonzero(stretched[:, 9])[0].tolist() == [19]
    with pytest.raises(GroundTruthError, match="scale must be a finite number > 0"):
        alignment_ranges(20, 10, 1, scale=0.0)


def line_matches(n=300, scale=1.0, offset=0.0, outliers=0.2, seed=0) -> Matches:
    rng = np.random.default_rng(seed)
    ref = np.round(offset + scale * np.arange(n)).astype(np.int64)
    bad = rng.random(n) < outliers
    ref[bad] = rng.integers(0, int(offset + scale * n), bad.sum())
    return Matches(torch.from_numpy(ref), torch.rand(n, dtype=torch.float64), True)


def test_match_line_finds_the_line_the_matches_follow():
    m = line_matches(scale=1.0, offset=40.0)  # a query covering a part of a longer reference
    stretched = alignment_ranges(700, 300, 2)  # query j at reference 2.33 j: misaligned
    line = match_line(m, stretched)
    assert line.disagrees() and abs(line.scale - 1) < 0.01 and abs(line.offset - 40) < 1
    assert line.share > 0.75 and line.correct < 0.05 and line.band == 1.5
    right = match_line(m, alignment_ranges(700, 300, 2, offset=40, scale=1.0))
    assert not right.disagrees() and right.correct == pytest.approx(right.share)
    noise = match_line(line_matches(outliers=1.0), stretched)  # no route matched: no line
    assert not noise.disagrees() and noise.share < 0.1


def eval_run(tmp_path, capsys, *args):
    code = run_main(cli_eval.main, "torchseq eval", [
        "--engine", "seqslam", *args, "--no-progress", "--no-tensorboard",
        "--out", str(tmp_path / "o"), "--overwrite"])
    return code, capsys.readouterr()


def test_tolerance_on_unequal_lengths_is_explained(tmp_path, capsys):
    corridor = shared_data("corridor")
    part = tmp_path / "query"  # the first half of the corridor's query traverse
    part.mkdir()
    for i in range(55):
        (part / f"{i:07d}.jpg").symlink_to(corridor / "query" / f"{i:07d}.jpg")
    base = ["--reference", str(corridor / "ref"), "--query", str(part), "--tolerance", "2"]
    code, out = eval_run(tmp_path, capsys, *base)
    said = [line for line in out.err.splitlines() if "warning" in line]
    assert code == 0 and len(said) == 2, out.err
    assert "query has 55 frames, reference 111: --tolerance stretches the query over the " \
           "whole reference (2.037 reference frames per query frame)" in said[0]
    assert "seqslam: 0.0% of matches are correct, yet" in said[1]
    assert "the ground truth looks misaligned (try --gt-scale 1." in said[1]
    assert all(len(line) < 240 for line in said)
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert len(metrics["warnings"]) == 2 and metrics["seqslam"]["recall_at_1"] == 0.0
    code, out = eval_run(tmp_path, capsys, *base, "--gt-scale", "1")
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert code == 0 and "warning" not in out.err and metrics["seqslam"]["recall_at_1"] > 0.4
    assert metrics["inputs"]["ground_truth"] == "index alignment, tolerance 2.0, scale 1"


def test_alignment_flags_without_index_alignment_are_refused(tmp_path, capsys):
    code, out = eval_run(tmp_path, capsys, "--gt-scale", "1")
    assert code == 2 and "--gt-scale shapes index alignment (--tolerance alone)" in out.err


@pytest.fixture(scope="module")
def event_runs(tmp_path_factory):
    """Simulated event runs of nordland-b's first 80 places: reference, and half the speed."""
    from torchseq.events.plain import write_npz
    from torchseq.events.runs import simulate_run
    from torchseq.sources import FrameSelection, load_traverse

    frames = load_traverse(shared_data("nordland-b", "summer"), progress=False,
                           select=FrameSelection(stop=80)).numpy()
    folder = tmp_path_factory.mktemp("events")
    positions = np.arange(len(frames), dtype=np.float64)
    for name, speed, seed in (("ref", 1.0, 1), ("query", 0.5, 2)):
        run = simulate_run(frames, positions, speed, 100.0, seed=seed, contrast_threshold=0.2,
                           threshold_noise=0.03, noise_rate_hz=1.0)
        write_npz(folder / f"{name}.npz", run.stream)
    return folder


def test_events_preset_takes_the_speed_ratio_from_the_window_counts(tmp_path, capsys,
                                                                    event_runs):
    base = ["--reference", str(event_runs / "ref.npz"), "--query",
            str(event_runs / "query.npz"), "--tolerance", "2", "--preset", "events",
            "--ds", "20"]
    code, out = eval_run(tmp_path, capsys, *base)
    assert code == 0, out.err
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    config = json.loads((tmp_path / "o" / "config.json").read_text())
    ratio = metrics["inputs"]["speed_ratio"]
    assert ratio["value"] == pytest.approx(0.5, abs=0.01) and ratio["from"].startswith(
        "window counts 79 / ")
    assert config["seqslam"]["speed_ratio"] == ratio["value"] and config["seqslam"]["ds"] == 20
    assert f"speed ratio {ratio['value']:.3f} reference per query window, from the window " \
           f"counts" in out.err
    estimated = metrics["seqslam"]["recall_at_1"]
    code, out = eval_run(tmp_path, capsys, *base, "--speed-ratio", "1")  # the old default
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert code == 0 and "speed ratio" not in out.err and "speed_ratio" not in metrics["inputs"]
    assert estimated >= 0.9 and estimated - metrics["seqslam"]["recall_at_1"] >= 0.3


def test_candidate_mode_that_loses_recall_is_warned_about(tmp_path, capsys):
    nordland = shared_data("nordland-b")
    base = ["--reference", str(nordland / "summer"), "--query", str(nordland / "winter"),
            "--max-frames", "400", "--threads", "1"]

    def run(*extra):
        code, out = eval_run(tmp_path, capsys, *base, *extra)
        assert code == 0, out.err
        seqslam = json.loads((tmp_path / "o" / "metrics.json").read_text())["seqslam"]
        return seqslam, [line for line in out.err.splitlines() if "warning" in line]

    small, said = run("--tolerance", "2", "--candidates", "3")
    check = small["candidate_agreement"]
    assert check["candidates"] == 3 and check["queries"] == [72, 327]
    assert check["candidates_recall_at_1"] < check["exact_recall_at_1"] - 0.2
    assert len(said) == 1 and said[0].endswith(
        f"--candidates 3: recall@1 {check['candidates_recall_at_1']:.3f} against the exact "
        f"mode's {check['exact_recall_at_1']:.3f} on 256 sampled queries; raise K or give "
        f"--candidates 0 (the exact mode)")
    exact, said = run("--tolerance", "2", "--candidates", "0")
    assert "candidate_agreement" not in exact and not said
    assert exact["recall_at_1"] > small["recall_at_1"]
    large, said = run("--tolerance", "2", "--candidates", "200")  # half the route: holds
    assert not said and large["candidate_agreement"]["candidates_recall_at_1"] >= \
        large["candidate_agreement"]["exact_recall_at_1"] - 0.02
    blind, said = run("--candidates", "3")  # no ground truth: the exact mode's matches found
    assert blind["candidate_agreement"]["exact_match_found"] < 0.75
    assert len(said) == 1 and "--candidates 3: finds the exact mode's match for" in said[0]


def test_no_progress_bars_in_a_redirected_log(tmp_path, capsys):
    import torchseq
    import torchseq.cli.map as cli_map
    import torchseq.cli.train as cli_train

    corridor = shared_data("corridor")
    torchseq.load_traverse(corridor / "ref")  # the library's default: a bar on a terminal only
    assert "reading" not in capsys.readouterr().err
    assert run_main(cli_map.main, "torchseq map", [
        "build", "--reference", str(corridor / "ref"), "--out", str(tmp_path / "map")]) == 0
    assert run_main(cli_train.main, "torchseq train", [
        "--reference", str(corridor / "ref"), "--out", str(tmp_path / "train"),
        "--no-tensorboard"]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err and "it/s" not in err and "frame/s" not in err, err[:300]


def test_summary_line_names_the_unmatched_ends():
    from torchseq.cli.report import summary_line

    m = {"recall_at_1": 0.952, "auc": 0.951, "n_queries": 249, "seconds": 0.1,
         "versus_single_frame": {"single_frame_recall_at_1": 1.0, "made_worse": 0.048,
                                 "made_better": 0.0, "n_without_sequence_match": 10,
                                 "n_queries": 249}}
    assert "made worse 4.8% / better 0.0% of queries (4.0% unmatched at the route's ends; " \
           "--edges matches them), AUC" in summary_line("seqslam", m)
    m["versus_single_frame"]["n_without_sequence_match"] = 0
    assert "unmatched" not in summary_line("seqslam", m)


def test_event_frame_defaults_agree_between_api_and_cli():
    import inspect

    from torchseq.cli.event_options import EventFlags
    from torchseq.events.ensemble import accumulate_ensemble
    from torchseq.events.frames import accumulate
    from torchseq.sources import EventFrameOptions

    modes = {inspect.signature(accumulate).parameters["mode"].default,
             inspect.signature(accumulate_ensemble).parameters["mode"].default,
             EventFrameOptions().mode, EventFlags().event_mode}
    assert modes == {"count"}

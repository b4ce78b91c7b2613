"""The eval command hands its report typed results (torchseq.cli.results), and metrics.json
keeps the keys, in the order, that it had when the report took dicts."""

import json

import torchseq.cli.eval as cli_eval
from torchseq.cli.results import EvalOutcome, NeuralRun, SeqSLAMRun
from torchseq.cli.runs import run_main

METRICS = ["recall_at_1", "auc", "recall_at_100_precision", "coverage", "correct_coverage",
           "n_queries", "n_matched", "n_positive_queries", "recall_at_5", "recall_at_10",
           "recall", "operating_point"]
# metrics.json of `eval.py --demo-frames 60` on main before the move (the dicts' keys), with
# SeqSLAM's "kernels" (the kernel that ran per stage) added after "parameters"
KEYS = {"seqslam": [*METRICS, "seconds", "parameters", "kernels", "versus_single_frame"],
        "neural": [*METRICS, "seconds", "fit_seconds", "model_bytes", "seqslam_template_bytes",
                   "frames_per_unit", "stage", "sequence_frames",
                   "self_check", "preset", "parameters", "versus_single_frame"]}
TOP = ["inputs", "warnings", "versions", "single_frame", "seqslam", "neural", "status"]


def test_metrics_json_keeps_its_keys_and_the_report_gets_an_outcome(tmp_path, monkeypatch):
    seen = []
    report = cli_eval.report

    def spy(outcome, notes):
        seen.append(outcome)
        return report(outcome, notes)

    monkeypatch.setattr(cli_eval, "report", spy)
    out = tmp_path / "o"
    code = run_main(cli_eval.main, "eval.py", [
        "--demo-frames", "40", "--neural-hidden", "256", "--neural-n-output", "40",
        "--no-progress", "--no-tensorboard", "--out", str(out)])
    assert code == 0
    written = json.loads((out / "metrics.json").read_text())
    assert list(written) == TOP
    for engine, keys in KEYS.items():
        assert list(written[engine]) == keys, engine
    (outcome,) = seen
    assert isinstance(outcome, EvalOutcome) and outcome.out == out
    assert isinstance(outcome.engines["seqslam"], SeqSLAMRun)
    assert isinstance(outcome.engines["neural"], NeuralRun)
    assert outcome.metrics == written  # the report keeps what it wrote
    # the difference kernel l1_choice's size rule picks for 40 x 40 demo frames
    assert written["seqslam"]["kernels"]["difference"] == "thermometer"
    assert written["seqslam"]["kernels"]["matrices"] == "full"
    assert outcome.engines["neural"].reported()["model_bytes"] == written["neural"]["model_bytes"]


# train.json of `torchseq train --demo-frames 40 --neural-hidden 256 --neural-n-output 40` on
# main (1427cd5)
# before the train command handed its report a TrainRun: keys in order, and every value but the
# timing and the git commit
TRAIN_JSON = {
    "reference": {"source": "demo", "demo_frames": 40, "demo_seed": 0, "n_frames": 40,
                  "frame_size": [96, 128]},
    "neural_preset": "default", "fit_seconds": None, "versions": None, "model_bytes": 1662304,
    "seqslam_template_bytes": 81920, "n_units": 40, "self_check": 0.9, "warnings": []}


def test_train_json_is_unchanged_and_written_from_a_train_run(tmp_path, monkeypatch):
    import copy

    import torchseq.cli.train as cli_train
    from torchseq.cli.results import TrainRun
    from torchseq.versions import versions

    seen = []
    write = cli_train.write_train_json

    def spy(run, notes, out):
        seen.append(copy.deepcopy(run))
        return write(run, notes, out)

    monkeypatch.setattr(cli_train, "write_train_json", spy)
    out = tmp_path / "t"
    code = run_main(cli_train.main, "train.py", [
        "--demo-frames", "40", "--neural-hidden", "256", "--neural-n-output", "40", "--no-progress",
        "--no-tensorboard", "--out", str(out)])
    assert code == 0
    text = (out / "train.json").read_text()
    written = json.loads(text)
    assert list(written) == list(TRAIN_JSON)
    assert written["fit_seconds"] > 0 and written["versions"] == versions()
    assert {**written, "fit_seconds": None, "versions": None} == TRAIN_JSON
    first, last = seen  # after the fit, and again at the end (the export's verdict with --export)
    assert isinstance(last, TrainRun) and last == first and last.export_passed is None
    # every value comes from the object, in the file's layout
    assert written == json.loads(json.dumps({**last.reported(), "warnings": []}))
    assert written["fit_seconds"] == last.fit_seconds and written["n_units"] == last.n_units
    assert text == json.dumps(written, indent=2) + "\n"  # the layout main wrote


def test_train_run_reports_the_export_verdict_after_its_self_check():
    from torchseq.cli.results import TrainRun

    run = TrainRun(reference={"source": "demo"}, neural_preset="default", fit_seconds=1.5,
                   versions={"torch": "x"}, model_bytes=10, seqslam_template_bytes=20,
                   n_units=3, self_check=None)
    assert list(run.reported()) == [k for k in TRAIN_JSON if k != "warnings"]
    run.export_passed = False
    assert list(run.reported())[-2:] == ["self_check", "export_passed"]
    assert run.reported()["export_passed"] is False

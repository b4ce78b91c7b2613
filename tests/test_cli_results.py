"""The eval command hands its report typed results (torchseq.cli.results), and metrics.json
keeps the keys, in the order, that it had when the report took dicts."""

import json

import torchseq.cli.eval as cli_eval
from torchseq.cli.results import EvalOutcome, NeuralRun, SeqSLAMRun
from torchseq.cli.runs import run_main

METRICS = ["recall_at_1", "auc", "recall_at_100_precision", "coverage", "correct_coverage",
           "n_queries", "n_matched", "n_positive_queries", "recall_at_5", "recall_at_10",
           "recall", "operating_point"]
# metrics.json of `eval.py --demo-frames 60` on main before the move (the dicts' keys)
KEYS = {"seqslam": [*METRICS, "seconds", "parameters", "versus_single_frame"],
        "neural": [*METRICS, "seconds", "fit_seconds", "model_bytes", "seqslam_template_bytes",
                   "frames_per_unit",
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
    assert outcome.engines["neural"].reported()["model_bytes"] == written["neural"]["model_bytes"]

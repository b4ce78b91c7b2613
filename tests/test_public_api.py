"""The public API: fails when a public name disappears (add names here when you add them)."""

import importlib

import pytest

PUBLIC = {
    "torchseq": [
        "DemoRoute", "EventFormatError", "EventFrameOptions", "EventStream", "Matches",
        "NeuralConfig", "NeuralSeqSLAM", "SeqSLAM", "SeqSLAMConfig", "StreamingSeqSLAM",
        "TraverseError", "accumulate", "alignment_ground_truth", "frames_to_events",
        "load_event_frames", "load_ground_truth", "load_traverse", "make_demo", "metrics",
        "patch_normalise", "preprocess", "read_events", "resize", "to_grey", "write_aedat2",
        "write_npz",
    ],
    "torchseq.metrics": [
        "PRCurve", "auc", "correct", "coverage", "evaluate", "precision_recall_curve",
        "recall_at_100_precision", "recall_at_k",
    ],
    "torchseq.seqslam": [
        "SeqSLAM", "SeqSLAMConfig", "SeqSLAMResult", "StreamingMatch", "StreamingSeqSLAM",
        "difference_matrix", "enhance_contrast", "search", "trajectory_offsets", "velocities",
        "CandidateIndex", "CandidateSeqSLAM", "StreamingState",
    ],
    "torchseq.layers": [
        "KWinnersTakeAll", "MaskedLinear", "OutputRing", "RingParams", "RingState",
        "cohort_normalise", "kwta", "learn_shift_matrix", "make_mask", "masked_linear",
        "ring_scan", "ring_step",
    ],
    "torchseq.neural": [
        "NeuralConfig", "NeuralError", "NeuralFitLog", "NeuralInference", "NeuralResult",
        "NeuralSeqSLAM", "NeuralStep", "seqslam_bytes",
    ],
    "torchseq.events": [
        "EVENT_DTYPE", "EventFormatError", "EventRun", "EventStream", "accumulate",
        "as_event_array", "detect_format", "frames_to_events", "hot_pixel_mask", "iter_aedat2",
        "iter_aedat4", "iter_events", "iter_raw", "load_event_frames", "make_events",
        "read_csv", "read_events", "read_npz", "refractory_mask", "simulate_run",
        "write_aedat2", "write_npz",
    ],
    "torchseq.neural.fixed_point": [
        "factor_power_of_two", "factor_rows", "integer_weights", "quantise_input", "round_rows",
    ],
    "torchseq.ground_truth": ["GroundTruthError", "alignment_ground_truth", "load_ground_truth"],
    "torchseq.sources": ["EventFrameOptions", "TraverseError", "load_traverse"],
    "torchseq.plots": [
        "figure_to_array", "plot_activity_raster", "plot_difference_matrix", "plot_matched_pairs",
        "plot_matrix", "plot_pr_curves", "save_figure",
    ],
}


@pytest.mark.parametrize("module", sorted(PUBLIC))
def test_public_names_exist(module):
    mod = importlib.import_module(module)
    missing = [name for name in PUBLIC[module] if not hasattr(mod, name)]
    assert not missing, f"{module} lost public names: {missing}"
    if hasattr(mod, "__all__"):
        assert set(PUBLIC[module]) <= set(mod.__all__), \
            f"{module}.__all__ lacks {set(PUBLIC[module]) - set(mod.__all__)}"

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
        "PlaceDataset", "load_descriptors", "open_dataset",
    ],
    "torchseq.metrics": [
        "PRCurve", "auc", "correct", "coverage", "evaluate", "precision_recall_curve",
        "recall_at_100_precision", "recall_at_k",
        "RECALL_KS", "RecallAtK", "recall_at_ks", "recall_table", "sequence_vs_single",
        "tie_ranks",
    ],
    "torchseq.descriptors": [
        "DescriptorError", "as_descriptors", "describe", "descriptor_kind", "load_descriptors",
        "load_hook", "neural_config", "neural_input", "save_descriptors",
    ],
    "torchseq.datasets": [
        "DATASETS", "DatasetError", "EventTraverse", "FrameFolder", "PlaceDataset",
        "brisbane_event", "gardens_point", "nordland", "open_dataset", "read_nmea",
        "vpr_bench", "window_times", "gps_positions",
    ],
    "torchseq.seqslam": [
        "SeqSLAM", "SeqSLAMConfig", "SeqSLAMResult", "StreamingMatch", "StreamingSeqSLAM",
        "difference_matrix", "enhance_contrast", "search", "trajectory_offsets", "velocities",
        "CandidateIndex", "CandidateSeqSLAM", "StreamingState",
        "SingleFrameResult", "single_frame",
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
        # HDF5 / Parquet readers and writers, window anchors, positions along a route
        "iter_hdf5", "read_hdf5_positions", "write_hdf5", "iter_parquet", "write_parquet",
        "window_origin", "window_times", "positions_at", "geodetic_to_ecef",
        "ground_truth_within",
    ],
    "torchseq.events.ensemble": ["accumulate_ensemble", "ensemble_base", "match_ensemble"],
    "torchseq.events.traverse": ["TRAVERSE_MODES", "accumulate_pool", "crop_events",
                                 "load_event_frames"],
    "torchseq.events.frames": ["MODES", "accumulate", "sensor_wh", "window_origin"],
    "torchseq.area": ["Partial", "area_mean", "finish", "reduce_rows"],
    "torchseq.events.times": ["FLOAT_SECONDS_BELOW", "float_times_to_us", "with_us_times",
                              "float_time_unit", "FloatTimeRule", "UNITS_PER_US"],
    "torchseq.seqslam.config": ["PRESETS", "SeqSLAMConfig"],
    "torchseq.maps": ["FORMAT", "VERSION", "MapError", "ReferenceMap", "build_map", "load_map"],
    "torchseq.seqslam.sharded": ["ShardWorker", "ShardedSeqSLAM", "edge_rows", "rank_merged",
                                 "shard_ranges"],
    # the training grids
    "torchseq.quantise": [
        "factor_power_of_two", "factor_rows", "integer_weights", "round_rows",
    ],
    "torchseq.preprocess": ["quantise_input"],
    "torchseq.ground_truth": ["GroundTruthError", "alignment_ground_truth", "load_ground_truth"],
    "torchseq.sources": [
        "EventFrameOptions", "FrameSelection", "TraverseError", "frames_from_array",
        "iter_image_folder", "iter_traverse", "iter_video", "load_image_folder",
        "load_traverse", "load_traverse_sizes", "natural_key", "thumbnail_size",
    ],
    # the command lines: one console script and the eval/train front ends it dispatches to
    "torchseq.cli": ["COMMANDS", "main"],
    "torchseq.cli.eval": ["EvalConfig", "Settings", "build_parser", "cli", "main",
                          "parse_args", "seqslam_preset"],
    "torchseq.cli.train": ["TrainConfig", "build_parser", "cli", "main", "parse_args"],
    "torchseq.cli.export": ["build_parser", "main", "summary_lines"],
    "torchseq.cli.results": ["EngineRun", "EvalOutcome", "NeuralRun", "SeqSLAMRun"],
    # the spiking model and its NIR export (docs/guide/nir.md)
    "torchseq.neural.spiking": ["DT", "SpikingConfig", "SpikingError", "SpikingSeqSLAM",
                                "SpikingState", "SpikingStep", "ladder", "lif_step",
                                "input_events", "quantise_rows"],
    "torchseq.export.nir_export": ["FORMAT", "NIRExportError", "read_nir", "require_nir",
                                   "to_nir", "write_nir", "drop_zero_resets",
                                   "quantisation_metadata", "event_input_nodes"],
    "torchseq.export.nir_consumers": ["CONSUMERS", "available", "compare", "run_consumer"],
    "torchseq.export.hardware_budget": ["LIMITS", "budget", "check", "CHIPS", "ChipLimits",
                                        "memory_bytes", "layer_kernel_entries", "speck_layers",
                                        "pow2_rows"],
    "torchseq.export.nir_validate": ["calibration_frames", "export_nir"],
    "torchseq.neural.spiking_events": ["EventSpikingSeqSLAM", "pool_matrix", "check_counts",
                                       "block_centring", "block_scales", "count_frames"],
    "torchseq.cli.plots": [
        "figure_to_array", "plot_activity_raster", "plot_matrix", "save_figure",
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


def test_seqslam_presets_build():
    # every named preset is a valid config; the events preset reads 16x16 event frames
    from torchseq.seqslam import SeqSLAMConfig
    from torchseq.seqslam.config import PRESETS

    assert set(PRESETS) >= {"default", "openseqslam", "events"}
    for name in PRESETS:
        assert isinstance(SeqSLAMConfig.preset(name), SeqSLAMConfig)
    assert tuple(SeqSLAMConfig.preset("events").image_size) == (16, 16)
    with pytest.raises(ValueError, match="preset"):
        SeqSLAMConfig.preset("bogus")


def test_event_modes_of_the_library_and_the_command_line_agree():
    # every --event-mode the CLI offers is a mode load_event_frames accepts, and vice versa
    from torchseq.cli.event_options import EVENT_MODES
    from torchseq.events.traverse import TRAVERSE_MODES

    assert {m.replace("-", "_") for m in EVENT_MODES} == set(TRAVERSE_MODES) == {
        "count", "signed", "two_channel", "binary"}


def test_the_export_package_holds_the_quantiser_names():
    # the same objects as torchseq.quantise
    import torchseq.export as export
    import torchseq.quantise as one

    for name in ("Quantised", "dequantise", "fixed_point", "quantise"):
        assert getattr(export, name) is getattr(one, name), name

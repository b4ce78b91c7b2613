"""What an eval run depends on: :class:`EvalConfig`, the engines' configs, their flag texts.

SeqSLAM settings are the plain flags (``--ds``, ``--patch-size``, ...); Neural SeqSLAM
settings carry a ``--neural-`` prefix (``--neural-patch-size``, ...). :class:`Settings`
bundles the three configs of one run; :func:`config_dict` is its ``config.json``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from torchseq.cli.event_options import EventFlags
from torchseq.cli.presets import preset_help
from torchseq.cli.runs import to_jsonable
from torchseq.neural import NeuralConfig
from torchseq.seqslam import SeqSLAMConfig
from torchseq.seqslam.config import LIMITS as SEQSLAM_FIELD_LIMITS

ENGINES = ("seqslam", "neural", "both")


MAX_DEMO_QUERY = 50_000  # demo query frames (96x128 float32 each)


SEQSLAM_FIELDS = {f.name for f in dataclasses.fields(SeqSLAMConfig)}


@dataclass
class EvalConfig(EventFlags):
    """What an evaluation run depends on besides the engines' own configs."""

    reference: str | None = None
    query: str | None = None
    ground_truth: str | None = None
    tolerance: float | None = None
    gt_offset: float = 0.0
    gt_scale: float | None = None
    engine: str = "both"
    checkpoint: str | None = None
    preset: str | None = None
    neural_preset: str | None = None
    out: str | None = None
    overwrite: bool = False
    target_precision: float = 0.99
    start: int = 0
    stop: int | None = None
    frame_step: int = 1
    max_frames: int | None = None
    demo_frames: int = 200
    demo_speed: float = 0.8
    seed: int = 0
    device: str = "cpu"
    tensorboard: bool = True
    progress: bool = True
    descriptor: str | None = None
    descriptor_batch: int = 64
    dataset: str | None = None
    root: str | None = None
    reference_split: str | None = None
    query_split: str | None = None
    map: str | None = None
    shards: int | None = None
    ray_address: str | None = None
    matches_top_k: int = 5


HELP = {
    "reference": "reference traverse: image folder, video, frame array, event file or (T, D) "
                 "descriptors (docs/reference/data-formats.md); default: the built-in demo",
    "query": "query traverse, same kinds as --reference (required with --reference)",
    "ground_truth": "ground truth: CSV 'query,references', (reference x query) 0/1 .npy matrix, "
                    "or VPR-Bench per-query .npy of admissible indices; with --tolerance it is "
                    "widened by that many reference frames",
    "tolerance": "ground truth by index alignment: admissible distance in reference frames "
                 "(with --ground-truth: widen that file's ground truth)",
    "gt_offset": "index alignment: reference frame where the query starts (traverses that "
                 "begin at different places)",
    "gt_scale": "index alignment: reference frames per query frame (1: the query covers part "
                "of the reference at its pace; default: stretched over the whole reference)",
    "engine": f"engine to run: one of {', '.join(ENGINES)}",
    "checkpoint": "neural model checkpoint (model.pt from train.py); without it the neural "
                  "engine is trained on the reference first",
    "preset": "SeqSLAM preset: openseqslam (OpenSeqSLAM 2013 exactly) or events "
              "(SeqSLAMConfig.events: 16x16, ds 100 / R, edges; docs/results/event-preset.md); "
              "SeqSLAM flags you type override it",
    "neural_preset": preset_help("the --neural-* flags"),
    "out": "output folder of this run (default: a new runs/eval-<UTC time>)",
    "overwrite": "replace a previous run's --out folder instead of refusing",
    "target_precision": "metrics.json operating point: the confidence threshold that reaches "
                        "this precision with the most recall",
    "start": "first frame of each traverse to use (0-based; OpenSeqSLAM's image indices)",
    "stop": "frame index of each traverse to stop before",
    "frame_step": "use every N-th frame from --start (OpenSeqSLAM's image skip)",
    "max_frames": "use at most this many frames of each traverse",
    "demo_frames": "demo: reference frames",
    "demo_speed": "demo: query speed relative to the reference",
    "seed": "random seed (demo data; the neural model unless --neural-seed)",
    "device": "cpu, cuda or auto",
    "tensorboard": "write TensorBoard logs",
    "progress": "show progress bars",
    "descriptor": "descriptor hook 'module:callable': a function or nn.Module mapping (B, H, W) "
                  "float32 grey frames (0..255) to (B, D) descriptors, run on --device while "
                  "the frames stream in; the engines then match descriptors (SeqSLAM with "
                  "--metric)",
    "descriptor_batch": "frames per call of the --descriptor hook",
    "dataset": "a dataset's local copy under --root (nothing is downloaded): nordland, "
               "gardens-point, vpr-bench or brisbane-event; gives reference, query and "
               "ground truth (--tolerance: frames, or metres for brisbane-event)",
    "root": "the --dataset folder",
    "reference_split": "--dataset split of the reference (nordland: a season folder; "
                       "default: the dataset's own, e.g. summer)",
    "query_split": "--dataset split of the query (default: the dataset's own, e.g. winter)",
    "map": "reference map folder (torchseq map build) to match against instead of "
           "--reference: its descriptors and index, no reference images read",
    "shards": "spread --map over this many Ray actors, each holding its part (candidate "
              "mode: needs --candidates K)",
    "ray_address": "Ray cluster to run --shards on (default: a local cluster started for "
                   "this run and stopped after it)",
    "matches_top_k": "matches.csv: the best K reference candidates of each query (the "
                     "'candidates' column, best first; at most the K the engine ranks)",
    # SeqSLAMConfig fields whose docstring reads poorly as a flag
    "ds": "SeqSLAM sequence length in frames (rounded up to even)",
    "image_size": "SeqSLAM image size HxW after resizing",
}


LIMITS = {
    "tolerance": (0.0, 1e9), "gt_offset": (-1e9, 1e9), "gt_scale": (1e-6, 1e6),
    "target_precision": (0.0, 1.0),
    "demo_frames": (2, 20_000), "demo_speed": (0.01, 100.0), "seed": (0, 2 ** 32 - 1),
    "start": (0, 2 ** 40), "stop": (1, 2 ** 40), "frame_step": (1, 2 ** 40),
    "max_frames": (1, 2 ** 40), "descriptor_batch": (1, 2 ** 20),
    "shards": (1, 10 ** 5), "matches_top_k": (1, 1000),
}


SEQSLAM_LIMITS = SEQSLAM_FIELD_LIMITS  # SeqSLAMConfig.validate holds every path to them


@dataclass
class Settings:
    """Everything one run needs: the front end's, SeqSLAM's and Neural SeqSLAM's configs."""

    run: EvalConfig
    seqslam: SeqSLAMConfig
    neural: NeuralConfig
    given: frozenset = frozenset()  # event fields the command line gave, whatever their value
    # --preset events without --speed-ratio: the preset's overrides, the ratio from the data
    speed_from_data: dict | None = None


def config_dict(s: Settings) -> dict:
    """config.json: the front end's fields, then ``seqslam`` and ``neural`` sections."""
    return {**to_jsonable(s.run), "seqslam": to_jsonable(s.seqslam),
            "neural": to_jsonable(s.neural)}

"""Run a query traverse through torchseq's engines and report place-recognition metrics.

With no arguments it runs on the built-in demo route. Each run writes into its own folder
(``--out``, default a new ``runs/eval-<time>``): ``metrics.json``, ``matches.csv``, PNG plots,
``config.json`` (replay it with ``--config``) and TensorBoard logs in ``tensorboard/``.
SeqSLAM settings are the plain flags (``--ds``, ``--patch-size``, ...); Neural SeqSLAM settings
carry a ``--neural-`` prefix (``--neural-patch-size``, ...).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import math
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchseq import metrics
from torchseq.atomic import write_json, write_text
from torchseq.cli import help as cli_help
from torchseq.cli import plots
from torchseq.cli.flags import (
    EVENT_FIELDS,
    EVENT_HELP,
    EventFlags,
    Parser,
    UsageError,
    add_config_flags,
    changed_fields,
    check_event_flags_apply,
    check_neural,
    check_ranges,
    config_file_defaults,
    config_from_args,
    config_text,
    event_frame_options,
    frame_selection,
    given_flags,
    load_model,
    resolve_device,
    run_folder,
    run_main,
    sweep_grid,
    to_jsonable,
    warn,
)
from torchseq.cli.help import organise_help
from torchseq.cli.map import check_map_flags, map_seqslam_config, map_traverse, run_seqslam_map
from torchseq.cli.presets import apply_preset, preset_config, preset_help, preset_name
from torchseq.cli.run_warnings import WarningLog, warning_list
from torchseq.demo import make_demo
from torchseq.descriptors import (
    DescriptorError,
    describe,
    descriptor_kind,
    load_descriptors,
    load_hook,
    neural_config,
    neural_input,
)
from torchseq.ground_truth import GroundTruthRanges, alignment_ranges, load_ground_truth
from torchseq.neural import NeuralConfig
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
from torchseq.sources import FrameSelection, load_traverse_sizes
from torchseq.versions import VERSIONS_KEY, versions

PROG = "torchseq eval"  # set by main() to the name the user ran
ENGINES = ("seqslam", "neural", "both")
Notes = WarningLog | list  # where a run's warnings go (a plain list in tests of one step)
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
    "tolerance": (0.0, 1e9), "gt_offset": (-1e9, 1e9), "target_precision": (0.0, 1.0),
    "demo_frames": (2, 20_000), "demo_speed": (0.01, 100.0), "seed": (0, 2 ** 32 - 1),
    "start": (0, 2 ** 40), "stop": (1, 2 ** 40), "frame_step": (1, 2 ** 40),
    "max_frames": (1, 2 ** 40), "descriptor_batch": (1, 2 ** 20),
    "shards": (1, 10 ** 5), "matches_top_k": (1, 1000),
}
THUMBNAIL = 160  # longer side of the frames kept for plots
SEQSLAM_LIMITS = {
    "patch_size": (0, 4096), "enhance_window": (0, 10 ** 6), "ds": (2, 10 ** 5),
    "vmin": (1e-3, 1e3), "vmax": (1e-3, 1e3), "speed_ratio": (1e-3, 1e3),
    "speed_tolerance": (0.0, 1.0), "rwindow": (0, 10 ** 6), "top_k": (1, 1000),
    "max_chunk_elements": (1, 2 ** 40), "candidates": (0, 10 ** 6),
}


@dataclass
class Settings:
    """Everything one run needs: the front end's, SeqSLAM's and Neural SeqSLAM's configs."""

    run: EvalConfig
    seqslam: SeqSLAMConfig
    neural: NeuralConfig
    given: frozenset = frozenset()  # event fields the command line gave, whatever their value


def build_parser() -> argparse.ArgumentParser:
    """The eval.py flags: EvalConfig, SeqSLAMConfig (plain) and NeuralConfig (``--neural-``)."""
    parser = Parser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("--config", help="replay a run: its config.json gives the defaults, "
                        "flags override them")
    parser.add_argument("--sweep", action="append", default=[], metavar="NAME=V1,V2,...",
                        help="run every setting of a small grid (repeat for more axes), e.g. "
                        "--sweep ds=10,20,40; writes sweep.csv with one row per setting")
    add_config_flags(parser, EvalConfig, HELP, skip=EventFlags)
    add_config_flags(parser.add_argument_group("event files"), EventFlags, EVENT_HELP)
    add_config_flags(parser.add_argument_group("SeqSLAM (SeqSLAMConfig)"), SeqSLAMConfig,
                     {k: v for k, v in HELP.items() if k in ("ds", "image_size")})
    add_config_flags(parser.add_argument_group("Neural SeqSLAM (NeuralConfig)"), NeuralConfig,
                     {"seed": "seed of the random masks and L1 weights (default: --seed)"},
                     prefix="neural_")
    parser.set_defaults(neural_seed=None)
    organise_help(parser, cli_help.EVAL, cli_help.EVAL_EXAMPLES)
    return parser


def settings_from(args: argparse.Namespace, typed: frozenset[str] = frozenset(),
                  replayed: frozenset[str] = frozenset(), recorded: str | None = None,
                  seqslam_typed: frozenset[str] = frozenset()) -> Settings:
    """Parsed flags -> checked :class:`Settings` (ranges first, then each config's rules).

    Args:
        args: the parsed flags.
        typed: NeuralConfig fields whose ``--neural-*`` flag the command line gave.
        replayed: NeuralConfig fields a ``--config`` file gave.
        recorded: the ``--neural-preset`` that file recorded.
        seqslam_typed: SeqSLAMConfig fields whose flag the command line gave: they win over
            ``--preset`` even at their default value (``--preset events --no-edges``).
    """
    cfg = config_from_args(EvalConfig, args)
    if cfg.neural_preset is not None:
        cfg.neural_preset = preset_name(cfg.neural_preset)
    check_ranges(cfg, LIMITS)
    if cfg.engine not in ENGINES:
        raise UsageError(f"--engine must be one of {', '.join(ENGINES)}, got {cfg.engine!r}")
    check_map_flags(cfg)
    if cfg.map is not None and cfg.engine == "both":
        cfg.engine = "seqslam"  # a map holds SeqSLAM descriptors only
    if cfg.reference is None and (cfg.demo_frames - 1) / cfg.demo_speed + 1 > MAX_DEMO_QUERY:
        raise UsageError(f"the demo query would have more than {MAX_DEMO_QUERY} frames; lower "
                         f"--demo-frames or raise --demo-speed")
    scfg = config_from_args(SeqSLAMConfig, args)
    check_ranges(scfg, {k: v for k, v in SEQSLAM_LIMITS.items() if hasattr(scfg, k)})
    scfg.validate()
    if cfg.preset is not None:
        two_channel = str(cfg.event_mode).replace("_", "-") == "two-channel"
        scfg = seqslam_preset(cfg.preset, scfg, two_channel, seqslam_typed)
    if cfg.map is not None:
        scfg = map_seqslam_config(cfg.map, scfg)
    # a neural seed of its own (a replayed config.json holds the run's --seed there)
    neural_seed_given = args.neural_seed is not None and args.neural_seed != cfg.seed
    if args.neural_seed is None:
        args.neural_seed = cfg.seed
    ncfg = apply_preset(config_from_args(NeuralConfig, args, prefix="neural_"),
                        cfg.neural_preset, typed, replayed, recorded)
    check_neural(ncfg, "neural_")
    ncfg.validate()
    if cfg.checkpoint and cfg.neural_preset is not None:
        raise UsageError("--neural-preset has no effect with --checkpoint (the checkpoint "
                         "carries its own config); drop one of them")
    if cfg.checkpoint and (neural_seed_given or
                           dataclasses.replace(ncfg, seed=0) != NeuralConfig(seed=0)):
        raise UsageError("--neural-* settings have no effect with --checkpoint (the "
                         "checkpoint carries its own config); drop one of them")
    preset = dataclasses.replace(preset_config(cfg.neural_preset), seed=0)
    check_unused(cfg, changed_flags(config_from_args(SeqSLAMConfig, args), SeqSLAMConfig()),
                 ["--neural-preset"] * (cfg.neural_preset is not None)
                 + changed_flags(dataclasses.replace(ncfg, seed=0), preset, "neural_")
                 + ["--neural-seed"] * neural_seed_given)
    return Settings(cfg, scfg, ncfg)


def changed_flags(config, default, prefix: str = "") -> list[str]:
    """The ``--flag`` names of the fields of ``config`` that differ from ``default``."""
    return [f"--{(prefix + name).replace('_', '-')}" for name in changed_fields(config, default)]


def check_unused(cfg: EvalConfig, seqslam_flags: list[str], neural_flags: list[str]) -> None:
    """Refuse settings this run would silently ignore (an engine it does not run, the demo)."""
    unused = []
    if cfg.engine == "neural":
        unused += seqslam_flags + (["--preset"] if cfg.preset is not None else [])
    if cfg.engine == "seqslam":
        unused += neural_flags + (["--checkpoint"] if cfg.checkpoint else [])
    if unused:
        raise UsageError(f"{', '.join(unused)} ha{'s' if len(unused) == 1 else 've'} no effect "
                         f"with --engine {cfg.engine}; drop "
                         f"{'it' if len(unused) == 1 else 'them'} or run --engine both")
    default = EvalConfig()
    demo = [f"--{k.replace('_', '-')}" for k in ("demo_frames", "demo_speed")
            if getattr(cfg, k) != getattr(default, k)]
    split = [f"--{k.replace('_', '-')}" for k in ("root", "reference_split", "query_split")
             if getattr(cfg, k) is not None]
    if split and cfg.dataset is None:
        raise UsageError(f"{', '.join(split)} belong{'s' if len(split) == 1 else ''} to "
                         f"--dataset; give --dataset NAME or drop "
                         f"{'it' if len(split) == 1 else 'them'}")
    if demo and cfg.dataset is not None:
        raise UsageError(f"{', '.join(demo)} shape the built-in demo route, not --dataset; "
                         f"drop {'it' if len(demo) == 1 else 'them'}")
    no_truth = (cfg.reference is not None and cfg.ground_truth is None and cfg.tolerance is None
                and cfg.dataset is None)
    if no_truth and cfg.target_precision != default.target_precision:
        raise UsageError("--target-precision picks an operating point from the ground truth, "
                         "and this run has none (--ground-truth or --tolerance); drop it or "
                         "give one")
    if demo and cfg.reference is not None:
        raise UsageError(f"{', '.join(demo)} shape{'s' if len(demo) == 1 else ''} the built-in "
                         f"demo route, not --reference/--query; drop "
                         f"{'it' if len(demo) == 1 else 'them'}")


def seqslam_preset(name: str, flags: SeqSLAMConfig, two_channel: bool = False,
                   typed: frozenset[str] = frozenset()) -> SeqSLAMConfig:
    """``--preset NAME``, with the SeqSLAM flags whose value differs from the default on top.

    ``--preset events`` sizes images as its event frames: with ``--event-mode two-channel``
    (OFF | ON side by side, twice as wide) its 16x16 becomes 16x32 unless ``--image-size``
    is given, so the halves are not squeezed into one square.
    """
    changed = changed_fields(flags, SeqSLAMConfig())
    changed.update({field: getattr(flags, field) for field in typed})  # typed flags win
    if name == "events" and two_channel and "image_size" not in changed:
        h, w = SeqSLAMConfig.events().image_size
        changed["image_size"] = (h, 2 * w)
    try:
        return SeqSLAMConfig.preset(name, **changed)
    except ValueError as err:
        raise UsageError(f"--preset: {err}") from None


def parse_args(argv: list[str] | None
               ) -> tuple[Settings, list[Settings], list[list[str]], list[str]]:
    """Flags -> (the run's settings, settings per ``--sweep`` point, their flags, the specs)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    pre, _ = parser.parse_known_args(argv)
    replayed = frozenset()
    neural = {"neural_" + f.name: f.name for f in dataclasses.fields(NeuralConfig)}
    if pre.config:
        before = {a.dest: a.default for a in parser._actions}
        replayed = config_file_defaults(parser, pre.config, {"seqslam": "", "neural": "neural_"})
        replayed -= _unused_replay(parser, argv, replayed, before, set(neural))
    seqslam_replayed = frozenset(d for d in replayed if d in SEQSLAM_FIELDS)  # the run's own
    replayed = frozenset(neural[d] for d in replayed if d in neural)
    recorded = parser.get_default("neural_preset")

    def settings(flags: list[str]) -> Settings:
        typed = frozenset(neural[d] for d in given_flags(parser, flags, set(neural)))
        seqslam_typed = given_flags(parser, flags, SEQSLAM_FIELDS) | seqslam_replayed
        return dataclasses.replace(
            settings_from(parser.parse_args(flags), typed, replayed, recorded, seqslam_typed),
            given=given_flags(parser, flags, EVENT_FIELDS))

    base = settings(argv)
    args = parser.parse_args(argv)
    grid = sweep_grid(args.sweep, parser)
    points = [settings(argv + extra) for extra in grid]
    return base, points, grid, list(args.sweep)


def _unused_replay(parser: argparse.ArgumentParser, argv: list[str], replayed: frozenset[str],
                   before: dict, neural: set[str]) -> frozenset[str]:
    """Drop a ``--config`` file's settings for an engine this command does not configure.

    The file holds the replayed run's SeqSLAM and neural settings; with ``--engine seqslam``
    or ``--checkpoint`` (neural) or ``--engine neural`` (SeqSLAM) typed now, those are not
    this command's choice, so they go back to their defaults instead of being refused as
    flags that would be ignored (flags typed now still are). Returns the dests reset.
    """
    args = parser.parse_args(argv)
    seqslam = {f.name for f in dataclasses.fields(SeqSLAMConfig)} | {"preset"}
    unused = set()
    if args.engine == "seqslam" or args.checkpoint:
        unused |= neural | {"neural_preset"}
    if args.engine == "neural":
        unused |= seqslam
    unused = (unused & replayed) - given_flags(parser, argv, unused & replayed)
    parser.set_defaults(**{d: before[d] for d in unused})
    return frozenset(unused)


def size_key(size) -> str:
    """``(32, 64)`` -> ``"32x64"``."""
    return f"{int(size[0])}x{int(size[1])}"


@dataclass
class Traverse:
    """A loaded traverse: frames at each size an engine needs, thumbnails for plots, facts."""

    frames: dict
    thumbnail: torch.Tensor | None
    info: dict
    descriptors: torch.Tensor | None = None  # (T, D) for a traverse of descriptors
    members: list | None = None  # temporal-window ensemble: one frames dict per member

    def __len__(self) -> int:
        return int(self.info["n_frames"])

    def at(self, size) -> torch.Tensor:
        """``(T, h, w)`` frames at ``size``."""
        return self.frames[size_key(size)]

    def members_at(self, size) -> list[torch.Tensor]:
        """The ensemble members' ``(T, h, w)`` frames at ``size``, in ``--window-ms`` order."""
        return [m[size_key(size)] for m in self.members]


def needed_sizes(settings: list[Settings], model=None, baseline: bool = True) -> dict:
    """Every frame size the run's engines read, by key.

    ``baseline``: SeqSLAM's size always, since its descriptors are the single-frame baseline
    of every run; False: only the sizes of the engines that run (what the warnings name).
    """
    sizes = {}
    for s in settings:
        if baseline or s.run.engine in ("seqslam", "both"):
            sizes[size_key(s.seqslam.image_size)] = tuple(s.seqslam.image_size)
        if s.run.engine in ("neural", "both"):
            size = model.config.input_size if model is not None else s.neural.input_size
            sizes[size_key(size)] = tuple(size)
    return sizes


def load_traverse_for(source, what: str, cfg: EvalConfig, sizes: dict, select) -> Traverse:
    """One traverse, shrunk frame by frame to ``sizes`` (a library error names it).

    A descriptor file (:func:`torchseq.descriptors.descriptor_kind`) is read as ``(T, D)``
    descriptors; with ``--descriptor`` the hook describes the frames as they stream in.
    """
    name = "demo" if not isinstance(source, (str, Path)) else source
    try:
        if cfg.descriptor is not None:
            return describe_traverse(source, cfg, select)
        if isinstance(source, (str, Path)) and Path(source).exists() and \
                descriptor_kind(source) is not None:
            desc = load_descriptors(source)
            keep = list(select.validate().indices(len(desc)))
            if not keep:
                raise DescriptorError(f"{source}: no descriptor in the selected range "
                                      f"({len(desc)} rows)")
            return Traverse({}, None, {"n_frames": len(keep), "frame_size": None,
                                       "indices": keep, "n_total": len(desc), "events": False,
                                       "descriptor_dim": int(desc.shape[1])}, desc[keep])
    except (ValueError, OSError) as err:
        raise UsageError(f"{what} traverse {name}: {str(err).splitlines()[0]}") from err
    try:
        frames, info = load_traverse_sizes(source, sizes, event_frame_options(cfg),
                                           cfg.progress, select, thumbnail=THUMBNAIL)
    except (ValueError, OSError) as err:
        name = "demo" if not isinstance(source, (str, Path)) else source
        text = str(err).splitlines()[0]
        text = text.removeprefix(f"{name}: ")  # the file named once
        raise UsageError(f"{what} traverse {name}: {text}") from err
    members = None
    opts = event_frame_options(cfg)
    if opts.members_ms is not None and info.get("events"):
        members = []
        for ms in opts.members_ms:  # one traverse per member, frames centred on the steps
            member = dataclasses.replace(opts, members_ms=None, centred_ms=ms)
            try:
                m, _ = load_traverse_sizes(source, sizes, member, cfg.progress, select)
            except (ValueError, OSError) as err:
                raise UsageError(f"{what} traverse {source}, {ms:g} ms member: "
                                 f"{str(err).splitlines()[0]}") from err
            if len(next(iter(m.values()))) != info["n_frames"]:
                raise UsageError(f"{what} traverse {source}: the {ms:g} ms member has "
                                 f"{len(next(iter(m.values())))} frames, the "
                                 f"{opts.window_ms:g} ms steps {info['n_frames']}")
            members.append(m)
    return Traverse({k: v for k, v in frames.items() if k != "thumbnail"},
                    frames["thumbnail"], info, members=members)


def describe_traverse(source, cfg: EvalConfig, select) -> Traverse:
    """A traverse described by the ``--descriptor`` hook as its frames stream (thumbnails kept)."""
    from torchseq.preprocess import resize
    from torchseq.sources import iter_traverse, thumbnail_size

    hook = load_hook(cfg.descriptor)
    thumbs, sizes, total = [], [], {}

    def keep(frame: torch.Tensor) -> None:
        if not sizes:
            sizes.append(tuple(int(v) for v in frame.shape))
        size = thumbnail_size(sizes[0], THUMBNAIL)
        thumbs.append(resize(frame[None], size)[0].round().clamp(0, 255).to(torch.uint8))

    frames = iter_traverse(source, event_frame_options(cfg), cfg.progress, select, total)
    desc = describe(frames, hook, resolve_device(cfg.device), cfg.descriptor_batch, keep)
    n = len(desc)
    return Traverse({}, torch.stack(thumbs), {
        "n_frames": n, "frame_size": list(sizes[0]),
        "indices": list(range(select.start, select.start + n * select.step, select.step)),
        "n_total": total.get("n_total"), "events": bool(total.get("events")),
        "descriptor_dim": int(desc.shape[1]), "descriptor_hook": cfg.descriptor}, desc)


def selected_ground_truth(gt_full, ref: Traverse, query: Traverse):
    """Rows and columns of the selected frames of a ground truth over whole traverses."""
    if isinstance(gt_full, GroundTruthRanges):
        return gt_full.take(ref.info["indices"], query.info["indices"])
    return gt_full[np.ix_(ref.info["indices"], query.info["indices"])]


def load_data(cfg: EvalConfig, sizes: dict, notes: Notes, engine_sizes: dict | None = None):
    """Reference and query traverses, ``(R, Q)`` ground truth (or None) and a description.

    ``sizes``: every size to load; ``engine_sizes``: those the engines read, which the
    small-frame warnings name (default: ``sizes``).
    """
    select = frame_selection(cfg.start, cfg.stop, cfg.frame_step, cfg.max_frames)
    if cfg.dataset is not None:
        ds = open_place_dataset(cfg)
        ref = load_traverse_for(ds.reference.path, "reference", cfg, sizes, select)
        query = load_traverse_for(ds.query.path, "query", cfg, sizes, select)
        gt = ds.ground_truth
        source = {"dataset": ds.name, "root": str(ds.root), "reference": ds.splits[0],
                  "query": ds.splits[1], "ground_truth": ds.description}
    elif cfg.reference is None and cfg.query is None:
        demo = make_demo(n_reference=cfg.demo_frames, speed=cfg.demo_speed, seed=cfg.seed)
        ref = load_traverse_for(demo.reference, "reference", cfg, sizes, select)
        query = load_traverse_for(demo.query, "query", cfg, sizes, select)
        gt = selected_ground_truth(demo.ground_truth, ref, query)
        source = {"reference": "demo", "query": "demo", "ground_truth": "demo (exact)"}
    elif cfg.map is not None:  # the reference is the map's: no frames read
        ref = map_traverse(cfg.map, Traverse)
        query = load_traverse_for(cfg.query, "query", cfg, sizes, select)
        gt, source = None, {"reference": f"map {cfg.map}", "query": cfg.query}
    elif cfg.reference is None or cfg.query is None:
        raise UsageError("give both --reference and --query (or neither, for the demo)")
    else:
        ref = load_traverse_for(cfg.reference, "reference", cfg, sizes, select)
        query = load_traverse_for(cfg.query, "query", cfg, sizes, select)
        gt, source = None, {"reference": cfg.reference, "query": cfg.query}
        check_descriptor_pair(ref, query)
        if ref.descriptors is not None:
            source["descriptors"] = {"dim": ref.info["descriptor_dim"],
                                     "hook": cfg.descriptor}
    selected = select != FrameSelection()
    totals = (ref.info["n_total"], query.info["n_total"])
    if selected and (cfg.ground_truth is not None or cfg.tolerance is not None) and None in totals:
        raise UsageError("a video's frame count is unknown to its container, so ground truth "
                         "cannot be matched to --start/--stop/--frame-step; convert it to "
                         "images or drop the selection")
    n_ref, n_query = totals if selected else (len(ref), len(query))
    if cfg.dataset is not None:
        pass  # the dataset's own ground truth (its tolerance applied)
    elif cfg.ground_truth is not None:
        gt = load_ground_truth(cfg.ground_truth, n_ref, n_query, widen=cfg.tolerance or 0.0)
        source["ground_truth"] = cfg.ground_truth + (
            f", widened by {cfg.tolerance} frames" if cfg.tolerance else "")
    elif cfg.tolerance is not None:
        gt = alignment_ranges(n_ref, n_query, cfg.tolerance, offset=cfg.gt_offset)  # sparse
        source["ground_truth"] = f"index alignment, tolerance {cfg.tolerance}" + (
            f", offset {cfg.gt_offset}" if cfg.gt_offset else "")
    if selected and (cfg.reference is not None or cfg.dataset is not None) and gt is not None:
        gt = selected_ground_truth(gt, ref, query)
    if (ref.members is None) != (query.members is None):
        raise UsageError("--window-ms with several windows (an ensemble) needs event files for "
                         "both --reference and --query")
    if ref.members is not None:
        source["window_ensemble_ms"] = list(event_frame_options(cfg).members_ms)
    if selected:
        source["selection"] = {"start": cfg.start, "stop": cfg.stop,
                               "frame_step": cfg.frame_step, "max_frames": cfg.max_frames}
    two_channel = str(cfg.event_mode).replace("_", "-") == "two-channel"
    causes: dict = {}  # one warning per cause: (kind, frame size) -> traverses, engine sizes
    for what, t in (("reference", ref), ("query", query)):
        if t.descriptors is not None:
            continue
        fh, fw = t.info["frame_size"]
        for key, (h, w) in (sizes if engine_sizes is None else engine_sizes).items():
            if h > fh or w > fw:
                cause = ("small", fh, fw)
            elif two_channel and t.info.get("events") and h * fw != w * fh:
                cause = ("halves", fh, fw)
            else:
                continue
            whats, keys = causes.setdefault(cause, ({}, {}))  # dicts: ordered sets
            whats[what] = keys[key] = None
    for (kind, fh, fw), (whats, keys) in causes.items():
        what, key = " and ".join(whats), " and ".join(keys)
        if kind == "small":
            warn(PROG, f"{what} frames are {fh}x{fw}, smaller than the {key} an engine "
                 f"reads: they are upsampled (set --image-size or --neural-input-size "
                 f"to the frame size)", notes)
        else:
            warn(PROG, f"{what} two-channel event frames are {fh}x{fw} (OFF | ON side by "
                 f"side), resized to {key}: the halves change shape (set --image-size or "
                 f"--neural-input-size to {fh}x{fw}, or a size of that shape)", notes)
    return ref, query, gt, source


def open_place_dataset(cfg: EvalConfig):
    """``--dataset NAME --root DIR [--reference-split A --query-split B]`` -> PlaceDataset."""
    from torchseq.datasets import DatasetError, open_dataset

    given = [f for f in ("reference", "query", "ground_truth") if getattr(cfg, f) is not None]
    if given:
        flags = ", ".join(f"--{f.replace('_', '-')}" for f in given)
        raise UsageError(f"--dataset gives the reference, query and ground truth; drop {flags}")
    if cfg.root is None:
        raise UsageError("--dataset needs --root, the folder of its local copy")
    kwargs = {}
    if str(cfg.dataset).lower().replace("_", "-") == "brisbane-event":
        kwargs["events"] = event_frame_options(cfg)
    try:
        return open_dataset(cfg.dataset, cfg.root, cfg.reference_split, cfg.query_split,
                            cfg.tolerance, **kwargs)
    except (DatasetError, ValueError, OSError) as err:
        raise UsageError(f"--dataset: {str(err).splitlines()[0]}") from err


def check_descriptor_pair(ref: Traverse, query: Traverse) -> None:
    """Both traverses descriptors of one size, or both frames."""
    if (ref.descriptors is None) != (query.descriptors is None):
        which = "reference" if ref.descriptors is not None else "query"
        raise UsageError(f"the {which} traverse holds descriptors and the other frames: give "
                         f"descriptors for both (or frames for both)")
    if ref.descriptors is not None and ref.descriptors.shape[1] != query.descriptors.shape[1]:
        raise UsageError(f"reference descriptors have {ref.descriptors.shape[1]} values, query "
                         f"descriptors {query.descriptors.shape[1]}: they must be the same size")


def transposed_size(size, frame_size) -> str | None:
    """A warning when ``size`` ``(h, w)`` has the transposed aspect of ``frame_size`` ``(H, W)``.

    OpenSeqSLAM and much of the literature write image sizes as width x height (64x32);
    ``--image-size`` is height x width, so the transposed spelling squeezes landscape frames
    into portrait images (corridor recall@1 0.441 -> 0.216).
    """
    (h, w), (fh, fw) = (int(v) for v in size), (int(v) for v in frame_size)
    if h == w or fh == fw or (h > w) == (fh > fw):
        return None
    # closer to the frames' aspect when swapped?
    if abs(math.log((w / h) / (fw / fh))) <= abs(math.log((h / w) / (fw / fh))):
        return None
    return (f"--image-size {h}x{w} is height x width ({h} high, {w} wide), the transposed "
            f"shape of these {fh}x{fw} frames ({'landscape' if fw > fh else 'portrait'}); "
            f"give --image-size {w}x{h} if you meant width x height (OpenSeqSLAM's 64x32 is "
            f"32x64 here)")


def run_seqslam(s: Settings, ref, query, device, notes: Notes):
    """Classic SeqSLAM: matches, ranked candidates, the matrix to plot, seconds, parameters."""
    ds = s.seqslam.sequence_length
    if ds > len(query):
        hint = ""
        if query.info.get("events") and s.run.event_count is None:
            n, w = query.info["n_total"], event_frame_options(s.run).window_ms
            if n > 1:  # the events span more than (n - 1) windows
                hint = (f": the query recording fills {n} windows of {w:g} ms (more than "
                        f"{(n - 1) * w:g} ms of events); --window-ms {(n - 1) * w / ds:.3g} "
                        f"or less gives at least {ds} frames")
            else:
                hint = (f": the query recording is shorter than one {w:g} ms window; give "
                        f"shorter windows (--window-ms) or a fixed number of events per frame "
                        f"(--event-count N makes frames of N events each)")
        raise UsageError(f"--ds {s.seqslam.ds} is longer than the query ({len(query)} frames)"
                         + hint)
    if s.run.map is not None:
        return run_seqslam_map(s, query, device, s.run.progress)
    size = s.seqslam.image_size
    if ref.descriptors is None:
        transposed = transposed_size(size, ref.info["frame_size"])
        if transposed:
            warn(PROG, transposed, notes)
    config = ranked_config(s.seqslam)
    if ref.descriptors is not None:
        result = SeqSLAM(config, device=device).match_descriptors(
            ref.descriptors, query.descriptors, progress=s.run.progress)
    elif ref.members is not None:  # temporal-window ensemble (--window-ms 5,10,20)
        from torchseq.events.ensemble import match_ensemble

        result = match_ensemble(ref.members_at(size), query.members_at(size), config, device)
    else:
        result = SeqSLAM(config, device=device).match(ref.at(size), query.at(size),
                                                      progress=s.run.progress)
    # plots draw the engine's reduced copy (area averages, at most 1024 a side; the whole
    # matrix below that) in full-matrix coordinates; long routes keep nothing else. Without
    # one, the enhanced matrix (a sparse one is reduced as it is, never made dense)
    matrix = result.preview if result.preview is not None else result.enhanced
    return {"matches": result.matches, "ranked": result.ranked,
            "ranked_score": result.ranked_score, "matrix": matrix,
            "matrix_shape": (len(ref), len(query)), "matrix_reduced": result.enhanced is None,
            "seconds": result.seconds["total"], "parameters": to_jsonable(config)}


RANKED = max(metrics.RECALL_KS) + 1  # candidates ranked: recall@20 and the tie past it


def ranked_config(config: SeqSLAMConfig) -> SeqSLAMConfig:
    """The run's SeqSLAM config with at least :data:`RANKED` ranked candidates.

    ``top_k`` only sizes the ranked list (it changes no match); metrics.json's recall@20
    needs 20 candidates and one more to see a tie at the 20th.
    """
    return dataclasses.replace(config, top_k=max(config.top_k, RANKED))


def describe_reference(cfg: EvalConfig, ref: Traverse) -> dict:
    """What identifies a reference traverse: source, frames, frame size, selection, events."""
    if cfg.reference is None:
        source = {"source": "demo", "demo_frames": cfg.demo_frames, "demo_seed": cfg.seed}
    else:
        source = {"source": str(Path(cfg.reference).resolve()), "select": to_jsonable(
            frame_selection(cfg.start, cfg.stop, cfg.frame_step, cfg.max_frames))}
        if ref.info.get("events"):
            source["events"] = to_jsonable(event_frame_options(cfg))
    size = ref.info["frame_size"]
    return {**source, "n_frames": len(ref), "frame_size": None if size is None else list(size)}


# event settings that change no frame (the same events either way, or a complete file read)
SAME_FRAMES = {"evt3_kernel", "truncated"}


def _setting_changes(learnt: dict, now: dict) -> str:
    """``"mode 'count' -> 'signed', ..."`` for the settings both dicts hold that differ."""
    return ", ".join(f"{k} {learnt[k]!r} -> {now[k]!r}" for k in now
                     if k in learnt and k not in SAME_FRAMES and learnt[k] != now[k])


def checkpoint_mismatch(model, this: dict) -> str | None:
    """Say how a checkpoint's learnt reference differs from this run's reference, if it does."""
    learnt = model.extra.get("reference") if isinstance(model.extra, dict) else None
    n_learnt = int(model.unit_to_reference[-1, 1])
    problems = []
    if n_learnt != this["n_frames"]:
        problems.append(f"it learnt {n_learnt} reference frames, this reference has "
                        f"{this['n_frames']}")
    if isinstance(learnt, dict):
        keys = ("source", "demo_frames", "demo_seed")
        was = {k: learnt.get(k) for k in keys if k in learnt or k in this}
        now = {k: this.get(k) for k in keys if k in learnt or k in this}
        if was != now:
            problems.append(f"it learnt {learnt.get('source')}, this reference is "
                            f"{this['source']}")
        if learnt.get("frame_size") not in (None, this["frame_size"]) and this["frame_size"]:
            fs = learnt["frame_size"]
            problems.append(f"its frames were {fs[0]}x{fs[1]}, these are "
                            f"{this['frame_size'][0]}x{this['frame_size'][1]}")
        for key, what in (("events", "event frame settings differ"),
                          ("select", "frame selection differs")):
            if isinstance(learnt.get(key), dict) and isinstance(this.get(key), dict):
                changed = _setting_changes(learnt[key], this[key])
                if changed:
                    problems.append(f"its {what} ({changed})")
    elif not problems:
        return None  # an API-saved model: the frame count is all there is to check
    if not problems:
        return None
    return ("the checkpoint does not match this reference (" + "; ".join(problems) +
            "): its matches index the reference it learnt, so the metrics are meaningless "
            "unless that is the same route")


def run_neural(s: Settings, ref, query, device, notes: Notes, model=None):
    """Neural SeqSLAM, from a checkpoint (``model``, loaded) or trained on the reference now."""
    from torchseq.neural import NeuralSeqSLAM
    from torchseq.neural.model import COARSE_UNIT_FRAMES

    cfg = s.run
    start = time.perf_counter()
    if model is not None:
        problem = checkpoint_mismatch(model, describe_reference(cfg, ref))
        if problem:
            warn(PROG, problem, notes)
    elif ref.descriptors is not None:
        model = NeuralSeqSLAM(neural_config(s.neural, ref.descriptors.shape[1]), device=device)
        model.fit(neural_input(ref.descriptors), progress=cfg.progress)
    else:
        model = NeuralSeqSLAM(s.neural, device=device)
        with warnings.catch_warnings():  # one warning per cause: the run's own, below, names
            warnings.filterwarnings(      # the flag (--neural-n-output)
                "ignore", message=r"a route of \d+ frames on \d+ output units")
            model.fit(ref.at(s.neural.input_size), progress=cfg.progress)
    size = model.config.input_size
    if ref.descriptors is not None and tuple(size) != (1, ref.descriptors.shape[1]):
        raise UsageError(f"the checkpoint's L1 takes {size[0]}x{size[1]} inputs, not "
                         f"{ref.descriptors.shape[1]}-value descriptors (train it on these "
                         f"descriptors)")
    fit_seconds = time.perf_counter() - start
    n_ref = int(model.unit_to_reference[-1, 1])
    per_unit = n_ref / model.n_units
    readout = model.config.readout
    if per_unit > (COARSE_UNIT_FRAMES if readout == "interpolate" else 1):
        how = ("matches are unit centres" if readout == "centre" else
               "too coarse for the interpolating readout")
        warn(PROG, f"neural: {n_ref} reference frames on {model.n_units} output units, one "
             f"unit stands for about {per_unit:.1f} frames ({how}; raise --neural-n-output "
             f"for a finer place resolution; measured on nordland-b, 1,788 frames: recall@1 "
             f"0.25 at 3.2 frames per unit against 0.59 at one; "
             f"docs/results/neural-long-routes.md)", notes)
    self_check = model.self_check  # fit's figure, or the one a trained checkpoint carries
    if self_check is None:
        self_check = (getattr(model, "extra", None) or {}).get("self_check")
    t0 = time.perf_counter()
    result = model.run(query.at(size) if query.descriptors is None else
                       neural_input(query.descriptors), progress=cfg.progress)
    run_seconds = time.perf_counter() - t0
    k = min(RANKED, model.n_units)
    top = result.activity.topk(k, dim=1)  # activity: higher is better, as the confidence
    ranked = model.unit_centre.cpu()[top.indices]
    preset = None if cfg.checkpoint else preset_name(cfg.neural_preset)
    return {"matches": result.matches, "ranked": ranked, "ranked_score": top.values,
            "activity": result.activity, "unit_spans": model.unit_to_reference.cpu(),
            "seconds": run_seconds, "fit_seconds": fit_seconds, "preset": preset,
            "parameters": to_jsonable(model.config), "model_bytes": int(model.model_bytes()),
            "frames_per_unit": per_unit, "self_check": self_check}


def matches_csv(results: dict, gt=None, top_k: int = 5) -> str:
    """``engine,query,reference,score[,correct],candidates`` rows.

    Empty reference and score where no match; ``correct`` (1/0, only with ground truth):
    the ground truth admits the match; ``candidates``: the best ``top_k`` reference indices
    the engine ranked, best first, space-separated.
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["engine", "query", "reference", "score", *(["correct"] if gt is not None
                                                            else []), "candidates"])
    for name, r in results.items():
        ref = r["matches"].reference.cpu().numpy()
        score = r["matches"].score.cpu().numpy()
        good = metrics.correct(r["matches"], gt) if gt is not None else None
        ranked = np.asarray(r["ranked"].cpu() if torch.is_tensor(r["ranked"]) else r["ranked"])
        ranked = ranked.reshape(len(ref), -1)[:, :top_k]
        for q, (i, s) in enumerate(zip(ref, score)):
            row = [name, q, int(i) if i >= 0 else "", f"{s:.6g}" if i >= 0 else ""]
            if good is not None:
                row.append(int(good[q]))
            row.append(" ".join(str(int(c)) for c in ranked[q] if c >= 0))
            w.writerow(row)
    return buf.getvalue()


def engine_metrics(r: dict, gt, target_precision: float) -> dict:
    """metrics.json entry of one engine."""
    if gt is None:
        m = {"recall_at_1": None, "auc": None, "recall_at_100_precision": None,
             "n_queries": len(r["matches"]), "coverage": metrics.coverage(r["matches"])}
    else:
        m = metrics.evaluate(r["matches"], gt, r["ranked"], r.get("ranked_score"))
        m["operating_point"] = metrics.operating_point(r["matches"], gt, target_precision)
    m.update({k: r[k] for k in ("seconds", "fit_seconds", "model_bytes", "frames_per_unit",
                                "self_check", "preset", "parameters") if k in r})
    return m


def config_dict(s: Settings) -> dict:
    """config.json: the front end's fields, then ``seqslam`` and ``neural`` sections."""
    return {**to_jsonable(s.run), "seqslam": to_jsonable(s.seqslam),
            "neural": to_jsonable(s.neural)}


SINGLE_FRAME_RULE = ("each query's nearest reference by the run's --metric on the same "
                     "descriptors (SeqSLAM's own for frames), no contrast enhancement, no "
                     "sequence (ds = 1)")


def single_frame_baseline(s: Settings, ref: Traverse, query: Traverse, device):
    """Single-frame matches on the run's descriptors (:func:`torchseq.seqslam.single_frame`)."""
    from torchseq.seqslam.single import single_frame

    if ref.descriptors is not None:
        r, q = ref.descriptors, query.descriptors
    else:
        engine = SeqSLAM(s.seqslam, device=device)
        size = s.seqslam.image_size
        r, q = engine.descriptors(ref.at(size)), engine.descriptors(query.at(size))
    return single_frame(r.to(device), q.to(device), s.seqslam.metric, RANKED,
                        s.seqslam.max_chunk_elements)


def report(s: Settings, ref, query, gt, source, results, out: Path, notes: Notes,
           single=None) -> dict:
    """Write metrics.json, matches.csv, plots and TensorBoard logs; return the metrics.

    ``single``: the single-frame baseline (:func:`single_frame_baseline`), reported beside
    each engine with the share of queries the sequence makes worse (needs ground truth).
    """
    summary = {"inputs": {**source, "n_reference": len(ref), "n_query": len(query),
                          "reference_frame_size": ref.info["frame_size"],
                          "query_frame_size": query.info["frame_size"]},
               "warnings": warning_list(notes), VERSIONS_KEY: versions()}
    if single is not None and gt is not None:
        summary["single_frame"] = {
            "rule": SINGLE_FRAME_RULE, "metric": s.seqslam.metric,
            **metrics.evaluate(single.matches, gt, single.ranked, single.ranked_score)}
    curves = {}
    for name, r in results.items():
        summary[name] = engine_metrics(r, gt, s.run.target_precision)
        if gt is not None:
            curves[name] = metrics.precision_recall_curve(r["matches"], gt)
            if single is not None:
                summary[name]["versus_single_frame"] = metrics.sequence_vs_single(
                    r["matches"], single.matches, gt)
    mark_incomplete(out)  # before the first file: an interrupted run never looks finished
    summary["status"] = "incomplete"  # until the plots and logs are written too
    write_json(out / "metrics.json", summary)
    write_text(out / "matches.csv", matches_csv(results, gt, s.run.matches_top_k))
    write_text(out / "config.json",
               config_text({**config_dict(s), VERSIONS_KEY: versions()}) + "\n")
    figures = {}
    if "seqslam" in results and results["seqslam"]["matrix"] is not None:
        r = results["seqslam"]
        figures["seqslam_difference_matrix"] = plots.plot_difference_matrix(
            r["matrix"], r["matches"], gt, "SeqSLAM contrast-enhanced difference matrix"
            + (" (banded run: reduced copy)" if r["matrix_reduced"] else ""),
            shape=r["matrix_shape"])
    if "neural" in results:
        r = results["neural"]
        truth = (None if gt is None else
                 plots.true_units(gt, r["unit_spans"], r["activity"].shape[0]))
        figures["neural_activity"] = plots.plot_activity_raster(
            r["activity"], title="neural output activity over the query", truth=truth)
    for name, r in results.items():
        if ref.thumbnail is None or query.thumbnail is None:
            continue  # descriptor files and maps: no frames to show
        figures[f"{name}_matched_pairs"] = plots.plot_matched_pairs(
            ref.thumbnail, query.thumbnail, r["matches"], gt,
            title=f"{name}: query (top) and matched reference")
    if curves:
        figures["pr_curve"] = plots.plot_pr_curves(curves)
    images = {k: plots.figure_to_array(f) for k, f in figures.items()}  # drawn once
    for k, img in images.items():
        plots.save_image(img, out / f"{k}.png")
        figures[k].clear()
    if s.run.tensorboard:
        log_tensorboard(s, out, summary, results, gt, images)
    summary["status"] = "complete"
    write_json(out / "metrics.json", summary)
    return summary


INCOMPLETE = "INCOMPLETE"  # a run folder holding this file is partial: stopped or failed


def mark_incomplete(out: Path) -> None:
    """Leave ``OUT/INCOMPLETE`` until the run has written everything (see :func:`run`)."""
    write_text(out / INCOMPLETE, "this run stopped before it finished (interrupted or failed): "
               "its files are partial; metrics.json says \"status\": \"complete\" only "
               "when every file was written\n")


def mark_complete(out: Path) -> None:
    """Remove ``OUT/INCOMPLETE``: the run wrote everything."""
    (out / INCOMPLETE).unlink(missing_ok=True)


def log_tensorboard(s: Settings, out: Path, summary: dict, results: dict, gt,
                    images: dict) -> None:
    """Scalars, images, PR curves and the config in ``OUT/tensorboard``."""
    from torch.utils.tensorboard import SummaryWriter

    with SummaryWriter(log_dir=str(out / "tensorboard")) as tb:
        tb.add_text("config", "```\n" + config_text(config_dict(s)) + "\n```")
        for name in results:
            for key, value in summary[name].items():
                if isinstance(value, (int, float)) and value is not None and np.isfinite(value):
                    tb.add_scalar(f"{name}/{key}", value)
        for key, img in images.items():
            tb.add_image(key, img, dataformats="HWC")
        for name in results:  # the HParams tab: this run's settings beside its results
            tb.add_hparams(hparams(s, name), {
                f"hparam/{name}/{k}": float(v) for k, v in summary[name].items()
                if k in ("recall_at_1", "recall_at_5", "auc", "seconds")
                and isinstance(v, (int, float)) and np.isfinite(v)}, run_name=name)
        if gt is None:
            return
        for name, r in results.items():
            m = r["matches"]
            has = m.reference >= 0
            if not bool(has.any()):
                continue
            labels = torch.from_numpy(metrics.correct(m, gt))[has]
            conf = m.confidence[has]
            lo, hi = conf.min(), conf.max()
            pred = (conf - lo) / (hi - lo) if hi > lo else torch.ones_like(conf)
            tb.add_pr_curve(f"{name}/pr_curve", labels, pred.float())


def hparams(s: Settings, engine: str) -> dict:
    """TensorBoard hparams of one engine: the run's and that engine's scalar settings."""
    section = to_jsonable(s.seqslam if engine == "seqslam" else s.neural)
    flat = {**{k: v for k, v in to_jsonable(s.run).items()}, **{
        f"{engine}.{k}": v for k, v in section.items()}}
    out = {"engine": engine}
    for k, v in flat.items():
        if isinstance(v, (bool, int, float, str)):
            out[k] = v
        elif isinstance(v, (list, tuple)) and v and all(isinstance(x, (int, float)) for x in v):
            out[k] = "x".join(str(x) for x in v)
    return out


def run_engines(s: Settings, ref, query, device, notes: Notes, model=None) -> dict:
    """Every engine the run asks for, by name (``model``: a loaded checkpoint)."""
    names = ["seqslam", "neural"] if s.run.engine == "both" else [s.run.engine]
    return {name: run_seqslam(s, ref, query, device, notes) if name == "seqslam" else
            run_neural(s, ref, query, device, notes, model) for name in names}


def sweep(base: Settings, points: list[Settings], grid: list[list[str]], specs: list[str],
          ref, query, gt, source, device, out: Path, notes: Notes, model=None) -> int:
    """Run every grid point; write sweep.csv (one row per setting and engine) and sweep.json."""
    mark_incomplete(out)
    rows = []
    for point, flags in zip(points, grid):
        setting = " ".join(flags)
        print(f"sweep: {setting}", file=sys.stderr)
        for name, r in run_engines(point, ref, query, device, notes, model).items():
            m = engine_metrics(r, gt, point.run.target_precision)
            op = m.get("operating_point") or {}
            rows.append({"setting": setting, "engine": name,
                         **{k: m.get(k) for k in ("recall_at_1", "recall_at_5", "recall_at_10",
                                                  "auc", "recall_at_100_precision")},
                         "operating_recall": op.get("recall"),
                         "operating_threshold": op.get("score_threshold"),
                         "seconds": m["seconds"]})
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    write_text(out / "sweep.csv", buf.getvalue())
    write_json(out / "sweep.json", {"inputs": source, "rows": rows,
                                     "warnings": warning_list(notes), VERSIONS_KEY: versions()})
    write_text(out / "config.json", config_text({**config_dict(base), "sweep": specs,
                                                 VERSIONS_KEY: versions()}) + "\n")
    for row in rows:
        r1 = "n/a" if row["recall_at_1"] is None else f"{row['recall_at_1']:.3f}"
        print(f"{row['setting']}: {row['engine']} recall@1 {r1}")
    print(f"wrote {out / 'sweep.csv'}")
    return 0


def progress_wanted(argv: list[str] | None, stream=None) -> bool:
    """Progress bars only on a terminal: redirected logs get no carriage-return lines.

    ``--progress`` given on the command line keeps them anywhere.
    """
    argv = sys.argv[1:] if argv is None else argv
    stream = sys.stderr if stream is None else stream
    return "--progress" in argv or bool(getattr(stream, "isatty", lambda: False)())


def quiet(s: Settings) -> Settings:
    """``s`` with progress bars off."""
    return dataclasses.replace(s, run=dataclasses.replace(s.run, progress=False))


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """Entry point; returns the exit code (errors raise, see :func:`torchseq.cli.flags.run_main`).

    Args:
        argv: the flags (None: ``sys.argv[1:]``).
        prog: the command's name in messages (``eval.py``, ``torchseq eval``).
    """
    global PROG
    PROG = prog or PROG
    s, points, grid, specs = parse_args(argv)
    if not progress_wanted(argv):
        s, points = quiet(s), [quiet(p) for p in points]
    notes = WarningLog(PROG)  # the library's warnings and the front end's, once each
    with notes.capture():
        return run(s, points, grid, specs, notes)


def run(s: Settings, points: list[Settings], grid: list[list[str]], specs: list[str],
        notes: WarningLog) -> int:
    """One eval run (or sweep) of checked settings; its warnings go to ``notes``."""
    cfg = s.run
    device = resolve_device(cfg.device)
    event_frame_options(cfg)  # checked before any work
    inputs = {"--reference": cfg.reference, "--query": cfg.query}
    if cfg.dataset is not None:
        inputs = {"--dataset": cfg.dataset}
    for point in (s, *points):  # event flags with no event file would be silently ignored
        if str(cfg.dataset).lower().replace("_", "-") != "brisbane-event":
            check_event_flags_apply(point.run, inputs, point.given)
    frame_selection(cfg.start, cfg.stop, cfg.frame_step, cfg.max_frames)
    out = run_folder(cfg.out, "eval", cfg.overwrite)
    torch.manual_seed(cfg.seed)
    model = None
    if cfg.checkpoint and cfg.engine in ("neural", "both"):
        model = load_model(cfg.checkpoint, device)
    ref, query, gt, source = load_data(cfg, needed_sizes([s, *points], model), notes,
                                       needed_sizes([s, *points], model, baseline=False))
    if ref.descriptors is not None and cfg.engine != "neural" and cfg.preset is None:
        default = SeqSLAMConfig()
        typed = [f"--{k.replace('_', '-')}" for k in ("image_size", "patch_size",
                                                      "preprocessing")
                 if any(getattr(p.seqslam, k) != getattr(default, k) for p in (s, *points))]
        if typed:
            raise UsageError(f"{', '.join(typed)} shape{'s' if len(typed) == 1 else ''} "
                             f"SeqSLAM's own descriptors, and this run matches given "
                             f"descriptors; drop {'it' if len(typed) == 1 else 'them'}")
    if ref.descriptors is not None and cfg.engine != "seqslam" and model is None:
        preset = preset_config(cfg.neural_preset)
        typed = [f"--neural-{k.replace('_', '-')}" for k in ("input_size", "patch_size")
                 if any(getattr(p.neural, k) != getattr(preset, k) for p in (s, *points))]
        if typed:
            raise UsageError(f"{', '.join(typed)} ha{'s' if len(typed) == 1 else 've'} no "
                             f"effect on descriptors: the network's L1 takes the "
                             f"{ref.info['descriptor_dim']} values of each descriptor")
    if grid:
        code = sweep(s, points, grid, specs, ref, query, gt, source, device, out, notes, model)
        mark_complete(out)
        return code
    results = run_engines(s, ref, query, device, notes, model)
    # the baseline needs the reference's descriptors: a map run reads none (sharded maps)
    single = (single_frame_baseline(s, ref, query, device)
              if gt is not None and s.run.map is None else None)
    summary = report(s, ref, query, gt, source, results, out, notes, single)
    mark_complete(out)
    for name in results:
        print(summary_line(name, summary[name]))
    print(f"wrote {out / 'metrics.json'}, {out / 'matches.csv'} and plots to {out}")
    return 0


def summary_line(name: str, m: dict) -> str:
    """One engine's line: recall@1 (ties both ways), single frame, share made worse, AUC."""
    if m.get("recall_at_1") is None:
        return (f"{name}: recall@1 n/a (no ground truth) over {m['n_queries']} queries "
                f"({m['seconds']:.2f} s)")
    text = f"{name}: recall@1 {m['recall_at_1']:.3f}"
    rec = m.get("recall", {}).get("queries_with_a_true_match")
    if rec and rec["ties_for"]["1"] != rec["ties_against"]["1"]:
        text += f" (ties {rec['ties_against']['1']:.3f}..{rec['ties_for']['1']:.3f})"
    vs = m.get("versus_single_frame")
    if vs:
        text += (f", single frame {vs['single_frame_recall_at_1']:.3f}, made worse "
                 f"{100 * vs['made_worse']:.1f}% / better {100 * vs['made_better']:.1f}% "
                 f"of queries")
    return (f"{text}, AUC {m['auc']:.3f} over {m['n_queries']} queries "
            f"({m['seconds']:.2f} s)")


def cli(argv: list[str] | None = None, prog: str | None = None) -> int:
    """Run as a command: expected failures become one ``prog: error:`` line and exit 2."""
    prog = prog or PROG
    return run_main(lambda a: main(a, prog), prog, argv)


if __name__ == "__main__":
    raise SystemExit(cli())

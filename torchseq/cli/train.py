"""Learn a Neural SeqSLAM model from a reference traverse (one pass, local learning rules).

With no arguments it trains on the built-in demo route. Each run writes into its own folder
(``--out``, default a new ``runs/train-<time>``): ``model.pt`` (the checkpoint carries its
config and a record of its reference), ``config.json`` (replay it with ``--config``), PNG
plots and TensorBoard logs in ``tensorboard/``. ``--export`` then writes the deployment files
to ``OUT/export``, validated as ``python -m torchseq.export`` does.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torchseq.cli.help as cli_help
from torchseq.atomic import write_text
from torchseq.cli.errors import UsageError
from torchseq.cli.event_options import (
    EVENT_FIELDS,
    EVENT_HELP,
    EventFlags,
    check_event_flags_apply,
    event_frame_options,
)
from torchseq.cli.flags import (
    Parser,
    add_config_flags,
    check_neural,
    check_ranges,
    config_from_args,
    frame_selection,
    given_flags,
    parse_size,
    resolve_device,
)
from torchseq.cli.help import organise_help
from torchseq.cli.presets import apply_preset, preset_help, preset_name
from torchseq.cli.report import log_training, write_train_json
from torchseq.cli.results import TrainRun
from torchseq.cli.run_warnings import WarningLog
from torchseq.cli.runs import (
    config_file_defaults,
    config_text,
    progress_wanted,
    run_folder,
    run_main,
    to_jsonable,
)
from torchseq.demo import make_demo
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.neural.memory import seqslam_template_bytes
from torchseq.sources import FrameSelection, is_event_file, load_traverse, load_traverse_sizes
from torchseq.versions import VERSIONS_KEY, versions

PROG = "torchseq train"  # set by main() to the name the user ran


@dataclass
class TrainConfig(EventFlags):
    """What a training run depends on besides the model's own :class:`NeuralConfig`."""

    reference: str | None = None
    neural_preset: str | None = None
    out: str | None = None
    overwrite: bool = False
    start: int = 0
    stop: int | None = None
    frame_step: int = 1
    max_frames: int | None = None
    demo_frames: int = 200
    demo_seed: int = 0
    device: str = "cpu"
    tensorboard: bool = True
    progress: bool = True
    export: bool = False
    export_query: str | None = None
    export_ground_truth: str | None = None
    export_frame_size: str | None = None
    export_chip_report: bool = False
    export_timed_spiking: bool = False


HELP = {
    "reference": "reference traverse: image folder, video, frame array (.npy/.npz) or event file; "
                 "default: the built-in demo route",
    "neural_preset": preset_help("the model (NeuralConfig) flags"),
    "out": "output folder of this run (default: a new runs/train-<UTC time>)",
    "overwrite": "replace a previous run's --out folder instead of refusing",
    "demo_frames": "demo: reference frames",
    "demo_seed": "demo: random seed of the route",
    "device": "cpu, cuda or auto",
    "tensorboard": "write TensorBoard logs",
    "progress": "show progress bars",
    "start": "first reference frame to use (0-based)",
    "stop": "reference frame index to stop before",
    "frame_step": "use every N-th reference frame from --start",
    "max_frames": "use at most this many reference frames",
    "export": "after training, export ONNX and integer files to OUT/export and validate them",
    "export_query": "query traverse to validate the export on (default: the model's own "
                    "reference, as python -m torchseq.export)",
    "export_ground_truth": "ground truth of --export-query (CSV or .npy, see eval.py)",
    "export_chip_report": "with --export: also check the spiking model against each chip's "
                          "limits (torchseq export --chip-report)",
    "export_timed_spiking": "with --export: also run the timed spiking model on the query "
                            "(torchseq export --timed-spiking)",
    "export_frame_size": "camera frame size HxW the integer device takes (default: the "
                         "reference's frame size)",
}
LIMITS = {"demo_frames": (2, 20_000), "demo_seed": (0, 2 ** 32 - 1), "start": (0, 2 ** 40),
          "stop": (1, 2 ** 40), "frame_step": (1, 2 ** 40), "max_frames": (1, 2 ** 40)}


def build_parser() -> argparse.ArgumentParser:
    """The train.py flags: TrainConfig, then every NeuralConfig field."""
    parser = Parser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("--config", help="replay a run: its config.json gives the defaults, "
                        "flags override them")
    add_config_flags(parser, TrainConfig, HELP, skip=EventFlags)
    add_config_flags(parser.add_argument_group("event files"), EventFlags, EVENT_HELP)
    add_config_flags(parser.add_argument_group("model (NeuralConfig)"), NeuralConfig, {},
                     prefix="neural_")
    organise_help(parser, cli_help.TRAIN, cli_help.TRAIN_EXAMPLES)
    return parser


def parse_args(argv: list[str] | None) -> tuple[TrainConfig, NeuralConfig]:
    """Flags -> (:class:`TrainConfig`, :class:`NeuralConfig`), every number range-checked."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    pre, _ = parser.parse_known_args(argv)
    replayed = frozenset()
    if pre.config:
        replayed = config_file_defaults(parser, pre.config, {"train": "", "model": "neural_"})
    args = parser.parse_args(argv)
    cfg = config_from_args(TrainConfig, args)
    check_ranges(cfg, LIMITS)
    parse_size(cfg.export_frame_size)
    if cfg.neural_preset is not None:
        cfg.neural_preset = preset_name(cfg.neural_preset)
    neural = {"neural_" + f.name: f.name for f in dataclasses.fields(NeuralConfig)}
    ncfg = apply_preset(config_from_args(NeuralConfig, args, "neural_"), cfg.neural_preset,
                        frozenset(neural[d] for d in given_flags(parser, argv, set(neural))),
                        frozenset(neural[d] for d in replayed if d in neural),
                        parser.get_default("neural_preset"))
    check_neural(ncfg, "neural_")
    return cfg, ncfg.validate()


def export_query(cfg: TrainConfig, events):
    """``--export-query`` for the export: an event file becomes frames made as the reference's.

    The export reads a path with default event settings; the model learnt frames made with
    this run's (window, frame size, mode, filters), so an event query is read here with them.
    """
    path = cfg.export_query
    if path is None or not Path(path).is_file():
        return path  # the export names a missing query itself
    try:
        if not is_event_file(path):
            return path
        frames = load_traverse(path, events=events, progress=cfg.progress)
    except (ValueError, OSError) as err:
        raise UsageError(f"--export-query {path}: {str(err).splitlines()[0]}") from err
    print(f"export: validation query {path}: {len(frames)} event frames made with the "
          f"reference's event settings")
    return frames


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """Entry point; returns the exit code (errors raise, see :func:`torchseq.cli.flags.run_main`).

    Args:
        argv: the flags (None: ``sys.argv[1:]``).
        prog: the command's name in messages (``eval.py``, ``torchseq eval``).
    """
    global PROG
    PROG = prog or PROG
    argv = list(sys.argv[1:] if argv is None else argv)
    cfg, ncfg = parse_args(argv)
    cfg.progress = cfg.progress and progress_wanted(argv)  # no bars in a redirected log
    given = given_flags(build_parser(), argv, EVENT_FIELDS)  # event flags typed, any value
    notes = WarningLog(PROG)  # the library's warnings, once each, also in train.json
    with notes.capture():
        return train(cfg, ncfg, notes, given)


def train(cfg: TrainConfig, ncfg: NeuralConfig, notes: WarningLog,
          given: frozenset = frozenset()) -> int:
    """One training run of checked settings (and its export); warnings go to ``notes``.

    ``given``: the event fields the command line gave, whatever their value.
    """
    device = resolve_device(cfg.device)
    events = event_frame_options(cfg)
    if events.members_ms is not None:  # the neural model learns one frame per window
        raise UsageError("--window-ms with several windows (a temporal-window ensemble) is for "
                         "eval's SeqSLAM; give train one window")
    orphans = [f"--{k.replace('_', '-')}" for k in ("export_query", "export_ground_truth",
                                                     "export_frame_size", "export_chip_report",
                                                     "export_timed_spiking")
               if getattr(cfg, k) not in (None, False)]
    if orphans and not cfg.export:  # they would be silently ignored
        raise UsageError(f"{', '.join(orphans)} set{'s' if len(orphans) == 1 else ''} up the "
                         f"export, which runs only with --export; add it or drop them")
    check_event_flags_apply(cfg, {"--reference": cfg.reference,
                                  **({"--export-query": cfg.export_query}
                                     if cfg.export and cfg.export_query else {})},
                            given)
    select = frame_selection(cfg.start, cfg.stop, cfg.frame_step, cfg.max_frames)
    out = run_folder(cfg.out, "train", cfg.overwrite)
    if cfg.reference is None:
        if select != FrameSelection():
            raise UsageError("--start/--stop/--frame-step/--max-frames select frames of "
                             "--reference, not of the demo route (use --demo-frames)")
        source = make_demo(n_reference=cfg.demo_frames, seed=cfg.demo_seed).reference
        reference = {"source": "demo", "demo_frames": cfg.demo_frames,
                     "demo_seed": cfg.demo_seed}
    else:
        source = cfg.reference
        reference = {"source": str(Path(cfg.reference).resolve()),
                     "events": to_jsonable(events), "select": to_jsonable(select)}
    try:  # shrunk frame by frame to the model's input size: long videos fit in memory
        loaded, info = load_traverse_sizes(source, {"input": ncfg.input_size}, events,
                                           cfg.progress, select)
    except (ValueError, OSError) as err:
        raise UsageError(f"reference traverse {cfg.reference}: {str(err).splitlines()[0]}"
                         ) from err
    frames = loaded["input"]
    reference.update(n_frames=info["n_frames"], frame_size=info["frame_size"])
    model = NeuralSeqSLAM(ncfg, device=device)
    start = time.perf_counter()
    log = model.fit(frames, progress=cfg.progress)
    seconds = time.perf_counter() - start
    model.save(out / "model.pt", extra={"train_config": to_jsonable(cfg),
                                        "reference": reference, "self_check": log.self_check})
    write_text(out / "config.json", config_text({"train": cfg, "model": ncfg,
                                                 VERSIONS_KEY: versions()}) + "\n")
    run = TrainRun(reference=reference, neural_preset=preset_name(cfg.neural_preset),
                   fit_seconds=seconds, versions=versions(),
                   model_bytes=int(model.model_bytes()),
                   seqslam_template_bytes=seqslam_template_bytes(len(frames)),
                   n_units=int(model.n_units), self_check=log.self_check)
    write_train_json(run, notes, out)
    log_training(cfg, ncfg, model, log, out)
    print(f"trained on {len(frames)} reference frames in {seconds:.2f} s "
          f"({1e3 * seconds / len(frames):.2f} ms/frame); model {model.model_bytes()} bytes; "
          f"wrote {out / 'model.pt'}")
    if cfg.export:
        from torchseq.cli.export import summary_lines
        from torchseq.export.checkpoint import export_checkpoint

        ok = export_checkpoint(out / "model.pt", out / "export",
                               query=export_query(cfg, events),
                               ground_truth=cfg.export_ground_truth,
                               frame_size=parse_size(cfg.export_frame_size),
                               progress=cfg.progress, chips=cfg.export_chip_report,
                               timed=cfg.export_timed_spiking)
        for line in summary_lines(out / "export"):
            print(f"export: {line}")
        run.export_passed = bool(ok)
    write_train_json(run, notes, out)
    if cfg.export and not ok:
        print(f"{PROG}: export validation failed, see {out / 'export' / 'validation.json'}",
              file=sys.stderr)
        return 1
    return 0


def cli(argv: list[str] | None = None, prog: str | None = None) -> int:
    """Run as a command: expected failures become one ``prog: error:`` line and exit 2."""
    prog = prog or PROG
    return run_main(lambda a: main(a, prog), prog, argv)


if __name__ == "__main__":
    raise SystemExit(cli())

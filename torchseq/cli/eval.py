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
import sys
from pathlib import Path

import torch

import torchseq.cli.help as cli_help
from torchseq.atomic import write_json, write_text
from torchseq.cli.engines import candidate_check, run_engines, single_frame_baseline
from torchseq.cli.errors import UsageError
from torchseq.cli.eval_settings import (
    ENGINES,
    HELP,
    LIMITS,
    MAX_DEMO_QUERY,
    SEQSLAM_FIELDS,
    SEQSLAM_LIMITS,
    EvalConfig,
    Settings,
    config_dict,
)
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
    changed_fields,
    check_neural,
    check_ranges,
    config_from_args,
    frame_selection,
    given_flags,
    resolve_device,
)
from torchseq.cli.help import organise_help
from torchseq.cli.inputs import load_data, load_model, needed_sizes
from torchseq.cli.map import check_map_flags, map_seqslam_config
from torchseq.cli.presets import apply_preset, preset_config, preset_name
from torchseq.cli.report import engine_metrics, report, summary_line
from torchseq.cli.results import EvalOutcome
from torchseq.cli.run_warnings import WarningLog, warning_list
from torchseq.cli.runs import (
    Notes,
    config_file_defaults,
    config_text,
    mark_complete,
    mark_incomplete,
    progress_wanted,
    run_folder,
    run_main,
    sweep_grid,
)
from torchseq.neural import NeuralConfig
from torchseq.seqslam import SeqSLAMConfig
from torchseq.versions import VERSIONS_KEY, versions

PROG = "torchseq eval"  # set by main() to the name the user ran


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
    speed = None
    if cfg.preset is not None:
        two_channel = str(cfg.event_mode).replace("_", "-") == "two-channel"
        overrides = preset_overrides(cfg.preset, scfg, two_channel, seqslam_typed)
        if cfg.preset == "events" and "speed_ratio" not in overrides and cfg.map is None:
            speed = overrides  # the ratio comes from the traverses once they are read
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
    return Settings(cfg, scfg, ncfg, speed_from_data=speed)


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
    alignment = [f"--{k.replace('_', '-')}" for k in ("gt_offset", "gt_scale")
                 if getattr(cfg, k) != getattr(default, k)]
    if alignment and (cfg.tolerance is None or cfg.ground_truth is not None
                      or cfg.dataset is not None):
        raise UsageError(f"{', '.join(alignment)} shape{'s' if len(alignment) == 1 else ''} "
                         f"index alignment (--tolerance alone); drop "
                         f"{'it' if len(alignment) == 1 else 'them'} or the ground-truth file")
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
    try:
        return SeqSLAMConfig.preset(name, **preset_overrides(name, flags, two_channel, typed))
    except ValueError as err:
        raise UsageError(f"--preset: {err}") from None


def preset_overrides(name: str, flags: SeqSLAMConfig, two_channel: bool = False,
                     typed: frozenset[str] = frozenset()) -> dict:
    """The fields :func:`seqslam_preset` lays over the preset (flags given, event frame size)."""
    changed = changed_fields(flags, SeqSLAMConfig())
    changed.update({field: getattr(flags, field) for field in typed})  # typed flags win
    if name == "events" and two_channel and "image_size" not in changed:
        h, w = SeqSLAMConfig.events().image_size
        changed["image_size"] = (h, 2 * w)
    return changed


def speed_from_data(s: Settings, ref, query, source: dict) -> Settings:
    """``--preset events`` without ``--speed-ratio``: the ratio from the traverses' lengths.

    Both traverses cover one route, in windows of one length, so reference windows per
    query window is their count ratio (the durations' ratio). Said on stderr, recorded in
    ``source`` (metrics.json ``inputs.speed_ratio``) and in the run's config; ``--speed-ratio``
    overrides it.
    """
    if s.speed_from_data is None:
        return s
    ratio = len(ref) / len(query)
    what = "window" if ref.info.get("events") and query.info.get("events") else "frame"
    scfg = SeqSLAMConfig.events(**{**s.speed_from_data, "speed_ratio": ratio})
    source["speed_ratio"] = {"value": ratio, "from": f"{what} counts {len(ref)} / {len(query)}"}
    print(f"{PROG}: speed ratio {ratio:.3f} reference per query {what}, from the {what} counts "
          f"({len(ref)} / {len(query)}), ds {scfg.ds}; --speed-ratio overrides", file=sys.stderr)
    return dataclasses.replace(s, seqslam=scfg)


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
    s, points = speed_from_data(s, ref, query, source), [
        speed_from_data(p, ref, query, {}) for p in points]
    if grid:
        code = sweep(s, points, grid, specs, ref, query, gt, source, device, out, notes, model)
        mark_complete(out)
        return code
    results = run_engines(s, ref, query, device, notes, model)
    if "seqslam" in results:
        candidate_check(s, results["seqslam"], ref, query, gt, device, notes)
    # the baseline needs the reference's descriptors: a map run reads none (sharded maps)
    seqslam_run = results.get("seqslam")  # a SeqSLAMRun: its difference matrix, if kept
    difference = None if seqslam_run is None else seqslam_run.difference
    single = (single_frame_baseline(s, ref, query, device, difference)
              if gt is not None and s.run.map is None else None)
    if seqslam_run is not None:
        seqslam_run.difference = None  # ranked: no longer needed
    summary = report(EvalOutcome(s, ref, query, gt, source, results, out, single), notes)
    mark_complete(out)
    for name in results:
        print(summary_line(name, summary[name]))
    print(f"wrote {out / 'metrics.json'}, {out / 'matches.csv'} and plots to {out}")
    return 0


def cli(argv: list[str] | None = None, prog: str | None = None) -> int:
    """Run as a command: expected failures become one ``prog: error:`` line and exit 2."""
    prog = prog or PROG
    return run_main(lambda a: main(a, prog), prog, argv)


if __name__ == "__main__":
    raise SystemExit(cli())

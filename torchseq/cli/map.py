"""``torchseq map build|verify``, and what ``torchseq eval --map`` needs from a map.

``torchseq map build --reference REF --out MAP`` computes the reference's SeqSLAM
descriptors once and writes them, their FAISS index, the settings and the reference's record
as a reference map (:mod:`torchseq.maps`). ``torchseq eval --map MAP --query Q`` then matches
against the map without reading the reference's images; ``--shards N`` spreads the map over
``N`` Ray actors (:mod:`torchseq.seqslam.sharded`).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from dataclasses import dataclass
from pathlib import Path

import torch

from torchseq.cli.errors import UsageError
from torchseq.cli.event_options import EVENT_HELP, EventFlags, event_frame_options
from torchseq.cli.flags import (
    Parser,
    add_config_flags,
    changed_fields,
    check_ranges,
    config_from_args,
    docstring_help,
    frame_selection,
)
from torchseq.cli.results import SeqSLAMRun
from torchseq.cli.runs import progress_wanted, run_main, to_jsonable
from torchseq.maps import MapError, ReferenceMap, build_map
from torchseq.maps.build import DEFAULT_SHARD_SIZE
from torchseq.maps.format import DESCRIPTOR_FIELDS
from torchseq.seqslam import SeqSLAMConfig
from torchseq.seqslam.ann_index import INDEX_KINDS

PROG = "torchseq map"
FRAMES_PER_CHUNK = 4096  # frames turned into descriptors at a time


@dataclass
class MapBuildConfig(EventFlags):
    """What ``torchseq map build`` needs."""

    reference: str | None = None
    out: str | None = None
    shard_size: int = DEFAULT_SHARD_SIZE
    index: str = "auto"
    image_size: tuple[int, int] = (32, 64)
    patch_size: int = 8
    preprocessing: str = "torchseq"
    metric: str = "l1"
    start: int = 0
    stop: int | None = None
    frame_step: int = 1
    max_frames: int | None = None
    overwrite: bool = False
    progress: bool = True


HELP = {
    "reference": "reference traverse: image folder, video, frame array (.npy/.npz) or event "
                 "file (required)",
    "out": "the map folder to write (required)",
    "shard_size": "places per shard file (the unit --shards spreads over actors)",
    "index": f"FAISS index kind for candidate mode: one of {', '.join(INDEX_KINDS)} (auto: "
             f"flat up to 5,000 places, ivf above)",
    "image_size": "SeqSLAM image size HxW after resizing",
    "start": "first reference frame to use (0-based)",
    "stop": "frame index to stop before",
    "frame_step": "use every N-th frame from --start",
    "max_frames": "use at most this many frames",
    "overwrite": "replace an existing map at --out",
    "progress": "show progress bars",
}
LIMITS = {"shard_size": (1, 2 ** 40), "patch_size": (0, 4096), "start": (0, 2 ** 40),
          "stop": (1, 2 ** 40), "frame_step": (1, 2 ** 40), "max_frames": (1, 2 ** 40)}


def build_parser(prog: str) -> argparse.ArgumentParser:
    """``torchseq map build`` flags (MapBuildConfig) and ``torchseq map verify MAP``."""
    parser = Parser(prog=prog, description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    build = sub.add_parser("build", help="compute a reference's descriptors and write a map")
    add_config_flags(build, MapBuildConfig, {**docstring_help(SeqSLAMConfig), **HELP},
                     skip=EventFlags)
    add_config_flags(build.add_argument_group("event files"), EventFlags, EVENT_HELP)
    verify = sub.add_parser("verify", help="check every file of a map (sizes, checksums)")
    verify.add_argument("map", help="the map folder")
    return parser


def reference_record(cfg: MapBuildConfig, info: dict) -> dict:
    """The map's record of its reference: source, selection, events, frames, frame size."""
    record = {"source": str(Path(cfg.reference).resolve()),
              "select": to_jsonable(frame_selection(cfg.start, cfg.stop, cfg.frame_step,
                                                    cfg.max_frames)),
              "n_frames": int(info["n_frames"]), "frame_size": list(info["frame_size"])}
    if info.get("events"):
        record["events"] = to_jsonable(event_frame_options(cfg))
    return record


def descriptors_of(frames: torch.Tensor, config: SeqSLAMConfig) -> torch.Tensor:
    """``(T, h, w)`` frames -> ``(T, D)`` SeqSLAM descriptors, a chunk of frames at a time."""
    from torchseq.seqslam import SeqSLAM

    engine = SeqSLAM(config)
    return torch.cat([engine.descriptors(frames[i:i + FRAMES_PER_CHUNK])
                      for i in range(0, len(frames), FRAMES_PER_CHUNK)])


def run_build(cfg: MapBuildConfig) -> int:
    """``torchseq map build``: load, describe, write."""
    from torchseq.sources import load_traverse_sizes

    if cfg.reference is None or cfg.out is None:
        raise UsageError("give --reference (the traverse) and --out (the map folder)")
    check_ranges(cfg, LIMITS)
    if cfg.index not in INDEX_KINDS:
        raise UsageError(f"--index must be one of {', '.join(INDEX_KINDS)}, got {cfg.index!r}")
    try:
        config = SeqSLAMConfig(**{k: getattr(cfg, k) for k in DESCRIPTOR_FIELDS}).validate()
    except ValueError as err:
        raise UsageError(str(err)) from None
    select = frame_selection(cfg.start, cfg.stop, cfg.frame_step, cfg.max_frames)
    key = "x".join(map(str, config.image_size))
    try:
        frames, info = load_traverse_sizes(cfg.reference, {key: tuple(config.image_size)},
                                           event_frame_options(cfg), cfg.progress, select)
    except (ValueError, OSError) as err:
        raise UsageError(f"reference traverse {cfg.reference}: {str(err).splitlines()[0]}") \
            from err
    desc = descriptors_of(frames[key], config)
    m = build_map(desc, cfg.out, config, cfg.shard_size, cfg.index,
                  record=reference_record(cfg, info), overwrite=cfg.overwrite)
    index = m.manifest["index"]
    size = sum(s.bytes for s in m.shards) + (index["bytes"] if index else 0)
    print(f"wrote map {cfg.out}: {m.n_places} places x {m.dim} ({m.dtype}), "
          f"{len(m.shards)} shard(s) of up to {m.shard_size}, index "
          f"{index['kind'] if index else 'none'}, {size / 1e6:.1f} MB")
    return 0


def run_verify(path: str) -> int:
    """``torchseq map verify MAP``: check every file; print what the map holds."""
    m = ReferenceMap(path)
    checked = m.verify()
    src = m.reference.get("source", "?")
    print(f"{path}: map format {m.manifest['format']}/{m.manifest['version']}, "
          f"{m.n_places} places x {m.dim} ({m.dtype}), {len(m.shards)} shard(s), index "
          f"{(m.manifest['index'] or {}).get('kind', 'none')}; reference {src}: intact "
          f"({checked} checked)")
    return 0


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """Entry point of ``torchseq map``; returns the exit code (errors raise)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser(prog or PROG).parse_args(argv)
    if args.command == "verify":
        return run_verify(args.map)
    cfg = config_from_args(MapBuildConfig, args)
    cfg.progress = cfg.progress and progress_wanted(argv)  # no bars in a redirected log
    return run_build(cfg)


def cli(argv: list[str] | None = None, prog: str | None = None) -> int:
    """Run as a command: expected failures become one ``prog: error:`` line and exit 2."""
    prog = prog or PROG
    return run_main(lambda a: main(a, prog), prog, argv)


# ----------------------------------------------------------------------------- eval --map


def check_map_flags(cfg, typed_engine: bool = False) -> None:
    """Refuse eval flags that do not go with ``--map`` / ``--shards`` / ``--ray-address``."""
    if cfg.map is None:
        if cfg.shards is not None:
            raise UsageError("--shards spreads a reference map over Ray actors; give --map")
        if cfg.ray_address is not None:
            raise UsageError("--ray-address needs --map and --shards")
        return
    if cfg.shards is None and cfg.ray_address is not None:
        raise UsageError("--ray-address needs --shards (without it the map is matched here)")
    if cfg.reference is not None:
        raise UsageError("--map replaces --reference (the map holds the reference's "
                         "descriptors); drop one of them")
    if cfg.query is None:
        raise UsageError("--map needs --query")
    if cfg.engine == "neural":
        raise UsageError("--map holds SeqSLAM descriptors: the neural engine needs the "
                         "reference's frames (--reference)")
    selection = [f"--{k.replace('_', '-')}" for k, v in
                 (("start", cfg.start != 0), ("stop", cfg.stop is not None),
                  ("frame_step", cfg.frame_step != 1), ("max_frames", cfg.max_frames is not None))
                 if v]
    if selection:
        raise UsageError(f"{', '.join(selection)} select reference and query frames together; "
                         f"with --map the reference was fixed when the map was built")


def map_seqslam_config(path: str, scfg: SeqSLAMConfig) -> SeqSLAMConfig:
    """This run's SeqSLAM config with the map's descriptor settings (changed flags refused)."""
    try:
        built = ReferenceMap(path).config
    except MapError as err:
        raise UsageError(f"--map {err}") from None
    changed = changed_fields(scfg, SeqSLAMConfig())
    for key in DESCRIPTOR_FIELDS:
        if key in changed and getattr(scfg, key) != getattr(built, key):
            flag = "--" + key.replace("_", "-")
            raise UsageError(f"{flag} {getattr(scfg, key)!r} differs from the map's "
                             f"{getattr(built, key)!r} (its descriptors were built with it); "
                             f"drop {flag} or build another map")
    return dataclasses.replace(scfg, **{k: getattr(built, k) for k in DESCRIPTOR_FIELDS})


def map_traverse(path: str, traverse_cls):
    """The reference side of an eval from a map: its record, no frames, no thumbnails."""
    m = ReferenceMap(path)
    rec = m.reference
    size = rec.get("frame_size") or list(m.config.image_size)
    info = {"n_frames": m.n_places, "frame_size": [int(v) for v in size],
            "indices": list(range(m.n_places)), "n_total": m.n_places, "map": str(path)}
    return traverse_cls({}, None, info)


def run_seqslam_map(s, query, device, progress: bool) -> SeqSLAMRun:
    """SeqSLAM against a map: exact mode, candidate mode with its index, or sharded on Ray."""
    from torchseq.seqslam import SeqSLAM
    from torchseq.seqslam.candidates import CandidateSeqSLAM, resolve_candidates

    cfg, scfg = s.run, s.seqslam
    m = ReferenceMap(cfg.map)
    engine = SeqSLAM(scfg, device=device)
    q = engine.descriptors(query.at(scfg.image_size))
    k = resolve_candidates(scfg, m.n_places, len(q))
    sharding = None
    if cfg.shards is not None:
        from torchseq.seqslam.sharded import ShardedSeqSLAM

        if not k:
            raise UsageError("--shards runs candidate mode: give --candidates K (K >= 1)")
        with ShardedSeqSLAM(cfg.map, scfg, cfg.shards, address=cfg.ray_address) as sharded:
            result = sharded.match_descriptors(q)
            sharding = {"shards": cfg.shards, "restarted_shards": sharded.restarted()}
    elif k:
        ref = m.descriptors()
        result = CandidateSeqSLAM(ref, scfg, k, index=m.index(), device=device).\
            match_descriptors(q, progress)
    else:
        result = engine.match_descriptors(m.descriptors(), q, progress=progress)
    matrix = result.preview if result.preview is not None else result.enhanced
    return SeqSLAMRun(matches=result.matches, ranked=result.ranked, ranked_score=None,
                      matrix=matrix, matrix_shape=(m.n_places, len(query)),
                      matrix_reduced=result.enhanced is None,
                      seconds=result.seconds["total"], parameters=to_jsonable(scfg),
                      kernels=to_jsonable(result.kernels) or None, sharding=sharding)

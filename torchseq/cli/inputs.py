"""An eval run's inputs: traverses at the sizes its engines read, ground truth, checkpoint.

:func:`load_data` reads the reference and query (the demo, a ``--dataset``, files or a
``--map``), each shrunk frame by frame to every size an engine reads (:class:`Traverse`), and
the ground truth over the selected frames.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from torchseq.cli.errors import UsageError
from torchseq.cli.eval_settings import EvalConfig, Settings
from torchseq.cli.event_options import event_frame_options
from torchseq.cli.flags import frame_selection, resolve_device
from torchseq.cli.map import map_traverse
from torchseq.cli.runs import Notes, warn
from torchseq.cli.traverse import Traverse, size_key
from torchseq.demo import make_demo
from torchseq.descriptors import (
    DescriptorError,
    describe,
    descriptor_kind,
    load_descriptors,
    load_hook,
)
from torchseq.ground_truth import (
    GroundTruthRanges,
    alignment_ranges,
    alignment_scale,
    load_ground_truth,
)
from torchseq.sources import FrameSelection, load_traverse_sizes

PROG = "torchseq eval"  # names warnings given a plain list (a run's WarningLog names itself)


def load_model(path: str, device=None):
    """Read a Neural SeqSLAM checkpoint for a script; any failure is a :class:`UsageError`."""
    from torchseq.neural import NeuralSeqSLAM

    try:
        return NeuralSeqSLAM.load(path, map_location=device)
    except Exception as err:  # noqa: BLE001 - a hostile checkpoint must not end in a traceback
        text = str(err).splitlines()[0] if str(err) else ""
        where = "" if str(path) in text else f"{path}: "
        raise UsageError(f"checkpoint {where}{text or 'unreadable'} "
                         f"({type(err).__name__})") from err


THUMBNAIL = 160  # longer side of the frames kept for plots


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
        gt = alignment_ranges(n_ref, n_query, cfg.tolerance, cfg.gt_offset, cfg.gt_scale)
        scale = cfg.gt_scale or alignment_scale(n_ref, n_query, cfg.gt_offset)
        source["ground_truth"] = (f"index alignment, tolerance {cfg.tolerance}, scale "
                                  f"{scale:.4g}" + (f", offset {cfg.gt_offset}"
                                                    if cfg.gt_offset else ""))
        if cfg.gt_scale is None and n_ref != n_query:
            warn(PROG, f"query has {n_query} frames, reference {n_ref}: --tolerance stretches "
                 f"the query over the whole reference ({scale:.3f} reference frames per query "
                 f"frame); if it covers a part, give --gt-scale and --gt-offset or "
                 f"--ground-truth", notes)
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

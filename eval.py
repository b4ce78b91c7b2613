"""Run a query traverse through torchseq's engines and report place-recognition metrics.

With no arguments it runs on the built-in demo route. Writes ``OUT/metrics.json``,
``OUT/matches.csv``, PNG plots, ``OUT/config.json`` and TensorBoard logs in ``OUT/tensorboard``.
"""

from __future__ import annotations

import argparse
import csv
import io
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchseq import metrics, plots
from torchseq.atomic import write_json, write_text
from torchseq.demo import make_demo
from torchseq.frontend import (
    UsageError,
    add_config_flags,
    config_from_args,
    config_text,
    event_options,
    load_frames,
    resolve_device,
    run_main,
    to_jsonable,
)
from torchseq.ground_truth import alignment_ground_truth, load_ground_truth
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
from torchseq.seqslam.candidates import evaluated_dense

ENGINES = ("seqslam", "neural", "both")


@dataclass
class EvalConfig:
    """Everything an evaluation run depends on; saved beside its outputs."""

    reference: str | None = None
    query: str | None = None
    ground_truth: str | None = None
    tolerance: float | None = None
    engine: str = "both"
    checkpoint: str | None = None
    out: str = "runs/eval"
    ds: int = 10
    vmin: float = 0.8
    vmax: float = 1.2
    speed_ratio: float | None = None
    speed_tolerance: float = 0.2
    match_at: str | None = None
    metric: str = "l1"
    image_size: str = "32x64"
    patch_size: int = 8
    enhance_window: int = 10
    rwindow: int = 10
    candidates: int | None = None
    window_ms: float = 10.0
    event_count: int | None = None
    frame_size: str | None = None
    demo_frames: int = 200
    demo_speed: float = 0.8
    seed: int = 0
    device: str = "cpu"
    tensorboard: bool = True
    progress: bool = True


HELP = {
    "reference": "reference traverse: image folder, video, frame array (.npy/.npz) or event file "
                 "(.aedat, .aedat4, .raw, event .npy/.npz, .csv); default: the built-in demo",
    "query": "query traverse, same kinds as --reference (required with --reference)",
    "ground_truth": "ground truth: CSV 'query,references' or (reference x query) 0/1 .npy matrix",
    "tolerance": "ground truth by index alignment: admissible distance in reference frames",
    "engine": f"engine to run: one of {', '.join(ENGINES)}",
    "checkpoint": "neural model checkpoint (model.pt from train.py); without it the neural "
                  "engine is trained on the reference first",
    "out": "output folder",
    "ds": "SeqSLAM sequence length in frames (rounded up to even)",
    "vmin": "SeqSLAM slowest trajectory slope, reference frames per query frame",
    "vmax": "SeqSLAM fastest trajectory slope",
    "speed_ratio": "known speed ratio (reference frames per query frame): centres the velocity "
                   "range on it, overriding --vmin/--vmax",
    "speed_tolerance": "fractional width of the velocity range around --speed-ratio",
    "match_at": "SeqSLAM reported place: 'start' (start + ds/2, OpenSeqSLAM) or 'trajectory' "
                "(where the best trajectory crosses the query centre); default: trajectory "
                "with --speed-ratio, else start",
    "metric": "frame difference: l1 (OpenSeqSLAM), l2 or cosine",
    "image_size": "SeqSLAM image size HxW after resizing",
    "patch_size": "patch normalisation side in pixels (0 disables it)",
    "enhance_window": "local contrast enhancement window R in reference frames",
    "rwindow": "uniqueness exclusion window Rwindow in reference frames",
    "candidates": "SeqSLAM candidate mode: score only trajectories through the K nearest "
                  "references of each query (FAISS index); 0 = exact all-pairs; default: exact "
                  "up to 2**31 reference x query pairs",
    "window_ms": "event files: accumulation window in milliseconds",
    "event_count": "event files: events per frame instead of a time window",
    "frame_size": "event files: downsample frames to HxW by area pooling (e.g. 16x16)",
    "demo_frames": "demo: reference frames",
    "demo_speed": "demo: query speed relative to the reference",
    "seed": "random seed (demo data and neural model)",
    "device": "cpu, cuda or auto",
    "tensorboard": "write TensorBoard logs",
    "progress": "show progress bars",
}


def parse_args(argv: list[str] | None) -> EvalConfig:
    """Flags -> :class:`EvalConfig`."""
    parser = argparse.ArgumentParser(prog="eval.py", description=__doc__)
    add_config_flags(parser, EvalConfig, HELP)
    return config_from_args(EvalConfig, parser.parse_args(argv))


def load_data(cfg: EvalConfig):
    """Reference and query frames plus ``(R, Q)`` ground truth (or None) and a description."""
    events = event_options(cfg.window_ms, cfg.event_count, cfg.frame_size)
    if cfg.reference is None and cfg.query is None:
        demo = make_demo(n_reference=cfg.demo_frames, speed=cfg.demo_speed, seed=cfg.seed)
        ref, query, gt = demo.reference, demo.query, demo.ground_truth
        source = {"reference": "demo", "query": "demo", "ground_truth": "demo (exact)"}
    elif cfg.reference is None or cfg.query is None:
        raise UsageError("give both --reference and --query (or neither, for the demo)")
    else:
        ref = load_frames(cfg.reference, "reference", events, cfg.progress)
        query = load_frames(cfg.query, "query", events, cfg.progress)
        gt, source = None, {"reference": cfg.reference, "query": cfg.query}
    if cfg.ground_truth is not None and cfg.tolerance is not None:
        raise UsageError("give --ground-truth or --tolerance, not both")
    if cfg.ground_truth is not None:
        gt = load_ground_truth(cfg.ground_truth, len(ref), len(query))
        source["ground_truth"] = cfg.ground_truth
    elif cfg.tolerance is not None:
        gt = alignment_ground_truth(len(ref), len(query), cfg.tolerance)
        source["ground_truth"] = f"index alignment, tolerance {cfg.tolerance}"
    return ref, query, gt, source


def run_seqslam(cfg: EvalConfig, ref, query, device):
    """Classic SeqSLAM: matches, ranked candidates, the matrix to plot, seconds, parameters."""
    scfg = SeqSLAMConfig(
        image_size=cfg.image_size, patch_size=cfg.patch_size, metric=cfg.metric,
        enhance_window=cfg.enhance_window, ds=cfg.ds, vmin=cfg.vmin, vmax=cfg.vmax,
        speed_ratio=cfg.speed_ratio, speed_tolerance=cfg.speed_tolerance, rwindow=cfg.rwindow,
        match_at=cfg.match_at, candidates=cfg.candidates)
    result = SeqSLAM(scfg, device=device).match(ref, query, progress=cfg.progress)
    matrix = result.enhanced
    if matrix.is_sparse:  # candidate mode: the evaluated entries only, NaN (blank) elsewhere
        matrix = evaluated_dense(matrix)
    return {"matches": result.matches, "ranked": result.ranked, "matrix": matrix,
            "seconds": result.seconds["total"], "parameters": to_jsonable(scfg)}


def run_neural(cfg: EvalConfig, ref, query, device):
    """Neural SeqSLAM, from a checkpoint or trained on the reference now."""
    from torchseq.neural import NeuralConfig, NeuralSeqSLAM

    start = time.perf_counter()
    if cfg.checkpoint:
        model = NeuralSeqSLAM.load(cfg.checkpoint, map_location=device)
    else:
        model = NeuralSeqSLAM(NeuralConfig(seed=cfg.seed), device=device)
        model.fit(ref, progress=cfg.progress)
    fit_seconds = time.perf_counter() - start
    result = model.run(query, progress=cfg.progress)
    return {"matches": result.matches, "ranked": None, "activity": result.activity,
            "seconds": float(result.seconds),
            "fit_seconds": fit_seconds, "parameters": to_jsonable(model.config),
            "model_bytes": int(model.model_bytes())}


def matches_csv(results: dict) -> str:
    """``engine,query,reference,score`` rows, empty reference and score where no match."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["engine", "query", "reference", "score"])
    for name, r in results.items():
        ref = r["matches"].reference.cpu().numpy()
        score = r["matches"].score.cpu().numpy()
        for q, (i, s) in enumerate(zip(ref, score)):
            w.writerow([name, q, int(i) if i >= 0 else "", f"{s:.6g}" if i >= 0 else ""])
    return buf.getvalue()


def report(cfg: EvalConfig, ref, query, gt, source, results, out: Path) -> dict:
    """Write metrics.json, matches.csv, plots and TensorBoard logs; return the metrics."""
    summary = {"inputs": {**source, "n_reference": len(ref), "n_query": len(query)}}
    curves = {}
    for name, r in results.items():
        m = metrics.evaluate(r["matches"], gt, r["ranked"]) if gt is not None else \
            {"recall_at_1": None, "auc": None, "recall_at_100_precision": None,
             "n_queries": len(r["matches"]), "coverage": metrics.coverage(r["matches"])}
        m.update({k: r[k] for k in ("seconds", "fit_seconds", "model_bytes", "parameters")
                  if k in r})
        summary[name] = m
        if gt is not None:
            curves[name] = metrics.precision_recall_curve(r["matches"], gt)
    write_json(out / "metrics.json", summary)
    write_text(out / "matches.csv", matches_csv(results))
    write_text(out / "config.json", config_text(cfg) + "\n")
    figures = {}
    if "seqslam" in results:
        figures["seqslam_difference_matrix"] = plots.plot_difference_matrix(
            results["seqslam"]["matrix"], results["seqslam"]["matches"], gt,
            "SeqSLAM contrast-enhanced difference matrix")
    if "neural" in results:
        figures["neural_activity"] = plots.plot_activity_raster(
            results["neural"]["activity"], title="neural output activity over the query")
    for name, r in results.items():
        figures[f"{name}_matched_pairs"] = plots.plot_matched_pairs(
            ref, query, r["matches"], gt, title=f"{name}: query (top) and matched reference")
    if curves:
        figures["pr_curve"] = plots.plot_pr_curves(curves)
    images = {k: plots.figure_to_array(f) for k, f in figures.items()}
    for k, f in figures.items():
        plots.save_figure(f, out / f"{k}.png")
    if cfg.tensorboard:
        log_tensorboard(cfg, out, summary, results, gt, images)
    return summary


def log_tensorboard(cfg, out: Path, summary: dict, results: dict, gt, images: dict) -> None:
    """Scalars, images, PR curves and the config in ``OUT/tensorboard``."""
    from torch.utils.tensorboard import SummaryWriter

    with SummaryWriter(log_dir=str(out / "tensorboard")) as tb:
        tb.add_text("config", "```\n" + config_text(cfg) + "\n```")
        for name in results:
            for key, value in summary[name].items():
                if isinstance(value, (int, float)) and value is not None and np.isfinite(value):
                    tb.add_scalar(f"{name}/{key}", value)
        for key, img in images.items():
            tb.add_image(key, img, dataformats="HWC")
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


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    cfg = parse_args(argv)
    if cfg.engine not in ENGINES:
        raise UsageError(f"--engine must be one of {', '.join(ENGINES)}, got {cfg.engine!r}")
    device = resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    ref, query, gt, source = load_data(cfg)
    out = Path(cfg.out)
    runners = {"seqslam": run_seqslam, "neural": run_neural}
    names = ["seqslam", "neural"] if cfg.engine == "both" else [cfg.engine]
    results = {name: runners[name](cfg, ref, query, device) for name in names}
    summary = report(cfg, ref, query, gt, source, results, out)
    for name in names:
        m = summary[name]
        r1 = "n/a (no ground truth)" if m.get("recall_at_1") is None else \
            f"{m['recall_at_1']:.3f}"
        auc = "" if m.get("auc") is None else f", AUC {m['auc']:.3f}"
        print(f"{name}: recall@1 {r1}{auc} over {m['n_queries']} queries "
              f"({m['seconds']:.2f} s)")
    print(f"wrote {out / 'metrics.json'}, {out / 'matches.csv'} and plots to {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main, "eval.py"))

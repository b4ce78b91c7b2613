"""Learn a Neural SeqSLAM model from a reference traverse (one pass, local learning rules).

With no arguments it trains on the built-in demo route. Writes ``OUT/model.pt`` (the
checkpoint carries its config), ``OUT/config.json``, PNG plots and TensorBoard logs in
``OUT/tensorboard``. ``--export`` then writes the deployment files to ``OUT/export``.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from torchseq import plots
from torchseq.atomic import write_text
from torchseq.demo import make_demo
from torchseq.frontend import (
    add_config_flags,
    config_from_args,
    config_text,
    event_options,
    load_frames,
    resolve_device,
    run_main,
    to_jsonable,
)
from torchseq.ground_truth import alignment_ground_truth
from torchseq.neural import NeuralConfig, NeuralFitLog, NeuralSeqSLAM


@dataclass
class TrainConfig:
    """What a training run depends on besides the model's own :class:`NeuralConfig`."""

    reference: str | None = None
    out: str = "runs/train"
    window_ms: float = 10.0
    event_count: int | None = None
    frame_size: str | None = None
    demo_frames: int = 200
    demo_seed: int = 0
    device: str = "cpu"
    tensorboard: bool = True
    progress: bool = True
    export: bool = False
    export_query: str | None = None
    export_ground_truth: str | None = None


HELP = {
    "reference": "reference traverse: image folder, video, frame array (.npy/.npz) or event file; "
                 "default: the built-in demo route",
    "out": "output folder",
    "window_ms": "event files: accumulation window in milliseconds",
    "event_count": "event files: events per frame instead of a time window",
    "frame_size": "event files: downsample frames to HxW by area pooling",
    "demo_frames": "demo: reference frames",
    "demo_seed": "demo: random seed of the route",
    "device": "cpu, cuda or auto",
    "tensorboard": "write TensorBoard logs",
    "progress": "show progress bars",
    "export": "after training, export ONNX and integer files to OUT/export and validate them",
    "export_query": "query traverse to validate the export on (default: the demo query when "
                    "training on the demo, else a replay of the reference)",
    "export_ground_truth": "ground truth of --export-query (CSV or .npy, see eval.py)",
}


def parse_args(argv: list[str] | None) -> tuple[TrainConfig, NeuralConfig]:
    """Flags -> (:class:`TrainConfig`, :class:`NeuralConfig`); every model field is a flag."""
    parser = argparse.ArgumentParser(prog="train.py", description=__doc__)
    add_config_flags(parser, TrainConfig, HELP)
    model = parser.add_argument_group("model (NeuralConfig)")
    add_config_flags(model, NeuralConfig, {})
    args = parser.parse_args(argv)
    return config_from_args(TrainConfig, args), config_from_args(NeuralConfig, args).validate()


def log_training(cfg: TrainConfig, ncfg: NeuralConfig, model: NeuralSeqSLAM,
                 log: NeuralFitLog, out: Path) -> None:
    """Figures as PNG and, with TensorBoard on, scalars, images, histograms and the config."""
    activity = log.evidence
    figures = {
        "reference_activity": plots.plot_activity_raster(
            activity, log.winners, "output activity over the reference (winners marked)"),
        "ring_shift_matrix": plots.plot_matrix(model.ring.shift, "learnt ring shift matrix"),
    }
    images = {k: plots.figure_to_array(f) for k, f in figures.items()}
    for k, f in figures.items():
        plots.save_figure(f, out / f"{k}.png")
    if not cfg.tensorboard:
        return
    from torch.utils.tensorboard import SummaryWriter

    with SummaryWriter(log_dir=str(out / "tensorboard")) as tb:
        text = config_text({"train": cfg, "model": ncfg})
        tb.add_text("config", "```\n" + text + "\n```")
        for k, img in images.items():
            tb.add_image(k, img, dataformats="HWC")
        for name, p in list(model.named_parameters()) + list(model.named_buffers()):
            if p.is_floating_point() and p.numel() > 1:
                tb.add_histogram(f"weights/{name}", p.detach().float().cpu())
        tb.add_histogram("activity/reference", torch.as_tensor(activity).float())
        tb.add_scalar("train/reference_frames", len(activity))
        tb.add_scalar("train/model_bytes", model.model_bytes())


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    cfg, ncfg = parse_args(argv)
    device = resolve_device(cfg.device)
    events = event_options(cfg.window_ms, cfg.event_count, cfg.frame_size)
    demo = None
    if cfg.reference is None:
        demo = make_demo(n_reference=cfg.demo_frames, seed=cfg.demo_seed)
        frames = demo.reference
    else:
        frames = load_frames(cfg.reference, "reference", events, cfg.progress)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    model = NeuralSeqSLAM(ncfg, device=device)
    start = time.perf_counter()
    log = model.fit(frames, progress=cfg.progress)
    seconds = time.perf_counter() - start
    model.save(out / "model.pt", extra={"train_config": to_jsonable(cfg)})
    write_text(out / "config.json", config_text({"train": cfg, "model": ncfg}) + "\n")
    log_training(cfg, ncfg, model, log, out)
    print(f"trained on {len(frames)} reference frames in {seconds:.2f} s "
          f"({1e3 * seconds / len(frames):.2f} ms/frame); model {model.model_bytes()} bytes; "
          f"wrote {out / 'model.pt'}")
    if cfg.export:
        from torchseq.export.cli import export_checkpoint

        if cfg.export_query is not None:
            query, gt = cfg.export_query, cfg.export_ground_truth
        elif demo is not None:
            query, gt = demo.query, demo.ground_truth
        else:  # a replay of the reference: each frame should come back to itself
            query, gt = frames, alignment_ground_truth(len(frames), len(frames), 0)
        ok = export_checkpoint(out / "model.pt", out / "export", query=query, ground_truth=gt)
        if not ok:
            print("train.py: export validation failed, see export/validation.json",
                  file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main, "train.py"))

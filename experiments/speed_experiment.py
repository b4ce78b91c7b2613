"""Event-camera speed experiment: match slower event traverses to a fast one with SeqSLAM.

Runs A (reference), B (66% of A's speed) and C (25%) drive the same route; events are
simulated from rendered views (the demo route, or the corridor reference images), put into
10 ms windows, area-pooled to 16x16 and matched B->A and C->A with classic SeqSLAM (ds=100)
whose velocity search is narrowed around the known speed ratio (reference windows per query
window). Ground truth comes exactly from the route positions. Also evaluates SeqSLAM on the
real event frames of lens-davis128.

Temporal-window ensembles (``--ensemble-ms``, default 5 10 20): frames at each window
length centred on the same 10 ms steps (one pass over the events), matched alone and as an
ensemble (averaged enhanced difference matrices), for B, C and a query whose appearance
changed (``Bdark``: B's speed, frames relit darker with a lighting ramp and sensor noise).

    python experiments/speed_experiment.py --out runs/events_speed
    python experiments/speed_experiment.py --small --out /tmp/x   # the fast test setting
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import matplotlib
import numpy as np
import torch

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from torchseq.demo import make_world, relight, render  # noqa: E402
from torchseq.events import accumulate  # noqa: E402
from torchseq.events.ensemble import accumulate_ensemble, match_ensemble  # noqa: E402
from torchseq.events.runs import ground_truth, simulate_run  # noqa: E402
from torchseq.metrics import evaluate  # noqa: E402
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig  # noqa: E402
from torchseq.sources import load_traverse  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@dataclass
class Config:
    route: str = "demo"
    n_reference: int = 200          # reference (A) windows along the route
    step_px: float = 8.0            # demo: A moves this many pixels per window
    frame_size: tuple = (128, 128)  # demo view (H, W)
    window_ms: float = 10.0
    speeds: dict = field(default_factory=lambda: {"B": 0.66, "C": 0.25})
    pooled: tuple = (16, 16)
    mode: str = "count"             # accumulation mode for the matched frames
    ds: int = 100
    patch_size: int = 8
    enhance_window: int = 10
    speed_tolerance: float = 0.2
    tolerance: float = 2.0          # ground truth, in reference windows
    contrast_threshold: float = 0.2
    threshold_noise: float = 0.03
    noise_rate_hz: float = 1.0
    refractory_us: int = 0
    seed: int = 0
    lens_ds: int = 10
    ensemble_ms: tuple = (5.0, 10.0, 20.0)  # member windows; () skips the ensembles
    # the appearance-changed query: B's speed, relit (gain, gamma, ramp, noise as demo.relight)
    changed: dict = field(default_factory=lambda: {"name": "Bdark", "speed": 0.66, "gain": 0.5,
                                                   "gamma": 1.6, "gradient": 0.3,
                                                   "noise": 6.0})


def route_frames(cfg: Config) -> tuple[np.ndarray, np.ndarray, float]:
    """Views along the route, their positions and A's speed in route units per second."""
    window_s = cfg.window_ms * 1e-3
    if cfg.route == "demo":
        h, w = cfg.frame_size
        length = cfg.n_reference * cfg.step_px
        world = make_world(int(np.ceil(length)) + w + 2, h, cfg.seed)  # make_demo's world
        positions = np.arange(0.0, length + 1.0, 1.0)  # 1 px between rendered views
        return render(world, positions, w), positions, cfg.step_px / window_s
    if cfg.route == "corridor":
        ref = DATA / "corridor" / "ref"
        if not ref.exists():
            raise SystemExit(f"corridor data not found at {ref}")
        frames = load_traverse(ref, progress=False).numpy()
        positions = np.arange(len(frames), dtype=np.float64)
        # A covers the whole corridor in n_reference windows
        return frames, positions, (len(frames) - 1) / (cfg.n_reference * window_s)
    raise SystemExit(f"unknown route {cfg.route!r} (demo or corridor)")


def event_frames(run, cfg: Config, n_windows: int | None = None):
    window_us = int(round(cfg.window_ms * 1000))
    full = accumulate(run.stream, window_us=window_us, mode=cfg.mode, anchor="zero")
    if n_windows is not None:
        full = full[:n_windows]
    pooled = torch.nn.functional.adaptive_avg_pool2d(full[:, None], cfg.pooled)[:, 0]
    return full, pooled


def plot_matrix(path: Path, result, gt: np.ndarray, title: str) -> None:
    ref = result.matches.reference.numpy()
    q = np.nonzero(ref >= 0)[0]
    ok = gt[ref[q], q]
    fig, ax = plt.subplots(figsize=(7, 5))
    ax.imshow(result.enhanced.numpy(), aspect="auto", cmap="viridis", origin="upper")
    ax.contour(gt.astype(float), levels=[0.5], colors="white", linewidths=0.6)
    ax.scatter(q[ok], ref[q][ok], s=4, c="lime", label="correct match")
    ax.scatter(q[~ok], ref[q][~ok], s=4, c="red", label="wrong match")
    ax.set_xlabel("query window (10 ms)")
    ax.set_ylabel("reference window A (10 ms)")
    ax.set_title(title)
    ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_pairs(path: Path, ref_full, query_full, result, title: str, n: int = 6) -> None:
    ref = result.matches.reference.numpy()
    q = np.nonzero(ref >= 0)[0]
    if not len(q):
        return
    pick = q[np.linspace(0, len(q) - 1, min(n, len(q))).round().astype(int)]
    fig, axes = plt.subplots(2, len(pick), figsize=(2 * len(pick), 4.4), squeeze=False)
    for i, j in enumerate(pick):
        for row, (img, label) in enumerate(((query_full[j], f"query {j}"),
                                            (ref_full[ref[j]], f"ref {ref[j]}"))):
            axes[row, i].imshow(np.asarray(img), cmap="gray")
            axes[row, i].set_title(label, fontsize=8)
            axes[row, i].axis("off")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def ensemble_frames(run, cfg: Config, n_windows: int) -> torch.Tensor:
    """``(M, T, 16, 16)`` member frames centred on the 10 ms steps (anchor: time zero)."""
    step = int(round(cfg.window_ms * 1000))
    members = accumulate_ensemble(run.stream, [int(round(ms * 1000)) for ms in cfg.ensemble_ms],
                                  step_us=step, mode=cfg.mode, downsample=cfg.pooled,
                                  anchor="zero")
    return members[:, :n_windows]


def ensemble_rows(ref_members, q_members, gt, sc: SeqSLAMConfig, cfg: Config) -> dict:
    """Single members and the ensemble on one pair: recall@1 and correct coverage."""
    rows = {}
    for i, ms in enumerate(cfg.ensemble_ms):
        m = evaluate(SeqSLAM(sc).match(ref_members[i], q_members[i]).matches, gt)
        rows[f"single {ms:g} ms"] = {k: m[k] for k in ("recall_at_1", "correct_coverage",
                                                        "coverage", "auc")}
    m = evaluate(match_ensemble(list(ref_members), list(q_members), sc).matches, gt)
    rows["ensemble " + "+".join(f"{ms:g}" for ms in cfg.ensemble_ms) + " ms"] = {
        k: m[k] for k in ("recall_at_1", "correct_coverage", "coverage", "auc")}
    return rows


def run_speed_pairs(cfg: Config, out: Path) -> dict:
    t0 = time.perf_counter()
    frames, positions, units_per_s = route_frames(cfg)
    sim = dict(contrast_threshold=cfg.contrast_threshold, threshold_noise=cfg.threshold_noise,
               noise_rate_hz=cfg.noise_rate_hz, refractory_us=cfg.refractory_us)
    window_us = int(round(cfg.window_ms * 1000))
    a = simulate_run(frames, positions, 1.0, units_per_s, seed=cfg.seed + 1, **sim)
    a_full, a_small = event_frames(a, cfg, cfg.n_reference)
    a_pos = a.window_positions(len(a_small), window_us) / (units_per_s * cfg.window_ms * 1e-3)
    results = {"route": cfg.route, "n_events": {"A": len(a.stream)},
               "windows": {"A": len(a_small)}}
    a_members = ensemble_frames(a, cfg, cfg.n_reference) if cfg.ensemble_ms else None
    queries = list(cfg.speeds.items())
    if cfg.ensemble_ms and cfg.changed:
        queries.append((cfg.changed["name"], cfg.changed["speed"]))
    for k, (name, speed) in enumerate(queries):
        views = frames
        if cfg.changed and name == cfg.changed["name"]:
            c = cfg.changed
            views = relight(frames, c["gain"], c["gamma"], c["gradient"], c["noise"],
                            np.random.default_rng(cfg.seed + 99))
        run = simulate_run(views, positions, speed, units_per_s, seed=cfg.seed + 2 + k, **sim)
        n_q = int(np.floor(cfg.n_reference / speed))
        q_full, q_small = event_frames(run, cfg, n_q)
        q_pos = run.window_positions(len(q_small), window_us) / (
            units_per_s * cfg.window_ms * 1e-3)  # in reference windows
        gt = ground_truth(a_pos, q_pos, cfg.tolerance)
        sc = SeqSLAMConfig(image_size=cfg.pooled, patch_size=cfg.patch_size, ds=cfg.ds,
                           enhance_window=cfg.enhance_window, speed_ratio=speed,
                           speed_tolerance=cfg.speed_tolerance)
        # speed_ratio set -> the engine reports the row the best trajectory crosses at the
        # query centre (match_at="trajectory"); OpenSeqSLAM's start + ds/2 is kept for contrast
        res = SeqSLAM(sc).match(a_small, q_small)
        start_rule = SeqSLAM(replace(sc, match_at="start")).match(a_small, q_small)
        raw = evaluate(start_rule.matches, gt, start_rule.ranked)
        metrics = evaluate(res.matches, gt)
        metrics["correct_of_matched"] = (metrics["correct_coverage"]
                                         / max(metrics["coverage"], 1e-12))
        metrics["openseqslam_start_rule"] = {k: raw[k] for k in (
            "recall_at_1", "correct_coverage", "auc", "recall_at_100_precision")}
        metrics.update(speed_ratio=speed, n_events=len(run.stream), windows=len(q_small),
                       events_per_window=len(run.stream) / max(len(q_small), 1),
                       seconds=res.seconds["total"])
        if a_members is not None:
            metrics["ensembles"] = ensemble_rows(a_members, ensemble_frames(run, cfg, n_q), gt,
                                                 sc, cfg)
        results[f"{name}->A"] = metrics
        plot_matrix(out / f"{cfg.route}_{name}_to_A_matrix.png", res, gt,
                    f"{cfg.route}: {name} ({speed:.0%} of A) -> A, enhanced differences")
        plot_pairs(out / f"{cfg.route}_{name}_to_A_pairs.png", a_full, q_full, res,
                   f"{cfg.route}: matched windows {name} -> A (event counts, 10 ms)")
    results["events_per_window_A"] = len(a.stream) / len(a_small)
    results["seconds"] = time.perf_counter() - t0
    return results


def run_lens(cfg: Config, out: Path) -> dict | None:
    root = DATA / "lens-davis128"
    if not root.exists():
        return None
    ref = load_traverse(root / "example-reference", progress=False)
    qry = load_traverse(root / "example-query", progress=False)
    gt = np.load(root / "example-reference_example-query_GT.npy").astype(bool)  # (R, Q)
    sc = SeqSLAMConfig(image_size=cfg.pooled, patch_size=cfg.patch_size, ds=cfg.lens_ds,
                       enhance_window=cfg.enhance_window, speed_ratio=1.0,
                       speed_tolerance=cfg.speed_tolerance)
    res = SeqSLAM(sc).match(ref, qry)
    plot_matrix(out / "lens_davis128_matrix.png", res, gt, "lens-davis128: query -> reference")
    metrics = evaluate(res.matches, gt, res.ranked)
    near = np.abs(np.arange(len(gt))[:, None] - np.arange(gt.shape[1])[None, :]) <= 2
    metrics["recall_at_1_within_2_frames"] = evaluate(res.matches, near)["recall_at_1"]
    metrics["config"] = asdict(sc)
    return metrics


def parse(argv=None) -> tuple[Config, Path]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--small", action="store_true", help="fast configuration (for tests)")
    p.add_argument("--route", choices=("demo", "corridor"), default="demo")
    p.add_argument("--out", type=Path, default=Path("runs/events_speed"))
    p.add_argument("--mode", choices=("count", "signed", "binary"), default=None)
    p.add_argument("--patch-size", type=int, default=None)
    p.add_argument("--speed-tolerance", type=float, default=None)
    p.add_argument("--ds", type=int, default=None)
    p.add_argument("--no-lens", action="store_true")
    p.add_argument("--ensemble-ms", type=float, nargs="*", default=None,
                   help="member window lengths in ms (none: skip the ensembles)")
    args = p.parse_args(argv)
    cfg = Config(route=args.route)
    if args.small:
        cfg.n_reference, cfg.ds, cfg.frame_size, cfg.lens_ds = 48, 20, (64, 64), 6
    for name in ("mode", "patch_size", "speed_tolerance", "ds"):
        if getattr(args, name) is not None:
            setattr(cfg, name, getattr(args, name))
    cfg.no_lens = args.no_lens
    if args.ensemble_ms is not None:
        cfg.ensemble_ms = tuple(args.ensemble_ms)
    return cfg, args.out


def main(argv=None) -> dict:
    cfg, out = parse(argv)
    torch.set_num_threads(min(torch.get_num_threads(), 2))
    out.mkdir(parents=True, exist_ok=True)
    results = {"config": {k: v for k, v in asdict(cfg).items()}}
    results["speed"] = run_speed_pairs(cfg, out)
    if not getattr(cfg, "no_lens", False):
        results["lens_davis128"] = run_lens(cfg, out)
    tmp = out / "results.json.tmp"
    tmp.write_text(json.dumps(results, indent=2, default=str))
    tmp.replace(out / "results.json")
    for key in [k for k in results["speed"] if "->" in k]:
        m = results["speed"][key]
        print(f"{cfg.route} {key}: recall@1 {m['recall_at_1']:.3f}  correct coverage "
              f"{m['correct_coverage']:.3f}  coverage {m['coverage']:.3f}  "
              f"R@100P {m['recall_at_100_precision']:.3f}  AUC {m['auc']:.3f}")
        for row, e in m.get("ensembles", {}).items():
            print(f"    {row:24s} recall@1 {e['recall_at_1']:.3f}  correct coverage "
                  f"{e['correct_coverage']:.3f}  AUC {e['auc']:.3f}")
    if results.get("lens_davis128"):
        m = results["lens_davis128"]
        print(f"lens-davis128: recall@1 {m['recall_at_1']:.3f}  AUC {m['auc']:.3f}")
    return results


if __name__ == "__main__":
    sys.exit(0 if main() else 1)

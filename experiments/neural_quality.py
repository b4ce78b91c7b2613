"""Neural SeqSLAM quality: recall@1 / AUC on the demo, corridor and LENS DAVIS data.

One command (from the repository root):

    .venv/bin/python experiments/neural_quality.py [--out experiments/results] [--ablation]

Writes ``neural_quality.json`` and ``neural_quality.md`` (a Markdown table) under ``--out``,
prints the table. With ``--ablation`` it also runs the ablation over the model's settings
and the harder demo variants (appearance change, speed, repetitive scenery), and rewrites
the tables in docs/neural.md (unless ``--no-docs``).
Classic SeqSLAM (``torchseq.seqslam``, default settings) runs beside it on the same data.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchseq.atomic import write_text  # noqa: E402
from torchseq.demo import make_demo  # noqa: E402
from torchseq.ground_truth import load_ground_truth  # noqa: E402
from torchseq.metrics import evaluate  # noqa: E402
from torchseq.neural import NeuralConfig, NeuralSeqSLAM  # noqa: E402
from torchseq.sources import load_traverse  # noqa: E402

DATA = ROOT.parent / "shared" / "data"


def datasets(names=("demo", "corridor", "lens")) -> dict:
    """``name -> (reference (R,H,W), query (Q,H,W), gt (R,Q) bool)``; absent data are skipped."""
    out = {}
    if "demo" in names:
        d = make_demo()
        out["demo"] = (d.reference, d.query, d.ground_truth)
    if "corridor" in names and (DATA / "corridor").exists():
        r = load_traverse(DATA / "corridor" / "ref", progress=False)
        q = load_traverse(DATA / "corridor" / "query", progress=False)
        out["corridor"] = (r, q, load_ground_truth(DATA / "corridor" / "ground_truth.csv",
                                                   len(r), len(q)))
    lens = DATA / "lens-davis128"
    if "lens" in names and lens.exists():
        r = load_traverse(lens / "example-reference", progress=False)
        q = load_traverse(lens / "example-query", progress=False)
        gt = load_ground_truth(lens / "example-reference_example-query_GT.npy", len(r), len(q))
        out["lens"] = (r, q, gt)
        # the LENS ground truth admits exactly one frame; also score within +-2 frames
        i = np.arange(len(r))
        out["lens+-2"] = (r, q, np.abs(i[:, None] - np.arange(len(q))[None, :]) <= 2)
    return out


def hard_demos() -> dict:
    """Demo variants: stronger appearance change, and repetitive scenery."""
    out = {}
    for name, kw in {"demo-light": dict(gain=0.6, gamma=1.8, gradient=0.3, noise=12.0),
                     "demo-severe": dict(gain=0.45, gamma=2.4, gradient=0.45, noise=20.0),
                     "demo-speed0.6": dict(speed=0.6),
                     "demo-speed1.3": dict(speed=1.3),
                     "demo-speed1.6": dict(speed=1.6)}.items():
        d = make_demo(**kw)
        out[name] = (d.reference, d.query, d.ground_truth)
    try:
        d = make_demo(repeat=3)
        out["demo-repeat"] = (d.reference, d.query, d.ground_truth)
    except TypeError:  # make_demo without the repeat option
        pass
    return out


def degradation_demos(levels=(0.0, 0.25, 0.5, 0.75, 1.0, 1.25)) -> dict:
    """Demo queries from no appearance change (0) to ``demo-severe`` (1) and beyond.

    Level ``s`` interpolates gain 1 -> 0.45, gamma 1 -> 2.4, gradient 0 -> 0.45 and noise
    2 -> 20 grey levels linearly (gain clipped at 0.2).
    """
    out = {}
    for s in levels:
        d = make_demo(gain=max(0.2, 1 - 0.55 * s), gamma=1 + 1.4 * s, gradient=0.45 * s,
                      noise=2 + 18 * s)
        out[f"{s:.2f}"] = (d.reference, d.query, d.ground_truth)
    return out


def run_neural(cfg: NeuralConfig, ref, query, gt) -> dict:
    model = NeuralSeqSLAM(cfg)
    t0 = time.perf_counter()
    model.fit(ref, log=False)
    fit_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = model.run(query)
    run_s = time.perf_counter() - t0
    m = evaluate(res.matches, gt)
    return {"recall_at_1": m["recall_at_1"], "auc": m["auc"],
            "recall_at_100_precision": m["recall_at_100_precision"],
            "fit_s": fit_s, "run_s": run_s, "bytes": model.model_bytes()}


def run_seqslam(ref, query, gt) -> dict | None:
    try:
        from torchseq.seqslam import SeqSLAM
    except ImportError:
        return None
    res = SeqSLAM().match(ref, query)
    m = evaluate(res.matches, gt)
    return {"recall_at_1": m["recall_at_1"], "auc": m["auc"],
            "recall_at_100_precision": m["recall_at_100_precision"]}


ABLATION = {
    "default": {},
    "float input (input_steps 0)": dict(input_steps=0),
    "float weights (l1_levels 0, l3_levels 0)": dict(l1_levels=0, l3_levels=0),
    "all float (no integer grids)": dict(input_steps=0, l1_levels=0, l3_levels=0),
    "Table 1 winners (k 5%)": dict(k_fraction=0.05),
    "dense readout (density_out 1.0, decay 0.96)": dict(density_out=1.0, ring_decay=0.96),
    "patch 8": dict(patch_size=8),
    "patch seqslam rounding": dict(patch_mode="seqslam"),
    "no rectify": dict(rectify=False),
    "no ring (decay 0)": dict(ring_decay=0.0, ring_gain=1.0),
    "ring decay 0.9": dict(ring_decay=0.9),
    "ring decay 0.95": dict(ring_decay=0.95),
    "ring decay 0.96": dict(ring_decay=0.96),
    "ring decay 0.98": dict(ring_decay=0.98),
    "spread 1, no stay": dict(ring_spread=1, ring_stay=0.0),
    "spread 3": dict(ring_spread=3),
    "hebbian mean": dict(hebbian="mean"),
    "k 15%": dict(k_fraction=0.15),
    "density_out 0.5": dict(density_out=0.5),
    "density_out 1.0": dict(density_out=1.0),
    "cohorts 4": dict(n_cohorts=4),
    "cohorts 8": dict(n_cohorts=8),
}


def table(rows: list[dict], cols: list[str]) -> str:
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = [f"{r[c]:.3f}" if isinstance(r.get(c), float) else str(r.get(c, "")) for c in cols]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=ROOT / "experiments" / "results")
    p.add_argument("--ablation", action="store_true",
                   help="also run the ablation and the appearance-change sweep")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seeds", type=int, default=8,
                   help="model seeds averaged in the main table (masks and L1 weights)")
    p.add_argument("--ablation-seeds", type=int, default=3,
                   help="model seeds averaged in the ablation and the appearance sweep")
    p.add_argument("--no-docs", action="store_true",
                   help="with --ablation, do not rewrite the tables in docs/neural.md")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    base = NeuralConfig()
    data = datasets()
    results = {"config": base.to_dict(), "main": [], "ablation": []}
    for name, (ref, query, gt) in data.items():
        row = {"data": name, "R": len(ref), "Q": len(query)}
        runs = [run_neural(replace(base, seed=seed), ref, query, gt) for seed in range(args.seeds)]
        for key in ("recall_at_1", "auc", "recall_at_100_precision"):
            vals = np.array([r[key] for r in runs])
            row[f"neural {key}"] = f"{vals.mean():.3f} +- {vals.std():.3f}"
        row["neural recall_at_1 seed 0"] = runs[0]["recall_at_1"]
        row["neural recall_at_1 min"] = float(min(r["recall_at_1"] for r in runs))
        row["neural fit_s"], row["neural run_s"] = runs[0]["fit_s"], runs[0]["run_s"]
        s = run_seqslam(ref, query, gt)
        if s is not None:
            row.update({f"seqslam {k}": v for k, v in s.items()})
        results["main"].append(row)
        print(row, flush=True)
    cols = ["data", "R", "Q", "neural recall_at_1", "neural recall_at_1 min",
            "neural recall_at_1 seed 0", "neural auc", "neural recall_at_100_precision",
            "seqslam recall_at_1", "seqslam auc", "seqslam recall_at_100_precision"]
    md = (f"### Recall@1 and AUC, default settings (neural: mean +- std over {args.seeds} model "
          "seeds, their minimum, and seed 0)\n\n" + table(results["main"], cols) + "\n")
    if args.ablation:
        data.update(hard_demos())
        for label, kw in ABLATION.items():
            cfg = replace(base, **kw).validate()
            row = {"setting": label}
            for name, (ref, query, gt) in data.items():
                row[name] = float(np.mean([
                    run_neural(replace(cfg, seed=seed), ref, query, gt)["recall_at_1"]
                    for seed in range(args.ablation_seeds)]))
            results["ablation"].append(row)
            print(row, flush=True)
        row = {"setting": "classic SeqSLAM"}
        for name, (ref, query, gt) in data.items():
            s = run_seqslam(ref, query, gt)
            row[name] = s["recall_at_1"] if s else ""
        results["ablation"].append(row)
        md += (f"\n### Ablation: recall@1 (neural: mean over {args.ablation_seeds} model seeds; "
               "each row changes the default in one way)\n\n") + table(results["ablation"],
                                                    ["setting", *data.keys()]) + "\n"
        results["degradation"] = []
        for level, (ref, query, gt) in degradation_demos().items():
            row = {"appearance change": level, "neural recall_at_1": float(np.mean([
                run_neural(replace(base, seed=seed), ref, query, gt)["recall_at_1"]
                for seed in range(args.ablation_seeds)]))}
            s = run_seqslam(ref, query, gt)
            row["seqslam recall_at_1"] = s["recall_at_1"] if s else ""
            results["degradation"].append(row)
            print(row, flush=True)
        md += ("\n### Appearance change sweep (demo, 0 = none, 1 = demo-severe): recall@1 "
               f"(neural: mean over {args.ablation_seeds} seeds)\n\n"
               + table(results["degradation"], ["appearance change", "neural recall_at_1",
                                                "seqslam recall_at_1"]) + "\n")
    write_text(args.out / "neural_quality.json", json.dumps(results, indent=1, default=float))
    write_text(args.out / "neural_quality.md", md)
    docs = ROOT / "docs" / "neural.md"
    if args.ablation and not args.no_docs and docs.exists():
        text = docs.read_text()
        a, b = "<!-- quality:start -->", "<!-- quality:end -->"
        if a in text and b in text:
            body = md.replace("### ", "#### ").strip()
            write_text(docs, text.split(a)[0] + a + "\n" + body + "\n" + b + text.split(b)[1])
    print(md)
    return results


if __name__ == "__main__":
    main()

"""Spiking Neural SeqSLAM beside the rate model: agreement, recall, spikes, latency, consumers.

One command (from the repository root, about a minute):

    .venv/bin/python experiments/spiking_quality.py [--out experiments/results] [--no-consumers]

For the demo, ../shared/data/corridor and ../shared/data/lens-davis128 (also scored within
+-2 frames, ``lens+-2``): the rate model (``NeuralSeqSLAM()`` defaults, fitted on the
reference) and its spiking conversion (``SpikingSeqSLAM.convert``) for several ring ladders;
place-decision agreement and recall@1, L2 and ring spikes and synaptic operations per frame,
and the latency to the first correct decision (query frames from the start); the agreement
of four ladders over seeds 0..3 of the rate model, and the rate model's lead of its winning
unit over the next (what the ladder must resolve; also with the former 20% L2 -> L3 mask).
With the
consumers installed, the default conversion is exported to NIR and run in snnTorch and Norse.
Writes ``spiking_quality.json`` and ``spiking_quality.md`` under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

from neural_quality import datasets  # noqa: E402

from torchseq.atomic import write_json, write_text  # noqa: E402
from torchseq.metrics import recall_at_k  # noqa: E402
from torchseq.neural import NeuralConfig, NeuralSeqSLAM  # noqa: E402
from torchseq.neural.spiking import SpikingConfig, SpikingSeqSLAM  # noqa: E402

LADDERS = {
    "geometric K=32": SpikingConfig(levels=32),
    "geometric K=64": SpikingConfig(levels=64),
    "geometric K=64 low=0.03 (former default)": SpikingConfig(levels=64, low=0.03),
    "geometric K=128 low=0.03": SpikingConfig(levels=128, low=0.03),
    "geometric K=128 (default)": SpikingConfig(),
    "geometric K=192": SpikingConfig(levels=192),
    "uniform K=128": SpikingConfig(spacing="uniform"),
}
# the ladders compared over several seeds of the rate model (its masks and L1 weights)
SEED_LADDERS = ("geometric K=64 low=0.03 (former default)", "geometric K=128 low=0.03",
                "geometric K=128 (default)", "geometric K=192")
SEEDS = (0, 1, 2, 3)


def top_gap(activity: torch.Tensor) -> dict:
    """Quantiles of the rate model's lead of its winning unit over the next, relative."""
    top = activity.topk(2, dim=1).values
    gap = ((top[:, 0] - top[:, 1]) / top[:, 0].clamp_min(1e-12)).numpy()
    return {f"q{int(q * 100)}": float(np.quantile(gap, q)) for q in (0.1, 0.25, 0.5)}


def first_correct(refs: np.ndarray, gt: np.ndarray) -> int | None:
    """Index of the first query frame whose decision is correct (None: never)."""
    ok = np.flatnonzero(gt[refs, np.arange(len(refs))])
    return int(ok[0]) if len(ok) else None


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results"))
    ap.add_argument("--no-consumers", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    results = {}
    fitted, gaps20 = {}, {}
    for name, (ref, qry, gt) in datasets(("demo", "corridor", "lens")).items():
        key = "lens" if name.startswith("lens") else name
        if key not in fitted:
            model = NeuralSeqSLAM(NeuralConfig())
            model.fit(ref, log=False)
            fitted[key] = model
        model = fitted[key]
        gt = np.asarray(gt, dtype=bool)
        result = model.run(qry)
        rate = result.matches.reference.numpy()
        row = {"frames": int(len(qry)), "units": model.n_units,
               "rate": {"recall_at_1": recall_at_k(torch.as_tensor(rate), gt, 1),
                        "first_correct": first_correct(rate, gt),
                        "top_gap": top_gap(result.activity)}}
        if key not in gaps20:  # the same lead with the former 20% L2 -> L3 mask
            sparse = NeuralSeqSLAM(NeuralConfig(density_out=0.2))
            sparse.fit(ref, log=False)
            gaps20[key] = top_gap(sparse.run(qry).activity)
        row["rate"]["top_gap_density_out_0.2"] = gaps20[key]
        for label, cfg in LADDERS.items():
            sp = SpikingSeqSLAM.convert(model, ref, cfg)
            t0 = time.perf_counter()
            out = sp.run(qry)
            refs = out["reference"].numpy()
            row[label] = {
                "agreement": float(np.mean(refs == rate)),
                "recall_at_1": recall_at_k(torch.as_tensor(refs), gt, 1),
                "first_correct": first_correct(refs, gt),
                "l2_spikes_per_frame": float(out["l2_spikes"].mean()),
                "ring_spikes_per_frame": float(out["ring_spikes"].mean()),
                "synaptic_ops_per_frame": float(out["synaptic_ops"].mean()),
                "neurons": sp.sizes["l2"] + sp.sizes["ring"],
                "steps_per_frame": 1, "seconds": round(time.perf_counter() - t0, 3),
            }
            if label.endswith("(default)"):
                row["unquantised ring (ablation)"] = unquantised(sp, qry, rate, gt)
            if label.endswith("(default)") and not args.no_consumers \
                    and not name.endswith("+-2"):
                row["consumers"] = consumers(sp, qry, gt)
        if not name.endswith("+-2"):
            row["seeds"] = seed_agreement(ref, qry, model)
        results[name] = row
        print(name, json.dumps(row["rate"]), {k: (v["agreement"], v["recall_at_1"])
                                               for k, v in row.items() if k in LADDERS})
    out_dir = Path(args.out)
    write_json(out_dir / "spiking_quality.json", results)
    write_text(out_dir / "spiking_quality.md", table(results))
    print(table(results))
    return results


def seed_agreement(ref, qry, seed0) -> dict:
    """Agreement with the rate model of :data:`SEED_LADDERS` for the rate model's seeds."""
    out = {label: [] for label in SEED_LADDERS}
    for seed in SEEDS:
        model = seed0 if seed == 0 else NeuralSeqSLAM(NeuralConfig(seed=seed))
        if seed:
            model.fit(ref, log=False)
        rate = model.run(qry).matches.reference.numpy()
        x = None
        for label in SEED_LADDERS:
            sp = SpikingSeqSLAM.convert(model, ref, LADDERS[label])
            x = sp.encode(qry) if x is None else x
            out[label].append(float(np.mean(sp.run(x, encoded=True)["reference"].numpy() == rate)))
    return out


def unquantised(sp, qry, rate, gt) -> dict:
    """The spiking model's L2 threshold code and fixed normalisation, ring not quantised.

    ``a = max(e + decay * S a, 0)`` (the calibration's ring): separates the cost of the
    k-WTA and normalisation approximations from the cost of the ladder.
    """
    x = sp.encode(qry)
    e = (x @ sp.w1.T > 1).float() @ sp.w3.T
    a = torch.zeros(sp.n_units)
    refs = []
    for t in range(e.shape[0]):
        a = (e[t] + sp.shift @ a).clamp_min(0.0)
        refs.append(int(sp.decide(a[None])[0]))
    refs = np.array(refs)
    return {"agreement": float(np.mean(refs == rate)),
            "recall_at_1": recall_at_k(torch.as_tensor(refs), gt, 1)}


def consumers(sp, qry, gt) -> dict:
    from torchseq.export.nir_consumers import compare
    from torchseq.export.nir_export import write_nir

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "model.nir"
        write_nir(sp, path)
        rep = compare(sp, path, sp.encode(qry), gt)
    return {k: {f: v for f, v in r.items() if f != "differing_frames"} | (
        {"differing_frames": r["differing_frames"]} if r.get("differing_frames") else {})
        for k, r in rep.items()}


def table(results: dict) -> str:
    lines = ["| data | model | agreement with rate | recall@1 | first correct frame | "
             "L2 spikes/frame | ring spikes/frame | synaptic ops/frame | neurons |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, row in results.items():
        r = row["rate"]
        lines.append(f"| {name} | rate model | 1 | {r['recall_at_1']:.3f} | "
                     f"{r['first_correct']} | | | | |")
        u = row["unquantised ring (ablation)"]
        lines.append(f"| {name} | threshold code + fixed sigma, unquantised ring (ablation) | "
                     f"{u['agreement']:.3f} | {u['recall_at_1']:.3f} | | | | | |")
        for label in LADDERS:
            s = row[label]
            lines.append(f"| {name} | spiking, {label} | {s['agreement']:.3f} | "
                         f"{s['recall_at_1']:.3f} | {s['first_correct']} | "
                         f"{s['l2_spikes_per_frame']:.0f} | {s['ring_spikes_per_frame']:.0f} | "
                         f"{s['synaptic_ops_per_frame']:.3g} | {s['neurons']} |")
    lines += ["", "| data | ladder | " + " | ".join(f"seed {s}" for s in SEEDS)
              + " | mean | worst |", "|---|---|" + "---|" * (len(SEEDS) + 2)]
    for name, row in results.items():
        for label, agree in row.get("seeds", {}).items():
            lines.append(f"| {name} | {label} | " + " | ".join(f"{a:.3f}" for a in agree)
                         + f" | {np.mean(agree):.3f} | {min(agree):.3f} |")
    lines += ["", "| data | rate model's lead of the winner over the next unit, quantiles "
              "10% / 25% / 50% | the same with density_out=0.2 (the former 20% mask) |",
              "|---|---|---|"]
    for name, row in results.items():
        g, g20 = row["rate"]["top_gap"], row["rate"]["top_gap_density_out_0.2"]
        lines.append(f"| {name} | {g['q10']:.4f} / {g['q25']:.4f} / {g['q50']:.4f} | "
                     f"{g20['q10']:.4f} / {g20['q25']:.4f} / {g20['q50']:.4f} |")
    lines += ["", "| data | consumer | agreement with torchseq spiking | ring spike agreement | "
              "recall@1 | time steps |", "|---|---|---|---|---|---|"]
    for name, row in results.items():
        for cname, c in row.get("consumers", {}).items():
            if cname == "torchseq":
                continue
            if "skipped" in c:
                lines.append(f"| {name} | {cname} | skipped: {c['skipped']} | | | |")
                continue
            lines.append(f"| {name} | {cname} | {c['agreement']:.4f} | "
                         f"{c['spike_agreement']:.6f} | {c['recall_at_1']:.3f} | "
                         f"{c['time_steps']} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()

"""Spiking vs rate model: decision agreement over seeds 0..7 on the corridor and lens-davis128.

One command (from the repository root, one thread):

    .venv/bin/python experiments/spiking_agreement.py [--seeds 0-7] [--data corridor,lens]
        [--variant default] [--out experiments/results]

For each seed of the rate model (``NeuralConfig(seed=s)``, fitted on the reference) the
spiking conversion is calibrated on the reference only (never the query) and run over the
query; agreement = fraction of query frames whose reference frame equals the rate model's.
Also per seed: recall@1 of the spiking model, of the rate model and of classic SeqSLAM
(default settings; the same for every seed) against the route's ground truth (``lens``: the
exact frame, and ``lens+-2``: within +-2 frames), and the spread of the number of L2 units
that fire per query frame (the rate model's k-WTA keeps exactly ``k = 307``).
``--variant`` picks a :class:`SpikingConfig` from :data:`VARIANTS` (calibration ideas tried).
Writes ``spiking_agreement_<variant>.json`` under ``--out`` and prints markdown tables.
Where the disagreement comes from, stage by stage: ``experiments/spiking_split.py``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

from neural_quality import datasets, run_seqslam  # noqa: E402

from torchseq.atomic import write_json  # noqa: E402
from torchseq.metrics import recall_at_k  # noqa: E402
from torchseq.neural import NeuralConfig, NeuralSeqSLAM  # noqa: E402
from torchseq.neural.spiking import SpikingConfig, SpikingSeqSLAM  # noqa: E402

VARIANTS = {
    "default": SpikingConfig(),
    "K=256": SpikingConfig(levels=256),
    "K=256 low=0.003": SpikingConfig(levels=256, low=0.003),
}


def seeds_arg(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-7")
    ap.add_argument("--data", default="corridor,lens")
    ap.add_argument("--variant", default="default", choices=sorted(VARIANTS))
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    seeds = seeds_arg(args.seeds)
    cfg = VARIANTS[args.variant]
    results, details = {}, {}
    data = datasets(tuple(args.data.split(",")))
    for name, (ref, qry, gt) in data.items():
        if name.endswith("+-2"):
            continue
        gts = {name: torch.as_tensor(gt)}
        if f"{name}+-2" in data:
            gts[f"{name}+-2"] = torch.as_tensor(data[f"{name}+-2"][2])
        seqslam = {g: (run_seqslam(ref, qry, t) or {}).get("recall_at_1") for g, t in gts.items()}
        row, per_seed = [], {}
        for seed in seeds:
            t0 = time.perf_counter()
            model = NeuralSeqSLAM(NeuralConfig(seed=seed))
            model.fit(ref, log=False)
            rate = model.run(qry).matches.reference.numpy()
            sp = SpikingSeqSLAM.convert(model, ref, cfg)
            out = sp.run(qry)
            refs = out["reference"].numpy()
            fired = out["l2_spikes"].numpy()
            row.append(float(np.mean(refs == rate)))
            per_seed[str(seed)] = {
                "agreement": row[-1],
                "l2_firing_min_median_max": [int(fired.min()), float(np.median(fired)),
                                             int(fired.max())],
                "recall_at_1": {g: {"spiking": recall_at_k(torch.as_tensor(refs), t, 1),
                                    "rate": recall_at_k(torch.as_tensor(rate), t, 1),
                                    "seqslam": seqslam[g]} for g, t in gts.items()}}
            print(f"{name} seed {seed}: {row[-1]:.3f} ({time.perf_counter() - t0:.1f} s)",
                  flush=True)
        results[name] = dict(zip(map(str, seeds), row))
        details[name] = per_seed
    write_json(Path(args.out) / f"spiking_agreement_{args.variant.replace(' ', '_')}.json",
               {"variant": args.variant, "seeds": seeds, "agreement": results,
                "per_seed": details})
    head = "| data | variant | " + " | ".join(f"seed {s}" for s in seeds) + " | worst |"
    print(head)
    print("|" + "---|" * (len(seeds) + 3))
    for name, row in results.items():
        vals = list(row.values())
        print(f"| {name} | {args.variant} | " + " | ".join(f"{v:.3f}" for v in vals)
              + f" | {min(vals):.3f} |")
    print()
    print("| data | seed | agreement | L2 units firing per frame (min / median / max) | "
          "recall@1 spiking | recall@1 rate | recall@1 SeqSLAM |")
    print("|---|---|---|---|---|---|---|")
    for name, per_seed in details.items():
        for seed, d in per_seed.items():
            lo, med, hi = d["l2_firing_min_median_max"]
            for g, r in d["recall_at_1"].items():
                sq = "" if r["seqslam"] is None else f"{r['seqslam']:.3f}"
                print(f"| {g} | {seed} | {d['agreement']:.3f} | {lo} / {med:.0f} / {hi} | "
                      f"{r['spiking']:.3f} | {r['rate']:.3f} | {sq} |")
    return results


if __name__ == "__main__":
    main()

"""Spiking vs rate model: decision agreement over seeds 0..7 on the corridor and lens-davis128.

One command (from the repository root, one thread):

    .venv/bin/python experiments/spiking_agreement.py [--seeds 0-7] [--data corridor,lens]
        [--variant default] [--out experiments/results]

For each seed of the rate model (``NeuralConfig(seed=s)``, fitted on the reference) the
spiking conversion is calibrated on the reference only (never the query) and run over the
query; agreement = fraction of query frames whose reference frame equals the rate model's.
``--variant`` picks a :class:`SpikingConfig` from :data:`VARIANTS` (calibration ideas tried).
Writes ``spiking_agreement_<variant>.json`` under ``--out`` and prints a markdown table.
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

from neural_quality import datasets  # noqa: E402

from torchseq.atomic import write_json  # noqa: E402
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
    results = {}
    for name, (ref, qry, _gt) in datasets(tuple(args.data.split(","))).items():
        if name.endswith("+-2"):
            continue
        row = []
        for seed in seeds:
            t0 = time.perf_counter()
            model = NeuralSeqSLAM(NeuralConfig(seed=seed))
            model.fit(ref, log=False)
            rate = model.run(qry).matches.reference.numpy()
            sp = SpikingSeqSLAM.convert(model, ref, cfg)
            refs = sp.run(qry)["reference"].numpy()
            row.append(float(np.mean(refs == rate)))
            print(f"{name} seed {seed}: {row[-1]:.3f} ({time.perf_counter() - t0:.1f} s)",
                  flush=True)
        results[name] = dict(zip(map(str, seeds), row))
    write_json(Path(args.out) / f"spiking_agreement_{args.variant.replace(' ', '_')}.json",
               {"variant": args.variant, "seeds": seeds, "agreement": results})
    head = "| data | variant | " + " | ".join(f"seed {s}" for s in seeds) + " | worst |"
    print(head)
    print("|" + "---|" * (len(seeds) + 3))
    for name, row in results.items():
        vals = list(row.values())
        print(f"| {name} | {args.variant} | " + " | ".join(f"{v:.3f}" for v in vals)
              + f" | {min(vals):.3f} |")
    return results


if __name__ == "__main__":
    main()

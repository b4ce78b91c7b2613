"""Spiking configurations that fit a chip: budget, recall, spikes and energy per decision.

One command (from the repository root, one thread; a few minutes with nordland-b):

    .venv/bin/python experiments/spiking_chips.py [--data corridor,lens,nordland500]
        [--out experiments/results]

For each route and each configuration of :data:`CONFIGS` (a rate model ``NeuralConfig`` and
its spiking conversion ``SpikingConfig``, calibrated on the reference only): the NIR graph's
hardware budget and the chips it fits (``hardware_budget.check``), recall@1 of the spiking
model, of the rate model of the same configuration, of the default rate model and of classic
SeqSLAM (default settings), the spiking model's agreement with its rate model, and per
decision (one query frame, one time step): input events, L2 and ring spikes, synaptic
operations on a chip holding the effective synapses (``SpikingSeqSLAM.chip_ops``), and the
energy those operations cost at a published energy per synaptic operation (:data:`PJ_PER_SOP`),
beside the rate model's multiply-accumulates per frame at a published CPU energy per MAC
(:data:`PJ_PER_MAC`). ``nordland500``: the first 500 places of nordland-b, summer reference,
winter query, +-2 places. Writes ``spiking_chips.json`` under ``--out``; prints a table.
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
from torchseq.export.hardware_budget import budget, check, memory_bytes  # noqa: E402
from torchseq.export.nir_export import to_nir  # noqa: E402
from torchseq.metrics import recall_at_k  # noqa: E402
from torchseq.neural import NeuralConfig, NeuralSeqSLAM  # noqa: E402
from torchseq.neural.spiking import SpikingConfig, SpikingSeqSLAM  # noqa: E402

NORDLAND = ROOT.parent / "shared" / "data" / "nordland-b"

# name -> (NeuralConfig overrides, SpikingConfig, the chip it is sized for)
CONFIGS = {
    "default (K=128, float32)": ({}, SpikingConfig(), None),
    "L1: K=32, 8-bit": ({}, SpikingConfig(levels=32, weight_bits=8), "loihi2"),
    "L2: hidden 1024, K=64, 8-bit": ({"hidden": 1024}, SpikingConfig(levels=64, weight_bits=8),
                                     "loihi2"),
    "L3: hidden 512, K=32, 8-bit": ({"hidden": 512}, SpikingConfig(levels=32, weight_bits=8),
                                    "loihi2"),
    "S1: 12x16 events, hidden 128, 32 units, K=4, 8-bit": (
        {"input_size": (12, 16), "hidden": 128, "n_output": 32},
        SpikingConfig(levels=4, weight_bits=8, input_threshold=0.5), "speck"),
    "S2: 12x16 events, hidden 128, 16 units, K=8 uniform, 8-bit": (
        {"input_size": (12, 16), "hidden": 128, "n_output": 16},
        SpikingConfig(levels=8, spacing="uniform", weight_bits=8, input_threshold=1.0), "speck"),
    "S3: 8x12 events, hidden 256, 32 units, K=4, 8-bit": (
        {"input_size": (8, 12), "hidden": 256, "n_output": 32},
        SpikingConfig(levels=4, weight_bits=8, input_threshold=0.5), "speck"),
    "S4: 12x16 events, hidden 128, 8 units, K=16 uniform, 8-bit": (
        {"input_size": (12, 16), "hidden": 128, "n_output": 8},
        SpikingConfig(levels=16, spacing="uniform", weight_bits=8, input_threshold=0.5), "speck"),
}

# energy per synaptic operation (pJ) and its source; None: no published figure found
PJ_PER_SOP = {
    "loihi2": (23.6, "Loihi (1), Davies et al., IEEE Micro 38(1) 2018 (minimum synaptic spike "
                     "op energy; no per-op figure is published for Loihi 2: Tang et al., "
                     "'SENECA', Front. Neurosci. 2023, Table 3 lists it as NA)"),
    "speck": (None, "no energy per synaptic operation published in the sources found (Yao et "
                    "al., Nat. Commun. 15, 4464, 2024, give 0.42 mW resting power)"),
}
# CPU energy per multiply-accumulate (pJ), arithmetic only (45 nm), and its source
PJ_PER_MAC = {"float32": (3.7 + 0.9, "M. Horowitz, 'Computing's energy problem', ISSCC 2014: "
                                     "fp32 multiply 3.7 pJ + add 0.9 pJ"),
              "int8": (0.2 + 0.03, "Horowitz 2014: int8 multiply 0.2 pJ + add 0.03 pJ")}


def nordland(places: int = 500):
    from torchseq.sources import load_traverse

    ref = load_traverse(NORDLAND / "summer", progress=False)[:places]
    qry = load_traverse(NORDLAND / "winter", progress=False)[:places]
    i = np.arange(places)
    return ref, qry, np.abs(i[:, None] - i[None, :]) <= 2


def rate_macs(model) -> int:
    """Multiply-accumulates of one rate-model step as the CPU runs it (dense products)."""
    m, d = model.l1.weight.shape
    n = model.n_units
    return m * d + n * m + n * n


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="corridor,lens,nordland500")
    ap.add_argument("--configs", default="", help="comma-separated name prefixes (L1,S1,..)")
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    names = args.data.split(",")
    data = {k: v for k, v in datasets(tuple(n for n in names if n != "nordland500")).items()
            if k in names or (k == "lens+-2" and "lens" in names)}
    if "nordland500" in names and NORDLAND.exists():
        data["nordland500"] = nordland()
    pick = [c for c in CONFIGS if not args.configs
            or any(c.startswith(p) for p in args.configs.split(","))]
    results = {}
    for name, (ref, qry, gt) in data.items():
        gt = np.asarray(gt, dtype=bool)
        row = {"seqslam": (run_seqslam(ref, qry, torch.as_tensor(gt)) or {}).get("recall_at_1")}
        default = None
        for label in pick:
            over, scfg, chip = CONFIGS[label]
            t0 = time.perf_counter()
            model = NeuralSeqSLAM(NeuralConfig(**over))
            model.fit(ref, log=False)
            rate = model.run(qry).matches.reference.numpy()
            if not over:
                default = rate
            sp = SpikingSeqSLAM.convert(model, ref, scfg)
            out = sp.run(qry)
            refs = out["reference"].numpy()
            b = budget(to_nir(sp))
            fits = check(b)
            ops = {k: float(v.mean()) for k, v in out["chip_ops"].items()}
            sops = sum(ops.values())
            pj = PJ_PER_SOP.get(chip or "loihi2", (None, ""))[0]
            row[label] = {
                "chip": chip, "fits": {c: r["fits"] for c, r in fits.items()},
                "exceeds": {c: r["exceeds"] for c, r in fits.items()},
                "units": model.n_units, "neurons": b["neurons"],
                "synapses": b["effective_synapses"],
                "memory_bytes_8bit": memory_bytes(b, 8),
                "recall_at_1": recall_at_k(torch.as_tensor(refs), gt, 1),
                "rate_recall_at_1": recall_at_k(torch.as_tensor(rate), gt, 1),
                "agreement_with_rate": float(np.mean(refs == rate)),
                "input_events": float(out["input_events"].mean()),
                "l2_spikes": float(out["l2_spikes"].mean()),
                "ring_spikes": float(out["ring_spikes"].mean()),
                "chip_sops": ops, "chip_sops_total": sops,
                "energy_nj": None if pj is None else sops * pj * 1e-3,
                "rate_macs": rate_macs(model),
                "rate_energy_nj_fp32": rate_macs(model) * PJ_PER_MAC["float32"][0] * 1e-3,
                "seconds": round(time.perf_counter() - t0, 1),
            }
            print(name, label, {k: row[label][k] for k in
                                ("fits", "recall_at_1", "rate_recall_at_1", "agreement_with_rate",
                                 "chip_sops_total", "seconds")}, flush=True)
        if default is not None:
            row["rate_default_recall_at_1"] = recall_at_k(torch.as_tensor(default), gt, 1)
        results[name] = row
    write_json(Path(args.out) / "spiking_chips.json",
               {"results": results, "pj_per_sop": PJ_PER_SOP, "pj_per_mac": PJ_PER_MAC})
    print(table(results))
    return results


def table(results: dict) -> str:
    lines = ["| data | configuration | fits | units | neurons | synapses | memory (8-bit) | "
             "recall@1 spiking | recall@1 its rate model | agreement | SeqSLAM | "
             "events / L2 / ring spikes per decision | chip SOPs per decision | energy (nJ) | "
             "rate model MACs (fp32 nJ) |", "|" + "---|" * 15]
    for name, row in results.items():
        for label, r in row.items():
            if not isinstance(r, dict):
                continue
            fits = ", ".join(c for c, ok in r["fits"].items() if ok) or "none"
            e = "" if r["energy_nj"] is None else f"{r['energy_nj']:.0f}"
            lines.append(
                f"| {name} | {label} | {fits} | {r['units']} | {r['neurons']:,} | "
                f"{r['synapses']:,} | {r['memory_bytes_8bit'] / 2**20:.1f} MiB | "
                f"{r['recall_at_1']:.3f} | {r['rate_recall_at_1']:.3f} | "
                f"{r['agreement_with_rate']:.3f} | {row['seqslam'] or float('nan'):.3f} | "
                f"{r['input_events']:.0f} / {r['l2_spikes']:.0f} / {r['ring_spikes']:.0f} | "
                f"{r['chip_sops_total']:,.0f} | {e} | {r['rate_macs']:,} "
                f"({r['rate_energy_nj_fp32']:.0f}) |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()

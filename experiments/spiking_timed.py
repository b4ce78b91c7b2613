"""The timed spiking model: agreement with its rate model, recall, budget and energy.

One command (from the repository root, one thread; 10.4 minutes on the shared 2-core host):

    PYTHONPATH=. .venv/bin/python experiments/spiking_timed.py [--seeds 0-7]
        [--data corridor,lens,nordland500] [--nordland-seeds 0-7] [--out experiments/results]

For each route and each seed of the rate model (``NeuralConfig(seed=s)``, fitted on the
reference), the timed spiking conversion (:class:`TimedSpikingSeqSLAM`, calibrated on the
reference only) with float weights (``TimedConfig()``) and with 8-bit weights
(``TimedConfig(weight_bits=8)``), and for comparison the one-step conversion
(``SpikingSeqSLAM.convert(model, ref)``, default config), are run over the query:
agreement = fraction of query frames whose decided reference equals the rate model's
(``model.run(query).matches.reference``). Per seed also recall@1 of the three spiking
models, of the rate model and of classic SeqSLAM (default settings; the same for every
seed) against each ground truth (``lens``: the exact frame, ``lens+-2``: within +-2 frames;
``nordland500``: the first 500 places of nordland-b, summer reference, winter query, +-2
places, loaded as ``spiking_chips.py`` does), and the clipped windows of phase B
(``windows == 0``). For seed 0 of each route, 8-bit: the budget (``net.budget()``), the
chips it fits (``hardware_budget.check``) and why the others do not, steps per frame, the
median spikes and synaptic operations per decision by phase, and the energy per decision at
Loihi's published energy per synaptic operation (``spiking_chips.PJ_PER_SOP``) beside the
rate model's multiply-accumulates per frame (``spiking_chips.rate_macs``) at
``spiking_chips.PJ_PER_MAC``. Latency is reported in steps per frame only: no published
wall-clock time per step of Loihi 2 was found (``docs/results/nir.md``, "Energy and latency
per decision"). ``--nordland-seeds`` limits the seeds run on nordland500 and nordland.
``--data nordland``: all 1,788 places of nordland-b with one output unit per place
(``n_output=1788``: the default 555 units would make the rate model decide by its unit
search, which no spiking form has); one seed takes several minutes. Writes
``spiking_timed.json`` under ``--out`` (``spiking_timed_<routes>.json`` for other
``--data``); prints markdown tables.
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
from spiking_agreement import seeds_arg  # noqa: E402
from spiking_chips import NORDLAND, PJ_PER_MAC, PJ_PER_SOP, nordland, rate_macs  # noqa: E402

from torchseq.atomic import write_json  # noqa: E402
from torchseq.export.hardware_budget import check, memory_bytes  # noqa: E402
from torchseq.metrics import recall_at_k  # noqa: E402
from torchseq.neural import NeuralConfig, NeuralSeqSLAM  # noqa: E402
from torchseq.neural.spiking import SpikingSeqSLAM  # noqa: E402
from torchseq.neural.spiking_timed import TimedConfig, TimedSpikingSeqSLAM  # noqa: E402

MODELS = {"timed 8-bit": TimedConfig(weight_bits=8), "timed float": TimedConfig()}
ROUTES = ("corridor", "lens", "nordland500")
PLACES_ALL = 1788  # nordland-b's places: route "nordland", one output unit per place


def routes(names) -> dict:
    """``route -> (ref, query, {gt name: (R, Q) bool})``: lens carries lens and lens+-2."""
    data = datasets(tuple(n for n in names if not n.startswith("nordland")))
    out = {}
    for name in names:
        if name.startswith("nordland"):
            if NORDLAND.exists():
                ref, qry, gt = nordland(500 if name == "nordland500" else PLACES_ALL)
                out[name] = (ref, qry, {name: gt})
        elif name in data:
            ref, qry, gt = data[name]
            gts = {name: gt}
            if f"{name}+-2" in data:
                gts[f"{name}+-2"] = data[f"{name}+-2"][2]
            out[name] = (ref, qry, gts)
    return {k: (r, q, {g: torch.as_tensor(np.asarray(t, dtype=bool)) for g, t in gts.items()})
            for k, (r, q, gts) in out.items()}


def median(t: torch.Tensor) -> float:
    return float(t.double().median())


def chip_summary(net: TimedSpikingSeqSLAM, out: dict, model) -> dict:
    """Budget, chips, steps, spikes, synaptic operations and energy per decision (8-bit)."""
    b = net.budget()
    fits = check(b)
    ops = {k: median(v) for k, v in out["synaptic_ops"].items()}
    total = out["synaptic_ops"]["a"] + out["synaptic_ops"]["b"] + out["synaptic_ops"]["c"]
    pj = PJ_PER_SOP["loihi2"][0]
    macs = rate_macs(model)
    return {
        "neurons": b["neurons"], "populations": b["populations"],
        "effective_synapses": b["effective_synapses"],
        "memory_bytes_8bit": memory_bytes(b, 8),
        "max_fan_in": b["max_fan_in"], "max_fan_out": b["max_fan_out"],
        "max_fan_in_by_population": b["max_fan_in_by_population"],
        "max_fan_out_by_population": b["max_fan_out_by_population"],
        "fits": {c: r["fits"] for c, r in fits.items()},
        "exceeds": {c: r["exceeds"] for c, r in fits.items()},
        "steps_per_frame": out["steps_per_frame"],
        "rungs": net.calibration["rungs"],
        "spikes_median": {k: median(v) for k, v in out["spikes"].items()},
        "synaptic_ops_median": ops, "synaptic_ops_total_median": median(total),
        "synaptic_ops_total_min_max": [float(total.min()), float(total.max())],
        "energy_uj_loihi": median(total) * pj * 1e-6,
        "rate_macs": macs,
        "rate_energy_uj_fp32": macs * PJ_PER_MAC["float32"][0] * 1e-6,
        "rate_energy_uj_int8": macs * PJ_PER_MAC["int8"][0] * 1e-6,
    }


def run_seed(seed: int, ref, qry, gts: dict, chips: bool) -> dict:
    t0 = time.perf_counter()
    # one unit per place: a route longer than the default 555 units would take the unit
    # search, which no spiking form has (nordland: n_output = 1,788)
    model = NeuralSeqSLAM(NeuralConfig(seed=seed, n_output=max(555, len(ref))))
    model.fit(ref, log=False)
    rate = model.run(qry).matches.reference
    decisions, res = {"rate": rate}, {"seconds": {}}
    for label, cfg in MODELS.items():
        t1 = time.perf_counter()
        net = TimedSpikingSeqSLAM.convert(model, ref, cfg)
        out = net.run(qry)
        res["seconds"][label] = round(time.perf_counter() - t1, 1)
        decisions[label] = out["reference"]
        w = out["windows"]
        res[label] = {"clipped_windows": int((w == 0).sum()),
                      "frames_with_clipped_window": int((w == 0).any(1).sum()),
                      "windows_min_median_max": [float(w[w > 0].min()), median(w[w > 0]),
                                                 float(w.max())],
                      "winners_min_max": [int(out["winners"].min()),
                                          int(out["winners"].max())]}
        if chips and label == "timed 8-bit":
            res["chip"] = chip_summary(net, out, model)
    t1 = time.perf_counter()
    one = SpikingSeqSLAM.convert(model, ref)
    out = one.run(qry)
    res["seconds"]["one-step"] = round(time.perf_counter() - t1, 1)
    decisions["one-step"] = out["reference"]
    if chips:
        res["one_step_chip_sops"] = float(sum(v.double().mean() for v in out["chip_ops"].values()))
    res["agreement"] = {k: float((v == rate).double().mean())
                        for k, v in decisions.items() if k != "rate"}
    res["recall_at_1"] = {g: {k: recall_at_k(v, gt, 1) for k, v in decisions.items()}
                          for g, gt in gts.items()}
    res["seconds"]["total"] = round(time.perf_counter() - t0, 1)
    return res


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-7")
    ap.add_argument("--nordland-seeds", default="0-7",
                    help="seeds on nordland500 and nordland (a subset of --seeds)")
    ap.add_argument("--data", default=",".join(ROUTES))
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    seeds = seeds_arg(args.seeds)
    names = args.data.split(",")
    nl_seeds = [s for s in seeds_arg(args.nordland_seeds) if s in seeds]
    results = {}
    for name, (ref, qry, gts) in routes(names).items():
        seqslam = {g: (run_seqslam(ref, qry, gt) or {}).get("recall_at_1")
                   for g, gt in gts.items()}
        per_seed = {}
        run = nl_seeds if name.startswith("nordland") else seeds
        for seed in run:
            r = run_seed(seed, ref, qry, gts, chips=seed == run[0])
            per_seed[str(seed)] = r
            print(f"{name} seed {seed}: agreement " + ", ".join(
                f"{k} {v:.3f}" for k, v in r["agreement"].items()) + f" {r['seconds']}",
                flush=True)
        results[name] = {"seqslam_recall_at_1": seqslam, "per_seed": per_seed}
    json_name = ("spiking_timed.json" if tuple(names) == ROUTES
                 else f"spiking_timed_{'_'.join(names)}.json")
    write_json(Path(args.out) / json_name,
               {"seeds": seeds, "nordland_seeds": nl_seeds, "models": {
                   k: vars(v) for k, v in MODELS.items()}, "results": results,
                "pj_per_sop": PJ_PER_SOP, "pj_per_mac": PJ_PER_MAC})
    print(tables(results, seeds))
    return results


def tables(results: dict, seeds: list[int]) -> str:
    labels = ("timed float", "timed 8-bit", "one-step")
    lines = ["| data | model | " + " | ".join(f"seed {s}" for s in seeds)
             + " | worst | mean | clipped windows (all seeds) |",
             "|" + "---|" * (len(seeds) + 5)]
    for name, row in results.items():
        ps = row["per_seed"]
        for label in labels:
            vals = [ps[str(s)]["agreement"][label] if str(s) in ps else None for s in seeds]
            got = [v for v in vals if v is not None]
            clip = sum(ps[s][label]["clipped_windows"] for s in ps) if label in MODELS else ""
            lines.append(f"| {name} | {label} | "
                         + " | ".join("" if v is None else f"{v:.3f}" for v in vals)
                         + f" | {min(got):.3f} | {np.mean(got):.3f} | {clip} |")
    lines += ["", "| data | seeds | recall@1, seed 0 (mean over the seeds): timed 8-bit | "
              "timed float | one-step | rate model | SeqSLAM (default) |",
              "|---|---|---|---|---|---|---|"]
    for name, row in results.items():
        ps = row["per_seed"]
        for g, sq in row["seqslam_recall_at_1"].items():
            def rec(k):
                v = [ps[s]["recall_at_1"][g][k] for s in ps]
                return f"{v[0]:.3f}" if len(v) == 1 else f"{v[0]:.3f} (mean {np.mean(v):.3f})"
            lines.append(f"| {g} | {','.join(ps)} | " + " | ".join(
                rec(k) for k in ("timed 8-bit", "timed float", "one-step", "rate"))
                + f" | {'' if sq is None else f'{sq:.3f}'} |")
    lines += ["", "| data | neurons | effective synapses | memory, 8-bit | max fan-in / "
              "fan-out | fits | steps per frame | spikes per decision L2 / norm / ring "
              "(median) | synaptic ops per decision (median: A + B + C) | energy per "
              "decision on Loihi (23.6 pJ/op) | one-step model (default), chip SOPs per decision "
              "(mean) and energy | rate model MACs per frame (fp32 / int8) |",
              "|" + "---|" * 12]
    for name, row in results.items():
        ps = row["per_seed"]
        s0 = next((s for s in ps if "chip" in ps[s]), None)
        if s0 is None:
            continue
        c, one = ps[s0]["chip"], ps[s0]["one_step_chip_sops"]
        fits = ", ".join(k for k, ok in c["fits"].items() if ok) or "none"
        sp, op = c["spikes_median"], c["synaptic_ops_median"]
        lines.append(
            f"| {name} | {c['neurons']:,} | {c['effective_synapses']:,} | "
            f"{c['memory_bytes_8bit'] / 2**20:.2f} MiB | {c['max_fan_in']:,} / "
            f"{c['max_fan_out']:,} | {fits} | {c['steps_per_frame']:,} | "
            f"{sp['l2']:.0f} / {sp['norm']:,.0f} / {sp['ring']:,.0f} | "
            f"{c['synaptic_ops_total_median'] / 1e6:.2f} M ({op['a'] / 1e6:.2f} + "
            f"{op['b'] / 1e6:.2f} + {op['c'] / 1e6:.2f}) | {c['energy_uj_loihi']:.0f} uJ | "
            f"{one / 1e6:.2f} M ({one * PJ_PER_SOP['loihi2'][0] * 1e-6:.0f} uJ) | "
            f"{c['rate_macs'] / 1e6:.2f} M ({c['rate_energy_uj_fp32']:.1f} / "
            f"{c['rate_energy_uj_int8']:.2f} uJ) |")
    lines += ["", "Chips that do not fit (seed 0, 8-bit):"]
    for name, row in results.items():
        for s in row["per_seed"].values():
            for chip, why in s.get("chip", {}).get("exceeds", {}).items():
                if why:
                    lines.append(f"- {name}, {chip}: " + "; ".join(why))
    return "\n".join(lines)


if __name__ == "__main__":
    main()

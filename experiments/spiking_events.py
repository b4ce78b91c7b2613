"""Event-driven spiking model beside the frame-driven one, the rate model and SeqSLAM.

One command (from the repository root, one thread):

    .venv/bin/python experiments/spiking_events.py [--places 400] [--seeds 0-2]
        [--consumers] [--ablation] [--weight-bits 8,4] [--out experiments/results]

Data (``../shared/data``):

- ``lens``: lens-davis128, 100 + 100 frames of 80x80 whose pixels are the event counts of
  one window of a DAVIS camera. Each pixel's count is taken as that window's events; the
  polarity is unknown (all counted as ON; the input stage sums both polarities anyway).
  Ground truth: the exact frame (``lens``) and +-2 frames (``lens+-2``).
- ``nordland``: the first ``--places`` places of nordland-b, summer reference, winter query;
  events from torchseq's simulator (``frames_to_events``, contrast threshold 0.2, 10 places
  a second, ``simulate_run``) over each traverse, one window per pair of consecutive places
  (``EventRun.windows``): window ``t`` holds the events from place ``t`` to ``t + 1`` and is
  scored against the reference windows by index within +-2.

Per seed of the rate model (``NeuralConfig(seed=s)``, fitted on the reference windows' count
frames: both polarities summed, i.e. the events accumulated on the host): recall@1 of the
rate model, of the frame-driven spiking model (``SpikingSeqSLAM.convert``: the rate model's
nonlinear ``encode`` of the count frame as analog current), of the event-driven spiking
model (``EventSpikingSeqSLAM.convert_events``: the ``(2, H, W)`` counts of each window
through sum pooling and the linear z-score stand-in), the decision agreement of the
event-driven model with the frame-driven one and with the rate model, and SeqSLAM (default
settings) on the count frames. Calibration uses the reference windows only. For nordland
the rate model and SeqSLAM on the intensity frames of the same places are given as
context (what the events lose). ``--consumers`` also exports the event-driven model of seed
0 to NIR and runs snnTorch and Norse on the query windows (16-window streams);
``--ablation`` also runs the event-driven model with per-patch scales (``scale="patch"``)
beside the default one global scale. ``--weight-bits 8,4`` adds the event-driven model at
each chip precision (``SpikingConfig(weight_bits=b)``), and with ``--consumers`` exports
each of those of seed 0 and runs the consumers on it too. With ``--consumers`` the real
DVS128 recording ``../shared/data/events/alex_walking_again.aedat`` (100 ms windows, the
first 34 as reference, the other 35 as query; one traverse, so no recall) is exported and
run too.
Writes ``spiking_events.json`` and ``spiking_events.md`` under ``--out``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

from spiking_agreement import seeds_arg  # noqa: E402

from torchseq.atomic import write_json, write_text  # noqa: E402
from torchseq.events import simulate_run  # noqa: E402
from torchseq.metrics import recall_at_k  # noqa: E402
from torchseq.neural import NeuralConfig, NeuralSeqSLAM  # noqa: E402
from torchseq.neural.spiking import SpikingConfig, SpikingSeqSLAM  # noqa: E402
from torchseq.neural.spiking_events import (  # noqa: E402
    EventSpikingSeqSLAM,
    count_frames,
)
from torchseq.sources import load_traverse  # noqa: E402

DATA = ROOT.parent / "shared" / "data"


def within(n_ref: int, n_query: int, tol: int) -> np.ndarray:
    i = np.arange(n_ref)
    return np.abs(i[:, None] - np.arange(n_query)[None, :]) <= tol


def lens() -> dict:
    root = DATA / "lens-davis128"
    ref = load_traverse(root / "example-reference", progress=False).float()
    qry = load_traverse(root / "example-query", progress=False).float()
    on = lambda f: torch.stack([torch.zeros_like(f), f], 1)  # noqa: E731 - polarity unknown
    gt = np.load(root / "example-reference_example-query_GT.npy").astype(bool)
    return {"events": (on(ref), on(qry)), "gt": {"lens": gt, "lens+-2": within(100, 100, 2)}}


FPS = 10.0  # places a second: one window per pair of consecutive places
WINDOW_US = int(1e6 / FPS)


def event_run(frames: torch.Tensor) -> torch.Tensor:
    """Simulated windows ``(T - 1, 2, H, W)`` of one traverse (window ``t``: places t, t + 1)."""
    run = simulate_run(frames, np.arange(len(frames)), 1.0, FPS)
    return run.windows(len(frames) - 1, WINDOW_US)


def nordland(places: int) -> dict:
    root = DATA / "nordland-b"
    ref = load_traverse(root / "summer", progress=False)[:places].float()
    qry = load_traverse(root / "winter", progress=False)[:places].float()
    if ref.dim() == 4:  # RGB
        from torchseq.preprocess import to_grey

        ref, qry = to_grey(ref), to_grey(qry)
    ev_ref, ev_qry = event_run(ref), event_run(qry)
    # by index: both runs' window t is centred on place t + 0.5 (runs.ground_truth on the
    # float window positions would drop pairs 2 apart whose difference rounds above 2)
    n = places - 1
    return {"events": (ev_ref, ev_qry), "gt": {f"nordland {places}+-2": within(n, n, 2)},
            "intensity": (ref[1:], qry[1:])}


def dvs128() -> tuple[torch.Tensor, torch.Tensor]:
    """The DVS128 recording in 100 ms windows: the first 34 as reference, the other 35 as query
    (one traverse only: no ground truth, so consumers only)."""
    from torchseq.events import accumulate, read_events

    stream = read_events(DATA / "events" / "alex_walking_again.aedat")
    windows = accumulate(stream, window_us=100_000, mode="two_channel")
    return windows[:34], windows[34:]


def seqslam_recall(ref, qry, gts) -> dict:
    from torchseq.seqslam import SeqSLAM

    res = SeqSLAM().match(ref, qry)
    return {k: recall_at_k(res.matches.reference, gt, 1) for k, gt in gts.items()}


def rate_recall(ref, qry, gts, seed) -> dict:
    model = NeuralSeqSLAM(NeuralConfig(seed=seed))
    model.fit(ref, log=False)
    refs = model.run(qry).matches.reference
    return {k: recall_at_k(refs, gt, 1) for k, gt in gts.items()}


def one_seed(ev_ref, ev_qry, gts, seed: int, ablation: bool = False,
             bits: tuple[int, ...] = ()) -> tuple[dict, EventSpikingSeqSLAM, dict]:
    ref, qry = count_frames(ev_ref), count_frames(ev_qry)
    model = NeuralSeqSLAM(NeuralConfig(seed=seed))
    model.fit(ref, log=False)
    rate = model.run(qry).matches.reference
    frame = SpikingSeqSLAM.convert(model, ref).run(qry)
    ev = EventSpikingSeqSLAM.convert_events(model, ev_ref)
    evrun = ev.run(ev_qry)
    out = {}
    for key, refs in (("rate", rate), ("frame-driven spiking", frame["reference"]),
                      ("event-driven spiking", evrun["reference"])):
        out[key] = {k: recall_at_k(refs, gt, 1) for k, gt in gts.items()}
    e = evrun["reference"].numpy()
    out["agreement event vs frame-driven"] = float(np.mean(e == frame["reference"].numpy()))
    out["agreement event vs rate"] = float(np.mean(e == rate.numpy()))
    out["agreement frame-driven vs rate"] = float(np.mean(frame["reference"].numpy()
                                                          == rate.numpy()))
    out["event l2 spikes/window"] = float(evrun["l2_spikes"].mean())
    out["frame l2 spikes/frame"] = float(frame["l2_spikes"].mean())
    out["input events/window"] = float(ev_qry.sum((1, 2, 3)).mean())
    if ablation:
        patch = EventSpikingSeqSLAM.convert_events(model, ev_ref, scale="patch")
        refs = patch.run(ev_qry)["reference"]
        out["event-driven, per-patch scales"] = {k: recall_at_k(refs, gt, 1)
                                                 for k, gt in gts.items()}
    quantised = {}
    for b in bits:  # the event-driven model at chip precision
        quantised[b] = EventSpikingSeqSLAM.convert_events(model, ev_ref,
                                                          SpikingConfig(weight_bits=b))
        refs = quantised[b].run(ev_qry)["reference"]
        out[f"event-driven, {b}-bit weights"] = {k: recall_at_k(refs, gt, 1)
                                                 for k, gt in gts.items()}
        out[f"agreement {b}-bit vs float event-driven"] = float(np.mean(refs.numpy() == e))
    return out, ev, quantised


def consumers(ev, ev_qry) -> dict:
    from torchseq.export.nir_consumers import compare
    from torchseq.export.nir_export import write_nir

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "events.nir"
        write_nir(ev, path)
        rep = compare(ev, path, ev.encode(ev_qry), segment=16)
    return {k: {f: v.get(f) for f in ("agreement", "spike_agreement", "skipped", "failed")
                if f in v} for k, v in rep.items() if k != "torchseq"}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--places", type=int, default=400)
    ap.add_argument("--seeds", default="0-2")
    ap.add_argument("--data", default="lens,nordland")
    ap.add_argument("--consumers", action="store_true")
    ap.add_argument("--ablation", action="store_true",
                    help="also the event-driven model with per-patch scales")
    ap.add_argument("--weight-bits", default="",
                    help="comma-separated chip precisions for the event-driven model, e.g. 8,4")
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results"))
    args = ap.parse_args(argv)
    bits = tuple(int(b) for b in args.weight_bits.split(",") if b)
    torch.set_num_threads(1)
    seeds = seeds_arg(args.seeds)
    sets = {}
    if "lens" in args.data:
        sets["lens"] = lens()
    if "nordland" in args.data:
        t0 = time.perf_counter()
        sets["nordland"] = nordland(args.places)
        print(f"nordland events simulated ({time.perf_counter() - t0:.1f} s)", flush=True)
    results = {}
    for name, d in sets.items():
        ev_ref, ev_qry = d["events"]
        gts = d["gt"]
        row = {"windows": [int(ev_ref.shape[0]), int(ev_qry.shape[0])],
               "sensor": list(ev_ref.shape[2:]), "seeds": {}}
        for seed in seeds:
            t0 = time.perf_counter()
            row["seeds"][str(seed)], ev, quantised = one_seed(ev_ref, ev_qry, gts, seed,
                                                                  args.ablation, bits)
            print(f"{name} seed {seed}: {row['seeds'][str(seed)]} "
                  f"({time.perf_counter() - t0:.1f} s)", flush=True)
            if seed == seeds[0] and args.consumers:
                row["consumers"] = consumers(ev, ev_qry)
                for b, q in quantised.items():
                    row["consumers"].update({f"{k}, {b}-bit": v
                                             for k, v in consumers(q, ev_qry).items()})
                print(f"{name} consumers: {row['consumers']}", flush=True)
        row["seqslam (count frames)"] = seqslam_recall(count_frames(ev_ref),
                                                       count_frames(ev_qry), gts)
        if "intensity" in d:
            r, q = d["intensity"]
            row["seqslam (intensity frames)"] = seqslam_recall(r, q, gts)
            row["rate (intensity frames, seed 0)"] = rate_recall(r, q, gts, 0)
        results[name] = row
    if args.consumers and (DATA / "events").exists():
        ref, qry = dvs128()
        model = NeuralSeqSLAM(NeuralConfig(seed=seeds[0]))
        model.fit(count_frames(ref), log=False)
        ev = EventSpikingSeqSLAM.convert_events(model, ref)
        results["dvs128 recording"] = {"windows": [34, 35], "sensor": [128, 128],
                                       "consumers": consumers(ev, qry)}
        print(f"dvs128 consumers: {results['dvs128 recording']['consumers']}", flush=True)
    out = Path(args.out)
    write_json(out / "spiking_events.json", {"seeds": seeds, "places": args.places,
                                             "results": results})
    md = table(results, seeds)
    write_text(out / "spiking_events.md", md)
    print(md)
    return results


def table(results: dict, seeds: list[int]) -> str:
    lines = ["| data (windows) | model | recall@1 (mean over seeds) | per seed |",
             "|---|---|---|---|"]
    scored = {n: r for n, r in results.items() if "seeds" in r}
    for name, row in scored.items():
        for gt in next(iter(row["seeds"].values()))["rate"]:
            label = f"{gt} ({row['windows'][1]})"
            first = row["seeds"][str(seeds[0])]
            models = [m for m in ("rate", "frame-driven spiking", "event-driven spiking",
                                  "event-driven, per-patch scales") if m in first]
            models += [m for m in first if m.endswith("-bit weights")]
            for model in models:
                vals = [row["seeds"][str(s)][model][gt] for s in seeds]
                lines.append(f"| {label} | {model} | {np.mean(vals):.3f} | "
                             + " ".join(f"{v:.3f}" for v in vals) + " |")
            lines.append(f"| {label} | SeqSLAM (count frames) | "
                         f"{row['seqslam (count frames)'][gt]:.3f} | |")
            for extra in ("seqslam (intensity frames)", "rate (intensity frames, seed 0)"):
                if extra in row:
                    lines.append(f"| {label} | {extra} | {row[extra][gt]:.3f} | |")
    lines += ["", "| data | event vs frame-driven | event vs rate | frame-driven vs rate | "
              "input events/window | event L2 spikes/window | frame L2 spikes/frame |",
              "|---|---|---|---|---|---|---|"]
    for name, row in scored.items():
        s = row["seeds"].values()

        def mean(key, s=s):
            return np.mean([v[key] for v in s])

        lines.append(f"| {name} | {mean('agreement event vs frame-driven'):.3f} | "
                     f"{mean('agreement event vs rate'):.3f} | "
                     f"{mean('agreement frame-driven vs rate'):.3f} | "
                     f"{mean('input events/window'):.0f} | {mean('event l2 spikes/window'):.0f} | "
                     f"{mean('frame l2 spikes/frame'):.0f} |")
    quant = sorted({k for r in scored.values() for v in r["seeds"].values() for k in v
                    if k.startswith("agreement") and k.endswith("vs float event-driven")})
    if quant:
        lines += ["", "| data | " + " | ".join(f"{k[len('agreement '):]} decisions"
                                               for k in quant) + " |",
                  "|---|" + "---|" * len(quant)]
        for name, row in scored.items():
            vals = [np.mean([v[k] for v in row["seeds"].values()]) for k in quant]
            lines.append(f"| {name} | " + " | ".join(f"{v:.3f}" for v in vals) + " |")
    cons = {n: r["consumers"] for n, r in results.items() if "consumers" in r}
    if cons:
        lines += ["", "| data | consumer | decision agreement | spike agreement |",
                  "|---|---|---|---|"]
        for n, c in cons.items():
            for k, v in c.items():
                agree = v.get("agreement", v.get("skipped", v.get("failed")))
                lines.append(f"| {n} | {k} | {agree} | {v.get('spike_agreement', '')} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()

"""Where the spiking model's decisions part from the rate model's: one stage at a time.

One command (from the repository root, one thread, about 3 minutes on a quiet host):

    PYTHONPATH=. .venv/bin/python experiments/spiking_split.py [--seeds 0-7]
        [--data corridor,lens] [--variants all] [--out experiments/results]

The spiking conversion (``torchseq.neural.spiking``) differs from the rate model
(``docs/guide/neural.md``, "Step maths") in four stages. This script recomputes the pipeline
in float64 with each stage either as the spiking model has it or as the rate model has it,
on the rate model of each seed (``NeuralConfig(seed=s)``, fitted on the reference; every
calibration on the reference only), and reports the agreement of its decisions with the rate
model's over the query frames. A variant is ``l2:norm:rect:ring``:

- ``l2``: ``fixed`` (the spiking model's one threshold ``theta2``, taken from
  :meth:`SpikingSeqSLAM.convert`), ``kwta`` (the rate model's exact ``k`` winners),
  ``centred`` (one threshold on ``x @ (w1 - row mean).T``: the frame's mean L1 sum removed),
  ``linear<lam>`` (a threshold linear in the input, ``b + x @ c``, ridge-fitted with
  ``lam * R`` on the reference frames' ``k``-th/``k+1``-th midpoints and folded into ``w1``:
  ``(w1 - 1 c^T) / b``).
- ``norm``: ``fixed`` (the calibrated ``sigma_c``) or ``frame`` (each frame's own std).
- ``rect``: ``ring`` (the ring rectifies ``e + cycle``, as the spiking ring does) or
  ``evidence`` (the rate model's ``max(z, 0)`` before the ring).
- ``ring``: ``K<n>`` (rounded onto the default geometric ladder of ``n`` rungs every frame)
  or ``exact``.

``fixed:fixed:ring:K128`` is the spiking model (checked: its decisions equal
``SpikingSeqSLAM.run``'s on every frame) and ``kwta:frame:evidence:exact`` the rate model
(checked: equal to ``NeuralSeqSLAM.run``'s on every frame; the script fails otherwise).
Writes ``spiking_split.json`` under ``--out`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

from neural_quality import datasets  # noqa: E402
from spiking_agreement import seeds_arg  # noqa: E402

from torchseq.atomic import write_json  # noqa: E402
from torchseq.layers.functional import kwta  # noqa: E402
from torchseq.neural import NeuralConfig, NeuralSeqSLAM  # noqa: E402
from torchseq.neural.readout import decide  # noqa: E402
from torchseq.neural.spiking import SpikingConfig, SpikingSeqSLAM, ladder  # noqa: E402

SPIKING = "fixed:fixed:ring:K128"
RATE = "kwta:frame:evidence:exact"
VARIANTS = {
    SPIKING: "the spiking model (default K = 128)",
    "fixed:frame:evidence:exact": "only L2 approximate (one threshold)",
    "kwta:fixed:evidence:exact": "only the normalisation approximate (calibrated sigma)",
    "kwta:frame:ring:exact": "only the rectification approximate (on the ring's input)",
    "kwta:frame:evidence:K128": "only the ladder approximate, K = 128",
    "kwta:frame:evidence:K512": "only the ladder approximate, K = 512",
    "kwta:frame:evidence:K1024": "only the ladder approximate, K = 1024",
    "kwta:frame:evidence:K2048": "only the ladder approximate, K = 2048",
    "fixed:fixed:ring:exact": "the spiking model, ring unquantised",
    "fixed:fixed:ring:K1024": "the spiking model, K = 1024",
    "fixed:fixed:evidence:exact": "the spiking model, evidence rectified, ring unquantised",
    "fixed:fixed:evidence:K128": "the spiking model, evidence rectified",
    "fixed:fixed:evidence:K1024": "the spiking model, evidence rectified, K = 1024",
    "fixed:frame:evidence:K2048": "only L2 approximate, K = 2048",
    "kwta:fixed:evidence:K2048": "only the normalisation approximate, K = 2048",
    "kwta:fixed:ring:K128": "the spiking model with an exact k-WTA",
    "kwta:fixed:ring:exact": "the spiking model with an exact k-WTA, ring unquantised",
    "centred:fixed:ring:K128": "the spiking model, w1 centred over L2 units",
    "linear0.001:fixed:ring:K128": "the spiking model, linear threshold (ridge 1e-3 R)",
    "linear1:fixed:ring:K128": "the spiking model, linear threshold (ridge R)",
    "linear30:fixed:ring:K128": "the spiking model, linear threshold (ridge 30 R)",
    "linear30:frame:evidence:exact": "only L2 approximate (linear threshold, ridge 30 R)",
    RATE: "the rate model (every stage exact)",
}


def l2_rule(kind: str, xr: torch.Tensor, w1: torch.Tensor, k: int, theta2: float):
    """``x (T, D) -> z2 (T, M)`` float64 0/1, calibrated on the reference inputs ``xr``."""
    if kind == "kwta":
        return lambda x: kwta(x @ w1.T, k, binary=True)
    if kind == "fixed":  # the spiking model's own theta2 (grid-centred)
        return lambda x: (x @ w1.T > theta2).double()
    if kind == "centred":
        w = w1 - w1.mean(0, keepdim=True)
        top = (xr @ w.T).topk(k + 1, dim=1).values
        th = float(torch.quantile((top[:, k - 1] + top[:, -1]) / 2, 0.5))
        return lambda x: (x @ w.T > th).double()
    if kind.startswith("linear"):
        top = (xr @ w1.T).topk(k + 1, dim=1).values
        mid = (top[:, k - 1] + top[:, -1]) / 2  # (R,) the per-frame threshold to fit
        a = torch.cat([torch.ones(xr.shape[0], 1, dtype=xr.dtype), xr], 1)
        reg = float(kind[6:]) * xr.shape[0] * torch.eye(a.shape[1], dtype=xr.dtype)
        reg[0, 0] = 0.0  # the intercept is not shrunk
        coef = torch.linalg.solve(a.T @ a + reg, a.T @ mid)
        b, c = float(coef[0]), coef[1:]
        if not b > 0:
            raise ValueError(f"linear threshold: intercept {b} <= 0 cannot be folded")
        w = (w1 - c[None, :]) / b
        return lambda x: (x @ w.T > 1.0).double()
    raise ValueError(f"unknown l2 rule {kind!r}")


def simulate(model, xr, xq, theta2: float, variant: str):
    """Decisions ``(T,)`` and L2 firing counts ``(T,)`` of one variant over the query."""
    l2, norm, rect, ring = variant.split(":")
    w1 = model.l1.folded_weight().detach().double()
    w3 = model.l3.folded_weight().detach().double()
    g = model.cohorts.detach().double()
    decay, gain = (float(v) for v in model.ring.params)
    s = model.ring.shift.detach().double()
    eps = model.config.eps
    code = l2_rule(l2, xr, w1, model.config.k, theta2)
    n_c = g.sum(0).clamp_min(1.0)

    def centred_sd(z2):
        e = z2 @ w3.T
        mu = ((e @ g) / n_c) @ g.T
        return e - mu, ((((e - mu) ** 2) @ g) / n_c).sqrt()  # (T, N), (T, C)

    def evidence(z2, sigma):
        c, sd = centred_sd(z2)
        e = gain * c / (sd @ g.T + eps) if norm == "frame" else gain * c / (sigma @ g.T)
        return e.clamp_min(0.0) if rect == "evidence" else e

    sigma = torch.quantile(centred_sd(code(xr))[1], 0.5, dim=0).clamp_min(eps)
    levels = None if ring == "exact" else int(ring[1:])
    if levels is not None:  # the ladder's top: the unquantised ring's largest activity
        er = evidence(code(xr), sigma)
        a, a_max = torch.zeros(er.shape[1], dtype=torch.float64), 0.0
        for t in range(er.shape[0]):
            a = (er[t] + decay * (s @ a)).clamp_min(0.0)
            a_max = max(a_max, float(a.max()))
        rungs, theta = ladder(SpikingConfig(levels=levels), a_max)
        values = torch.cat([torch.zeros(1, dtype=torch.float64), rungs])
    zq = code(xq)
    eq = evidence(zq, sigma)
    q, out = torch.zeros(eq.shape[1], dtype=torch.float64), []
    for t in range(eq.shape[0]):
        u = eq[t] + decay * (s @ q)
        if levels is None:
            q = u.clamp_min(0.0)
            out.append(q)
        else:
            count = (u[:, None] > theta[None, :]).sum(1)
            q = values[count]
            out.append(count.double())
    ref = decide(torch.stack(out), model.unit_centre, model.config.uniqueness_window)[0]
    return ref.numpy(), zq.sum(1).numpy()


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-7")
    ap.add_argument("--data", default="corridor,lens")
    ap.add_argument("--variants", default="all", help="'all' or comma-separated l2:norm:rect:ring")
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    seeds = seeds_arg(args.seeds)
    variants = list(VARIANTS) if args.variants == "all" else args.variants.split(",")
    results = {}
    for name, (ref, qry, _gt) in datasets(tuple(args.data.split(","))).items():
        if name.endswith("+-2"):
            continue
        agree = {v: [] for v in variants}
        firing = {v: [] for v in variants}
        for seed in seeds:
            model = NeuralSeqSLAM(NeuralConfig(seed=seed))
            model.fit(ref, log=False)
            rate = model.run(qry).matches.reference.numpy()
            sp = SpikingSeqSLAM.convert(model, ref)
            spiking = sp.run(qry)["reference"].numpy()
            xr, xq = model.encode(ref).double(), model.encode(qry).double()
            for v in variants:
                refs, fired = simulate(model, xr, xq, sp.calibration["theta2"], v)
                # the two ends of the split are the two models, frame for frame
                if v == RATE and not np.array_equal(refs, rate):
                    raise SystemExit(f"{name} seed {seed}: the all-exact variant is not the "
                                     f"rate model on {int(np.sum(refs != rate))} frames")
                if v == SPIKING and not np.array_equal(refs, spiking):
                    raise SystemExit(f"{name} seed {seed}: the spiking variant differs from "
                                     f"SpikingSeqSLAM on {int(np.sum(refs != spiking))} frames")
                agree[v].append(float(np.mean(refs == rate)))
                firing[v].append([int(fired.min()), float(np.median(fired)), int(fired.max())])
            print(f"{name} seed {seed} done", flush=True)
        results[name] = {v: {"agreement": agree[v], "l2_firing_min_median_max": firing[v]}
                         for v in variants}
    write_json(Path(args.out) / "spiking_split.json", {"seeds": seeds, "results": results})
    print("| data | variant | what | " + " | ".join(f"seed {s}" for s in seeds)
          + " | worst | mean | L2 units firing per frame (min..max) |")
    print("|" + "---|" * (len(seeds) + 6))
    for name, rows in results.items():
        for v, r in rows.items():
            a, f = r["agreement"], np.array(r["l2_firing_min_median_max"])
            print(f"| {name} | `{v}` | {VARIANTS.get(v, '')} | "
                  + " | ".join(f"{x:.3f}" for x in a)
                  + f" | {min(a):.3f} | {np.mean(a):.3f} | "
                  + f"{f[:, 0].min():.0f}..{f[:, 2].max():.0f} |")
    return results


if __name__ == "__main__":
    main()

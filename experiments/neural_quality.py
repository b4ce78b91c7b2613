"""Neural SeqSLAM quality: recall@1 / AUC on the demo, corridor and LENS DAVIS data.

One command (from the repository root):

    .venv/bin/python experiments/neural_quality.py [--out experiments/results] [--ablation]

Writes ``neural_quality.json`` and ``neural_quality.md`` (a Markdown table) under ``--out``,
prints the table. ``--offsets``, ``--long-routes 500,3000,20000`` and ``--repeat`` add the
offset histograms, the long-route table and the wrong-repeat counts (issue 15), each also
written to its own ``neural_<section>.json``/``.md`` and its block of docs/results/neural.md;
``--skip-main`` runs only those; ``--long-velocity`` adds the adaptive rings to the
long-route and units-of-several-frames tables. With ``--ablation`` it also runs the
ablation over the model's settings and the harder demo variants (appearance change, speed,
repetitive scenery). Every section rewrites its tables in docs/results/neural.md (unless
``--no-docs``).
Classic SeqSLAM (``torchseq.seqslam``, default settings) runs beside it on the same data.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from dataclasses import fields, replace
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
                     "demo-severe-1.0x": dict(gain=0.45, gamma=2.4, gradient=0.45, noise=20.0,
                                              speed=1.0),
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
    "Table 1 L2->L3 mask (density_out 0.2)": dict(density_out=0.2),
    "density_out 0.5": dict(density_out=0.5),
    "dense_readout() (decay 0.96)": dict(ring_decay=0.96),
    "patch 8": dict(patch_size=8),
    "patch seqslam rounding": dict(patch_mode="seqslam"),
    "no rectify": dict(rectify=False),
    "no ring (decay 0)": dict(ring_decay=0.0, ring_gain=1.0),
    "ring decay 0.9": dict(ring_decay=0.9),
    "ring decay 0.95": dict(ring_decay=0.95),
    "ring decay 0.98": dict(ring_decay=0.98),
    "spread 1, no stay": dict(ring_spread=1, ring_stay=0.0),
    "spread 3": dict(ring_spread=3),
    "stay 0.75 (ring prior 0.89x)": dict(ring_stay=0.75),
    "stay 0.25 (ring prior 1.14x)": dict(ring_stay=0.25),
    "hebbian mean": dict(hebbian="mean"),
    "k 15%": dict(k_fraction=0.15),
    "input 32x64": dict(input_size=(32, 64)),
    "cohorts 4": dict(n_cohorts=4),
    "cohorts 8": dict(n_cohorts=8),
    # issue 15: the ring's speed estimated online (torchseq/neural/velocity.py)
    "ring_velocity adaptive": dict(ring_velocity="adaptive"),
    "adaptive, rate 1 (no smoothing)": dict(ring_velocity="adaptive", velocity_rate=1.0),
    "adaptive, window 32": dict(ring_velocity="adaptive", velocity_window=32),
    "adaptive, stay 0.25, spread decay 0.25 (lags 0.25/1/0.25)": dict(
        ring_velocity="adaptive", ring_stay=0.25, ring_spread_decay=0.25),
    "adaptive_velocity() (adaptive, spread 1, no stay)": dict(
        ring_velocity="adaptive", ring_spread=1, ring_stay=0.0),
}


# ---------------------------------------------------------------- offsets (issue 15)
OFFSET_BINS = tuple(range(-3, 4))


def offset_row(label: str, engine: str, offsets: np.ndarray, n_unmatched: int = 0) -> dict:
    """Histogram of decision - truth (in reference frames, rounded), its median, exact share."""
    r = np.round(offsets).astype(np.int64)
    row = {"data": label, "engine": engine, "decisions": int(r.size)}
    row["< -3"] = f"{np.mean(r < -3):.2f}"
    for b in OFFSET_BINS:
        row[f"{b:+d}"] = f"{np.mean(r == b):.2f}"
    row["> +3"] = f"{np.mean(r > 3):.2f}"
    row["median"] = f"{np.median(offsets):+.1f}"
    row["exact"] = f"{np.mean(r == 0):.3f}"
    row["unmatched"] = n_unmatched
    return row


def content_alignment(ref: torch.Tensor, query: torch.Tensor, size=(24, 32), span=3) -> dict:
    """Engine-free alignment: mean L1 difference of whole-frame z-scored frames, query ``j``
    against reference ``j + d`` for ``d`` in ``-span..span`` (same-length traverses)."""
    from torchseq.preprocess import resize, to_grey
    def flat(x):
        x = resize(to_grey(x).to(torch.float32), size).reshape(len(x), -1).double()
        return (x - x.mean(1, keepdim=True)) / (x.std(1, keepdim=True) + 1e-9)
    r, q = flat(ref), flat(query)
    out = {}
    for d in range(-span, span + 1):
        j = np.arange(len(q))
        j = j[(j + d >= 0) & (j + d < len(r))]
        out[f"{d:+d}"] = float((q[j] - r[j + d]).abs().mean())
    return out


def offsets_section(data: dict, seeds: int) -> tuple[list[dict], list[dict]]:
    """Offsets of both engines' decisions: LENS and corridor against their query index (the
    centre of their ground truth), the demo against its exact query positions; SeqSLAM under
    each ``match_at`` rule."""
    rows, align = [], []
    cases = {}
    for name in ("lens", "corridor"):
        if name in data:
            ref, query, _ = data[name]
            cases[name] = (ref, query, np.arange(len(query), dtype=np.float64))
    for speed in (0.8, 1.0, 1.3):
        d = make_demo(speed=speed)
        cases[f"demo speed {speed}"] = (d.reference, d.query, d.query_position)
    for name, (ref, query, truth) in cases.items():
        off = []
        for seed in range(seeds):
            model = NeuralSeqSLAM(replace(NeuralConfig(), seed=seed))
            model.fit(ref, log=False)
            off.append(model.run(query).matches.reference.numpy() - truth)
        rows.append(offset_row(name, f"neural ({seeds} seeds)", np.concatenate(off)))
        for label, got in seqslam_places(ref, query).items():
            ok = got >= 0
            rows.append(offset_row(name, label, got[ok] - truth[ok], int((~ok).sum())))
        if name in ("lens", "corridor"):
            a = content_alignment(ref, query)
            align.append({"data": name, **{k: f"{v:.4f}" for k, v in a.items()},
                          "best": min(a, key=a.get)})
        print(*rows[-3:], sep="\n", flush=True)
    return rows, align


def seqslam_places(ref: torch.Tensor, query: torch.Tensor) -> dict:
    """Classic SeqSLAM's decisions under each ``match_at`` rule (the default config
    otherwise; one engine run, both rules read from its enhanced matrix by the engine's own
    search): ``{"SeqSLAM (trajectory, default)": (Q,), "SeqSLAM (start + ds/2)": (Q,)}``."""
    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
    from torchseq.seqslam.search import search
    cfg = replace(SeqSLAMConfig(), keep_matrices=True)
    engine = SeqSLAM(cfg)
    res = engine.match(ref, query)
    out = {}
    for rule, label in (("trajectory", "SeqSLAM (trajectory, default)"),
                        ("start", "SeqSLAM (start + ds/2)")):
        got = search(res.enhanced, cfg.sequence_length, engine.speeds, cfg.rwindow, cfg.top_k,
                     cfg.max_chunk_elements, match_at=rule)[0].numpy()
        if rule == cfg.match_rule and not np.array_equal(got, res.matches.reference.numpy()):
            raise RuntimeError("search on the enhanced matrix disagrees with the engine")
        out[label] = got
    return out


def frame_differences(ref: torch.Tensor, query: torch.Tensor, size=(24, 32),
                      patch: int = 0) -> np.ndarray:
    """``(Q, R)`` mean L1 difference of whole-frame z-scored frames (no engine); ``patch``
    > 0: of OpenSeqSLAM's patch-normalised images (``patch`` x ``patch`` blocks) instead."""
    from torchseq.preprocess import patch_normalise, resize, to_grey

    def flat(x):
        x = resize(to_grey(x).to(torch.float32), size)
        if patch:
            return patch_normalise(x, patch, "seqslam").reshape(len(x), -1).double()
        x = x.reshape(len(x), -1).double()
        return (x - x.mean(1, keepdim=True)) / (x.std(1, keepdim=True) + 1e-9)
    r, q = flat(ref), flat(query)
    return (torch.cdist(q, r, p=1) / r.shape[1]).numpy()


def local_content_offset(diff: np.ndarray, half: int = 2, search: int = 5) -> np.ndarray:
    """Per query ``j``, the offset ``d`` (``|d| <= search``) at which the content aligns:
    ``argmin_d mean_{k=-half..half} diff[j + k, j + k + d]`` (pairs inside both traverses;
    first ``d`` on ties). ``(Q, R) -> (Q,)`` int64; the query index is the reference."""
    n_q, n_r = diff.shape
    out = np.zeros(n_q, np.int64)
    for j in range(n_q):
        best = np.inf
        for d in range(-search, search + 1):
            k = np.arange(max(-half, -j, -j - d), min(half, n_q - 1 - j, n_r - 1 - j - d) + 1)
            if k.size == 0:
                continue
            v = diff[j + k, j + k + d].mean()
            if v < best:
                best, out[j] = v, d
    return out


def refined_decision(model: NeuralSeqSLAM, activity: torch.Tensor, evidence: torch.Tensor,
                     beta: float, window: int | None) -> np.ndarray:
    """Post-hoc readout experiment (not a library option): ``argmax(a + beta z)``, over the
    units within ``window`` of the ring's winner (None: every unit). ``beta = 0``: default."""
    score = activity + beta * evidence
    if window is not None:
        u0 = activity.argmax(1, keepdim=True)
        near = (torch.arange(activity.shape[1])[None, :] - u0).abs() <= window
        score = torch.where(near, score, torch.tensor(-float("inf")))
    return model.unit_centre[score.argmax(1)].numpy()


REFINE = {"ring argmax (default)": (0.0, None), "a + 0.3 z within +-1 unit": (0.3, 1),
          "a + 0.3 z within +-2 units": (0.3, 2), "a + 0.03 z": (0.03, None),
          "a + 0.1 z": (0.1, None)}


def preset_changes(cfg: NeuralConfig) -> dict:
    """The fields where ``cfg`` differs from the default ``NeuralConfig()``."""
    base = NeuralConfig()
    return {f.name: getattr(cfg, f.name) for f in fields(cfg)
            if getattr(cfg, f.name) != getattr(base, f.name)}


LONG_RINGS = {  # the rings of the long-route and several-frames tables (--long-velocity)
    "fixed": {},
    "ring_velocity adaptive": dict(ring_velocity="adaptive"),
    "adaptive_velocity()": preset_changes(NeuralConfig.adaptive_velocity()),
}


def median_speed_estimate(model: NeuralSeqSLAM, query: torch.Tensor) -> float:
    """An adaptive model's speed estimate, stepped frame by frame over ``query``: the
    median over its second half."""
    inf, state, v = model.inference(), None, []
    for t in range(len(query)):
        _, state = inf.step(query[t:t + 1], state)
        v.append(float(state.velocity[0]))
    return float(np.median(v[len(v) // 2:]))


def coarse_unit_rows(n_reference: int = 3000, speeds=(0.8, 1.0, 1.3),
                     rings=("fixed",)) -> list[dict]:
    """Signed offsets when units hold several frames (a long demo route on the default 555
    units, 48x64 frames as in the long-route table, seed 0): per ring (:data:`LONG_RINGS`)
    and readout the decisions against the exact positions, and which unit wins against the
    unit holding the query's nearest frame, for the ring and for the feed-forward evidence
    alone (argmax of z); for an adaptive ring also its speed estimate (median over the
    second half of the query; the demo's speed is the truth)."""
    rows = []
    for speed in speeds:
        d = make_demo(n_reference=n_reference, size=(48, 64), step=4.0,
                      dense_ground_truth=False, speed=speed)
        truth = np.asarray(d.query_position)
        for ring, readout in ((r, o) for r in rings for o in ("centre", "interpolate")):
            model = NeuralSeqSLAM(replace(NeuralConfig(), readout=readout, **LONG_RINGS[ring]))
            with warnings.catch_warnings():  # fit warns about units of several frames
                warnings.simplefilter("ignore")
                model.fit(d.reference, log=False)
            res = model.run(d.query)
            off = res.matches.reference.numpy() - truth
            row = {"speed": f"{speed}x", "ring": ring, "readout": readout,
                   "frames per unit": f"{n_reference / model.n_units:.1f}",
                   "median offset": f"{np.median(off):+.1f}",
                   "exact": f"{np.mean(np.round(off) == 0):.2f}",
                   "within +-2": f"{np.mean(np.abs(off) <= 2):.3f}"}
            if readout == "centre":
                last = model.unit_to_reference[:, 1].numpy()
                unit = np.searchsorted(last, np.clip(np.round(truth), 0, n_reference - 1),
                                       side="right")
                with torch.inference_mode():
                    z = model.evidence(model.code(model.encode(d.query)))
                for lab, x in (("ring", res.activity), ("evidence", z)):
                    du = x.argmax(1).numpy() - unit
                    row[f"{lab}: previous unit"] = f"{np.mean(du < 0):.2f}"
                    row[f"{lab}: right unit"] = f"{np.mean(du == 0):.2f}"
                if model.config.ring_velocity == "adaptive":
                    row["speed estimate"] = f"{median_speed_estimate(model, d.query):.2f}"
            rows.append(row)
            print(row, flush=True)
    return rows


def relative_offsets_section(data: dict, seeds: int) -> tuple[list[dict], list[dict],
                                                              list[dict]]:
    """Offsets measured against the data's own alignment instead of the file's ground truth:
    the local content offset (LENS, corridor), the network's own feed-forward evidence
    (argmax of z, no ring: what the ring adds) and SeqSLAM's decision; on LENS the same
    against content measured with other frames and diagonals; then the readout
    experiment (current evidence added at read-out) on LENS, corridor and demo speeds."""
    cases = {}
    for name in ("lens", "corridor"):
        if name in data:
            ref, query, gt = data[name]
            cases[name] = (ref, query, np.arange(len(query), dtype=np.float64), gt)
    if "lens" in data:
        i = np.arange(len(data["lens"][0]))
        cases["lens+-2"] = (*cases["lens"][:3], np.abs(i[:, None] - i[None, :]) <= 2)
    for speed in (0.6, 0.8, 1.0, 1.3, 1.6):
        d = make_demo(speed=speed)
        cases[f"demo speed {speed}"] = (d.reference, d.query, np.asarray(d.query_position),
                                        np.asarray(d.ground_truth))
    rows, robust, refine = [], [], {k: {"readout": k} for k in REFINE}
    for name, (ref, query, truth, gt) in cases.items():
        gt = np.asarray(gt, bool)
        places = seqslam_places(ref, query)
        ss = places["SeqSLAM (trajectory, default)"]
        ok = ss >= 0
        content = None
        if name in ("lens", "corridor"):
            content = np.arange(len(query)) + local_content_offset(frame_differences(ref, query))
        got, own, by = [], [], {k: ([], []) for k in REFINE}
        for seed in range(seeds):
            model = NeuralSeqSLAM(replace(NeuralConfig(), seed=seed))
            model.fit(ref, log=False)
            activity = model.run(query).activity
            with torch.inference_mode():
                z = model.evidence(model.code(model.encode(query)))
            got.append(model.unit_centre[activity.argmax(1)].numpy())
            own.append(model.unit_centre[z.argmax(1)].numpy())
            for k, (beta, window) in REFINE.items():
                dec = refined_decision(model, activity, z, beta, window)
                by[k][0].append(dec - (truth if content is None else content))
                by[k][1].append(gt[dec, np.arange(len(query))].mean())
        g, o = np.concatenate(got), np.concatenate(own)
        if name == "lens":  # the content measure's own choices: descriptor and diagonal
            for label, kw in (("z-scored 24x32", {}), ("z-scored 32x64", {"size": (32, 64)}),
                              ("SeqSLAM patch-normalised 32x64", {"size": (32, 64),
                                                                  "patch": 8})):
                diff = frame_differences(ref, query, **kw)
                for half in (1, 2, 5):
                    c = np.arange(len(query)) + local_content_offset(diff, half)
                    rn, rs = g - np.tile(c, seeds), (ss - c)[ok]
                    robust.append({"content frames": label, "diagonal": f"+-{half}",
                                   "content - truth median": f"{np.median(c - truth):+.0f}",
                                   "neural median": f"{np.median(rn):+.0f}",
                                   "neural exact": f"{np.mean(rn == 0):.2f}",
                                   "SeqSLAM median": f"{np.median(rs):+.0f}",
                                   "SeqSLAM exact": f"{np.mean(rs == 0):.2f}",
                                   "SeqSLAM +1": f"{np.mean(rs == 1):.2f}"})
        if content is not None:
            rows.append(offset_row(name, f"neural ({seeds} seeds)", g - np.tile(content, seeds)))
            rows[-1]["against"] = "content"
            for label, got in places.items():
                sel = got >= 0
                rows.append(offset_row(name, label, (got - content)[sel], int((~sel).sum())))
                rows[-1]["against"] = "content"
        if name != "lens+-2":
            rows.append(offset_row(name, f"neural ({seeds} seeds)", g - o))
            rows[-1]["against"] = "own evidence (no ring)"
            rows.append(offset_row(name, f"neural ({seeds} seeds)",
                                   (g - np.tile(ss, seeds))[np.tile(ok, seeds)]))
            rows[-1]["against"] = "SeqSLAM"
        against = "content" if content is not None else "truth"
        for k in REFINE:
            off = np.round(np.concatenate(by[k][0])).astype(np.int64)
            cell = f"{np.mean(by[k][1]):.3f}"
            if name != "lens+-2":
                cell += f" / {np.mean(off == 0):.2f} / {np.median(np.concatenate(by[k][0])):+.1f}"
            refine[k][name + ("" if name == "lens+-2" else f" (vs {against})")] = cell
        print(rows[-1], flush=True)
    order = ["data", "engine", "against"]
    rows = [{**{c: r[c] for c in order}, **{c: v for c, v in r.items() if c not in order}}
            for r in rows]
    return rows, robust, list(refine.values())


# ---------------------------------------------------------------- long routes (issue 15)
def long_route_row(n_reference: int, seeds: int, with_seqslam: bool,
                   readout: str = "centre", n_output: int | None = None,
                   recruit: str = "uniform", ring: str = "fixed") -> dict:
    """A demo route of ``n_reference`` frames (48x64 frames, 4 px per frame, query at 0.8x):
    recall@1 within the demo's +-2 frames, the decisions' |offset| (and their median signed
    offset), bytes beside SeqSLAM's; ``ring`` names a :data:`LONG_RINGS` setting."""
    from torchseq.neural.memory import seqslam_bytes
    d = make_demo(n_reference=n_reference, size=(48, 64), step=4.0, dense_ground_truth=False)
    truth = d.query_position
    row = {"reference frames": n_reference, "query frames": len(truth), "recruit": recruit,
           "ring": ring, "readout": readout}
    rec, med, p90, signed, fit_s, run_s, longest = [], [], [], [], [], [], []
    for seed in range(seeds):
        cfg = replace(NeuralConfig(), seed=seed, readout=readout, recruit=recruit,
                      **LONG_RINGS[ring])
        model = NeuralSeqSLAM(cfg if n_output is None else replace(cfg, n_output=n_output))
        t0 = time.perf_counter()
        with warnings.catch_warnings():  # fit warns about units of several frames
            warnings.simplefilter("ignore")
            model.fit(d.reference, log=False)
        fit_s.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        got = model.run(d.query).matches.reference.numpy()
        run_s.append(time.perf_counter() - t0)
        err = np.abs(got - truth)
        rec.append(float(np.mean(err <= d.tolerance)))  # every query is a positive here
        med.append(float(np.median(err)))
        p90.append(float(np.percentile(err, 90)))
        signed.append(float(np.median(got - truth)))
        spans = model.unit_to_reference
        longest.append(int((spans[:, 1] - spans[:, 0]).max()))
    row["units"] = model.n_units
    row["frames per unit (mean / longest)"] = f"{n_reference / model.n_units:.1f} / {max(longest)}"
    row["neural recall_at_1"] = f"{np.mean(rec):.3f}"
    row["neural median abs offset"] = f"{np.mean(med):.2f}"
    row["neural p90 abs offset"] = f"{np.mean(p90):.2f}"
    row["neural median offset"] = f"{np.mean(signed):+.2f}"
    row["neural MB (dense / masked)"] = (f"{model.model_bytes() / 1e6:.1f} / "
                                         f"{model.model_bytes(masked_only=True) / 1e6:.1f}")
    row["neural fit + run s"] = f"{np.mean(fit_s):.1f} + {np.mean(run_s):.1f}"
    row["SeqSLAM MB"] = f"{seqslam_bytes(n_reference) / 1e6:.1f}"
    row["seeds"] = seeds
    if with_seqslam:
        from torchseq.seqslam import SeqSLAM
        t0 = time.perf_counter()
        got = SeqSLAM().match(d.reference, d.query).matches.reference.numpy()
        ok = got >= 0
        err = np.abs(got - truth)
        row["SeqSLAM recall_at_1"] = f"{np.mean(ok & (err <= d.tolerance)):.3f}"
        row["SeqSLAM median abs offset"] = f"{np.median(err[ok]):.2f}"
        row["SeqSLAM s"] = f"{time.perf_counter() - t0:.1f}"
    print(row, flush=True)
    return row


def dwelling_demo(n_reference: int = 600, seed: int = 0):
    """A demo route whose scenery changes unevenly: the reference camera dwells.

    ``make_demo`` moves the reference camera at one speed; here it alternates stretches of
    60 frames at 4 px per frame with stretches of 60 frames at 0.5 px per frame (the demo's
    world, lighting and noise functions, 48x64 frames). The query moves at 3.2 px per frame
    (the long-route table's 0.8x of 4 px) under the demo's default relighting. Returns
    ``(reference, query, reference positions, query positions)``, positions in pixels.
    """
    from torchseq.demo import make_world, relight, render
    steps = np.where((np.arange(n_reference) // 60) % 2 == 0, 4.0, 0.5)
    ref_pos = np.concatenate([[0.0], np.cumsum(steps[:-1])])
    query_pos = np.arange(0.0, ref_pos[-1] + 1e-9, 3.2)
    world = make_world(int(np.ceil(ref_pos[-1])) + 64 + 2, 48, seed)
    rng = np.random.default_rng(seed + 1)
    ref = relight(render(world, ref_pos, 64), 1.0, 1.0, 0.0, 2.0, rng)
    query = relight(render(world, query_pos, 64), 0.8, 1.3, 0.15, 6.0, rng)
    return torch.from_numpy(ref), torch.from_numpy(query), ref_pos, query_pos


def recruit_real_rows(data: dict, seeds: int, rings=("fixed",)) -> list[dict]:
    """Uniform against novelty recruitment where units hold 2-3 frames: the corridor and
    LENS at 55 and 37 units (recall@1 at their ground truth; |offset| against the query
    index, their same-length traverses) and :func:`dwelling_demo` at 300 and 200 units (a
    decision is right within 8 px = two 4 px frames of the query's position; |offset| in
    those 4 px frames). ``rings`` beyond ``"fixed"`` (:data:`LONG_RINGS`) add rows with
    uniform recruitment."""
    cases = {name: (*data[name], (55, 37)) for name in ("corridor", "lens", "lens+-2")
             if name in data}
    ref, query, ref_pos, query_pos = dwelling_demo()
    cases["dwelling demo"] = (ref, query, None, (300, 200))
    rows = []
    for name, (ref, query, gt, n_outputs) in cases.items():
        for n_output in n_outputs:
            for readout in ("centre", "interpolate"):
                for recruit, ring in [("uniform", "fixed"), ("novelty", "fixed"),
                                      *(("uniform", r) for r in rings if r != "fixed")]:
                    rec, med = [], []
                    for seed in range(seeds):
                        cfg = replace(NeuralConfig(), seed=seed, n_output=n_output,
                                      readout=readout, recruit=recruit, **LONG_RINGS[ring])
                        model = NeuralSeqSLAM(cfg)
                        with warnings.catch_warnings():  # units of several frames: fit warns
                            warnings.simplefilter("ignore")
                            model.fit(ref, log=False)
                        res = model.run(query)
                        got = res.matches.reference.numpy()
                        if gt is None:  # the dwelling demo: positions in pixels
                            err = np.abs(ref_pos[got] - query_pos) / 4.0
                            rec.append(float(np.mean(err <= 2.0)))
                        else:
                            err = np.abs(got - np.arange(len(query)))
                            rec.append(evaluate(res.matches, gt)["recall_at_1"])
                        med.append(float(np.median(err)))
                    spans = model.unit_to_reference
                    rows.append({"data": name, "R": len(ref), "units": model.n_units,
                                 "readout": readout, "recruit": recruit, "ring": ring,
                                 "recall_at_1 mean / worst": f"{np.mean(rec):.3f} / "
                                                             f"{np.min(rec):.3f}",
                                 "median abs offset": f"{np.mean(med):.2f}",
                                 "longest unit (seed 7)": int((spans[:, 1] - spans[:, 0]).max()),
                                 "MB (dense / masked)": f"{model.model_bytes() / 1e6:.2f} / "
                                 f"{model.model_bytes(masked_only=True) / 1e6:.2f}",
                                 "seeds": seeds})
                    print(rows[-1], flush=True)
    return rows


# ---------------------------------------------------------------- repeats (issue 15)
def repeat_rows(repeats=(2, 3), seeds: int = 8, n_reference: int = 200) -> list[dict]:
    """False matches to the wrong repeat on ``make_demo(repeat=r)``.

    The repeated stretch is reference frames ``lo .. lo + r * seg`` (``lo = round(R / 4)``,
    ``seg = round(R / (2 r))``, as in :func:`torchseq.demo.make_demo`). A decision for a
    query whose true place lies there is "wrong repeat" when it is not within the tolerance
    of the truth but within it of the same place in another copy (truth +- k seg, k != 0).
    """
    from torchseq.seqslam import SeqSLAM
    rows = []
    for r in repeats:
        d = make_demo(repeat=r, n_reference=n_reference)
        lo, seg = round(0.25 * n_reference), max(1, round(0.5 * n_reference / r))
        truth = d.query_position
        inside = (truth >= lo) & (truth < lo + r * seg)
        ks = np.array([k for k in range(-r + 1, r) if k])

        def score(got, ok):
            err = np.abs(got - truth)
            right = ok & (err <= d.tolerance)
            other = np.abs(got[:, None] - (truth[:, None] + ks[None, :] * seg)).min(1)
            wrong_copy = ok & ~right & (other <= d.tolerance)
            lost = ~right & ~wrong_copy
            return (float(np.mean(right[inside])), float(np.mean(wrong_copy[inside])),
                    float(np.mean(right[~inside])), float(np.mean(lost[inside])))

        res = []
        for seed in range(seeds):
            model = NeuralSeqSLAM(replace(NeuralConfig(), seed=seed))
            model.fit(d.reference, log=False)
            got = model.run(d.query).matches.reference.numpy()
            res.append(score(got, np.ones_like(got, dtype=bool)))
        res = np.array(res)
        rows.append({"route": f"repeat={r} (copies of {seg} frames)", "engine":
                     f"neural ({seeds} seeds)", "queries in copies": int(inside.sum()),
                     "recall_at_1 in copies": f"{res[:, 0].mean():.3f}",
                     "wrong copy": f"{res[:, 1].mean():.3f} (max {res[:, 1].max():.3f})",
                     "other errors in copies": f"{res[:, 3].mean():.3f}",
                     "recall_at_1 elsewhere": f"{res[:, 2].mean():.3f}"})
        got = SeqSLAM().match(d.reference, d.query).matches.reference.numpy()
        s = score(got, got >= 0)
        rows.append({"route": f"repeat={r} (copies of {seg} frames)", "engine": "SeqSLAM",
                     "queries in copies": int(inside.sum()),
                     "recall_at_1 in copies": f"{s[0]:.3f}", "wrong copy": f"{s[1]:.3f}",
                     "other errors in copies": f"{s[3]:.3f}",
                     "recall_at_1 elsewhere": f"{s[2]:.3f}"})
        print(rows[-2], rows[-1], flush=True)
    return rows


# issue 15: settings measured over 8 seeds (mean / worst seed); each row changes the default
SEED_SWEEP = {
    "default (density_out 1.0)": {},
    "Table 1 L2->L3 mask (density_out 0.2; the default before the dense layer)":
        dict(density_out=0.2),
    "density_out 0.5": dict(density_out=0.5),
    "dense_readout() (decay 0.96)": dict(ring_decay=0.96),
    "decay 0.975": dict(ring_decay=0.975),
    "k 15%": dict(k_fraction=0.15),
    "input 32x64 (2,048 L1 units: 2.7x the L1 weights)": dict(input_size=(32, 64)),
    "55 units, centre readout": dict(n_output=55),
    "55 units, interpolate readout": dict(n_output=55, readout="interpolate"),
    "37 units, centre readout": dict(n_output=37),
    "37 units, interpolate readout": dict(n_output=37, readout="interpolate"),
    "ring_velocity adaptive": dict(ring_velocity="adaptive"),
    "adaptive_velocity() (adaptive, spread 1, no stay)": dict(
        ring_velocity="adaptive", ring_spread=1, ring_stay=0.0),
}


# ---------------------------------------------------------------- adaptive velocity (issue 15)
VELOCITY_SETTINGS = {
    "fixed ring (default)": {},
    "spread 1, no stay (fixed)": dict(ring_spread=1, ring_stay=0.0),
    "ring_velocity adaptive": dict(ring_velocity="adaptive"),
    "adaptive_velocity()": dict(ring_velocity="adaptive", ring_spread=1, ring_stay=0.0),
}
VELOCITY_SPEEDS = (0.6, 0.8, 1.0, 1.3, 1.6)


def velocity_estimate_rows(data: dict, seeds: int) -> list[dict]:
    """The adaptive models' speed estimate on the real routes (about the reference speed):
    its distribution over every query frame of ``seeds`` model seeds."""
    rows = []
    for label, kw in list(VELOCITY_SETTINGS.items())[2:]:
        for name in ("corridor", "lens"):
            if name not in data:
                continue
            ref, query, _ = data[name]
            v = []
            for seed in range(seeds):
                model = NeuralSeqSLAM(replace(NeuralConfig(), **kw, seed=seed))
                model.fit(ref, log=False)
                state = None
                for t in range(len(query)):
                    _, state = model.step(query[t:t + 1], state)
                    v.append(float(state.velocity[0]))
            v = np.array(v)
            rows.append({"setting": label, "data": name, "min": f"{v.min():.2f}",
                         "5%": f"{np.percentile(v, 5):.2f}", "median": f"{np.median(v):.2f}",
                         "95%": f"{np.percentile(v, 95):.2f}", "max": f"{v.max():.2f}",
                         "share within 0.1 of 1": f"{np.mean(np.abs(v - 1) <= 0.1):.2f}"})
            print(rows[-1], flush=True)
    return rows


def velocity_rows(seeds: int) -> list[dict]:
    """Demo speeds against the exact query positions, fixed and adaptive rings: recall@1 /
    exact share / median offset (decision - position), and the adaptive model's speed
    estimate over the second half of the query (median; the demo's speed is the truth)."""
    rows = []
    demos = {speed: make_demo(speed=speed) for speed in VELOCITY_SPEEDS}
    for label, kw in VELOCITY_SETTINGS.items():
        row = {"setting": label}
        for speed, d in demos.items():
            rec, exact, med, est = [], [], [], []
            for seed in range(seeds):
                model = NeuralSeqSLAM(replace(NeuralConfig(), **kw, seed=seed))
                model.fit(d.reference, log=False)
                matches = model.run(d.query).matches
                off = matches.reference.numpy() - np.asarray(d.query_position)
                rec.append(evaluate(matches, d.ground_truth)["recall_at_1"])
                exact.append(np.mean(np.round(off) == 0))
                med.append(np.median(off))
                if model.config.ring_velocity == "adaptive":
                    state, v = None, []
                    for t in range(len(d.query)):
                        _, state = model.step(d.query[t:t + 1], state)
                        v.append(float(state.velocity[0]))
                    est.append(np.median(v[len(v) // 2:]))
            cell = f"{np.mean(rec):.3f} / {np.mean(exact):.2f} / {np.median(med):+.1f}"
            row[f"speed {speed}"] = cell + (f" / v {np.mean(est):.2f}" if est else "")
        rows.append(row)
        print(row, flush=True)
    return rows
SWEEP_DATA = ("corridor", "lens", "lens+-2", "demo", "demo-severe", "demo-severe-1.0x",
              "demo-repeat", "demo-speed0.6", "demo-speed1.6")


def seed_sweep_rows(data: dict, seeds: int) -> list[dict]:
    """Recall@1 mean / worst over ``seeds`` model seeds for each :data:`SEED_SWEEP` row."""
    rows = []
    for label, kw in SEED_SWEEP.items():
        row = {"setting": label}
        for name in SWEEP_DATA:
            if name not in data:
                continue
            ref, query, gt = data[name]
            with warnings.catch_warnings():  # units of several frames: fit warns
                warnings.simplefilter("ignore")
                v = [run_neural(replace(NeuralConfig(), **kw, seed=seed), ref, query,
                                gt)["recall_at_1"] for seed in range(seeds)]
            row[name] = f"{np.mean(v):.3f} / {np.min(v):.3f}"
        rows.append(row)
        print(row, flush=True)
    row = {"setting": "classic SeqSLAM"}
    for name in SWEEP_DATA:
        if name in data:
            row[name] = f"{run_seqslam(*data[name])['recall_at_1']:.3f}"
    rows.append(row)
    return rows


def replace_block(text: str, name: str, body: str) -> str:
    """Replace ``<!-- name:start -->...<!-- name:end -->`` in ``text`` (unchanged if absent)."""
    a, b = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    if a not in text or b not in text:
        return text
    return text.split(a)[0] + a + "\n" + body.strip() + "\n" + b + text.split(b)[1]


def table(rows: list[dict], cols: list[str]) -> str:
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = [f"{r[c]:.3f}" if isinstance(r.get(c), float) else str(r.get(c, "")) for c in cols]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _write(out: Path, stem: str, results: dict, md: str) -> None:
    write_text(out / f"{stem}.json", json.dumps(results, indent=1, default=float))
    write_text(out / f"{stem}.md", md)


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
                   help="do not rewrite the tables in docs/results/neural.md")
    p.add_argument("--offsets", action="store_true",
                   help="offset histograms of both engines' decisions (LENS, corridor, demo)")
    p.add_argument("--long-routes", default="",
                   help="comma-separated demo route lengths, e.g. 500,3000,20000")
    p.add_argument("--long-seeds", type=int, default=2,
                   help="model seeds per long route (one for routes over 5,000 frames)")
    p.add_argument("--long-extra-units", type=int, default=0,
                   help="also run routes longer than this with n_output = this (interpolate)")
    p.add_argument("--long-recruit", default="uniform,novelty",
                   help="comma-separated recruit rules of the long-route rows")
    p.add_argument("--recruit-real", action="store_true",
                   help="with --long-routes: uniform vs novelty recruitment at 55 and 37 "
                        "units on the corridor, LENS and a dwelling demo route")
    p.add_argument("--long-velocity", action="store_true",
                   help="with --long-routes / --recruit-real / --relative-offsets: add rows "
                        "with the adaptive rings (plain and adaptive_velocity())")
    p.add_argument("--long-seqslam-max", type=int, default=3000,
                   help="longest route classic SeqSLAM also runs on")
    p.add_argument("--relative-offsets", action="store_true",
                   help="offsets against the data's own alignment and the readout experiment")
    p.add_argument("--repeat", action="store_true",
                   help="false matches to the wrong repeat on make_demo(repeat=2, 3)")
    p.add_argument("--seed-sweep", action="store_true",
                   help="issue 15's settings over --seeds model seeds (mean / worst)")
    p.add_argument("--velocity", action="store_true",
                   help="demo speeds with the fixed and adaptive rings (offsets, speed estimate)")
    p.add_argument("--skip-main", action="store_true",
                   help="skip the main table (run only the sections asked for)")
    args = p.parse_args(argv)
    long_rings = tuple(LONG_RINGS) if args.long_velocity else ("fixed",)
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    base = NeuralConfig()
    data = datasets()
    results = {"config": base.to_dict(), "main": [], "ablation": []}
    blocks = {}  # docs/results/neural.md marker name -> Markdown
    md = ""
    for name, (ref, query, gt) in ({} if args.skip_main else data).items():
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
    if not args.skip_main:
        md = (f"### Recall@1 and AUC, default settings (neural: mean +- std over {args.seeds} "
              "model seeds, their minimum, and seed 0)\n\n" + table(results["main"], cols)
              + "\n")
    quality_md, ablation_md = md, ""
    if args.offsets:
        rows, align = offsets_section(data, args.seeds)
        results["offsets"], results["alignment"] = rows, align
        part = ("### Offsets of the decisions (decision - truth, reference frames; share of "
                "decisions per offset)\n\n" + table(rows, list(rows[0])) + "\n\n"
                "### Where the frames themselves align (no engine): mean L1 difference of "
                "whole-frame z-scored 24x32 frames, query j against reference j + d\n\n"
                + table(align, list(align[0])) + "\n")
        md += "\n" + part
        blocks["offsets"] = part
        _write(args.out, "neural_offsets", {k: v for k, v in results.items() if k != "ablation"
                                          and k != "main"}, part)
    if args.relative_offsets:
        rows, robust, refine = relative_offsets_section(data, args.seeds)
        results["relative_offsets"], results["readout_refinement"] = rows, refine
        results["content_variants"] = robust
        coarse = coarse_unit_rows(rings=long_rings)
        results["coarse_units"] = coarse
        part = ("### Offsets against the data's own alignment (decision - that alignment, "
                "reference frames; share of decisions per offset)\n\n"
                + table(rows, list(rows[0])) + "\n\n"
                + ("### LENS: the same against content measured with other frames and "
                   "diagonals (decision - content)\n\n" + table(robust, list(robust[0]))
                   + "\n\n" if robust else "")
                + "### Units of several frames: a 3,000-frame demo route on 555 units (seed 0; "
                "offsets against the exact positions; which unit wins, ring and evidence "
                "alone, against the unit holding the query's frame)\n\n"
                + table(coarse, list(dict.fromkeys(k for r in coarse for k in r))) + "\n\n"
                + "### Readout experiment: current evidence added at read-out (recall@1 / "
                "exact share / median offset; LENS and corridor against the content, the demo "
                "against its exact positions)\n\n"
                + table(refine, list(dict.fromkeys(k for r in refine for k in r))) + "\n")
        md += "\n" + part
        blocks["relative"] = part
        _write(args.out, "neural_relative_offsets",
               {"relative_offsets": rows, "content_variants": robust,
                "coarse_units": coarse, "readout_refinement": refine}, part)
    if args.long_routes:
        rows = []
        for n in [int(v) for v in args.long_routes.split(",") if v]:
            seeds = 1 if n > 5000 else args.long_seeds
            for recruit in args.long_recruit.split(","):
                for readout in ("centre", "interpolate"):
                    rows.append(long_route_row(
                        n, seeds, n <= args.long_seqslam_max and readout == "centre"
                        and recruit == "uniform", readout, recruit=recruit))
            for ring in long_rings[1:]:  # adaptive rings: uniform recruitment
                for readout in ("centre", "interpolate"):
                    rows.append(long_route_row(n, seeds, False, readout, ring=ring))
            if args.long_extra_units and n > args.long_extra_units:
                rows.append(long_route_row(n, seeds, False, "interpolate", args.long_extra_units))
                for ring in long_rings[1:]:
                    for readout in ("centre", "interpolate"):
                        rows.append(long_route_row(n, seeds, False, readout,
                                                   args.long_extra_units, ring=ring))
        results["long_routes"] = rows
        cols = list(dict.fromkeys(k for r in rows for k in r))
        part = ("### Long demo routes (48x64 frames, query at 0.8x speed, default model but "
                "for the ring column; SeqSLAM's columns on the uniform centre rows)\n\n"
                + table(rows, cols) + "\n")
        if args.recruit_real:
            real = recruit_real_rows(data, args.seeds,
                                     long_rings[:1] + long_rings[2:])  # fixed, preset
            results["recruit_real"] = real
            part += (f"\n### Recruitment on short routes, units of 2-3 frames ({args.seeds} "
                     "model seeds)\n\n" + table(real, list(real[0])) + "\n")
        md += "\n" + part
        blocks["long"] = part
        _write(args.out, "neural_long_routes", {k: v for k, v in results.items() if k != "ablation"
                                          and k != "main"}, part)
    if args.seed_sweep:
        sweep_data = {**data, **hard_demos()}
        rows = seed_sweep_rows(sweep_data, args.seeds)
        results["seed_sweep"] = rows
        part = (f"### Settings over {args.seeds} model seeds: recall@1 mean / worst seed\n\n"
                + table(rows, ["setting", *[n for n in SWEEP_DATA if n in sweep_data]]) + "\n")
        md += "\n" + part
        blocks["seeds"] = part
        _write(args.out, "neural_seed_sweep", {"seed_sweep": rows}, part)
    if args.velocity:
        rows = velocity_rows(args.ablation_seeds)
        estimates = velocity_estimate_rows(data, args.seeds)
        results["velocity"], results["velocity_estimates"] = rows, estimates
        part = (f"### Adaptive velocity on the demo speeds (mean over {args.ablation_seeds} "
                "seeds: recall@1 / exact share / median offset against the exact positions"
                " / the adaptive speed estimate over the second half)\n\n"
                + table(rows, list(rows[0])) + "\n\n"
                + f"### The adaptive speed estimate on the real routes ({args.seeds} seeds, "
                "every query frame; their speed is about the reference's)\n\n"
                + table(estimates, list(estimates[0])) + "\n")
        md += "\n" + part
        blocks["velocity"] = part
        _write(args.out, "neural_velocity", {"velocity": rows,
                                             "velocity_estimates": estimates}, part)
    if args.repeat:
        rows = repeat_rows(seeds=args.seeds)
        results["repeat"] = rows
        part = ("### Repetitive routes: false matches to the wrong copy\n\n"
                + table(rows, list(rows[0])) + "\n")
        md += "\n" + part
        blocks["repeat"] = part
        _write(args.out, "neural_repeat", {k: v for k, v in results.items() if k != "ablation"
                                          and k != "main"}, part)
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
        start = len(md)
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
        ablation_md = md[start:]
    if not args.skip_main:
        _write(args.out, "neural_quality", results, md)
    docs = ROOT / "docs" / "results" / "neural.md"
    if args.ablation and not args.skip_main:
        blocks["quality"] = quality_md + ablation_md
    if blocks and not args.no_docs and docs.exists():
        text = docs.read_text()
        for name, body in blocks.items():
            text = replace_block(text, name, body.replace("### ", "#### "))
        write_text(docs, text)
    print(md)
    return results


if __name__ == "__main__":
    main()

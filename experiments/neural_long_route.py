"""Neural SeqSLAM on a real long route (issue 20): where it loses, and what was tried.

Data: ``../shared/data/nordland-b`` (1,788 places of the Nordland railway, summer reference,
winter query, ground truth by index alignment, +-2 frames) and its first 500 places. One
command per table (from the repository root), one thread:

    .venv/bin/python experiments/neural_long_route.py stages    # code / L3 / ring vs SeqSLAM
    .venv/bin/python experiments/neural_long_route.py overlap   # L2 code overlap vs distance
    .venv/bin/python experiments/neural_long_route.py units     # L3 evidence, frames per unit
    .venv/bin/python experiments/neural_long_route.py ring      # the ring's behaviour
    .venv/bin/python experiments/neural_long_route.py shift     # learnt shift matrix
    .venv/bin/python experiments/neural_long_route.py tries     # section 2: what was tried
    .venv/bin/python experiments/neural_long_route.py others    # the tries on corridor/LENS/demo
    .venv/bin/python experiments/neural_long_route.py selfcheck # fit's self-check vs real
    .venv/bin/python experiments/neural_long_route.py bytes     # model bytes vs SeqSLAM's
    .venv/bin/python experiments/neural_long_route.py search --seeds 3  # section 2's result
    .venv/bin/python experiments/neural_long_route.py equal --seeds 3   # same frames as SeqSLAM
    .venv/bin/python experiments/neural_long_route.py stage --seeds 3   # ring or search, per route

Each writes ``neural_long_route_<table>.json`` and ``.md`` under ``--out`` and prints the
Markdown table (docs/results/neural-long-routes.md quotes them). SeqSLAM's results
(1,788 places: about 11 minutes on one busy core) are cached under ``--cache``.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

from torchseq.atomic import write_text  # noqa: E402
from torchseq.matches import Matches  # noqa: E402
from torchseq.metrics import evaluate  # noqa: E402
from torchseq.neural import NeuralConfig, NeuralSeqSLAM  # noqa: E402
from torchseq.neural.learning import recruit_units  # noqa: E402
from torchseq.sources import load_traverse  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "nordland-b"
TOL = 2


def nordland(n: int | None = None) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """``(summer (n, 32, 64), winter (n, 32, 64), gt (n, n) bool, +-2 frames)``."""
    ref = load_traverse(DATA / "summer", progress=False)
    query = load_traverse(DATA / "winter", progress=False)
    n = len(ref) if n is None else n
    return ref[:n], query[:n], _gt(n)


def recall(matches: Matches, gt: np.ndarray) -> float:
    return float(evaluate(matches, gt)["recall_at_1"])


def single(pred, score, gt) -> float:
    """recall@1 of per-frame decisions ``pred`` (higher ``score`` = more confident)."""
    return recall(Matches(torch.as_tensor(pred, dtype=torch.int64),
                          torch.as_tensor(score, dtype=torch.float32), False), gt)


def seqslam(n: int, cache: Path) -> dict:
    """SeqSLAM default (ds 10) on the first ``n`` places, and its single-frame (ds 1) decisions
    from the same difference matrices: raw and contrast-enhanced. Cached."""
    path = cache / f"seqslam_{n}.npz"
    if not path.exists():
        from torchseq.seqslam import SeqSLAM, SeqSLAMConfig

        ref, query, _ = nordland(n)
        res = SeqSLAM(SeqSLAMConfig(threads=1, keep_matrices=True)).match(ref, query)
        cache.mkdir(parents=True, exist_ok=True)
        np.savez(path, D=res.difference.numpy(), E=res.enhanced.numpy(),
                 ref=res.matches.reference.numpy(), score=res.matches.score.numpy())
    z = np.load(path)
    gt = _gt(n)
    out = {"seqslam ds=10": recall(Matches(torch.from_numpy(z["ref"]),
                                           torch.from_numpy(z["score"]), True), gt)}
    for key, name in (("D", "seqslam ds=1 (difference)"), ("E", "seqslam ds=1 (enhanced)")):
        m = z[key]
        out[name] = single(m.argmin(0), -m.min(0), gt)
    return out


def _gt(n: int) -> np.ndarray:
    i = np.arange(n)
    return np.abs(i[:, None] - i[None, :]) <= TOL


def codes(model: NeuralSeqSLAM, frames: torch.Tensor) -> torch.Tensor:
    """``(T, hidden)`` binary L2 codes."""
    with torch.no_grad():
        return torch.cat([model.code(model.encode(frames[i:i + 256]))
                          for i in range(0, len(frames), 256)])


def fitted(n: int, ref, **kw) -> NeuralSeqSLAM:
    """A model fitted on ``ref``; the ring alone (``unit_search="off"``) unless ``kw`` says:
    the diagnosis tables describe the ring as it was before the unit search."""
    kw.setdefault("unit_search", "off")
    model = NeuralSeqSLAM(NeuralConfig(**kw))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(ref, log=False)
    return model


def stage_recalls(model: NeuralSeqSLAM, ref, query, gt) -> dict:
    """recall@1 of each stage alone: nearest reference code, L3 argmax, the ring."""
    cr, cq = codes(model, ref), codes(model, query)
    overlap = cq @ cr.T  # (Q, R) shared winners
    best = overlap.max(1)
    with torch.no_grad():
        e = model.evidence(cq)
    top = e.max(1)
    return {"L2 code alone": single(best.indices, best.values, gt),
            "L3 read-out alone": single(model.unit_centre[top.indices], top.values, gt),
            "ring (full model)": recall(model.run(query).matches, gt)}


# ---------------------------------------------------------------- tables
def t_stages(args) -> list[dict]:
    rows = []
    for n in args.places:
        ref, query, gt = nordland(n)
        sq = seqslam(n, args.cache)
        for seed in range(args.seeds):
            for label, kw in (("default (n_output 555)", {}), ("one unit per frame",
                                                                {"n_output": n})):
                model = fitted(n, ref, seed=seed, **kw)
                r = stage_recalls(model, ref, query, gt)
                rows.append({"places": n, "seed": seed, "model": label,
                             "frames/unit": f"{n / model.n_units:.1f}",
                             **{k: f"{v:.3f}" for k, v in r.items()},
                             **{k: f"{v:.3f}" for k, v in sq.items()}})
    return rows


def t_overlap(args) -> list[dict]:
    ref, query, _ = nordland()
    model = fitted(len(ref), ref)
    cs, cw = codes(model, ref), codes(model, query)
    k = model.config.k
    n = len(ref)
    rows = []
    for d in (0, 1, 2, 3, 5, 10, 20, 50, 100, 500):
        i = np.arange(n - d)
        row = {"distance (frames)": d}
        for name, a, b in (("summer-summer", cs, cs), ("winter-winter", cw, cw),
                           ("summer-winter", cs, cw)):
            if d == 0 and a is b:
                continue
            row[name] = f"{float((a[i] * b[i + d]).sum(1).mean()) / k:.3f}"
        rows.append(row)
    # the distribution that decides: same place across seasons vs its strongest far rival
    ov = (cw @ cs.T) / k  # (Q, R)
    far = ov.clone()
    idx = torch.arange(n)
    far[(idx[:, None] - idx[None, :]).abs() <= 50] = -1
    same = ov[idx, idx]
    rows.append({"distance (frames)": "same place vs best place > 50 away (winter query)",
                 "summer-summer": "", "winter-winter": "",
                 "summer-winter": f"same {float(same.mean()):.3f}, best far "
                                  f"{float(far.max(1).values.mean()):.3f}, same wins "
                                  f"{float((same > far.max(1).values).float().mean()):.3f}"})
    return rows


def t_units(args) -> list[dict]:
    rows = []
    for n in args.places:
        ref, query, gt = nordland(n)
        for fpu in (1, 2, 3, 5, 7):
            model = fitted(n, ref, n_output=max(1, round(n / fpu)))
            cq = codes(model, query)
            with torch.no_grad():
                e = model.evidence(cq)  # (Q, N) z-scored, rectified
                raw = model.l3(cq)
            truth_unit = recruit_units(n, model.n_units)[0]  # unit of each query's place
            zt = (raw - raw.mean(1, keepdim=True)) / raw.std(1, unbiased=False, keepdim=True)
            z_true = zt[torch.arange(n), truth_unit]
            rank = (zt > z_true[:, None]).sum(1)
            top = e.max(1)
            l3 = single(model.unit_centre[top.indices], top.values, gt)
            rows.append({"places": n, "frames/unit": f"{n / model.n_units:.1f}",
                         "units": model.n_units,
                         "L3 recall@1 (+-2)": f"{l3:.3f}",
                         "true unit wins": f"{float((rank == 0).float().mean()):.3f}",
                         "true unit z (mean)": f"{float(z_true.mean()):.2f}",
                         "true unit rank (median)": int(rank.median()),
                         "ring recall@1": f"{recall(model.run(query).matches, gt):.3f}"})
    return rows


def ring_behaviour(ref: np.ndarray, n: int) -> dict:
    """Lock-on and recovery of a decision sequence ``ref`` (``(Q,)``, truth = index)."""
    ok = np.abs(ref - np.arange(n)) <= TOL
    runs, cur = [], 0
    for v in ok:
        if v:
            cur += 1
        elif cur:
            runs.append(cur)
            cur = 0
    if cur:
        runs.append(cur)
    # after losing the route (correct -> wrong), frames until the next correct decision
    lost = np.nonzero(ok[:-1] & ~ok[1:])[0] + 1
    gaps = []
    for t in lost:
        nxt = np.nonzero(ok[t:])[0]
        gaps.append(int(nxt[0]) if nxt.size else n - t)
    jumps = np.abs(np.diff(ref))
    near = np.mean(np.abs(ref - np.arange(n))[~ok] <= 50) if (~ok).any() else 1.0
    first_lock = next((t for t in range(n - 10) if ok[t:t + 10].all()), None)
    return {"recall@1": f"{ok.mean():.3f}",
            "first 10-frame lock at": first_lock,
            "correct runs": len(runs), "longest run": max(runs, default=0),
            "losses": int(lost.size),
            "frames to recover (median)": int(np.median(gaps)) if gaps else 0,
            "losses not recovered in 50": int(np.sum(np.asarray(gaps) > 50)),
            "wrong decisions within 50 frames": f"{near:.2f}",
            "winner jumps > 20 frames": f"{np.mean(jumps > 20):.3f}"}


def t_ring(args) -> list[dict]:
    rows = []
    for n in args.places:
        ref, query, gt = nordland(n)
        for label, kw in (("default", {}), ("one unit per frame", {"n_output": n}),
                          ("ring_decay 0.995", {"ring_decay": 0.995})):
            model = fitted(n, ref, **kw)
            got = model.run(query).matches.reference.numpy()
            rows.append({"places": n, "model": label, **ring_behaviour(got, n)})
    return rows


def t_shift(args) -> list[dict]:
    rows = []
    for frames, units in ((555, 555), (1788, 555), (3576, 555)):
        cfg = NeuralConfig()
        from torchseq.layers.functional import learn_shift_matrix

        unit, _ = recruit_units(frames, units)
        w = learn_shift_matrix(unit, units, cfg.ring_spread, cfg.ring_spread_decay,
                               cfg.ring_stay).double()
        fpu = frames / units
        a = torch.zeros(units, dtype=torch.float64)
        a[units // 4] = 1.0
        x = torch.arange(units, dtype=torch.float64)
        stats = {}
        for t in range(1, 34):
            a = w @ a
            if t in (10, 33):
                c = float((a * x).sum() / a.sum())
                sd = float(((a * (x - c) ** 2).sum() / a.sum()).sqrt())
                stats[t] = (c - units // 4, sd, float(a.sum()))
        mid = units // 4
        row_w = {j - mid: round(float(w[mid, j]), 3) for j in range(mid - 3, mid + 1)
                 if w[mid, j] > 0}
        rows.append({"frames/unit": f"{fpu:.1f}",
                     "row weights (lag: w)": str(row_w),
                     "move in 10 frames (units / expected)": f"{stats[10][0]:.2f} / "
                                                             f"{10 / fpu:.2f}",
                     "spread sd after 10 (frames)": f"{stats[10][1] * fpu:.1f}",
                     "spread sd after 33 (frames)": f"{stats[33][1] * fpu:.1f}",
                     "mass kept after 33": f"{stats[33][2]:.3f}"})
    return rows


def topk_evidence(model: NeuralSeqSLAM, query, k: int):
    """Diagnostic only (not a model stage): the ring over evidence kept at each frame's k
    largest units (zero elsewhere)."""
    inf = model.inference()
    e = torch.cat([inf.evidence(query[i:i + 256]) for i in range(0, len(query), 256)])
    th = e.topk(k, 1).values[:, -1:]
    act = inf.scan(e * (e >= th))
    ref, conf = inf.decide(act)
    return Matches(ref, conf, False)


TRIES = {
    "default": {},
    "readout interpolate": {"readout": "interpolate"},
    "n_output = places (model grows)": "per-frame",
    "n_cohorts 55 (evidence z-scored in blocks of 10 units)": {"n_cohorts": 55},
    "ring_decay 0.99": {"ring_decay": 0.99},
    "ring_decay 0.995": {"ring_decay": 0.995},
    "ring_decay 0.998": {"ring_decay": 0.998},
    "ring memory in units: decay 0.97 ** (units / frames)": "units-memory",
    "ring_decay 0.995, interpolate": {"ring_decay": 0.995, "readout": "interpolate"},
    "ring_decay 0.995, spread 1, no stay": {"ring_decay": 0.995, "ring_spread": 1,
                                            "ring_stay": 0.0},
    "evidence top-30 per frame (diagnostic)": ("topk", 30),
    "evidence top-100 per frame (diagnostic)": ("topk", 100),
}


def try_config(name: str, n: int) -> dict:
    spec = TRIES[name]
    if spec == "per-frame":
        return {"n_output": n}
    if spec == "units-memory":
        return {"ring_decay": 0.97 ** (min(n, 555) / n)}
    return spec if isinstance(spec, dict) else {}


def t_tries(args) -> list[dict]:
    rows = []
    for n in args.places:
        ref, query, gt = nordland(n)
        sq = seqslam(n, args.cache)["seqslam ds=10"]
        for name, spec in TRIES.items():
            got = []
            for seed in range(args.seeds):
                model = fitted(n, ref, seed=seed, **try_config(name, n))
                if isinstance(spec, tuple):
                    got.append(recall(topk_evidence(model, query, spec[1]), gt))
                else:
                    got.append(recall(model.run(query).matches, gt))
            rows.append({"places": n, "setting": name,
                         "recall@1 (seeds)": " ".join(f"{v:.3f}" for v in got),
                         "mean": f"{np.mean(got):.3f}", "SeqSLAM": f"{sq:.3f}",
                         "model bytes": model.model_bytes()})
    return rows


def t_others(args) -> list[dict]:
    from neural_quality import datasets

    rows = []
    data = datasets()
    for label, kw in (("default", {}), ("ring_decay 0.99", {"ring_decay": 0.99}),
                      ("ring_decay 0.995", {"ring_decay": 0.995}),
                      ("ring_decay 0.998", {"ring_decay": 0.998})):
        row = {"setting": label}
        for name, (ref, query, gt) in data.items():
            seeds = range(8) if name == "corridor" else range(3)
            got = []
            for seed in seeds:
                model = fitted(len(ref), ref, seed=seed, **kw)
                got.append(recall(model.run(query).matches, gt))
            row[name] = f"{np.mean(got):.3f} (min {min(got):.3f})"
        rows.append(row)
    return rows


def t_selfcheck(args) -> list[dict]:
    from neural_quality import datasets

    rows = []
    cases = [(f"nordland-b {n}", *nordland(n)) for n in args.places]
    cases += [(name, *v) for name, v in datasets().items() if name != "lens"]
    for name, ref, query, gt in cases:
        n = len(ref)
        settings = [("default", {})]
        if n > 555:
            settings += [("n_output = places", {"n_output": n}),
                         ("ring_decay 0.995", {"ring_decay": 0.995}),
                         ("n_output 279 (6.4 frames/unit)", {"n_output": 279})]
        for label, kw in settings:
            model = NeuralSeqSLAM(NeuralConfig(**kw))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                log = model.fit(ref, log=False)
            rows.append({"data": name, "setting": label,
                         "frames/unit": f"{n / model.n_units:.1f}",
                         "self-check": f"{log.self_check:.3f}",
                         "recall@1 (real query)": f"{recall(model.run(query).matches, gt):.3f}"})
    return rows


def t_bytes(args) -> list[dict]:
    from torchseq.export.int_format import encode
    from torchseq.export.int_model import integer_model

    rows = []
    for n in args.places:
        ref, _, _ = nordland(n)
        model = fitted(n, ref)
        int_bytes = len(encode(integer_model(model)))
        desc = 32 * 64  # SeqSLAM's template: one patch-normalised 64x32 frame per place
        rows.append({"places": n, "units": model.n_units,
                     "neural float (model_bytes)": model.model_bytes(),
                     "neural float, masked weights only": model.model_bytes(masked_only=True),
                     "neural integer file": int_bytes,
                     "SeqSLAM templates uint8": n * desc,
                     "SeqSLAM templates float32": n * desc * 4,
                     "integer / SeqSLAM uint8": f"{int_bytes / (n * desc):.2f}",
                     "places where integer = SeqSLAM uint8": f"{int_bytes / desc:.0f}"})
    return rows


def t_search(args) -> list[dict]:
    """Section 2's result: the default (unit search where units hold several frames) against
    the ring alone, nordland-b 1,788 and 500 places, corridor (8 seeds), LENS and the demo;
    and a demo route longer than the ring (1,500 frames at 0.8x speed)."""
    from neural_quality import datasets

    from torchseq.demo import make_demo

    cases = []
    for n in args.places:
        ref, query, gt = nordland(n)
        cases.append((f"nordland-b {n}", ref, query, gt, seqslam(n, args.cache)["seqslam ds=10"]))
    cases += [(name, *v, None) for name, v in datasets().items()]
    long_demo = make_demo(n_reference=1500)
    cases.append(("demo 1,500 frames (0.8x)", long_demo.reference, long_demo.query,
                  long_demo.ground_truth, None))
    settings = (("default (unit_search auto)", {"unit_search": "auto"}),
                ("ring alone (unit_search off)", {"unit_search": "off"}),
                ("unit search, search_length 50", {"unit_search": "auto", "search_length": 50}))
    rows = []
    for name, ref, query, gt, sq in cases:
        seeds = range(8) if name == "corridor" else range(args.seeds)
        for label, kw in settings:
            if "50" in label and not name.startswith("nordland-b 1788"):
                continue
            got, model = [], None
            for seed in seeds:
                model = fitted(len(ref), ref, seed=seed, **kw)
                got.append(recall(model.run(query).matches, gt))
            rows.append({"data": name, "setting": label,
                         "frames/unit": f"{len(ref) / model.n_units:.1f}",
                         "search active": "yes" if model.search is not None else "no",
                         "recall@1 (seeds)": " ".join(f"{v:.3f}" for v in got),
                         "mean": f"{np.mean(got):.3f}", "min": f"{min(got):.3f}",
                         "SeqSLAM ds=10": "" if sq is None else f"{sq:.3f}"})
            print(rows[-1], flush=True)
    return rows


def seqslam_at(ref, query, gt, ds: int) -> float:
    """SeqSLAM's recall@1 with sequence length ``ds`` (its other settings default)."""
    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig

    return recall(SeqSLAM(SeqSLAMConfig(threads=1, ds=ds)).match(ref, query).matches, gt)


def t_equal(args) -> list[dict]:
    """Issue 33: the network against SeqSLAM over the same query frames. Each network row
    records the frames its decision integrates (``model.sequence_frames``: the search's
    ``search_length``, the ring's ``1 / (1 - decay)``, rounded) and SeqSLAM runs with ``ds``
    set to it; SeqSLAM's default (ds 10) beside. Seeds 0..seeds-1."""
    settings = [("default", {})]
    for per in (1, 2):
        for length in (10, 20, 40):
            settings.append((f"1 unit per {per} frame{'s' if per > 1 else ''}, search "
                             f"{length}", {"units_per": per, "unit_search": "on",
                                           "search_length": length}))
    rows = []
    for n in args.places:
        ref, query, gt = nordland(n)
        sq = {10: seqslam_at(ref, query, gt, 10)}
        for label, kw in settings:
            kw = dict(kw)
            per = kw.pop("units_per", None)
            if per is not None:
                kw["n_output"] = n // per
            got, model = [], None
            for seed in range(args.seeds):
                model = fitted(n, ref, seed=seed, **{"unit_search": "auto", **kw})
                got.append(recall(model.run(query).matches, gt))
            ds = int(round(model.sequence_frames))
            if ds not in sq:
                sq[ds] = seqslam_at(ref, query, gt, ds)
            rows.append({"places": n, "network": label, "units": model.n_units,
                         "stage": model.stage, "sequence frames": ds,
                         "recall@1 (seeds)": " ".join(f"{v:.3f}" for v in got),
                         "mean": f"{np.mean(got):.3f}", "min": f"{min(got):.3f}",
                         "SeqSLAM same ds": f"{sq[ds]:.3f}", "SeqSLAM ds 10": f"{sq[10]:.3f}"})
            print(rows[-1], flush=True)
    return rows


def t_stage(args) -> list[dict]:
    """Issue 33: which stage should decide, one unit per frame: the ring against the unit
    search (search_length 10, 20, 40) on every route; corridor 8 seeds, the rest
    ``--seeds``."""
    from neural_quality import datasets

    cases = [(f"nordland-b {n}", *nordland(n)) for n in args.places]
    cases += [(name, *v) for name, v in datasets().items()]
    settings = [("ring", {"unit_search": "off"})]
    settings += [(f"search {n}", {"unit_search": "on", "search_length": n}) for n in (10, 20, 40)]
    rows = []
    for name, ref, query, gt in cases:
        seeds = range(8) if name == "corridor" else range(args.seeds)
        row = {"data": name, "frames": len(ref)}
        for label, kw in settings:
            got = [recall(fitted(len(ref), ref, seed=s, n_output=len(ref), **kw).run(query)
                          .matches, gt) for s in seeds]
            row[f"{label} mean / min"] = f"{np.mean(got):.3f} / {min(got):.3f}"
        rows.append(row)
        print(row, flush=True)
    return rows


TABLES = {"equal": t_equal, "stage": t_stage, "search": t_search, "stages": t_stages,
          "overlap": t_overlap, "units": t_units,
          "ring": t_ring, "shift": t_shift, "tries": t_tries, "others": t_others,
          "selfcheck": t_selfcheck,
          "bytes": t_bytes}


def table(rows: list[dict]) -> str:
    cols = list(dict.fromkeys(k for r in rows for k in r))
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(str(r.get(c, "")) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("table", choices=sorted(TABLES))
    p.add_argument("--places", default="500,1788", help="route lengths (first N places)")
    p.add_argument("--seeds", type=int, default=1, help="model seeds (stages, tries)")
    p.add_argument("--out", type=Path, default=ROOT / "experiments" / "results")
    p.add_argument("--cache", type=Path, default=Path("/tmp") / "torchseq-long-route")
    args = p.parse_args(argv)
    args.places = [int(v) for v in args.places.split(",")]
    torch.set_num_threads(1)
    if not DATA.exists():
        raise SystemExit(f"nordland-b not found at {DATA}")
    rows = TABLES[args.table](args)
    md = table(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"neural_long_route_{args.table}"
    write_text(stem.with_suffix(".json"), json.dumps(rows, indent=1, default=str) + "\n")
    write_text(stem.with_suffix(".md"), md + "\n")
    print(md)
    return rows


if __name__ == "__main__":
    main()

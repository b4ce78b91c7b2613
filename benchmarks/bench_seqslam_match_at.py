"""Where classic SeqSLAM's reported place sits: ``match_at="start"`` against ``"trajectory"``.

One command (from the repository root):

    .venv/bin/python benchmarks/bench_seqslam_match_at.py [--long 3000] [--json out.json]

For the default configuration (``SeqSLAMConfig()`` fields, only ``match_at`` forced) on the
demo at speeds 0.6 .. 1.6, its severe and repeat variants, the corridor, LENS (its file's
ground truth and the content's own alignment, ``experiments/neural_quality.py``'s
``local_content_offset``) and a long demo route: the decisions' offsets (decision - truth, in
reference frames: median, exact share, share within +-2), recall@1 at the data's tolerance and
PR AUC, for each rule. The engine runs once per route; both rules are read from its enhanced
matrix by ``torchseq.seqslam.search.search`` (the engine's own search). Two diagnostics that
are not library rules sit beside them: ``ceil``, ``s + ceil(v ds/2)`` (rounding the
half-frame of an odd ``v ds`` up instead of down, as ``round`` would), and, with edges on,
the offsets of the first and last ``ds/2`` queries (their own leading/trailing window).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchseq.demo import make_demo  # noqa: E402
from torchseq.metrics import evaluate  # noqa: E402
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig  # noqa: E402
from torchseq.seqslam.search import search, trajectory_offsets, trajectory_scores  # noqa: E402


def content_alignment(ref: torch.Tensor, query: torch.Tensor) -> np.ndarray:
    """``(Q,)`` reference each query's content aligns with, as ``--relative-offsets`` of
    ``experiments/neural_quality.py`` computes it (local diagonal of frame differences)."""
    sys.path.insert(0, str(ROOT / "experiments"))
    from neural_quality import frame_differences, local_content_offset
    return np.arange(len(query)) + local_content_offset(frame_differences(ref, query)).astype(
        np.float64)


def routes(long: int) -> dict:
    """``name -> (reference, query, truth (Q,) float, gt (R, Q) bool or None, tolerance)``."""
    out = {}
    for speed in (0.6, 0.8, 1.0, 1.3, 1.6):
        d = make_demo(speed=speed)
        out[f"demo {speed}x"] = (d.reference, d.query, d.query_position, d.ground_truth, 2)
    d = make_demo(gain=0.45, gamma=2.4, gradient=0.45, noise=20.0)
    out["demo-severe (0.8x)"] = (d.reference, d.query, d.query_position, d.ground_truth, 2)
    d = make_demo(repeat=3)
    out["demo-repeat 3 (0.8x)"] = (d.reference, d.query, d.query_position, d.ground_truth, 2)
    sys.path.insert(0, str(ROOT / "experiments"))
    from neural_quality import datasets  # the quality tables' loader (absent data skipped)
    real = datasets(("corridor", "lens"))
    if "corridor" in real:
        r, q, gt = real["corridor"]
        truth = np.arange(len(q), dtype=np.float64)
        out["corridor"] = (r, q, truth, gt, 2)
        out["corridor (content alignment)"] = (r, q, content_alignment(r, q), None, 0)
    if "lens" in real:
        r, q, gt = real["lens"]
        truth = np.arange(len(q), dtype=np.float64)
        out["lens (file GT)"] = (r, q, truth, gt, 0)
        out["lens (file GT +-2)"] = (r, q, truth, real["lens+-2"][2], 2)
        content = content_alignment(r, q)
        same = np.arange(len(r))[:, None] == content[None]
        out["lens (content alignment)"] = (r, q, content, same, 0)
    if long:
        d = make_demo(n_reference=long, size=(48, 64), step=4.0, dense_ground_truth=False)
        out[f"demo long {long} (0.8x)"] = (d.reference, d.query, d.query_position, None, 2)
    return out


def centre_velocity(enhanced: torch.Tensor, cfg: SeqSLAMConfig) -> tuple[np.ndarray, np.ndarray]:
    """Best start and ``m = v ds`` of its best velocity for every centred query (-1 else)."""
    ds, speeds = cfg.sequence_length, SeqSLAM(cfg).speeds
    offsets = trajectory_offsets(ds, speeds)
    n_query = enhanced.shape[1]
    scores, best_v = trajectory_scores(enhanced.T.contiguous(), ds // 2, n_query - ds // 2, ds,
                                       offsets, with_velocity=True)
    start = scores.argmin(1)
    m = torch.tensor([round(v * ds) for v in speeds])[best_v.gather(1, start[:, None])[:, 0]]
    pad = np.full(ds // 2, -1)
    return (np.r_[pad, start.numpy(), pad], np.r_[pad, m.numpy(), pad])


def stats(got: np.ndarray, truth: np.ndarray, gt, tol: float, matches=None) -> dict:
    ok = got >= 0
    off = got[ok] - truth[ok]
    row = {"matched": int(ok.sum()), "median": float(np.median(off)),
           "mean": float(np.mean(off)), "exact": float(np.mean(np.round(off) == 0)),
           "within2": float(np.mean(np.abs(off) <= 2))}
    if gt is not None and matches is not None:  # same uniqueness scores, this rule's places
        m = evaluate(replace(matches, reference=torch.from_numpy(got)), gt)
        row["recall_at_1"], row["auc"] = m["recall_at_1"], m["auc"]
    elif gt is None:  # every query is a positive: recall@1 = share within the tolerance
        row["recall_at_1"] = float(np.mean(ok & (np.abs(got - truth) <= tol)))
    return row


def measure(name, ref, query, truth, gt, tol) -> list[dict]:
    cfg = replace(SeqSLAMConfig(), match_at="start", keep_matrices=True)
    res = SeqSLAM(cfg).match(ref, query)
    e, ds = res.enhanced, cfg.sequence_length
    speeds = SeqSLAM(cfg).speeds
    args = (cfg.rwindow, cfg.top_k, cfg.max_chunk_elements)
    truth = np.asarray(truth, np.float64)
    rows = []
    for rule in ("start", "trajectory"):
        got = search(e, ds, speeds, *args, match_at=rule)[0].numpy()
        rows.append({"route": name, "rule": rule, **stats(got, truth, gt, tol, res.matches)})
    start, m = centre_velocity(e, cfg)
    ok = start >= 0
    half_up = np.where(ok, start + (m + 1) // 2, -1)  # round(v ds/2) with halves up
    rows.append({"route": name, "rule": "ceil (round half up, diagnostic)",
                 **stats(half_up, truth, None, tol)})
    rows[-1].pop("recall_at_1", None)
    rows[-1]["odd m share"] = float(np.mean(m[ok] % 2 == 1))
    edge_q = np.r_[0:ds // 2, len(query) - ds // 2:len(query)]
    got = search(e, ds, speeds, *args, match_at="trajectory", edges=True)[0].numpy()
    sel = np.zeros(len(query), bool)
    sel[edge_q] = True
    got_e = np.where(sel, got, -1)
    lead, trail = got_e.copy(), got_e.copy()
    lead[ds // 2:], trail[:len(query) - ds // 2] = -1, -1
    row = {"route": name, "rule": "edges: first / last ds/2 queries"}
    for lab, g in (("first", lead), ("last", trail)):
        s = stats(g, truth, None, tol)
        row[lab] = (f"{s['matched']} matched, median {s['median']:+.1f}, "
                    f"exact {s['exact']:.2f}, +-2 {s['within2']:.2f}")
    rows.append(row)
    for r in rows:
        print(json.dumps(r), flush=True)
    return rows


def table(rows: list[dict]) -> str:
    lines = ["| route | rule | median offset | mean offset | exact | within +-2 | recall@1 "
             "| PR AUC |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        if "median" not in r:
            continue
        rec = f"{r['recall_at_1']:.3f}" if "recall_at_1" in r else ""
        auc = f"{r['auc']:.3f}" if "auc" in r else ""
        lines.append(f"| {r['route']} | {r['rule']} | {r['median']:+.1f} | {r['mean']:+.2f} | "
                     f"{r['exact']:.3f} | {r['within2']:.3f} | {rec} | {auc} |")
    edges = [r for r in rows if "first" in r]
    lines += ["", "| route | edges=True: first ds/2 queries | last ds/2 queries |",
              "|---|---|---|"]
    lines += [f"| {r['route']} | {r['first']} | {r['last']} |" for r in edges]
    return "\n".join(lines)


def rank_cost(n: int = 3000, repeats: int = 3) -> str:
    """Seconds of ``search`` (both rules, one thread) listing each ranked place once against
    the same search listing the top-K starts as they come (places may repeat)."""
    import importlib
    import time

    search_module = importlib.import_module("torchseq.seqslam.search")  # the module

    torch.set_num_threads(1)
    e = torch.rand(n, n, generator=torch.Generator().manual_seed(0))
    speeds = SeqSLAM().speeds
    distinct = search_module._first_distinct

    def as_they_come(place, k):
        return place[:, :k], torch.full((len(place),), k)

    lines = [f"| {n} x {n}, one thread | each place once s | top-K starts s | ratio |",
             "|---|---:|---:|---:|"]
    for rule in ("trajectory", "start"):
        t = {}
        for label, fn in (("once", distinct), ("starts", as_they_come)):
            search_module._first_distinct = fn
            best = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                search(e, 10, speeds, match_at=rule)
                best.append(time.perf_counter() - t0)
            t[label] = min(best)
        search_module._first_distinct = distinct
        lines.append(f"| {rule} | {t['once']:.2f} | {t['starts']:.2f} | "
                     f"{t['once'] / t['starts']:.2f} |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--long", type=int, default=3000, help="long demo route (0: skip)")
    p.add_argument("--only", default="", help="comma-separated route name prefixes")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--rank-cost", action="store_true",
                   help="only: search time with ranked places listed once vs as they come")
    args = p.parse_args()
    if args.rank_cost:
        print(rank_cost())
        return
    rows = []
    for name, route in routes(args.long).items():
        if args.only and not any(name.startswith(x) for x in args.only.split(",")):
            continue
        rows += measure(name, *route)
    print(table(rows))
    if args.json:
        from torchseq.atomic import write_text
        write_text(args.json, json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()

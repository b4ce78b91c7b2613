"""SeqSLAM candidate mode: recall against the exact mode on real routes, time and memory at scale.

    .venv/bin/python benchmarks/bench_candidates.py --recall        # real routes (shared data)
    .venv/bin/python benchmarks/bench_candidates.py --scale         # 10^4 .. 10^6 references
    .venv/bin/python benchmarks/bench_candidates.py --scale --sizes 10000 --kinds flat,ivf
    .venv/bin/python benchmarks/bench_candidates.py --reuse   # issue 24: route, crossover, scale

One thread (torch and FAISS). Each scale run (size, index kind) is its own subprocess so its
peak RSS is clean. Synthetic descriptors: D = 2048 integers in 127 +- 8 (as patch
normalisation gives), stored as uint8; neighbouring reference frames look alike (an AR(1)
process with coefficient 0.9 per frame, as along a real route); the queries are a stretch of
the reference at speed 1 with integer noise (sd 1.5). A query counts as correct when its match
is within 2 frames of the truth.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
KS = (1, 2, 5, 10, 20, 50)


def peak_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmHWM")) / 1024


def one_thread():
    import faiss
    import torch

    torch.set_num_threads(1)
    faiss.omp_set_num_threads(1)


# ----------------------------------------------------------------------------- real routes
def real_routes():
    """(name, reference descriptors, query descriptors, (R, Q) ground truth) of each route."""
    import torch

    from torchseq.events import load_event_frames
    from torchseq.ground_truth import load_ground_truth
    from torchseq.seqslam import SeqSLAM
    from torchseq.sources import load_traverse

    engine = SeqSLAM()
    routes = []
    for name, ref, query, gt in (
            ("corridor", "corridor/ref", "corridor/query", "corridor/ground_truth.csv"),
            ("lens-davis128", "lens-davis128/example-reference", "lens-davis128/example-query",
             "lens-davis128/example-reference_example-query_GT.npy")):
        r = load_traverse(DATA / ref, progress=False)
        q = load_traverse(DATA / query, progress=False)
        routes.append((name, engine.descriptors(r), engine.descriptors(q),
                       load_ground_truth(DATA / gt, len(r), len(q))))
    # the longest pair the shared data gives: both routes one after the other, and every
    # frame of the real event recordings (10 ms windows) added to the reference as distractors
    distract = [engine.descriptors(load_event_frames(DATA / "events" / f))
                for f in ("alex_walking_again.aedat", "IMU_translBoxes.aedat", "sample.aedat4")]
    (_, r1, q1, g1), (_, r2, q2, g2) = routes
    ref = torch.cat([r1, r2, *distract])
    gt = np.zeros((len(ref), len(q1) + len(q2)), bool)
    gt[:len(r1), :len(q1)] = g1
    gt[len(r1):len(r1) + len(r2), len(q1):] = g2
    routes.append(("corridor + lens + event distractors", ref, torch.cat([q1, q2]), gt))
    return routes


def recall_table() -> list[str]:
    from torchseq.metrics import evaluate
    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
    from torchseq.seqslam.ann_index import CandidateIndex
    from torchseq.seqslam.candidates import CandidateSeqSLAM

    one_thread()
    lines = ["| route (R x Q) | enhancement | exact | " + " | ".join(f"K = {k}" for k in KS)
             + " |", "|---|---|---:|" + "---:|" * len(KS)]
    kinds = ["| route | enhancement | K | " + " | ".join(
        ("flat L1", "flat L2", "IVF (PCA 128)", "HNSW (PCA 128)")) + " |", "|---|---|---:|"
        + "---:|" * 4]
    for name, ref, query, gt in real_routes():
        for window in (10, 0):
            config = SeqSLAMConfig(enhance_window=window)
            exact = SeqSLAM(config).match_descriptors(ref, query)
            r0 = evaluate(exact.matches, gt)["recall_at_1"]
            cells = []
            for k in KS:
                res = SeqSLAM(SeqSLAMConfig(enhance_window=window, candidates=k)
                              ).match_descriptors(ref, query)
                same = float((res.matches.reference == exact.matches.reference).float().mean())
                cells.append(f"{evaluate(res.matches, gt)['recall_at_1']:.3f} ({same:.0%})")
            lines.append(f"| {name} ({len(ref)} x {len(query)}) | "
                         f"{'R = 10' if window else 'off'} | {r0:.3f} | " + " | ".join(cells)
                         + " |")
            print(lines[-1], flush=True)
            for k in (5, 20):
                row = []
                for metric, kind in (("l1", "flat"), ("l2", "flat"), ("l1", "ivf"),
                                     ("l1", "hnsw")):
                    index = CandidateIndex(ref, metric, kind)
                    res = CandidateSeqSLAM(ref, SeqSLAMConfig(enhance_window=window,
                                                              candidates=k), index=index
                                           ).match_descriptors(query)
                    row.append(f"{evaluate(res.matches, gt)['recall_at_1']:.3f}")
                kinds.append(f"| {name} | {'R = 10' if window else 'off'} | {k} | "
                             + " | ".join(row) + " |")
                print(kinds[-1], flush=True)
    return lines + [""] + kinds


# ----------------------------------------------------------------------------- scale
def synthetic(n_ref: int, n_query: int, seed: int = 0, dim: int = 2048):
    """uint8 AR(1) reference (R, D) and float32 queries (Q, D) with their true positions."""
    rng = np.random.default_rng(seed)
    ref = np.empty((n_ref, dim), np.uint8)
    z = rng.standard_normal(dim, dtype=np.float32) * 2.5
    a, b = 0.9, math.sqrt(1 - 0.81) * 2.5
    for r0 in range(0, n_ref, 4096):
        noise = rng.standard_normal((min(4096, n_ref - r0), dim), dtype=np.float32) * b
        block = np.empty_like(noise)
        for i in range(len(noise)):
            z = a * z + noise[i]
            block[i] = z
        ref[r0:r0 + len(noise)] = 127 + np.clip(np.rint(block), -8, 8)
    first = n_ref // 3
    pos = first + np.arange(n_query)
    noise = np.rint(rng.normal(0, 1.5, (n_query, dim)))
    query = np.clip(ref[pos].astype(np.float32) + noise, 119, 135).astype(np.float32)
    return ref, query, pos


def scale_child(n_ref: int, n_query: int, kind: str, k: int) -> dict:
    import torch

    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
    from torchseq.seqslam.candidates import CandidateSeqSLAM

    one_thread()
    t = time.perf_counter()
    ref, query, pos = synthetic(n_ref, n_query)
    data_s = time.perf_counter() - t
    base = peak_mb()
    ref_t, query_t = torch.from_numpy(ref), torch.from_numpy(query)
    t, cpu = time.perf_counter(), time.process_time()
    if kind == "exact":
        result = SeqSLAM(SeqSLAMConfig(candidates=0)).match_descriptors(ref_t.float(), query_t)
        build = build_cpu = 0.0
    else:
        engine = CandidateSeqSLAM(ref_t, SeqSLAMConfig(candidates=k), index=kind)
        build, build_cpu = engine.index_seconds, time.process_time() - cpu
        t, cpu = time.perf_counter(), time.process_time()
        result = engine.match_descriptors(query_t)
    run, run_cpu = time.perf_counter() - t, time.process_time() - cpu
    m = result.matches.reference.numpy()
    scored = m >= 0
    correct = float((np.abs(m[scored] - pos[scored]) <= 2).mean())
    per_q = {key: 1e3 * v / n_query for key, v in result.seconds.items()
             if key not in ("index", "total")}
    return {"n_ref": n_ref, "kind": kind, "k": k, "data_s": data_s, "build_s": build,
            "build_cpu_s": build_cpu, "cpu_ms_per_query": 1e3 * run_cpu / n_query,
            "ms_per_query": 1e3 * run / n_query, "queries_per_s": n_query / run,
            "stages_ms": per_q, "peak_mb": peak_mb(), "data_mb": base, "correct": correct,
            "pairs": (result.enhanced._nnz() if result.enhanced.is_sparse
                      else n_ref * n_query) / n_query}


def scale_table(sizes, kinds, k, n_query) -> list[str]:
    lines = ["| references | mode | build s (CPU s) | ms / query (CPU ms) | queries / s | "
             "stages, ms / query | pairs / query | peak RSS MB | data RSS MB | correct |",
             "|---:|---|---:|---:|---:|---|---:|---:|---:|---:|"]
    for n in sizes:
        for kind in kinds:
            if kind == "flat" and n > 200_000:
                lines.append(f"| {n} | flat | | not run: a float32 copy of R x 2048 "
                             f"({n * 2048 * 4 / 2**30:.1f} GiB) and R x D work per query | | | |"
                             " | | |")
                continue
            if kind == "exact" and n > 100_000:
                lines.append(f"| {n} | exact | | not run: a float32 copy of the reference "
                             f"({n * 2048 * 4 / 2**30:.1f} GiB) and two R x Q float32 matrices "
                             f"({2 * n * n_query * 4 / 2**30:.1f} GiB) | | | | | | |")
                continue
            if kind == "hnsw" and n > 200_000:
                lines.append(f"| {n} | hnsw | | not run (graph build time, see text) | | | |"
                             " | | |")
                continue
            cmd = [sys.executable, __file__, "--child", str(n), kind, str(k), str(n_query)]
            out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT,
                                 env={**os.environ, "PYTHONPATH": str(ROOT)})
            if out.returncode:
                print(out.stderr[-3000:], file=sys.stderr)
                lines.append(f"| {n} | {kind} | failed | | | | | | | |")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            stages = ", ".join(f"{s} {v:.2f}" for s, v in r["stages_ms"].items())
            name = "exact" if kind == "exact" else f"{kind}, K = {k}"
            lines.append(f"| {n} | {name} | {r['build_s']:.1f} ({r['build_cpu_s']:.1f}) | "
                         f"{r['ms_per_query']:.2f} ({r['cpu_ms_per_query']:.2f}) | "
                         f"{r['queries_per_s']:.0f} | {stages} | {r['pairs']:.0f} | "
                         f"{r['peak_mb']:.0f} | "
                         f"{r['data_mb']:.0f} | {r['correct']:.3f} |")
            print(lines[-1], flush=True)
    return lines


# ----------------------------------------------------------------------------- reuse (issue 24)
def nordland(double: bool):
    """Nordland-b descriptors: summer reference, winter query (1,788 places); ``double``:
    summer + winter against winter + summer (3,576). Ground truth: index +- 2."""
    import torch

    from torchseq.seqslam import SeqSLAM
    from torchseq.sources import load_traverse

    engine = SeqSLAM()
    s = engine.descriptors(load_traverse(DATA / "nordland-b" / "summer", progress=False))
    w = engine.descriptors(load_traverse(DATA / "nordland-b" / "winter", progress=False))
    ref, query = (torch.cat([s, w]), torch.cat([w, s])) if double else (s, w)
    n = len(query)
    truth = (np.arange(n) + len(s)) % n if double else np.arange(n)
    gt = np.abs(np.arange(len(ref))[:, None] - truth[None, :]) <= 2
    return ref, query, gt


def timed(fn):
    """(result, wall s, CPU s) of ``fn()``."""
    t, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t, time.process_time() - cpu


def route_table(double: bool, k: int, ds: int) -> list[str]:
    """Exact mode and candidate mode (shared and per-window layouts) on the Nordland route."""
    from torchseq.metrics import evaluate
    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
    from torchseq.seqslam.candidates import CandidateSeqSLAM

    one_thread()
    ref, query, gt = nordland(double)
    lines = [f"Nordland-b, {len(ref)} references x {len(query)} queries, ds = {ds}, one thread",
             "", "| mode | wall s | CPU s | CPU / exact | stages, CPU-loaded wall s | recall@1 "
             "(+-2) | same match as exact | identical to per-window |",
             "|---|---:|---:|---:|---|---:|---:|---:|"]
    exact, w0, c0 = timed(lambda: SeqSLAM(SeqSLAMConfig(ds=ds, candidates=0))
                          .match_descriptors(ref, query))
    rows = [("exact", exact, w0, c0)]
    config = SeqSLAMConfig(ds=ds, candidates=k)
    shared = CandidateSeqSLAM(ref, config)  # index built once, outside the timings
    for layout in ("shared", "per-window"):
        engine = CandidateSeqSLAM(ref, config, index=shared.index, layout=layout)
        res, w, c = timed(lambda: engine.match_descriptors(query))
        rows.append((f"candidates, K = {k}, {layout}", res, w, c))
    base = rows[2][1]
    for name, res, w, c in rows:
        stages = ", ".join(f"{key} {v:.1f}" for key, v in res.seconds.items()
                           if key not in ("index", "total"))
        same = float((res.matches.reference == exact.matches.reference).float().mean())
        ident = "" if name == "exact" else str(all(
            torch_equal(a, b) for a, b in ((res.matches.reference, base.matches.reference),
                                           (res.ranked, base.ranked),
                                           (res.matches.score, base.matches.score),
                                           (res.best_score, base.best_score))))
        lines.append(f"| {name} | {w:.1f} | {c:.1f} | {c / c0:.2f} | {stages} | "
                     f"{evaluate(res.matches, gt)['recall_at_1']:.3f} | {same:.3f} | {ident} |")
        print(lines[-1], flush=True)
    return lines


def route_repeats(k: int, ds: int, repeats: int) -> list[str]:
    """The 3,576-place route: exact mode and candidate mode side by side, interleaved,
    ``repeats`` times; each row the minimum CPU (and wall) seconds of its repeats."""
    from torchseq.metrics import evaluate
    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig, difference
    from torchseq.seqslam.candidates import CandidateSeqSLAM

    one_thread()
    ref, query, gt = nordland(True)
    config = SeqSLAMConfig(ds=ds, candidates=k)
    index = CandidateSeqSLAM(ref, config).index  # built once, outside the timings

    def without_sad():
        """Candidate mode with its whole columns by pair_differences (the size rule off)."""
        saved, difference.SAD_MIN_WORK = difference.SAD_MIN_WORK, 2**62
        try:
            return CandidateSeqSLAM(ref, config, index=index).match_descriptors(query)
        finally:
            difference.SAD_MIN_WORK = saved

    modes = {
        "exact": lambda: SeqSLAM(SeqSLAMConfig(ds=ds, candidates=0)).match_descriptors(
            ref, query),
        f"candidates, K = {k}, shared": lambda: CandidateSeqSLAM(
            ref, config, index=index).match_descriptors(query),
        f"candidates, K = {k}, shared, dense=False": lambda: CandidateSeqSLAM(
            ref, config, index=index, dense=False).match_descriptors(query),
        f"candidates, K = {k}, shared, whole columns without sad": without_sad,
    }
    best = {}
    load = [os.getloadavg()[0]]
    for rep in range(repeats):
        for name, fn in modes.items():
            res, w, c = timed(fn)
            print(f"repeat {rep}: {name}: wall {w:.1f} s, CPU {c:.1f} s", flush=True)
            if name not in best or c < best[name][2]:
                best[name] = (res, w, c)
    load.append(os.getloadavg()[0])
    exact = best["exact"][0]
    c0 = best["exact"][2]
    lines = [f"Nordland-b, {len(ref)} x {len(query)}, ds = {ds}, one thread, minimum of "
             f"{repeats} interleaved repeats, load average {load[0]:.1f} -> {load[1]:.1f}", "",
             "| mode | wall s | CPU s | CPU / exact | stages, wall s | recall@1 (+-2) | "
             "same match as exact | dense keys / tile keys | L1 kernel |",
             "|---|---:|---:|---:|---|---:|---:|---|---|"]
    for name, (res, w, c) in best.items():
        stages = ", ".join(f"{key} {v:.1f}" for key, v in res.seconds.items()
                           if key not in ("index", "total"))
        same = float((res.matches.reference == exact.matches.reference).float().mean())
        keys = (f"{res.kernels['dense_keys']} / {res.kernels['tile_keys']}"
                if "dense_keys" in res.kernels else "")
        kernel = res.kernels.get("dense_difference") or res.kernels.get("difference", "")
        lines.append(f"| {name} | {w:.1f} | {c:.1f} | {c / c0:.2f} | {stages} | "
                     f"{evaluate(res.matches, gt)['recall_at_1']:.3f} | {same:.3f} | {keys} | "
                     f"{kernel} |")
    return lines


def torch_equal(a, b) -> bool:
    import torch

    return bool(torch.equal(a.nan_to_num(-1.0), b.nan_to_num(-1.0)))


def crossover_table(sizes, n_query: int, k: int, ds: int) -> list[str]:
    """Both modes on synthetic routes of growing length: CPU per query, index build, recall.

    Recall@1: the match within 2 frames of the truth. "candidates, whole" adds the index's
    build (CPU) to the queries: the cost of one run of ``n_query`` queries from scratch.
    """
    import torch

    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
    from torchseq.seqslam.candidates import CandidateSeqSLAM

    one_thread()
    lines = [f"Synthetic routes, {n_query} queries, ds = {ds}, K = {k}, one thread", "",
             "| references | index | exact CPU ms / query | candidates CPU ms / query (index "
             "built outside) | exact / candidates | index build CPU s | exact / candidates, "
             "whole (build + queries) | recall@1 exact / candidates |",
             "|---:|---|---:|---:|---:|---:|---:|---|"]
    for n in sizes:
        ref, query, pos = synthetic(n, n_query)
        ref_t, query_t = torch.from_numpy(ref), torch.from_numpy(query)
        exact, _, ce = timed(lambda: SeqSLAM(SeqSLAMConfig(ds=ds, candidates=0))
                             .match_descriptors(ref_t.float(), query_t))
        engine, _, cb = timed(lambda: CandidateSeqSLAM(ref_t, SeqSLAMConfig(ds=ds,
                                                                             candidates=k)))
        cand, _, cc = timed(lambda: engine.match_descriptors(query_t))
        recall = [float((np.abs(r.matches.reference.numpy() - pos) <= 2).mean())
                  for r in (exact, cand)]
        lines.append(f"| {n} | {engine.index.kind} | {1e3 * ce / n_query:.2f} | "
                     f"{1e3 * cc / n_query:.2f} | {ce / cc:.2f} | {cb:.2f} | "
                     f"{ce / (cb + cc):.2f} | {recall[0]:.3f} / {recall[1]:.3f} |")
        print(lines[-1], flush=True)
    return lines


def layouts_table(n_ref: int, n_query: int, k: int, repeats: int = 2) -> list[str]:
    """Shared against per-window layout in one process: same index, same queries, CPU ms."""
    import torch

    from torchseq.seqslam import SeqSLAMConfig
    from torchseq.seqslam.candidates import CandidateSeqSLAM

    one_thread()
    ref, query, _ = synthetic(n_ref, n_query)
    ref_t, query_t = torch.from_numpy(ref), torch.from_numpy(query)
    shared = CandidateSeqSLAM(ref_t, SeqSLAMConfig(candidates=k))
    per = CandidateSeqSLAM(ref_t, SeqSLAMConfig(candidates=k), index=shared.index,
                           layout="per-window")
    lines = [f"{n_ref} references, {n_query} queries, {shared.index.kind}, K = {k}: CPU ms "
             "per query", "", "| repetition | shared | per-window | identical results |",
             "|---:|---:|---:|---|"]
    for rep in range(repeats):
        (a, _, ca), (b, _, cb) = (timed(lambda e=e: e.match_descriptors(query_t))
                                  for e in (shared, per))
        same = all(torch_equal(x, y) for x, y in (
            (a.matches.reference, b.matches.reference), (a.ranked, b.ranked),
            (a.matches.score, b.matches.score), (a.best_score, b.best_score)))
        lines.append(f"| {rep + 1} | {1e3 * ca / n_query:.2f} | {1e3 * cb / n_query:.2f} | "
                     f"{same} |")
        print(lines[-1], flush=True)
    return lines


def main() -> None:
    if sys.argv[1:2] == ["--child"]:
        n, kind, k, q = sys.argv[2:6]
        print(json.dumps(scale_child(int(n), int(q), kind, int(k))))
        return
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--recall", action="store_true")
    p.add_argument("--scale", action="store_true")
    p.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    p.add_argument("--kinds", default="exact,flat,ivf,hnsw")
    p.add_argument("--k", type=int, default=10)
    p.add_argument("--queries", type=int, default=1000)
    p.add_argument("--reuse", action="store_true",
                   help="issue 24: Nordland route, crossover and query rate at 10^5, 10^6")
    p.add_argument("--double", action="store_true", help="the 3,576-place Nordland route")
    p.add_argument("--crossover-sizes", type=int, nargs="+", default=[300, 1000, 3000])
    p.add_argument("--layouts", type=int, default=0, metavar="R",
                   help="shared against per-window layout at R synthetic references")
    p.add_argument("--route", action="store_true",
                   help="the 3,576-place route only: exact and candidate mode (K = 100, "
                        "ds = 20), interleaved, minimum of --repeats")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--crossover", action="store_true",
                   help="the crossover table alone: --crossover-sizes, --k, 200 queries, ds 20")
    args = p.parse_args()
    import torch

    print(f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores "
          f"(1 thread used), Python {platform.python_version()}, torch {torch.__version__}, "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}\n")
    if args.recall:
        print("\n".join(recall_table()) + "\n")
    if args.scale:
        print("\n".join(scale_table(args.sizes, args.kinds.split(","), args.k, args.queries)))
    if args.layouts:
        print("\n".join(layouts_table(args.layouts, 300, args.k)))
    if args.crossover:
        print("\n" + "\n".join(crossover_table(args.crossover_sizes, 200, args.k, 20)))
    if args.route:
        print("\n" + "\n".join(route_repeats(100, 20, args.repeats)))
    if args.reuse:
        out = route_table(args.double, 100, 20) + [""]
        out += crossover_table(args.crossover_sizes, 200, 100, 20) + [""]
        out += scale_table([100_000, 1_000_000], ["ivf"], 10, 300)
        print("\n" + "\n".join(out))


if __name__ == "__main__":
    main()

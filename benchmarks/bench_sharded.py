"""Sharded candidate mode on a local Ray cluster: query rate, memory per actor, merge cost.

    .venv/bin/python benchmarks/bench_sharded.py --places 100000 --shards 1,2,4
    .venv/bin/python benchmarks/bench_sharded.py --places 1000000 --shards 2,4 --queries 200
    .venv/bin/python benchmarks/bench_sharded.py --map MAP --query FRAMES   # real route

``--map``: a map built by ``torchseq map build`` and a query traverse; one-machine candidate
mode against the sharded path in-process (one worker, no Ray), one thread, side by side.

For each size a map is built once (synthetic descriptors, D = 64 uint8 in 127 +- 8; an AR(1)
route, coefficient 0.9 per frame; queries a stretch of it at speed 1 with integer noise, sd
1.5), then matched on one machine (:class:`CandidateSeqSLAM` with the map's index, one
thread) and by :class:`ShardedSeqSLAM` with each shard count on a local Ray cluster started
with ``--cpus`` CPUs (one thread per actor). Every sharded result is checked equal to the
one-machine one. Prints one JSON line per run and a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def route(n_ref: int, n_query: int, dim: int, seed: int = 0, block: int = 4096):
    """uint8 AR(1) route ``(n_ref, dim)``, float32 queries along it, the first query's place.

    Drawn ``block`` rows at a time: besides the uint8 route, memory is ``O(block x dim)`` (the
    whole float64 noise of 10^6 x 2,048 places was 16 GB).
    """
    rng = np.random.default_rng(seed)
    ref = np.empty((n_ref, dim), np.uint8)
    z = rng.normal(0, 2.5, dim).astype(np.float32)
    for r0 in range(0, n_ref, block):
        noise = rng.normal(0, 2.5 * math.sqrt(1 - 0.81),
                           (min(block, n_ref - r0), dim)).astype(np.float32)
        rows = np.empty_like(noise)
        for i in range(len(noise)):
            if r0 + i:  # the first place is z itself
                z = 0.9 * z + noise[i]
            rows[i] = z
        ref[r0:r0 + len(rows)] = 127 + np.clip(np.round(rows), -8, 8)
    first = n_ref // 3
    query = np.clip(ref[first:first + n_query].astype(np.float32)
                    + np.round(rng.normal(0, 1.5, (n_query, dim))), 119, 135).astype(np.float32)
    return ref, query, first


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def real_route(map_path: str, query_path: str, k: int) -> None:
    import faiss
    import torch

    from torchseq.maps import load_map
    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
    from torchseq.seqslam.candidates import CandidateSeqSLAM
    from torchseq.seqslam.sharded import ShardedSeqSLAM
    from torchseq.sources import load_traverse

    torch.set_num_threads(1)
    faiss.omp_set_num_threads(1)
    m = load_map(map_path)
    q = SeqSLAM(m.config).descriptors(load_traverse(query_path, progress=False))
    config = SeqSLAMConfig(candidates=k)
    a = ShardedSeqSLAM(m, config, 1, use_ray=False).match_descriptors(q)
    b = CandidateSeqSLAM(m.descriptors(), config, index=m.index()).match_descriptors(q)
    for name, r in (("ShardedSeqSLAM(use_ray=False), 1 worker", a), ("CandidateSeqSLAM", b)):
        print(name, {key: round(v, 2) for key, v in r.seconds.items()})
    print("same matches and rankings:", bool(torch.equal(a.matches.reference,
                                                         b.matches.reference)
                                              and torch.equal(a.ranked, b.ranked)))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--places", type=int, nargs="+", default=[100_000])
    p.add_argument("--shards", default="1,2,4")
    p.add_argument("--queries", type=int, default=300)
    p.add_argument("--dim", type=int, default=64)
    p.add_argument("--candidates", type=int, default=20)
    p.add_argument("--shard-size", type=int, default=25_000)
    p.add_argument("--cpus", type=int, default=2)
    p.add_argument("--index", default="auto")
    p.add_argument("--out", default=None, help="keep the maps here (default: a temp folder)")
    p.add_argument("--map", default=None, help="real route: a map folder (with --query)")
    p.add_argument("--query", default=None, help="real route: the query traverse")
    args = p.parse_args()
    if args.map:
        return real_route(args.map, args.query, args.candidates)

    import faiss
    import ray
    import torch

    from torchseq.maps import build_map
    from torchseq.seqslam import SeqSLAMConfig
    from torchseq.seqslam.candidates import CandidateSeqSLAM
    from torchseq.seqslam.sharded import ShardedSeqSLAM

    torch.set_num_threads(1)
    faiss.omp_set_num_threads(1)
    folder = Path(args.out or tempfile.mkdtemp(prefix="bench-sharded-"))
    config = SeqSLAMConfig(candidates=args.candidates)
    rows = []
    t = time.perf_counter()
    ray.init(num_cpus=args.cpus, include_dashboard=False, log_to_driver=False)
    ray_init = time.perf_counter() - t
    for n_ref in args.places:
        ref, query, first = route(n_ref, args.queries, args.dim)
        t = time.perf_counter()
        m = build_map(torch.from_numpy(ref), folder / f"map-{n_ref}", config,
                      shard_size=args.shard_size, index=args.index, overwrite=True)
        build = time.perf_counter() - t
        q = torch.from_numpy(query)
        index = m.index()
        engine = CandidateSeqSLAM(m.descriptors(), config, index=index)
        t = time.perf_counter()
        one = engine.match_descriptors(q)
        one_s = time.perf_counter() - t
        truth = torch.arange(first, first + len(q))
        ok = (one.matches.reference >= 0)
        recall = float(((one.matches.reference - truth).abs() <= 2)[ok].float().mean())
        base = {"places": n_ref, "dim": args.dim, "queries": len(q), "K": args.candidates,
                "index": index.kind, "build_s": round(build, 2)}
        row = {**base, "shards": "one machine", "seconds": round(one_s, 3),
               "qps": round(len(q) / one_s, 1), "recall": round(recall, 3),
               "candidates_s": round(one.seconds["candidates"], 3),
               "driver_rss_mb": round(rss_mb())}
        print(json.dumps(row), flush=True)
        rows.append(row)
        for n in [int(x) for x in args.shards.split(",")]:
            t = time.perf_counter()
            with ShardedSeqSLAM(m, config, n) as sharded:
                start = time.perf_counter() - t
                res = sharded.match_descriptors(q)
                mem = sharded.memory()
            same = bool(torch.equal(res.matches.reference, one.matches.reference)
                        and torch.equal(res.ranked, one.ranked)
                        and np.array_equal(res.matches.score.numpy(),
                                           one.matches.score.numpy(), equal_nan=True))
            s = res.seconds
            row = {**base, "shards": n, "seconds": round(s["total"], 3),
                   "qps": round(len(q) / s["total"], 1), "identical": same,
                   "start_s": round(start, 2), "candidates_s": round(s["candidates"], 3),
                   "round1_s": round(s["floor"], 3), "round2_s": round(s["scores"], 3),
                   "merge_s": round(s["merge"], 3),
                   "merge_ms_per_query": round(1e3 * s["merge"] / len(q), 3),
                   "actor_rows_mb": [round(x["rows_bytes"] / 2**20, 1) for x in mem],
                   "actor_rss_mb": [round(x["rss_bytes"] / 2**20) for x in mem]}
            print(json.dumps(row), flush=True)
            rows.append(row)
            if not same:
                raise SystemExit("sharded result differs from one machine")
    ray.shutdown()
    print(f"\nray.init: {ray_init:.1f} s; machine: {os.cpu_count()} CPUs\n")
    print("| places | index | shards | q/s | total s | index s | round 1 s | round 2 s | "
          "merge ms/query | rows MB per actor | RSS MB per actor | identical |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['places']:,} | {r['index']} | {r['shards']} | {r['qps']} | {r['seconds']} "
              f"| {r['candidates_s']} | {r.get('round1_s', '')} | {r.get('round2_s', '')} | "
              f"{r.get('merge_ms_per_query', '')} | {r.get('actor_rows_mb', '')} | "
              f"{r.get('actor_rss_mb', r.get('driver_rss_mb', ''))} | "
              f"{r.get('identical', '')} |")


if __name__ == "__main__":
    main()

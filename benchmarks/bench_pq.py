"""Product-quantised candidate indexes: bytes per place and recall of the candidate set.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_pq.py --places 100000 --queries 300

Real-ish descriptors: nordland-b's patch-normalised frames (summer + winter, 3,576 places,
64x32, D = 2048, integers 119..135) as the places to find, padded to ``--places`` with
distractors made from them (each a random nordland frame rolled sideways by 1..8 pixels,
with integer noise of sd 1, clipped to 119..135: frames that look like the route but are
not its places). Queries: ``--queries`` frames of the other season (query ``j`` is place
``(j + 1788) % 3576``, +- 2 frames).

For each index: bytes per place (the serialised FAISS index over the places; PQ codes,
ids, centroids), the recall of the exact top K (flat L1, the engine's metric) among the
index's ``refine * K`` proposals re-ranked exactly (what ``CandidateSeqSLAM.search`` keeps),
the place recall (a true place +- 2 among those K) and the search time per query (one
thread). Flat L1 is the reference row.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def realish(n_places: int, seed: int = 0):
    """``(N, 2048)`` float32 places (nordland first), ``(Q, 2048)`` queries, truth ``(Q,)``."""
    from bench_candidates import nordland

    ref, query, _ = nordland(True)
    ref, query = ref.numpy().astype(np.float32), query.numpy().astype(np.float32)
    n = len(ref)
    rng = np.random.default_rng(seed)
    extra = n_places - n
    src = rng.integers(0, n, extra)
    shift = rng.integers(1, 9, extra) * rng.choice([-1, 1], extra)
    out = np.empty((n_places, ref.shape[1]), np.float32)
    out[:n] = ref
    img = ref.reshape(n, 32, 64)
    for i0 in range(0, extra, 10_000):
        s, sh = src[i0:i0 + 10_000], shift[i0:i0 + 10_000]
        block = np.stack([np.roll(img[a], b, axis=1) for a, b in zip(s, sh)]).reshape(len(s), -1)
        noise = np.round(rng.normal(0, 1.0, block.shape)).astype(np.float32)
        out[n + i0:n + i0 + len(s)] = np.clip(block + noise, 119, 135)
    truth = (np.arange(len(query)) + n // 2) % n
    return out, query, truth


def exact_top(ref, query, k):
    import faiss

    index = faiss.IndexFlat(ref.shape[1], faiss.METRIC_L1)
    index.add(ref)
    t = time.process_time()
    _, idx = index.search(query, k)
    return idx, (time.process_time() - t) / len(query), index


def refine_l1(ref, query, prop, k):
    """Re-rank ``(Q, K')`` proposals by exact L1, keep ``k`` (ties -> lower index)."""
    out = np.empty((len(query), k), np.int64)
    for j in range(len(query)):
        p = prop[j][prop[j] >= 0]
        d = np.abs(ref[p] - query[j]).sum(1)
        order = np.lexsort((p, d))[:k]
        out[j, :len(order)] = p[order]
        out[j, len(order):] = -1
    return out


def index_bytes(index) -> int:
    import faiss

    return int(faiss.serialize_index(index).size)


def main() -> None:
    import faiss

    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--places", type=int, default=100_000)
    p.add_argument("--queries", type=int, default=300)
    p.add_argument("--ks", type=int, nargs="+", default=[20, 100])
    p.add_argument("--refine", type=int, default=4)
    p.add_argument("--train", type=int, default=20_000)
    args = p.parse_args()
    faiss.omp_set_num_threads(1)
    ref, query_all, truth_all = realish(args.places)
    rng = np.random.default_rng(1)
    pick = np.sort(rng.choice(len(query_all), args.queries, replace=False))
    query, truth = query_all[pick], truth_all[pick]
    kmax = max(args.ks)
    top, flat_s, flat = exact_top(ref, query, kmax)
    dim, train = ref.shape[1], ref[rng.choice(len(ref), min(args.train, len(ref)), False)]
    nlist = int(np.sqrt(len(ref)))
    kinds = {
        "PQ64x8": lambda: faiss.IndexPQ(dim, 64, 8),
        f"IVF{nlist},PQ64x8": lambda: faiss.IndexIVFPQ(faiss.IndexFlatL2(dim), dim, nlist, 64, 8),
    }
    print(f"{len(ref)} places (3,576 nordland-b + distractors), D = {dim}, {len(query)} "
          f"queries, refine {args.refine}, one thread, {time.strftime('%Y-%m-%d %H:%M UTC')}")
    print()
    print("| index | bytes / place | train + add s | search ms / query | "
          + " | ".join(f"recall of exact top {k} | place recall@{k}" for k in args.ks) + " |")
    print("|---|---:|---:|---:|" + "---:|---:|" * len(args.ks))

    def place_recall(cand):
        return float(np.mean([np.any(np.abs(c[c >= 0] - t) <= 2) for c, t in zip(cand, truth)]))

    cells = [f"{place_recall(top[:, :k]):.3f}" for k in args.ks]
    print(f"| flat L1 (exact) | {index_bytes(flat) / len(ref):.0f} | | {1e3 * flat_s:.1f} | "
          + " | ".join(f"1.000 | {c}" for c in cells) + " |", flush=True)
    for name, make in kinds.items():
        index = make()
        t = time.process_time()
        index.train(train)
        index.add(ref)
        build = time.process_time() - t
        if hasattr(index, "nprobe"):
            index.nprobe = 16
        t = time.process_time()
        _, prop = index.search(query, args.refine * kmax)
        search = (time.process_time() - t) / len(query)
        row = [name, f"{index_bytes(index) / len(ref):.1f}", f"{build:.1f}",
               f"{1e3 * search:.2f}"]
        for k in args.ks:
            cand = refine_l1(ref, query, prop[:, :args.refine * k], k)
            hit = np.mean([len(np.intersect1d(c, e)) / k for c, e in zip(cand, top[:, :k])])
            row += [f"{hit:.3f}", f"{place_recall(cand):.3f}"]
        print("| " + " | ".join(row) + " |", flush=True)


if __name__ == "__main__":
    main()

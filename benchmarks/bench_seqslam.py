"""Classic SeqSLAM speed and memory: tensorised engine vs a naive NumPy port vs the loop oracle.

    .venv/bin/python benchmarks/bench_seqslam.py            # N = M = 1000, 5000, 20000
    .venv/bin/python benchmarks/bench_seqslam.py --quick    # N = 300, 1000
    .venv/bin/python benchmarks/bench_seqslam.py --sizes 2000 --impls engine,numpy
    .venv/bin/python benchmarks/bench_seqslam.py --enhance --sizes 5000 20000  # stage only
    .venv/bin/python benchmarks/bench_seqslam.py --quality   # presets and edges on real data
    .venv/bin/python benchmarks/bench_seqslam.py --threads --sizes 3576 --baseline ../main
        # 1 thread vs the default, idle and beside a busy co-tenant process
    .venv/bin/python benchmarks/bench_seqslam.py --kernels --sizes 1024 3576 --kernel-threads 1 2
        # exact L1 kernels side by side: thermometer vs the compiled uint8 "sad"
    .venv/bin/python benchmarks/bench_seqslam.py --scale --sizes 1000 3576 10000 20000 35768
        # default engine (threads and matrices as configured by default): time, peak RSS

One thread (torch.set_num_threads(1)); every (size, implementation) runs in its own
subprocess so the peak RSS is clean. Descriptors: random 32x64 noise frames and noisy copies,
patch-normalised by torchseq.preprocess (D = 2048, integer grey levels as in OpenSeqSLAM).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
LOOP_MAX = 1000  # the pure-Python oracle is run up to this size only
NUMPY_MAX = 5000
ENGINE_ONLY_ABOVE = 5000


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def reset_peak() -> None:
    """Reset the kernel's high-water mark (VmHWM) so the peak covers only the timed run."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def peak_mb() -> float:
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmHWM")) / 1024
    except (OSError, StopIteration):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def make_descriptors(n: int, seed: int = 0):
    import torch

    from torchseq.preprocess import preprocess

    g = torch.Generator().manual_seed(seed)
    ref_frames = torch.rand(n, 32, 64, generator=g) * 255
    query_frames = (ref_frames + torch.randn(n, 32, 64, generator=g) * 40).clamp(0, 255)
    return (preprocess(ref_frames, (32, 64)).numpy(), preprocess(query_frames, (32, 64)).numpy())


def naive_numpy(ref, query, ds=10, vmin=0.8, vmax=1.2, rwindow=10, window=10, chunk=2**24):
    """The straightforward NumPy port: broadcast differences, row-loop enhancement,
    per-query fancy-index search (velocities and starts vectorised, as OpenSeqSLAM does)."""
    times = {}
    t = time.perf_counter()
    ref, query = ref.astype(np.float32), query.astype(np.float32)
    n_ref, n_query = len(ref), len(query)
    d = np.empty((n_ref, n_query), np.float32)
    step = max(1, chunk // (n_query * ref.shape[1]))
    for i in range(0, n_ref, step):
        d[i:i + step] = np.abs(ref[i:i + step, None, :] - query[None]).sum(-1)
    times["difference"] = time.perf_counter() - t
    t = time.perf_counter()
    e = np.empty_like(d)
    half = window // 2
    for i in range(n_ref):
        v = d[max(0, i - half):min(n_ref, i + half + 1)]
        std = v.std(0, ddof=1)
        e[i] = np.where(std > 0, (d[i] - v.mean(0)) / np.where(std > 0, std, 1), 0)
    e -= e.min()
    times["enhance"] = time.perf_counter() - t
    t = time.perf_counter()
    ext = np.vstack([e, np.full((1, n_query), np.inf, np.float32)])
    ms = np.arange(math.ceil(vmin * ds - 1e-9), math.floor(vmax * ds + 1e-9) + 1)
    off = (np.arange(ds + 1)[None] * ms[:, None]) // ds  # (V, K)
    starts = np.arange(n_ref + 1)
    rows = np.minimum(starts[:, None, None] + off[None], n_ref)  # (S, V, K)
    match = np.full(n_query, -1)
    for n in range(ds // 2, n_query - ds // 2):
        cols = n - ds // 2 + np.arange(ds + 1)
        score = ext[rows, cols[None, None]].sum(-1).min(-1)
        s = int(np.argmin(score))
        match[n] = min(s + ds // 2, n_ref - 1)
    times["search"] = time.perf_counter() - t
    return match, times


def enhance_contrast_shifted(difference, window=10, subtract_min=True, block=2**18):
    """The engine's previous contrast enhancement, kept as the speed reference: per block of
    query columns, window sums of ``2 half + 1`` shifted slices of a zero-padded copy (mean,
    then squared deviations about it), in the input dtype."""
    import torch

    n_ref, n_query = difference.shape
    half = window // 2
    d_t = difference.T
    out_t = torch.empty(n_query, n_ref, dtype=difference.dtype)
    pos = torch.arange(n_ref)
    cols = max(1, block // (n_ref + 2 * half))
    for q0 in range(0, n_query, cols):
        x = d_t[q0:q0 + cols]
        padded = torch.nn.functional.pad(x, (half, half))
        total, count, valid = torch.zeros_like(x), torch.zeros(n_ref, dtype=x.dtype), []
        for shift in range(2 * half + 1):
            ok = ((pos + shift - half >= 0) & (pos + shift - half < n_ref)).to(x.dtype)
            valid.append(ok)
            total += padded[:, shift:shift + n_ref]
            count += ok
        mean = total / count
        var = torch.zeros_like(x)
        for shift in range(2 * half + 1):
            dev = padded[:, shift:shift + n_ref] - mean
            var += dev * dev * valid[shift]
        std = (var / (count - 1)).sqrt()
        out_t[q0:q0 + cols] = torch.where(
            std > 0, (x - mean) / torch.where(std > 0, std, torch.ones_like(std)), 0.0)
    if subtract_min:
        out_t -= out_t.min()
    return out_t.T


def run_enhance(n: int, repeats: int) -> dict:
    """Old (shifted slices) and new enhancement on the same N x N float32 difference matrix,
    interleaved, best of ``repeats``; max |difference| between the two."""
    import torch

    from torchseq.seqslam import difference_matrix, enhance_contrast

    torch.set_num_threads(1)
    ref, query = make_descriptors(n)
    d = difference_matrix(torch.from_numpy(ref), torch.from_numpy(query))
    best = {"shifted": math.inf, "cumsum": math.inf}
    for _ in range(repeats):
        for name, fn in (("shifted", enhance_contrast_shifted), ("cumsum", enhance_contrast)):
            t = time.perf_counter()
            out = fn(d)
            best[name] = min(best[name], time.perf_counter() - t)
            if name == "shifted":
                old = out
            else:
                diff = float((out - old).abs().max())
            del out
    return dict(n=n, **best, max_abs_diff=diff)


def run_one(impl: str, n: int) -> dict:
    import torch

    torch.set_num_threads(1)
    ref, query = make_descriptors(n)
    if impl == "engine":
        from torchseq.seqslam import SeqSLAM  # import before the baseline
    elif impl == "loop":
        sys.path.insert(0, str(ROOT / "tests"))
        from seqslam_oracle import oracle_difference, oracle_enhance, oracle_seqslam
    reset_peak()
    base = rss_mb()
    t0 = time.perf_counter()
    if impl == "engine":  # OpenSeqSLAM's start + ds/2, the rule both baselines implement
        from torchseq.seqslam import SeqSLAMConfig
        result = SeqSLAM(SeqSLAMConfig(match_at="start")).match_descriptors(
            torch.from_numpy(ref), torch.from_numpy(query))
        times = dict(result.seconds)
        match = result.matches.reference.numpy()
    elif impl == "numpy":
        match, times = naive_numpy(ref, query)
    else:
        times = {}
        t = time.perf_counter()
        d = oracle_difference(ref, query)
        times["difference"] = time.perf_counter() - t
        t = time.perf_counter()
        e = oracle_enhance(d)
        times["enhance"] = time.perf_counter() - t
        t = time.perf_counter()
        match = oracle_seqslam(e)[0]
        times["search"] = time.perf_counter() - t
    times["total"] = time.perf_counter() - t0
    valid = match >= 0
    correct = float((np.abs(match[valid] - np.nonzero(valid)[0]) <= 2).mean())
    return dict(impl=impl, n=n, **times, peak_mb=peak_mb() - base, recall=correct,
                match_hash=int(np.sum(match * (np.arange(len(match)) % 97 + 1))))


def quality_data():
    """(name, reference frames, query frames, (R, Q) ground truth, base config) per route.

    corridor: colour frames as RGB (so the OpenSeqSLAM preset applies MATLAB's rgb2gray);
    lens-davis128: 80x80 event-count frames at the speed experiment's LENS setting.
    """
    import cv2
    import torch

    from torchseq.ground_truth import load_ground_truth
    from torchseq.seqslam import SeqSLAMConfig
    from torchseq.sources import load_traverse

    data = ROOT.parent / "shared" / "data"
    out = []
    root = data / "corridor"
    if root.exists():
        def rgb(folder):
            files = sorted(folder.glob("*.jpg"))
            return torch.from_numpy(np.stack([cv2.imread(str(f))[:, :, ::-1] for f in files]))

        ref, query = rgb(root / "ref"), rgb(root / "query")
        gt = load_ground_truth(root / "ground_truth.csv", len(ref), len(query))
        out.append(("corridor", ref, query, gt, {}))
    root = data / "lens-davis128"
    if root.exists():
        ref = load_traverse(root / "example-reference", progress=False)
        query = load_traverse(root / "example-query", progress=False)
        gt = np.load(root / "example-reference_example-query_GT.npy").astype(bool)
        near = np.abs(np.arange(len(ref))[:, None] - np.arange(len(query))[None]) <= 2
        base = dict(image_size=(16, 16), speed_ratio=1.0)
        out.append(("lens-davis128 (exact GT)", ref, query, gt, base))
        out.append(("lens-davis128 (+-2 frames)", ref, query, near, base))
    assert SeqSLAMConfig  # imported for the caller's presets
    return out


def run_quality() -> str:
    """Default vs OpenSeqSLAM preset vs default + edge matching on the real routes."""
    from torchseq.metrics import correct, evaluate
    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig

    lines = ["| data | configuration | recall@1 | recall@5 | PR AUC | coverage "
             "| edge queries matched / correct | same matches as default |",
             "|---|---|---:|---:|---:|---:|---|---:|"]
    for name, ref, query, gt, base in quality_data():
        configs = {"default": SeqSLAMConfig(**base),
                   "openseqslam preset": SeqSLAMConfig.openseqslam(**base),
                   "default + edges": SeqSLAMConfig(edges=True, **base)}
        default_match = None
        for label, cfg in configs.items():
            r = SeqSLAM(cfg).match(ref, query)
            m = evaluate(r.matches, gt, r.ranked.numpy())
            half = cfg.sequence_length // 2
            edge = np.r_[0:half, len(query) - half:len(query)]
            ok = correct(r.matches, gt)
            matched = int((r.matches.reference.numpy()[edge] >= 0).sum())
            match = r.matches.reference.numpy()
            if default_match is None:
                default_match = match
            same = float((match == default_match).mean())
            lines.append(f"| {name} | {label} | {m['recall_at_1']:.3f} | "
                         f"{m.get('recall_at_5', float('nan')):.3f} | {m['auc']:.3f} | "
                         f"{m['coverage']:.3f} | {matched}/{len(edge)} / {int(ok[edge].sum())} | "
                         f"{same:.1%} |")
    return "\n".join(lines)


def run_engine_threads(n: int, threads: int | None, repeats: int = 2) -> dict:
    """One engine run (best of ``repeats``) with ``threads`` intra-op threads (None: torch's
    default) and the engine's default thread use; stage seconds."""
    import torch

    if threads is not None:
        torch.set_num_threads(threads)
    from torchseq.seqslam import SeqSLAM

    ref, query = make_descriptors(n)
    ref, query = torch.from_numpy(ref), torch.from_numpy(query)
    best = None
    for _ in range(repeats):
        r = SeqSLAM().match_descriptors(ref, query)
        if best is None or r.seconds["total"] < best["total"]:
            best = dict(r.seconds)
            workers = getattr(r, "kernels", {}).get("threads")  # absent in older checkouts
    return dict(n=n, torch_threads=torch.get_num_threads(), workers=workers, **best)


def run_threads(sizes, baseline: Path | None, rounds: int = 3) -> str:
    """Engine at one thread vs at PyTorch's default, idle and with a busy co-tenant (a
    process spinning on one core); optionally the same for the code at ``baseline`` (another
    checkout, e.g. the previous version). Every configuration runs ``rounds`` times in its
    own subprocess, the configurations interleaved round by round; the best total counts."""
    roots = [("this", ROOT)] + ([("baseline", baseline.resolve())] if baseline else [])
    lines = ["| N = M | code | co-tenant | threads (intra-op) | workers per stage "
             "| difference s | enhance s | search s | total s | vs 1 thread |",
             "|---:|---|---|---|---|---:|---:|---:|---:|---:|"]
    for n in sizes:
        for busy in (False, True):
            hog = None
            if busy:
                hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
                time.sleep(0.5)
            best = {}
            try:
                for _ in range(rounds):
                    for label, root in roots:
                        for threads in ("1", "default"):
                            env = dict(os.environ, PYTHONPATH=str(root))
                            out = subprocess.run(
                                [sys.executable, __file__, "--one-threads", str(n), threads],
                                capture_output=True, text=True, cwd=ROOT, env=env)
                            if out.returncode:
                                raise SystemExit(out.stderr[-2000:])
                            r = json.loads(out.stdout.strip().splitlines()[-1])
                            key = (label, threads)
                            if key not in best or r["total"] < best[key]["total"]:
                                best[key] = r
            finally:
                if hog is not None:
                    hog.kill()
                    hog.wait()
            for (label, threads), r in best.items():
                one = best[(label, "1")]["total"]
                workers = r.get("workers")
                workers = "/".join(str(v) for v in workers.values()) if workers else "-"
                lines.append(
                    f"| {n} | {label} | {'busy' if busy else 'idle'} | {threads} "
                    f"({r['torch_threads']}) | {workers} | {r['difference']:.2f} | "
                    f"{r['enhance']:.2f} | {r['search']:.2f} | {r['total']:.2f} | "
                    f"{r['total'] / one:.2f}x |")
                print(lines[-1], file=sys.stderr, flush=True)
    return "\n".join(lines)


def run_scale_one(n: int) -> dict:
    """The default engine on N x N synthetic descriptors: seconds, peak RSS of the process
    (VmHWM, descriptors included) and the extra peak over the RSS before the match."""
    import torch

    from torchseq.seqslam import SeqSLAM

    ref, query = make_descriptors_chunked(n)
    engine = SeqSLAM()
    reset_peak()
    base = rss_mb()
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    r = engine.match_descriptors(ref, query)
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    valid = r.matches.reference.numpy() >= 0
    idx = np.nonzero(valid)[0]
    recall = float((np.abs(r.matches.reference.numpy()[valid] - idx) <= 2).mean())
    return dict(n=n, **r.seconds, cpu_s=cpu, peak_mb=peak_mb(), extra_mb=peak_mb() - base,
                descriptors_mb=(ref.numel() + query.numel()) * 4 / 2**20,
                matrices=r.kernels.get("matrices"), workers=str(r.kernels.get("threads")),
                recall=recall, torch_threads=torch.get_num_threads())


def make_descriptors_chunked(n: int, seed: int = 0, chunk: int = 4096):
    """``make_descriptors`` built ``chunk`` frames at a time (bounded temporaries)."""
    import torch

    from torchseq.preprocess import preprocess

    g = torch.Generator().manual_seed(seed)
    ref = torch.empty(n, 2048)
    query = torch.empty(n, 2048)
    for i in range(0, n, chunk):
        f = torch.rand(min(chunk, n - i), 32, 64, generator=g) * 255
        q = (f + torch.randn(f.shape, generator=g) * 40).clamp(0, 255)
        ref[i:i + len(f)] = preprocess(f, (32, 64))
        query[i:i + len(f)] = preprocess(q, (32, 64))
    return ref, query


def run_scale(sizes) -> str:
    lines = ["| N = M | matrices | workers per stage | difference s | enhance s | search s "
             "| total s (wall) | CPU s | peak RSS MB (process) | extra peak MB | descriptors MB "
             "| matched within 2 |", "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for n in sizes:
        out = subprocess.run([sys.executable, __file__, "--one-scale", str(n)],
                             capture_output=True, text=True, cwd=ROOT)
        if out.returncode:
            lines.append(f"| {n} | failed: {out.stderr[-300:]!r} |")
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        workers = r["workers"].replace("'", "").replace("{", "").replace("}", "")
        lines.append(f"| {n} | {r['matrices']} | {workers} | {r['difference']:.1f} | "
                     f"{r['enhance']:.1f} | {r['search']:.1f} | {r['total']:.1f} | "
                     f"{r['cpu_s']:.1f} | {r['peak_mb']:.0f} | {r['extra_mb']:.0f} | "
                     f"{r['descriptors_mb']:.0f} | "
                     f"{r['recall']:.3f} |")
        print(lines[-1], file=sys.stderr, flush=True)
    return "\n".join(lines)


def sad_parallel_ways(ref, query, workers: int) -> tuple[float, float]:
    """The library's compiled loop (``_l1_numba.sad``) over ``workers`` threads two ways:
    the engine's worker threads (``_l1_sad`` through ``_parallel.run_blocks``, the uint8
    reference built beforehand) and numba's own threads (``prange`` over 64-row tiles of the
    reference; benchmark-only). Seconds of each, without the checks and the reference's
    conversion that ``difference_with_kernel`` adds."""
    import numba
    import torch

    from torchseq.seqslam import _l1_numba
    from torchseq.seqslam.difference import _l1_sad, sad_codes

    @numba.njit(parallel=True, nogil=True)
    def spread(a, b, out):
        tile = _l1_numba.TILE
        for t in numba.prange((a.shape[0] + tile - 1) // tile):
            i0 = t * tile
            _l1_numba.sad(a[i0:min(i0 + tile, a.shape[0])], b, out, i0, 0)

    lo = float(min(ref.min(), query.min()))
    rt, qt = torch.from_numpy(ref), torch.from_numpy(query)
    codes = sad_codes(rt, lo)
    out_t = torch.empty(len(query), len(ref))
    t = time.perf_counter()
    _l1_sad(rt, qt, out_t, lo, 2**26, workers, codes)
    blocks = time.perf_counter() - t
    a, b = codes.numpy(), (qt - lo).to(torch.uint8).numpy()
    out = np.empty((len(b), len(a)), np.float32)
    numba.set_num_threads(workers)
    spread(a[:3], b[:3], out)  # compile outside the timing (the same array types)
    t = time.perf_counter()
    spread(a, b, out)
    prange = time.perf_counter() - t
    assert np.array_equal(out, out_t.numpy())
    return blocks, prange


def run_kernels(n: int, threads=(1,), repeats: int = 2) -> list[dict]:
    """Exact L1 difference matrix: the thermometer kernel (int8 or float32 product, whichever
    ``thermometer_product`` picks on this CPU) against the compiled uint8 ``"sad"`` kernel,
    each forced through ``difference_with_kernel(kernel=...)``, at each worker count
    (interleaved, best of repeats; torch on one intra-op thread). The first size also times
    the sad kernel's start-up (numba import + loading the cached compiled code, or compiling
    it when there is no cache); ``cdist_per_pair_us`` is torch.cdist(p=1) at one thread."""
    import torch

    from torchseq.seqslam.difference import difference_with_kernel, thermometer_product

    torch.set_num_threads(1)
    ref, query = make_descriptors(n)
    rt, qt = torch.from_numpy(ref), torch.from_numpy(query)
    started = "numba" in sys.modules
    t = time.perf_counter()
    difference_with_kernel(rt[:2], qt[:2], kernel="sad")  # numba import and load / compile
    startup = None if started else time.perf_counter() - t
    rows = []
    for workers in threads:
        best = {"thermometer": math.inf, "sad": math.inf}
        got = {}
        for _ in range(repeats):
            for kernel in best:
                t = time.perf_counter()
                d, ran = difference_with_kernel(rt, qt, threads=workers, kernel=kernel)
                best[kernel] = min(best[kernel], time.perf_counter() - t)
                assert ran == kernel
                got[kernel] = d
        ways = [sad_parallel_ways(ref, query, workers) for _ in range(repeats)]
        rows.append({"n": n, "threads": workers, "product": thermometer_product("cpu"),
                     "sad_loop_run_blocks_s": min(w[0] for w in ways),
                     "sad_loop_prange_s": min(w[1] for w in ways),
                     "thermometer_s": best["thermometer"], "sad_s": best["sad"],
                     "speedup": best["thermometer"] / best["sad"],
                     "exact": bool(torch.equal(got["sad"], got["thermometer"])),
                     "sad_startup_s": startup})
        startup = None
    m = min(n, 1000)
    t = time.perf_counter()
    torch.cdist(qt[:m], rt[:m], p=1)
    rows[0]["cdist_per_pair_us"] = (time.perf_counter() - t) / (m * m) * 1e6
    rows[0].update(run_banded_kernels(rt, qt))
    return rows


def run_banded_kernels(rt, qt) -> dict:
    """The banded engine's difference stage (keep_matrices=False, one worker) with each L1
    kernel, chosen by moving the size rule's threshold (``difference.SAD_MIN_WORK``)."""
    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig, difference

    out = {}
    real = difference.SAD_MIN_WORK
    try:
        for kernel, min_work in (("thermometer", 2**62), ("sad", 0)):
            difference.SAD_MIN_WORK = min_work
            if kernel == "sad" and difference.thermometer_product("cpu") != "float32":
                continue  # the rule keeps the int8 thermometer product on AVX-512
            r = SeqSLAM(SeqSLAMConfig(keep_matrices=False, threads=1)).match_descriptors(rt, qt)
            assert r.kernels["difference"] == kernel
            out[f"banded_difference_{kernel}_s"] = r.seconds["difference"]
            out[f"banded_total_{kernel}_s"] = r.seconds["total"]
    finally:
        difference.SAD_MIN_WORK = real
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 5000, 20000])
    parser.add_argument("--quick", action="store_true", help="sizes 300 and 1000")
    parser.add_argument("--impls", default="engine,numpy,loop")
    parser.add_argument("--enhance", action="store_true",
                        help="time only contrast enhancement, old (shifted slices) vs new")
    parser.add_argument("--repeats", type=int, default=2, help="with --enhance: best of")
    parser.add_argument("--quality", action="store_true",
                        help="recall of the default, the OpenSeqSLAM preset and edge matching "
                             "on the real routes in ../shared/data")
    parser.add_argument("--threads", action="store_true",
                        help="one thread vs the default, idle and with a busy co-tenant")
    parser.add_argument("--baseline", type=Path, default=None,
                        help="with --threads: also run the checkout at this path")
    parser.add_argument("--kernels", action="store_true",
                        help="exact L1 kernels (thermometer, sad) side by side")
    parser.add_argument("--kernel-threads", type=int, nargs="+", default=[1],
                        help="with --kernels: worker threads to run each kernel with")
    parser.add_argument("--scale", action="store_true",
                        help="default engine: time and peak RSS per size")
    parser.add_argument("--one-scale", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--one-threads", nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--one", nargs=2, metavar=("IMPL", "N"), help=argparse.SUPPRESS)
    parser.add_argument("--doc", type=Path, default=None,
                        help="also replace the benchmark table in this Markdown file")
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(args.one[0], int(args.one[1]))))
        return
    if args.quality:
        print(run_quality())
        return
    if args.one_threads:
        threads = None if args.one_threads[1] == "default" else int(args.one_threads[1])
        print(json.dumps(run_engine_threads(int(args.one_threads[0]), threads)))
        return
    if args.threads:
        print(run_threads(args.sizes, args.baseline))
        return
    if args.one_scale:
        print(json.dumps(run_scale_one(args.one_scale)))
        return
    if args.scale:
        print(run_scale(args.sizes))
        return
    if args.kernels:
        print("| N = M | threads | thermometer (product) s | sad s | speed-up | equal | "
              "sad loop alone: worker threads / numba prange s |\n"
              "|---:|---:|---:|---:|---:|---|---:|")
        banded = []
        for n in args.sizes:
            for r in run_kernels(n, args.kernel_threads):
                print(f"| {n} | {r['threads']} | {r['thermometer_s']:.2f} ({r['product']}) | "
                      f"{r['sad_s']:.2f} | {r['speedup']:.1f}x | {r['exact']} | "
                      f"{r['sad_loop_run_blocks_s']:.2f} / {r['sad_loop_prange_s']:.2f} |",
                      flush=True)
                print(json.dumps(r), file=sys.stderr, flush=True)
                if "banded_difference_sad_s" in r:
                    banded.append(f"| {n} | {r['banded_difference_thermometer_s']:.2f} | "
                                  f"{r['banded_difference_sad_s']:.2f} | "
                                  f"{r['banded_total_thermometer_s']:.2f} | "
                                  f"{r['banded_total_sad_s']:.2f} |")
        if banded:
            print("\nbanded engine (keep_matrices=False), one worker\n\n| N = M | difference, "
                  "thermometer s | difference, sad s | total, thermometer s | total, sad s |\n"
                  "|---:|---:|---:|---:|---:|")
            print("\n".join(banded))
        return
    sizes = [300, 1000] if args.quick else args.sizes
    if args.enhance:
        print("| N = M | shifted slices (old) s | cumulative sums (new) s | speed-up "
              "| max abs difference |\n|---:|---:|---:|---:|---:|")
        for n in sizes:
            r = run_enhance(n, args.repeats)
            print(f"| {n} | {r['shifted']:.2f} | {r['cumsum']:.2f} | "
                  f"{r['shifted'] / r['cumsum']:.1f}x | {r['max_abs_diff']:.1e} |", flush=True)
        return
    impls = args.impls.split(",")
    rows = []
    for n in sizes:
        for impl in impls:
            limit = {"loop": LOOP_MAX, "numpy": NUMPY_MAX}.get(impl, math.inf)
            if n > limit:
                rows.append(dict(impl=impl, n=n, skipped=f"not run (> {limit})"))
                continue
            out = subprocess.run([sys.executable, __file__, "--one", impl, str(n)],
                                 capture_output=True, text=True, cwd=ROOT)
            if out.returncode:
                rows.append(dict(impl=impl, n=n, skipped="failed: " + out.stderr[-200:]))
                continue
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(f"# {impl} N={n}: {rows[-1]['total']:.2f} s", file=sys.stderr, flush=True)
    lines = ["| N = M | implementation | difference s | enhance s | search s | total s "
             "| speed-up vs NumPy | peak extra RSS MB | same matches as engine |",
             "|---:|---|---:|---:|---:|---:|---:|---:|---|"]
    for row in rows:
        if "skipped" in row:
            lines.append(f"| {row['n']} | {row['impl']} | | | | {row['skipped']} | | | |")
            continue
        ref = {r["impl"]: r for r in rows if r["n"] == row["n"] and "skipped" not in r}
        numpy_total = ref.get("numpy", {}).get("total")
        speed = f"{numpy_total / row['total']:.1f}x" if numpy_total else ""
        same = ""
        if "engine" in ref and row["impl"] != "engine":
            same = "yes" if ref["engine"]["match_hash"] == row["match_hash"] else "NO"
        lines.append(
            f"| {row['n']} | {row['impl']} | {row['difference']:.2f} | {row['enhance']:.2f} | "
            f"{row['search']:.2f} | {row['total']:.2f} | {speed} | {row['peak_mb']:.0f} | "
            f"{same} |")
    cpu = platform.processor() or platform.machine()
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo")
                   if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    table = "\n".join(lines)
    header = (f"Machine: {cpu}, {os.cpu_count()} cores (1 thread used), Python "
              f"{platform.python_version()}, torch {__import__('torch').__version__}.")
    print(header + "\n\n" + table)
    if args.doc:
        text = args.doc.read_text()
        start, end = "<!-- bench:start -->", "<!-- bench:end -->"
        a, b = text.index(start) + len(start), text.index(end)
        from torchseq.atomic import write_text

        write_text(args.doc, text[:a] + "\n" + header + "\n\n" + table + "\n" + text[b:])


if __name__ == "__main__":
    main()

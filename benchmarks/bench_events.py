"""Event benchmarks: accumulation, readers and the speed experiment end to end; one thread.

    .venv/bin/python benchmarks/bench_events.py            # prints Markdown tables
    .venv/bin/python benchmarks/bench_events.py --write-docs   # also updates docs/results/events.md
    .venv/bin/python benchmarks/bench_events.py --only readers # one section

Accumulation: torchseq's bincount ``accumulate`` against a straightforward NumPy version
(``np.add.at`` per window in a Python loop over windows), a plain Python per-event loop (on
a slice, extrapolated per event) and tonic's ``to_frame_numpy`` when tonic is installed
(benchmark only; loaded without its dataset dependencies). Readers: events per second on
the real files (best of 5 whole-file reads) and on large files written by torchseq's writers
(AEDAT 2.0, AEDAT 4.0, EVT 3.0; 20 M events, streamed and read whole, with the peak
resident memory a fresh process adds), with the field's readers (`aedat`, `dv-processing`,
`evlib`) side by side when TORCHSEQ_BENCH_LIBS points at them, and in the same run the
NumPy EVT 3 kernel, the previous AEDAT 4 packet join and the previous whole read.

Accumulation rows also time the previous implementation (int64 flat index, one weighted
bincount; kept here as ``previous_accumulate``) in the same run, a 20M-event stream, CUDA
when available, and a three-member temporal-window ensemble (one pass) against three
separate accumulations. The experiment row times the seed's speed experiment end to end on
files: runs A and B (demo route) written as AEDAT 2.0, then read, accumulated into 10 ms
windows, pooled to 16x16 and matched with SeqSLAM (ds = 100).

Accumulation and experiment rates are events per second of *process CPU time* (one
thread): the cost on one core, which the time slices a busy shared host takes away do not
inflate (wall-clock rates on the 2-core host shared by several jobs moved 2-4x between runs;
CPU-time rates moved a few percent). Reader rows are CPU time too (all threads of a field
reader count), with the wall-time rate in their notes.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np
import torch

from torchseq.events import (
    EventStream,
    accumulate,
    iter_events,
    make_events,
    read_events,
    write_aedat2,
    write_aedat4,
)
from torchseq.events.ensemble import accumulate_ensemble
from torchseq.events.prophesee import EVT3_KERNEL, write_evt3

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "events"
DOC = ROOT / "docs" / "results" / "events.md"
BEGIN, END = "<!-- bench_events:begin -->", "<!-- bench_events:end -->"


def timed(fn, repeat=1):
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def cpu_timed(fn, repeat=1):
    """Best CPU time of the process (one thread): a per-core cost that time slices lost to
    other jobs on a shared host do not inflate (memory-bandwidth contention still does)."""
    best = float("inf")
    for _ in range(repeat):
        t = time.process_time()
        out = fn()
        best = min(best, time.process_time() - t)
    return best, out


def numpy_loop(ev, w, h, window_us):
    t0 = ev["t"][0]
    win = (ev["t"] - t0) // window_us
    n = int(win[-1]) + 1
    frames = np.zeros((n, h, w), np.float32)
    bounds = np.searchsorted(win, np.arange(n + 1))
    for k in range(n):
        sl = slice(bounds[k], bounds[k + 1])
        np.add.at(frames[k], (ev["y"][sl], ev["x"][sl]), 2.0 * ev["p"][sl] - 1.0)
    return frames


def python_loop(ev, w, h, window_us):
    t0 = int(ev["t"][0])
    frames = {}
    for t, x, y, p in zip(ev["t"].tolist(), ev["x"].tolist(), ev["y"].tolist(),
                          ev["p"].tolist()):
        f = frames.setdefault((t - t0) // window_us, np.zeros((h, w), np.float32))
        f[y, x] += 1 if p else -1
    return frames


def load_tonic_to_frame():
    spec = importlib.util.find_spec("tonic")
    if spec is None or not spec.submodule_search_locations:
        return None
    base = Path(list(spec.submodule_search_locations)[0])
    pkg = types.ModuleType("tonic")
    pkg.__path__ = [str(base)]
    saved = sys.modules.get("tonic")
    sys.modules["tonic"] = pkg
    try:
        for name, rel in (("tonic.slicers", "slicers.py"),
                          ("tonic.functional.to_frame", "functional/to_frame.py")):
            s = importlib.util.spec_from_file_location(name, base / rel)
            mod = importlib.util.module_from_spec(s)
            sys.modules[name] = mod
            s.loader.exec_module(mod)
        return sys.modules["tonic.functional.to_frame"].to_frame_numpy
    except Exception as err:  # noqa: BLE001 - any failure means "not available"
        print(f"tonic present but not loadable: {err}", file=sys.stderr)
        return None
    finally:
        if saved is not None:
            sys.modules["tonic"] = saved


def bench_accumulate(n_events: int) -> list[tuple[str, float, str]]:
    rng = np.random.default_rng(0)
    w = h = 128
    window_us = 10_000
    ev = make_events(np.sort(rng.integers(0, 2_000_000, n_events)), rng.integers(0, w, n_events),
                     rng.integers(0, h, n_events), rng.integers(0, 2, n_events))
    s = EventStream(ev, (w, h))
    rows = []
    t_vec, frames = cpu_timed(lambda: accumulate(s, window_us=window_us, mode="signed"), 3)
    rows.append(("torchseq accumulate (bincount, signed)", n_events / t_vec, "1.0x"))
    t_np, ref = cpu_timed(lambda: numpy_loop(ev, w, h, window_us))
    assert np.array_equal(ref, frames.numpy())
    rows.append(("NumPy np.add.at, loop over windows", n_events / t_np,
                 f"{t_np / t_vec:.1f}x slower"))
    m = min(n_events, 200_000)
    t_py, _ = cpu_timed(lambda: python_loop(ev[:m], w, h, window_us))
    rows.append(("plain Python loop per event", m / t_py,
                 f"{(t_py / m) / (t_vec / n_events):.0f}x slower"))
    to_frame = load_tonic_to_frame()
    if to_frame is not None:
        tev = np.zeros(n_events, [("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "<i1")])
        for f in "txyp":
            tev[f] = ev[f]
        t_to, out = cpu_timed(lambda: to_frame(tev, (w, h, 2), time_window=window_us), 3)
        signed = out[:, 1].astype(np.float32) - out[:, 0]  # tonic drops the partial last window
        agree = np.array_equal(signed, frames.numpy()[:len(signed)])
        rows.append((f"tonic to_frame_numpy (two-channel{', same frames' if agree else ''})",
                     n_events / t_to, f"{t_to / t_vec:.1f}x slower"))
    else:
        rows.append(("tonic to_frame_numpy", float("nan"), "not installed: skipped"))
    return rows


def previous_accumulate(ev, w, h, window_us):
    """The accumulate of the previous commit: int64 flat index, signed weights, bincount."""
    t0 = int(ev["t"].min())
    win = (ev["t"].astype(np.int64) - t0) // window_us
    n = int(win.max()) + 1
    flat = win * (h * w)
    flat += ev["y"].astype(np.int64) * w
    flat += ev["x"]
    weights = torch.from_numpy(ev["p"]).to(torch.float32).mul_(2).sub_(1)
    return torch.bincount(torch.from_numpy(flat), weights=weights,
                          minlength=n * h * w).reshape(n, h, w)


def random_stream(n_events, w=128, h=128, span_us=2_000_000, seed=0):
    rng = np.random.default_rng(seed)
    return EventStream(make_events(np.sort(rng.integers(0, span_us, n_events)),
                                   rng.integers(0, w, n_events), rng.integers(0, h, n_events),
                                   rng.integers(0, 2, n_events)), (w, h))


def bench_accumulate_kernels(sizes=(2_000_000, 20_000_000)) -> list[tuple[str, float, str]]:
    """This accumulate against the previous one, per size; CUDA and ensemble rows."""
    rows = []
    for n in sizes:
        s = random_stream(n)
        t_new, new = cpu_timed(lambda: accumulate(s, window_us=10_000, mode="signed"), 7)
        t_old, old = cpu_timed(lambda: previous_accumulate(s.events, 128, 128, 10_000), 7)
        assert torch.equal(new, old)
        rows.append((f"accumulate, {n / 1e6:g}M events (signed, CPU time)", n / t_new,
                     f"{t_old / t_new:.1f}x the previous implementation"))
        rows.append((f"previous accumulate, {n / 1e6:g}M events (CPU time)", n / t_old,
                     "same frames"))
        if torch.cuda.is_available():
            accumulate(s, window_us=10_000, device="cuda")
            torch.cuda.synchronize()

            def on_gpu():
                f = accumulate(s, window_us=10_000, device="cuda")
                torch.cuda.synchronize()
                return f

            t_gpu, f = timed(on_gpu, 3)
            assert torch.equal(f.cpu(), new)
            rows.append((f"accumulate, {n / 1e6:g}M events (CUDA, incl. host->device copy)",
                         n / t_gpu, f"{t_new / t_gpu:.1f}x the CPU"))
    s = random_stream(sizes[0])
    windows = (5_000, 10_000, 20_000)
    t_ens, _ = cpu_timed(lambda: accumulate_ensemble(s, windows, step_us=10_000, mode="count",
                                                     downsample=(16, 16)), 5)
    t_sep, _ = cpu_timed(lambda: [accumulate(s, window_us=L, mode="count", downsample=(16, 16))
                                  for L in windows], 5)
    rows.append((f"ensemble 5+10+20 ms, {sizes[0] / 1e6:g}M events, one pass (16x16)",
                 sizes[0] / t_ens, f"{t_sep / t_ens:.1f}x of three accumulations' time"
                 " (those give uncentred windows)"))
    return rows


def bench_experiment() -> list[tuple[str, float, str]]:
    """The seed's speed experiment (demo route, runs A and B) end to end from files."""
    sys.path.insert(0, str(ROOT / "experiments"))
    import speed_experiment as se

    from torchseq.events.runs import simulate_run
    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig

    cfg = se.Config()
    frames, positions, units_per_s = se.route_frames(cfg)
    sim = dict(contrast_threshold=cfg.contrast_threshold, threshold_noise=cfg.threshold_noise,
               noise_rate_hz=cfg.noise_rate_hz)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        paths = {}
        for name, speed, seed in (("A", 1.0, 1), ("B", 0.66, 2)):
            run = simulate_run(frames, positions, speed, units_per_s, seed=seed, **sim)
            paths[name] = Path(tmp) / f"{name}.aedat"
            write_aedat2(paths[name], run.stream)
        sc = SeqSLAMConfig(image_size=cfg.pooled, patch_size=cfg.patch_size, ds=cfg.ds,
                           enhance_window=cfg.enhance_window, speed_ratio=0.66)
        n_events = 0
        seconds = {"read": 0.0, "accumulate": 0.0, "match": 0.0}

        def pipeline():
            nonlocal n_events
            pooled = {}
            n_events = 0
            for name, path in paths.items():
                t = time.process_time()
                s = read_events(path)
                seconds["read"] += time.process_time() - t
                t = time.process_time()
                pooled[name] = accumulate(s, window_us=10_000, mode="count", anchor="zero",
                                          downsample=cfg.pooled)
                seconds["accumulate"] += time.process_time() - t
                n_events += len(s)
            t = time.process_time()
            res = SeqSLAM(sc).match(pooled["A"][:cfg.n_reference],
                                    pooled["B"][:int(cfg.n_reference / 0.66)])
            seconds["match"] += time.process_time() - t
            return res

        total, _ = cpu_timed(pipeline, 1)
        parts = ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in seconds.items())
        rows.append((f"speed experiment B->A end to end ({n_events:,} events in 2 AEDAT files)",
                     n_events / total, f"{total:.2f} s: {parts}"))
    return rows


# ---------------------------------------------------------------- readers (events-readers)
# Field readers compared when importable: `aedat` (MIT, Rust), `dv-processing` (Apache-2.0,
# C++), `evlib` (MIT, Rust + polars). They are not torchseq dependencies; install them
# anywhere and point TORCHSEQ_BENCH_LIBS at that folder (appended to sys.path, so this
# environment's numpy stays first), e.g. `pip install --target /tmp/evlibs aedat
# dv-processing evlib`.


def _field_readers() -> dict:
    extra = os.environ.get("TORCHSEQ_BENCH_LIBS")
    if extra:
        sys.path.append(extra)
    libs = {}
    for name in ("aedat", "dv_processing", "evlib"):
        try:
            libs[name] = importlib.import_module(name)
        except Exception as err:  # noqa: BLE001 - any failure means "not available"
            print(f"{name} not available: {type(err).__name__}", file=sys.stderr)
    return libs


def _aedat_pkg(mod, path):
    return np.concatenate([pk["events"] for pk in mod.Decoder(str(path)) if "events" in pk])


def _dv(mod, path):
    rec, parts = mod.io.MonoCameraRecording(str(path)), []
    while (batch := rec.getNextEventBatch()) is not None:
        parts.append(batch.numpy())
    return np.concatenate(parts)


def _evlib(mod, path):
    df = mod.load_events(str(path))
    df = df.collect() if hasattr(df, "collect") else df
    return {"t": df["t"].cast(int).to_numpy(), "x": df["x"].to_numpy(),
            "y": df["y"].to_numpy(), "p": df["polarity"].to_numpy() > 0}


# each field reader's native output (timed) and its conversion to our events (not timed)
FIELD = {"aedat": ("aedat 2.3 (Rust)", _aedat_pkg, {".aedat4"},
                   lambda e: make_events(e["t"], e["x"], e["y"], e["on"])),
         "dv_processing": ("dv-processing 2.0 (C++)", _dv, {".aedat4"},
                           lambda e: make_events(e["timestamp"], e["x"], e["y"], e["polarity"])),
         "evlib": ("evlib 0.13 (Rust, polars)", _evlib, {".aedat", ".aedat4", ".raw"},
                   lambda e: make_events(e["t"], e["x"], e["y"], e["p"]))}


def both_timed(fn, repeat=1):
    """Best CPU time and best wall time of ``repeat`` calls (reader rows give both)."""
    cpu = wall = float("inf")
    for _ in range(repeat):
        c, w = time.process_time(), time.perf_counter()
        out = fn()
        cpu, wall = min(cpu, time.process_time() - c), min(wall, time.perf_counter() - w)
    return cpu, wall, out


def _compare_row(label, fn, convert, path, ours, repeat):
    """A row for a field reader: its rate (native output) and whether it gives our events."""
    try:
        cpu, wall, native = both_timed(lambda: fn(path), repeat)
        ev = convert(native)
    except Exception as err:  # noqa: BLE001 - report any failure in the table
        return (label, float("nan"), f"fails: {type(err).__name__}: {str(err)[:60]}")
    if np.array_equal(ev, ours):
        verdict = "same events"
    elif len(ev) == len(ours) and all(np.array_equal(ev[f], ours[f]) for f in "xyp"):
        verdict = "same x, y, p; t differs"
    else:
        bad = (len(ev) - len(ours)) if len(ev) != len(ours) else int((ev != ours).sum())
        verdict = (f"different events ({len(ev):,} vs {len(ours):,}"
                   + (f"; {bad:,} differ)" if len(ev) == len(ours) else ")"))
    return (label, len(ev) / cpu, f"{len(ev) / wall / 1e6:.0f} M/s wall; {verdict}")


def _stream(path, chunk=1 << 20, **options):
    n = 0
    for c in iter_events(path, chunk, **options):
        n += len(c)
    return n


_RSS_CHILD = """
import re, sys
import numpy as np
from torchseq.events import iter_events, read_events
from torchseq.events.prophesee import EVT3_KERNEL, decode_evt3
decode_evt3(np.zeros(0, np.uint16), {}, kernel=EVT3_KERNEL)  # load the compiled kernel first
def rss(key):
    status = open("/proc/self/status").read()
    return int(re.search(key + r":\\s+(\\d+) kB", status).group(1))
base = rss("VmRSS")
with open("/proc/self/clear_refs", "w") as f:  # resets the peak (VmHWM) to the current RSS
    f.write("5")
kw = {"evt3_kernel": EVT3_KERNEL} if sys.argv[1].endswith(".raw") else {}
if sys.argv[2] == "stream":
    n = sum(len(c) for c in iter_events(sys.argv[1], 1 << 20, **kw))
else:
    n = len(read_events(sys.argv[1], **kw))
print(n, rss("VmHWM") - base)
"""


def _rss_growth(path, how) -> float:
    """Peak resident memory (MiB) a fresh process adds while it reads ``path`` (``how``:
    ``"stream"`` or ``"whole"``) over its resident memory after the imports (Linux: the
    peak is reset through /proc/self/clear_refs before reading; NaN where that fails)."""
    out = subprocess.run([sys.executable, "-c", _RSS_CHILD, str(path), how],
                         capture_output=True, text=True)
    if out.returncode:
        print(f"RSS measurement failed: {out.stderr[-300:]}", file=sys.stderr)
        return float("nan")
    return int(out.stdout.split()[1]) / 1024


def _bursts(n, w, h, seed=0, span_us=1_000_000):
    """Edge-like events: horizontal runs of 1-8 pixels at one (t, y, p), time-ordered."""
    rng = np.random.default_rng(seed)
    lens = rng.integers(1, 9, n // 4 + 1)
    lens = lens[: np.searchsorted(np.cumsum(lens), n) + 1]
    m = len(lens)
    owner = np.repeat(np.arange(m), lens)
    off = np.arange(len(owner)) - np.repeat(np.cumsum(lens) - lens, lens)
    t = np.sort(rng.integers(0, span_us, m))
    ev = make_events(t[owner], rng.integers(0, w - 8, m)[owner] + off,
                     rng.integers(0, h, m)[owner], rng.integers(0, 2, m)[owner])[:n]
    return EventStream(ev, (w, h))


def bench_readers(n_large: int = 20_000_000) -> list[tuple[str, float, str]]:
    """Reader rows: the real files whole, then large written files streamed, + field readers.

    Rates are events per second of process CPU time (all threads of a field reader count),
    the wall-time rate in the note; best of 5 (real files) or 3 (large files).
    """
    libs = _field_readers()
    rows = []
    files = [("IMU_translBoxes.aedat", "AEDAT 2.0 DAVIS", {}),
             ("alex_walking_again.aedat", "AEDAT 2.0 DVS128", {}),
             ("evt3_sample.raw", "EVT 3.0 .raw", {}),
             ("sample.aedat4", "AEDAT 4.0 (LZ4)", {})]
    for name, label, kw in files:
        path = DATA / name
        if not path.exists():
            continue
        cpu, wall, s = both_timed(lambda: read_events(path, **kw), 5)
        rows.append((f"torchseq, {label}: {name}", len(s) / cpu,
                     f"{len(s) / wall / 1e6:.0f} M/s wall, {path.stat().st_size / cpu / 1e6:.0f}"
                     f" MB/s"))
        for lib, mod in libs.items():
            label2, fn, sfx, convert = FIELD[lib]
            if path.suffix in sfx:
                rows.append(_compare_row(f"{label2}, same file", lambda p: fn(mod, p), convert,
                                         path, s.events, 5))
    with tempfile.TemporaryDirectory() as tmp:
        s = _bursts(n_large, 1280, 720, span_us=n_large // 20)  # 20 M events/s of scene
        ev = s.events
        big = [("AEDAT 2.0 DAVIS346", Path(tmp) / "big.aedat", lambda p: write_aedat2(
                   p, EventStream(make_events(ev["t"], ev["x"] % 346, ev["y"] % 260, ev["p"]),
                                  (346, 260)), layout="davis")),
               ("EVT 3.0 1280x720", Path(tmp) / "big.raw", lambda p: write_evt3(p, s)),
               ("AEDAT 4.0 LZ4 1280x720", Path(tmp) / "big.aedat4",
                lambda p: write_aedat4(p, s))]
        for label, path, write in big:
            write(path)
            mb = path.stat().st_size / 1e6
            # the numba kernel named: by default files under 128 MiB decode with NumPy
            fast = {"evt3_kernel": EVT3_KERNEL} if path.suffix == ".raw" else {}
            cpu, wall, n = both_timed(lambda: _stream(path, **fast), 3)
            rss = _rss_growth(path, "stream")
            rows.append((f"torchseq, {label}, {n:,} events ({mb:.0f} MB) written by torchseq, "
                         f"streamed (iter_events, 2^20 per chunk)", n / cpu,
                         f"{n / wall / 1e6:.0f} M/s wall, {mb / cpu:.0f} MB/s; peak RSS "
                         f"+{rss:.0f} MiB"))
            if path.suffix == ".raw":
                c2, w2, _ = both_timed(lambda: _stream(path, evt3_kernel="numpy"), 3)
                rows.append((f"torchseq, {label}, same file streamed, NumPy kernel "
                             "(evt3_kernel='numpy')", n / c2,
                             f"{n / w2 / 1e6:.0f} M/s wall; the numba kernel is "
                             f"{c2 / cpu:.1f}x faster"))
            if path.suffix == ".aedat4":
                import torchseq.events.aedat4 as a4

                saved, a4.concat_events = a4.concat_events, np.concatenate
                try:  # the previous packet join: NumPy copies the padded rows field by field
                    c2, w2, _ = both_timed(lambda: _stream(path), 3)
                finally:
                    a4.concat_events = saved
                rows.append((f"torchseq, {label}, same file streamed, packets joined by "
                             "np.concatenate (the previous reader)", n / c2,
                             f"{n / w2 / 1e6:.0f} M/s wall; concat_events is "
                             f"{c2 / cpu:.1f}x faster"))
            cpu, wall, whole = both_timed(lambda: read_events(path), 3)
            ours = whole.events
            rss = _rss_growth(path, "whole")
            rows.append((f"torchseq, {label}, same file (read_events, whole)", len(ours) / cpu,
                         f"{len(ours) / wall / 1e6:.0f} M/s wall; peak RSS +{rss:.0f} MiB (the "
                         f"events take {ours.nbytes / 2**20:.0f} MiB)"))
            c3, w3, prev = both_timed(
                lambda: np.concatenate([c.events for c in iter_events(path)]), 3)
            assert np.array_equal(prev, ours)
            del prev
            rows.append((f"torchseq, {label}, same file, the previous whole read (all chunks "
                         "kept, then np.concatenate)", len(ours) / c3,
                         f"{len(ours) / w3 / 1e6:.0f} M/s wall; read_events now "
                         f"{c3 / cpu:.1f}x faster"))
            for lib, mod in libs.items():
                label2, fn, sfx, convert = FIELD[lib]
                if path.suffix in sfx:
                    rows.append(_compare_row(f"{label2}, same file (whole read)",
                                             lambda p: fn(mod, p), convert, path, ours, 3))
            del whole, ours
            path.unlink()
    return rows


def table(title, rows, unit="events/s"):
    lines = [f"| {title} | {unit} | note |", "|---|---:|---|"]
    for name, rate, note in rows:
        lines.append(f"| {name} | {rate:,.0f} | {note} |" if np.isfinite(rate) else
                     f"| {name} | - | {note} |")
    return "\n".join(lines)


def _load() -> str:
    try:
        return Path("/proc/loadavg").read_text().split()[0]
    except OSError:
        return "?"


SECTIONS = ("accumulate", "readers", "experiment")


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--events", type=int, default=2_000_000)
    p.add_argument("--write-docs", action="store_true",
                   help="replace the table block of docs/results/events.md (all sections only)")
    p.add_argument("--reader-events", type=int, default=20_000_000)
    p.add_argument("--only", choices=SECTIONS, action="append",
                   help="run only these sections (repeatable)")
    args = p.parse_args()
    torch.set_num_threads(1)
    only = set(args.only or SECTIONS)
    parts = []
    if "accumulate" in only:
        parts.append(
            f"Accumulation of {args.events:,} random events (128x128, 10 ms windows over 2 s, "
            f"signed frames), one thread, events per second of process CPU time:\n\n"
            + table("accumulation", bench_accumulate(args.events)) + "\n\nAccumulation "
            "against the previous implementation (same frames, one run, events per second of "
            "process CPU time, best of 7):\n\n"
            + table("accumulation", bench_accumulate_kernels()))
    if "readers" in only:
        load = _load()
        rows = bench_readers(args.reader_events)
        parts.append(
            "Readers, one thread: events per second of process CPU time (a field reader's "
            "threads all count), the wall-time rate in the note; real files read whole, best "
            "of 5; large files best of 3; peak RSS is what a fresh process adds over its "
            f"imports (load average {load} at the start, {_load()} at the end):\n\n"
            + table("reader", rows))
    if "experiment" in only:
        parts.append("The seed's speed experiment end to end (read, accumulate, match; one "
                     "run, CPU time):\n\n" + table("pipeline", bench_experiment()))
    text = "\n\n".join(parts)
    print(text)
    if args.write_docs and only == set(SECTIONS) and DOC.exists():
        doc = DOC.read_text()
        if BEGIN in doc and END in doc:
            head, rest = doc.split(BEGIN, 1)
            tail = rest.split(END, 1)[1]
            DOC.write_text(f"{head}{BEGIN}\n{text}\n{END}{tail}")


if __name__ == "__main__":
    main()

"""Neural SeqSLAM speed on one CPU thread: step latency, batched throughput, fit time.

    .venv/bin/python benchmarks/bench_neural.py [--no-docs] [--repeats 5]

Compares, side by side in one run: the eager step (masks multiplied in on every call), the
step with masks folded into dense weights, the step with torch.sparse CSR weights, batched
streams, the single-stream ``run`` on its float32 path and on its int8 fast path, and the
cost of each stage. Frames are given at the model's input size
(24x32) unless the row says otherwise. Prints a Markdown table and writes it into
docs/neural.md between the ``bench`` markers.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torchseq.neural.fast as fast  # noqa: E402
from torchseq.atomic import write_text  # noqa: E402
from torchseq.demo import make_demo  # noqa: E402
from torchseq.layers import cohort_normalise, kwta  # noqa: E402
from torchseq.neural import NeuralConfig, NeuralSeqSLAM  # noqa: E402
from torchseq.neural.fixed_point import block_order  # noqa: E402
from torchseq.neural.readout import decide  # noqa: E402
from torchseq.preprocess import resize  # noqa: E402

START, END = "<!-- bench:start -->", "<!-- bench:end -->"


def best_time(fn, repeats: int, number: int) -> float:
    """Best mean seconds per call over ``repeats`` rounds of ``number`` calls."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best


def sparse_step(model: NeuralSeqSLAM, w1, w3, frames, state):
    """The step with CSR weights (``torch.sparse``) in both masked layers."""
    x = model.encode(frames)
    c = kwta((w1 @ x.T).T, model.config.k, binary=True)
    e = cohort_normalise((w3 @ c.T).T, model.cohorts, model.config.eps)
    a, state = model.ring(e, state)
    return decide(a, model.unit_centre, model.config.uniqueness_window), state


def ring_loop(drive, a0, shift, decay, diagonals):
    """The ring frame by frame on the diagonals (the scan before blocks), for a side-by-side row."""
    d = diagonals * decay
    out, a = torch.empty_like(drive), a0
    for t in range(drive.shape[0]):
        m = torch.addcmul(drive[t], d[0], a)
        for lag in range(1, d.shape[0]):
            m[lag:].addcmul_(d[lag, lag:], a[:-lag])
        a = m
        out[t] = a
    return out


def stage_rows(row, model, small, repeats):
    """Per-stage cost of the feed-forward over one ``chunk`` of frames, and of the ring."""
    f, cfg = model._folded, model.config
    k = cfg.k
    x = model.encode(small[:cfg.chunk])
    b = x.shape[0]
    h = x @ f["w1_t"]
    idx = torch.topk(h, k, dim=1, sorted=False).indices
    code = fast.kwta_code(h, k)
    stages = [
        ("encode (grey, patch normalisation, 1/32 grid)", lambda: model.encode(small[:b])),
        ("L1 float32 GEMM", lambda: x @ f["w1_t"]),
        ("k-WTA torch.topk(k, sorted=False)", lambda: torch.topk(h, k, dim=1, sorted=False)),
        ("k-WTA NumPy partition + tie fix (used)", lambda: fast.kwta_code(h, k)),
        ("L3 embedding_bag over winners (float path)",
         lambda: F.embedding_bag(idx, f["w3_t"], mode="sum")),
        ("cohort normalisation", lambda: cohort_normalise(h[:, :model.n_units], model.cohorts,
                                                          cfg.eps)),
    ]
    if f["l1_int8"] is not None:
        xq = (x * cfg.input_steps + 128).to(torch.uint8)[:, block_order(*cfg.input_size,
                                                                         cfg.patch_size)]
        stages[2:2] = [("L1 int8 GEMM, oneDNN (used)", lambda: f["l1_int8"](xq))]
        stages.insert(5, ("L3 int8 GEMM, oneDNN (used)", lambda: f["l3_int8"](code)))
    for name, fn in stages:
        row(f"stage: {name}, chunk of {b}", b, best_time(fn, repeats, 3))
    q = small.shape[0]
    drive = model._feedforward(small) * model.ring.params.gain
    a0 = torch.zeros(model.n_units)
    decay = model.ring.params.decay
    row(f"stage: ring frame by frame, {q} frames", q, best_time(
        lambda: ring_loop(drive, a0, model.ring.shift, decay, f["diagonals"]), repeats, 1))
    row(f"stage: ring in blocks of {fast.RING_BLOCK} (used), {q} frames", q, best_time(
        lambda: fast.ring_scan(drive, a0, model.ring.shift, decay, f["diagonals"],
                               power=f["ring_power"]), repeats, 1))
    act = fast.ring_scan(drive, a0, model.ring.shift, decay, f["diagonals"])
    row(f"stage: decide, {q} frames", q, best_time(
        lambda: decide(act, model.unit_centre, cfg.uniqueness_window), repeats, 1))


def main(argv=None) -> str:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--no-docs", action="store_true", help="do not update docs/neural.md")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    cfg = NeuralConfig()
    demo = make_demo(n_reference=555, speed=0.8)
    model = NeuralSeqSLAM(cfg)
    t0 = time.perf_counter()
    model.fit(demo.reference, log=False)
    fit_s = time.perf_counter() - t0
    raw = demo.query  # (Q, 96, 128)
    small = resize(raw, cfg.input_size)  # (Q, 24, 32)
    rows = []

    def row(name, batch, seconds_per_call):
        rows.append((name, batch, seconds_per_call * 1e6 / batch, batch / seconds_per_call))

    with torch.inference_mode():
        f1 = small[:1]
        _, st = model.step(f1)
        model.unfold()
        row("step, eager (mask * weight each call)", 1,
            best_time(lambda: model.step(f1, st), args.repeats, 20))
        model.fold()
        row("step, masks folded into dense weights", 1,
            best_time(lambda: model.step(f1, st), args.repeats, 50))
        row("step, folded, raw 96x128 frame (incl. resize)", 1,
            best_time(lambda: model.step(raw[:1], st), args.repeats, 50))
        w1 = model._folded["w1"].to_sparse_csr()
        w3 = model._folded["w3"].to_sparse_csr()
        row("step, torch.sparse CSR weights", 1,
            best_time(lambda: sparse_step(model, w1, w3, f1, st), args.repeats, 20))
        for b in (16, 256):
            fb = small[:b]
            _, sb = model.step(fb)
            row(f"step, folded, {b} independent streams", b,
                best_time(lambda: model.step(fb, sb), args.repeats, 5))
        _, sb = model.step(small[:256])
        w_b = small[:256]
        row("step, sparse CSR, 256 streams", 256,
            best_time(lambda: sparse_step(model, w1, w3, w_b, sb), args.repeats, 3))
        q = small.shape[0]
        fast_run = model.run(small)
        l1_int8 = model._folded["l1_int8"]
        model._folded["l1_int8"] = None  # the float path, side by side
        try:
            float_run = model.run(small)
            float_s = best_time(lambda: model.run(small), args.repeats, 1)
        finally:
            model._folded["l1_int8"] = l1_int8
        same = torch.equal(fast_run.matches.reference, float_run.matches.reference)
        row(f"run, float32 path (int8 GEMMs off), {q} frames", q, float_s)
        row(f"run (single stream fast path, int8 GEMMs: {l1_int8 is not None}), {q} frames, "
            f"same decisions as the float path: {same}", q,
            best_time(lambda: model.run(small), args.repeats, 1))
        stage_rows(row, model, small, args.repeats)
        row(f"run, raw 96x128 frames, {q} frames", q,
            best_time(lambda: model.run(raw), args.repeats, 1))
        row(f"feed-forward only (encode..evidence, fast path), {q} frames", q,
            best_time(lambda: model._feedforward(small), args.repeats, 1))
        exact = model.run(small).matches.reference
        approx = model.run(small, l1_dtype=torch.bfloat16).matches.reference
        same = float((approx == exact).float().mean())
        row(f"run(l1_dtype=torch.bfloat16): approximate, {same:.1%} same decisions, "
            f"{q} frames", q,
            best_time(lambda: model.run(small, l1_dtype=torch.bfloat16), args.repeats, 1))
    lines = [f"Machine: {platform.processor() or platform.machine()}, torch "
             f"{torch.__version__}, 1 thread; model: default NeuralConfig, route of "
             f"{demo.reference.shape[0]} reference frames ({model.n_units} output units).", "",
             "| path | batch | us per frame | frames/s |", "|---|---|---|---|"]
    lines += [f"| {n} | {b} | {us:.1f} | {fps:,.0f} |" for n, b, us, fps in rows]
    lines += ["", f"Fit: {fit_s:.2f} s for {demo.reference.shape[0]} reference frames "
              f"({fit_s / demo.reference.shape[0] * 1e3:.2f} ms per frame, raw 96x128 frames)."]
    table = "\n".join(lines)
    print(table)
    docs = ROOT / "docs" / "neural.md"
    if not args.no_docs and docs.exists():
        text = docs.read_text()
        if START in text and END in text:
            head, rest = text.split(START, 1)
            text = head + START + "\n" + table + "\n" + END + rest.split(END, 1)[1]
            write_text(docs, text)
    return table


if __name__ == "__main__":
    main()

"""Neural SeqSLAM speed on one CPU thread: step latency, batched throughput, fit time.

    .venv/bin/python benchmarks/bench_neural.py [--no-docs] [--repeats 5]

Compares, side by side in one run: the eager step (masks multiplied in on every call), the
step with masks folded into dense weights, the step with torch.sparse CSR weights, batched
streams, and the single-stream ``run`` fast path. Frames are given at the model's input size
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
from torchseq.neural.fast import feedforward  # noqa: E402
from torchseq.neural.learning import decide  # noqa: E402
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


def winners_rowcheck(h, k):
    """``fast.winners`` before the one-count tie check (per-row sums), for side-by-side rows."""
    vals, idx = torch.topk(h, k, dim=1, sorted=False)
    v = vals.min(dim=1, keepdim=True).values
    if bool(((h >= v).sum(1) == k).all()):
        return idx
    return fast.winners(h, k)


def stage_rows(row, model, small, repeats):
    """Per-stage cost of the exact float32 feed-forward over one ``chunk`` of frames."""
    f, k = model._folded, model.config.k
    x = model.encode(small[:model.config.chunk])
    b = x.shape[0]
    h = x @ f["w1_t"]
    vals, idx = torch.topk(h, k, dim=1, sorted=False)
    v = vals.amin(1, keepdim=True)
    code = torch.zeros_like(h).scatter_(1, idx, 1.0)
    stages = [
        ("encode (patch normalisation)", lambda: model.encode(small[:b])),
        ("L1 product (fp32 GEMM)", lambda: x @ f["w1_t"]),
        ("k-WTA torch.topk(k, sorted=False)", lambda: torch.topk(h, k, dim=1, sorted=False)),
        ("k-WTA tie check, old: per-row sums", lambda: bool(((h >= v).sum(1) == k).all())),
        ("k-WTA tie check, new: one count_nonzero", lambda: fast.has_tie(h, v, k)),
        ("L3 embedding_bag over winners (used)", lambda: F.embedding_bag(idx, f["w3_t"],
                                                                         mode="sum")),
        ("L3 dense code @ W3 (not bit-identical)", lambda: code @ f["w3_t"]),
    ]
    for name, fn in stages:
        row(f"stage: {name}, chunk of {b}", b, best_time(fn, repeats, 3))


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
        new_run = model.run(small)
        fast.winners, new_winners = winners_rowcheck, fast.winners
        try:
            old_run = model.run(small)
            same = (torch.equal(old_run.activity, new_run.activity)
                    and torch.equal(old_run.matches.reference, new_run.matches.reference))
            old_s = best_time(lambda: model.run(small), args.repeats, 1)
        finally:
            fast.winners = new_winners
        row(f"run, old tie check (per-row sums), {q} frames", q, old_s)
        row(f"run (single stream fast path), {q} frames, bit-identical to old: {same}", q,
            best_time(lambda: model.run(small), args.repeats, 1))
        stage_rows(row, model, small, args.repeats)
        row(f"run, raw 96x128 frames, {q} frames", q,
            best_time(lambda: model.run(raw), args.repeats, 1))
        f = model._folded
        row(f"feed-forward only (encode..evidence), fp32, {q} frames", q,
            best_time(lambda: feedforward(model.encode(small), f["w1_t"], f["w3_t"], cfg.k,
                                          model.cohorts, cfg.eps), args.repeats, 1))
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

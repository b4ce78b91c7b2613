"""Neural SeqSLAM speed on one CPU thread: the online step, its stages, the glue, streams, run.

    .venv/bin/python benchmarks/bench_neural.py [--no-docs] [--repeats 5] [--rounds 3]
        [--compare DIR | --compare none]

Printed as Markdown tables and written into docs/results/neural-step.md between the
``bench`` markers:

1. **This tree beside another checkout** (``--compare``, default ``../main`` when it exists;
   ``none`` skips it): the same measurements run in worker processes, one per tree
   (``PYTHONPATH`` set to it), alternated for ``--rounds`` rounds in this one run; the best
   of each is kept and the ratio printed. Measured through ``model.inference()``'s module
   (default model, ``inf.step(frame[None], state)`` under ``torch.inference_mode()``): the
   online step, 256 streams, ``run`` on one stream, the float ONNX graph at batch 1 and 256.
2. **The online step by stage** (this tree only): each stage's kernels, the one chosen
   marked, and whether the module's step makes exactly the eager step's decisions.
3. **The glue**: the module's whole step at batch 1 against the sum of the chosen kernels of
   its stages, timed in the same rounds (each round: every kernel, then the step, each
   ``--number`` calls; ``--glue-rounds`` rounds, the minimum and the median of each kept,
   and the median of the per-round ratios); the stage sum is also timed *inside* the step
   (the same calls in the step's order, a clock between stages), where the caches hold
   what the step leaves in them; then decisions per second for one stream and for 256, and
   the eager layers' step (``model.step``) beside it.

Frames are given at the model's input size (24x32). On a shared machine, read the minimum
and the medians, not a single run's mean.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
START, END = "<!-- bench:start -->", "<!-- bench:end -->"
DOCS = ROOT / "docs" / "results" / "neural-step.md"


def best_time(fn, repeats: int, number: int, clock=time.perf_counter) -> float:
    """Best mean seconds per call over ``repeats`` rounds of ``number`` calls.

    ``clock=time.process_time`` counts this process's CPU time only (on a shared host, the
    time it was not descheduled; cache misses caused by other jobs still count).
    """
    fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = clock()
        for _ in range(number):
            fn()
        best = min(best, (clock() - t0) / number)
    return best


def setup():
    """The default model fitted on the 555-frame demo route, the query at the input size."""
    import torch

    from torchseq.demo import make_demo
    from torchseq.neural import NeuralConfig, NeuralSeqSLAM
    from torchseq.preprocess import resize

    torch.set_num_threads(1)
    demo = make_demo(n_reference=555, speed=0.8)
    model = NeuralSeqSLAM(NeuralConfig())
    model.fit(demo.reference, log=False)
    return model, resize(demo.query, model.config.input_size)


def worker(repeats: int) -> dict:
    """The measurements of part 1 for the tree on ``sys.path``: microseconds per frame."""
    import numpy as np
    import torch

    model, small = setup()
    inf = model.inference()  # the documented fast path (both trees have it)
    out = {}
    with torch.inference_mode():
        f1 = small[:1]
        _, st = inf.step(f1)
        out["online step, batch 1"] = best_time(lambda: inf.step(f1, st), repeats, 200) * 1e6
        out["online step, batch 1, CPU time"] = best_time(
            lambda: inf.step(f1, st), repeats, 500, time.process_time) * 1e6
        fb = small[:256]
        _, sb = inf.step(fb)
        out["step, 256 streams"] = best_time(lambda: inf.step(fb, sb), repeats, 3) * 1e6 / 256
        q = small.shape[0]
        out[f"run, one stream of {q} frames"] = best_time(
            lambda: model.run(small), repeats, 1) * 1e6 / q
    try:
        import onnxruntime as ort

        from torchseq.export.onnx_float import build_float_onnx

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = opts.inter_op_num_threads = 1
        sess = ort.InferenceSession(build_float_onnx(model).SerializeToString(), opts,
                                    providers=["CPUExecutionProvider"])
        for b in (1, 256):
            feed = {"frames": small[:b].numpy(),
                    "state": np.zeros((b, model.n_units), np.float32)}
            out[f"float ONNX step, batch {b}"] = best_time(
                lambda: sess.run(None, feed), repeats, 100 if b == 1 else 3) * 1e6 / b
    except ImportError:
        pass
    return out


def compare(other: Path, rounds: int, repeats: int) -> list[str]:
    """Part 1: worker runs alternated between the two trees, best of each kept."""
    trees = {"this tree": ROOT, other.name: other}
    best: dict[str, dict[str, float]] = {name: {} for name in trees}
    for _ in range(rounds):
        for name, tree in trees.items():
            env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
            res = subprocess.run([sys.executable, __file__, "--worker", "--repeats",
                                  str(repeats)], env=env, cwd=tree, capture_output=True,
                                 text=True, check=True)
            for key, us in json.loads(res.stdout.strip().splitlines()[-1]).items():
                best[name][key] = min(best[name].get(key, float("inf")), us)
    mine, theirs = best["this tree"], best[other.name]
    lines = [f"| measurement (us per frame, best of {rounds} alternated rounds) | this tree | "
             f"{other.name} | {other.name} / this |", "|---|---|---|---|"]
    for key in mine:
        if key in theirs:
            lines.append(f"| {key} | {mine[key]:.1f} | {theirs[key]:.1f} | "
                         f"{theirs[key] / mine[key]:.2f}x |")
    return lines


def step_stages(inf, f1, st):
    """The chosen kernels of the module's step at batch 1, in the step's order.

    Returns ``(stages, inline)``: ``stages`` maps ``"stage (kernel)"`` to a call of that
    kernel on the inputs the step gives it; ``inline()`` runs the same calls in sequence,
    each feeding the next as in the step, and returns the seconds each took.
    """
    import numpy as np
    import torch

    from torchseq.layers import cohort_normalise, ring_step
    from torchseq.layers import kernels as K
    from torchseq.neural.readout import decide
    from torchseq.preprocess import zscore_pixel_major

    kern, cfg = inf.kernels, inf.config
    if kern["step"] != "stages":  # batch 1: one compiled pass (_step_numba.step) is the kernel
        from torchseq.neural import _step_numba

        grey = f1.numpy()
        prev = st.activity.numpy()
        outs = (np.empty_like(prev), np.empty(1, np.int64), np.empty(1, np.float32))
        name = "compiled step, z-score to decision (numba)"

        def compiled():
            return _step_numba.step(grey, prev, *inf._numba_args, *outs)

        def inline_numba(clock=time.perf_counter):
            t0 = clock()
            compiled()
            return [clock() - t0]

        return {name: compiled}, inline_numba
    if kern["input"] != "numpy" or kern["kwta"] != "partition" or kern["ring"] != "banded":
        raise SystemExit(f"this benchmark follows the auto CPU kernels, got {kern}")
    steps = np.float32(cfg.input_steps)
    l1_at_1 = "float32_gemm" if kern["l1"] == "int8_gemm_or_float32_gemm" else kern["l1"]
    int8 = l1_at_1 == "int8_gemm"  # batch 1: the or-kernel runs float32 below SMALL_BATCH

    def grid(z):  # the step's input grid (evidence(): uint8 for the int8 L1, else float)
        if int8:
            q = np.rint(z.numpy() * steps)
            q += 128
            return torch.from_numpy(q.astype(np.uint8).transpose(1, 2, 0).reshape(1, -1))
        x = z.permute(1, 2, 0).reshape(1, -1)
        return torch.round(x * cfg.input_steps) / cfg.input_steps

    l1 = inf.l1_int8 if int8 else (lambda x: x @ inf.w1_t)
    calls = [
        ("frame checks, grey (-)", lambda f: inf._grey(f)),
        ("patch z-score (numpy)", lambda g: zscore_pixel_major(g, cfg.patch_size, "numpy")),
        ("input grid (-)", grid),
        (f"L1 product ({l1_at_1})", l1),
        ("k-WTA winners (partition)", lambda h: K.kwta_partition_indices(h, cfg.k)),
        ("L3 product (embedding_bag)", lambda idx: K.sum_rows(idx, inf.w3_t)),
        (f"cohort normalisation ({kern['cohorts']})",
         lambda e: cohort_normalise(e, inf.cohorts, cfg.eps, cfg.rectify, kern["cohorts"])),
        ("ring step (banded)", lambda e: ring_step(e, st, inf.shift, inf.params,
                                                   inf.diagonals)[0]),
        (f"decision ({kern['decide']})",
         lambda a: decide(a, inf.unit_centre, cfg.uniqueness_window, kern["decide"], inf.spans)),
    ]
    inputs, x = [], f1
    for _, fn in calls:  # each stage's input, as the step computes it
        inputs.append(x)
        x = fn(x)
    stages = {name: (lambda fn=fn, x=x: fn(x)) for (name, fn), x in zip(calls, inputs)}

    def inline(clock=time.perf_counter):
        x, spent = f1, []
        for _, fn in calls:
            t0 = clock()
            x = fn(x)
            spent.append(clock() - t0)
        return spent

    return stages, inline


def stages(repeats: int) -> list[str]:
    """Part 2: the online step of this tree by stage, every kernel side by side."""
    import numpy as np
    import torch

    from torchseq.layers import cohort_normalise, kwta, ring_step
    from torchseq.layers import kernels as K
    from torchseq.neural.inference import SMALL_BATCH as SMALL
    from torchseq.neural.inference import int8_expected
    from torchseq.neural.readout import decide
    from torchseq.preprocess import zscore_pixel_major

    model, small = setup()
    inf = model.inference()
    kern, cfg = inf.kernels, model.config
    rows = []

    used = {**kern, "l3": "embedding_bag",  # batch 1 < SMALL_BATCH: the embedding-bag
            "l1": "float32_gemm" if kern["l1"] == "int8_gemm_or_float32_gemm" else kern["l1"]}
    compiled = kern["step"] != "stages"  # batch 1: the compiled pass instead of the stages

    def row(stage, kernel, fn, number=300, key=None):
        us = best_time(fn, repeats, number) * 1e6
        if compiled:  # batch 1: the compiled pass alone
            chosen = "**yes**" if key == "step" else ""
        else:
            chosen = "**yes**" if key is None or used[key] == kernel else ""
        rows.append(f"| {stage} | `{kernel}` | {chosen} | {us:.1f} |")

    with torch.inference_mode():
        f1 = small[:1]
        if compiled:
            from torchseq.neural import _step_numba

            _, st = inf.step(f1)
            outs = (np.empty_like(st.activity.numpy()), np.empty(1, np.int64),
                    np.empty(1, np.float32))
            row("whole step, z-score to decision", "numba", lambda: _step_numba.step(
                f1.numpy(), st.activity.numpy(), *inf._numba_args, *outs), key="step")
        grey = inf._grey(f1)
        row("frame checks, grey", "-", lambda: inf._grey(f1))
        row("patch z-score", "numpy",
            lambda: zscore_pixel_major(grey, cfg.patch_size, "numpy"), key="input")
        row("patch z-score", "torch",
            lambda: zscore_pixel_major(grey, cfg.patch_size, "torch"), key="input")
        z = zscore_pixel_major(grey, cfg.patch_size, "numpy")

        def grid():
            q = np.rint(z.numpy() * np.float32(cfg.input_steps))
            q += 128
            return torch.from_numpy(q.astype(np.uint8).transpose(1, 2, 0).reshape(1, -1))

        xq = grid()
        x = (xq.float() - 128) / cfg.input_steps
        row("input grid (uint8)", "-", grid)
        if inf.l1_int8 is not None:
            row("L1 product", "int8_gemm", lambda: inf.l1_int8(xq), key="l1")
        row("L1 product", "float32_gemm", lambda: x @ inf.w1_t, key="l1")
        h = x @ inf.w1_t
        row("k-WTA (winners' indices)", "partition", lambda: K.kwta_partition_indices(h, cfg.k),
            key="kwta")
        row("k-WTA (winners' indices)", "topk", lambda: K.topk_indices(h, cfg.k), key="kwta")
        code = K.kwta_partition(h, cfg.k)
        idx = K.kwta_partition_indices(h, cfg.k)
        row("L3 product", "embedding_bag", lambda: K.sum_rows(idx, inf.w3_t), key="l3")
        if inf.l3_int8 is not None:
            row("L3 product (from the uint8 code)", "int8_gemm",
                lambda: inf.l3_int8(code.view(torch.uint8)), key="l3")
        row("L3 product (from the 0/1 code)", "dense", lambda: kwta(h, cfg.k, True) @ inf.w3_t,
            key="l3")
        e = K.sum_rows(idx, inf.w3_t)
        for kernel in ("numpy", "torch"):
            row("cohort normalisation, rectify", kernel,
                lambda: cohort_normalise(e, inf.cohorts, cfg.eps, True, kernel), key="cohorts")
        _, st = inf.step(f1)
        if inf.diagonals is not None:
            row("ring step", "banded", lambda: ring_step(e, st, inf.shift, inf.params,
                                                         inf.diagonals), key="ring")
        row("ring step", "dense", lambda: ring_step(e, st, inf.shift, inf.params), key="ring")
        a = st.activity
        row("decision", "numpy", lambda: decide(a, inf.unit_centre, 5, "numpy"), key="decide")
        row("decision", "torch", lambda: decide(a, inf.unit_centre, 5, "torch"), key="decide")
        # exactly the eager step's decisions, frame by frame over the whole query
        s_fast = s_eager = None
        same, n = 0, small.shape[0]
        for t in range(n):
            o1, s_fast = inf.step(small[t:t + 1], s_fast)
            o2, s_eager = model.step(small[t:t + 1], s_eager)
            same += int(torch.equal(o1.reference, o2.reference))
    note = ("At batch 1 the step runs the compiled pass (`step` kernel "
            f"`{kern['step']}`); the stage kernels below run from {SMALL} frames on (and in "
            "`run`): none of them is marked as used at batch 1." if compiled else "")
    return [f"Kernels chosen (`model.inference().kernels`): "
            f"`{json.dumps(kern)}`; int8 expected on this machine: {int8_expected()}.", "",
            "| stage (batch 1) | kernel | used | us (best of the repeats) |", "|---|---|---|---|",
            *rows, "", *([note, ""] if note else []),
            f"The module's step (`inf.step`) against the eager step (`model.step`): {same}/{n} "
            "identical decisions on the query."]


def glue_table(inf, f1, st, rounds: int, number: int, calls_in_step: int):
    """The step of ``inf`` at batch 1 against the sum of its kernels: table lines, step times.

    Returns ``(lines, wall)``: the Markdown lines and the wall-clock seconds of the single
    steps timed inside the step part (for decisions per second).
    """
    import statistics

    import numpy as np

    clock = time.perf_counter
    calls, inline = step_stages(inf, f1, st)
    names = list(calls)
    calls = {**calls, "STEP": lambda: inf.step(f1, st)}
    # (a) hot loops: in each round every kernel, then the step, `number` calls in a row
    per = {name: [] for name in calls}
    cpu = {name: [] for name in calls}
    ratios = []
    for _ in range(rounds):
        for name, fn in calls.items():
            fn()
            t0, c0 = clock(), time.process_time()
            for _ in range(number):
                fn()
            per[name].append((clock() - t0) / number)
            cpu[name].append((time.process_time() - c0) / number)
        ratios.append(per["STEP"][-1] / sum(per[n][-1] for n in names))
    # (b) inside the step: the chained kernels, then the step, one call each, alternated;
    # CPU time of this process (a preempted call does not count its wait)
    cpu_clock = time.process_time
    empty = statistics.median(-(cpu_clock() - cpu_clock()) for _ in range(1000))
    chain, step, pair, wall = [], [], [], []
    for i in range(calls_in_step):
        if i % 2:
            spent = inline(cpu_clock)
        t0, c0 = clock(), cpu_clock()
        inf.step(f1, st)
        one, w = cpu_clock() - c0, clock() - t0
        if not i % 2:
            spent = inline(cpu_clock)
        spent = [max(s - empty, 0.0) for s in spent]
        chain.append(spent)
        step.append(max(one - empty, 0.0))
        wall.append(w)
        pair.append(step[-1] / max(sum(spent), 1e-9))
    after = {}
    if len(names) > 5:  # (c) the stages: why they cost more inside the step (see the docs)
        post = [calls[n] for n in names[4:]]
        flush = np.ones(4 << 20, np.uint8)

        def post_l1():
            total = 0.0
            for fn in post:
                c0 = cpu_clock()
                fn()
                total += cpu_clock() - c0 - empty
            return total

        after = {"the L1 product": [], "reading 4 MB": [], "themselves": []}
        for _ in range(calls_in_step // 2):
            calls[names[3]]()
            after["the L1 product"].append(post_l1())
            flush.sum()
            after["reading 4 MB"].append(post_l1())
            post_l1()
            after["themselves"].append(post_l1())

    def us(v):
        return f"{v * 1e6:.1f}"

    med = statistics.median
    lo = {n: min(per[n]) for n in calls}
    mid = {n: med(per[n]) for n in calls}
    cpu_lo = {n: min(cpu[n]) for n in calls}
    inside = [med(col) for col in zip(*chain)]
    sums = [sum(c) for c in chain]
    rows = [f"| {n} | {us(lo[n])} | {us(mid[n])} | {us(cpu_lo[n])} | {us(inside[i])} |"
            for i, n in enumerate(names)]
    k_lo, k_mid = sum(lo[n] for n in names), sum(mid[n] for n in names)
    k_cpu = sum(cpu_lo[n] for n in names)
    step_lo, step_mid = lo["STEP"], mid["STEP"]
    quart = statistics.quantiles(pair, n=4)
    lines = [
        "| stage (chosen kernel, batch 1) | hot loop, us, min | hot loop, us, median | "
        "hot loop, CPU us, min | inside the step, CPU us, median |", "|---|---|---|---|---|", *rows,
        f"| **sum of the stages' kernels** | **{us(k_lo)}** | **{us(k_mid)}** | "
        f"**{us(k_cpu)}** | **{us(med(sums))}** |",
        f"| **whole step** `inf.step(frame[None], state)` | **{us(step_lo)}** | "
        f"**{us(step_mid)}** | **{us(cpu_lo['STEP'])}** | **{us(med(step))}** |",
        f"| **step / kernel sum** | **{step_lo / k_lo:.2f}x** | **{step_mid / k_mid:.2f}x** | "
        f"**{cpu_lo['STEP'] / k_cpu:.2f}x** | **{med(step) / med(sums):.2f}x** |", "",
        f"Hot loops: {rounds} rounds, in each every kernel and then the whole step {number} "
        f"times in a row (wall clock, and this process's CPU time); median of the per-round "
        f"ratios {med(ratios):.2f}x (min {min(ratios):.2f}x). Inside the step: {calls_in_step} "
        "single calls of the chained kernels (each stage's input the previous stage's "
        "output, this process's CPU time read between stages, less one reading) alternated "
        f"with single calls of the step; median of the per-pair ratios **{med(pair):.2f}x** "
        f"(quartiles {quart[0]:.2f}x-{quart[2]:.2f}x"
        f"); fastest step {us(min(step))} against fastest chain {us(min(sums))} CPU us."]
    if after:
        lines += ["", "The five stages after the L1 product (k-WTA to decision), single calls, "
                  "CPU us (median): " + ", ".join(f"after {k} {us(med(v))}"
                                                  for k, v in after.items()) + "."]
    return lines, wall


def glue(rounds: int, number: int, calls_in_step: int) -> list[str]:
    """Part 3: the step against the sum of its kernels; decisions per second.

    Twice: the module ``model.inference()`` returns (auto kernels: at batch 1 the compiled
    step where numba is installed) and the same with ``kernels={"step": "stages"}`` (the
    stage kernels one after another: the path without numba).
    """
    import statistics

    import torch

    model, small = setup()
    inf = model.inference()
    f1, fb = small[:1], small[:256]
    with torch.inference_mode():
        _, st = inf.step(f1)
        _, sb = inf.step(fb)
        lines, wall = glue_table(inf, f1, st, rounds, number, calls_in_step)
        lines = [f"**The auto module** (`model.inference()`, `step` kernel "
                 f"`{inf.kernels['step']}`):", "", *lines]
        staged = wall_staged = None
        if inf.kernels["step"] != "stages":
            staged = model.inference({"step": "stages"})
            more, wall_staged = glue_table(staged, f1, st, rounds, number, calls_in_step)
            lines += ["", "**The stage kernels** (`model.inference({\"step\": \"stages\"})`: "
                      "the step without numba, and every step from 16 frames on):", "", *more]
        eager = [best_time(lambda: model.step(f1, st), 1, max(1, number // 5))
                 for _ in range(max(3, rounds // 5))]
        many = [best_time(lambda: inf.step(fb, sb), 1, 2) for _ in range(max(3, rounds // 5))]
    med = statistics.median
    lines += [
        "", "| decisions per second (one thread) | best | median |", "|---|---|---|",
        f"| 1 stream, `inf.step` (batch 1, `{inf.kernels['step']}`) | {1 / min(wall):,.0f} | "
        f"{1 / med(wall):,.0f} |"]
    if wall_staged:
        lines.append(f"| 1 stream, `inf.step` (batch 1, the stage kernels) | "
                     f"{1 / min(wall_staged):,.0f} | {1 / med(wall_staged):,.0f} |")
    lines += [
        f"| 256 streams, `inf.step` (batch 256) | {256 / min(many):,.0f} | "
        f"{256 / med(many):,.0f} |",
        f"| 1 stream, `model.step` (the eager layers, the definition) | {1 / min(eager):,.0f} | "
        f"{1 / med(eager):,.0f} |",
    ]
    return lines


def main(argv=None) -> str:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--compare", default=str(ROOT.parent / "main"),
                   help="another checkout to measure beside this one ('none': skip)")
    p.add_argument("--glue-rounds", type=int, default=60)
    p.add_argument("--number", type=int, default=20, help="calls per timing in the glue part")
    p.add_argument("--calls-in-step", type=int, default=3000,
                   help="single calls of the chained kernels and of the step (glue part)")
    p.add_argument("--no-docs", action="store_true",
                   help="do not update docs/results/neural-step.md")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.repeats)))
        return ""
    sys.path.insert(0, str(ROOT))
    import torch

    from torchseq.atomic import write_text

    lines = [f"Machine: {platform.processor() or platform.machine()}, torch "
             f"{torch.__version__}, 1 thread; model: default NeuralConfig, demo route of 555 "
             "reference frames (555 output units).", ""]
    other = Path(args.compare)
    if args.compare != "none" and other.exists() and other.resolve() != ROOT:
        lines += compare(other.resolve(), args.rounds, args.repeats) + [""]
    lines += glue(args.glue_rounds, args.number, args.calls_in_step) + [""]
    lines += stages(args.repeats)
    table = "\n".join(lines)
    print(table)
    docs = DOCS
    if not args.no_docs and docs.exists():
        text = docs.read_text()
        if START in text and END in text:
            head, rest = text.split(START, 1)
            text = head + START + "\n" + table + "\n" + END + rest.split(END, 1)[1]
            write_text(docs, text)
    return table


if __name__ == "__main__":
    main()

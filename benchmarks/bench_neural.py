"""Neural SeqSLAM speed on one CPU thread: the online step, its stages, streams, run, ONNX.

    .venv/bin/python benchmarks/bench_neural.py [--no-docs] [--repeats 5] [--compare DIR]

Two parts, printed as Markdown tables and written into docs/results/neural.md between the
``bench`` markers:

1. **This tree beside another checkout** (``--compare``, default ``../main`` when it exists):
   the same measurements run in worker processes, one per tree (``PYTHONPATH`` set to it),
   alternated for ``--rounds`` rounds in this one run; the best of each is kept and the
   ratio printed. Measured: the online step (one frame in, one decision out, batch 1,
   default model, ``step(frame[None], state)`` under ``torch.inference_mode()`` once the
   model is prepared: ``fold()`` here; on older trees ``run`` prepared it), 256 streams
   through ``step``, ``run`` on one stream, the float ONNX graph at batch 1 and 256.
2. **The online step by stage** (this tree only): each stage's kernels, the one chosen
   marked, and whether the prepared step makes exactly the eager step's decisions.

Frames are given at the model's input size (24x32).
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


def prepare(model, small):
    """Prepare for inference with whatever API the imported tree has."""
    if hasattr(model, "kernels"):
        model.fold()
    else:  # before the inference module: run folded the weights and step took them
        model.run(small[:5])


def worker(repeats: int) -> dict:
    """The measurements of part 1 for the tree on ``sys.path``: microseconds per frame."""
    import numpy as np
    import torch

    model, small = setup()
    prepare(model, small)
    out = {}
    with torch.inference_mode():
        f1 = small[:1]
        _, st = model.step(f1)
        out["online step, batch 1"] = best_time(lambda: model.step(f1, st), repeats, 200) * 1e6
        out["online step, batch 1, CPU time"] = best_time(
            lambda: model.step(f1, st), repeats, 500, time.process_time) * 1e6
        fb = small[:256]
        _, sb = model.step(fb)
        out["step, 256 streams"] = best_time(lambda: model.step(fb, sb), repeats, 3) * 1e6 / 256
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


def stages(repeats: int) -> list[str]:
    """Part 2: the online step of this tree by stage, kernels side by side."""
    import numpy as np
    import torch

    from torchseq.layers import cohort_normalise, kwta, ring_step
    from torchseq.layers import kernels as K
    from torchseq.neural.inference import int8_expected
    from torchseq.neural.readout import decide
    from torchseq.preprocess import zscore_pixel_major

    model, small = setup()
    inf = model.fold()
    kern, cfg = inf.kernels, model.config
    rows = []

    used = {**kern, "l3": "embedding_bag"}  # batch 1 < SMALL_BATCH: the embedding-bag

    def row(stage, kernel, fn, number=300, key=None):
        us = best_time(fn, repeats, number) * 1e6
        chosen = "**yes**" if key is None or used[key] == kernel else ""
        rows.append(f"| {stage} | `{kernel}` | {chosen} | {us:.1f} |")

    with torch.inference_mode():
        f1 = small[:1]
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
        _, st = model.step(f1)
        if inf.diagonals is not None:
            row("ring step", "banded", lambda: ring_step(e, st, inf.shift, inf.params,
                                                         inf.diagonals), key="ring")
        row("ring step", "dense", lambda: ring_step(e, st, inf.shift, inf.params), key="ring")
        a = st.activity
        row("decision", "numpy", lambda: decide(a, inf.unit_centre, 5, "numpy"), key="decide")
        row("decision", "torch", lambda: decide(a, inf.unit_centre, 5, "torch"), key="decide")
        total = best_time(lambda: model.step(f1, st), repeats, 300) * 1e6
        total_cpu = best_time(lambda: model.step(f1, st), repeats, 500, time.process_time) * 1e6
        model.unfold()
        eager = best_time(lambda: model.step(f1, st), repeats, 50) * 1e6
        # exactly the eager step's decisions, frame by frame over the whole query
        s_fast = s_eager = None
        same, n = 0, small.shape[0]
        inf_step = inf
        for t in range(n):
            o1, s_fast = inf_step(small[t:t + 1], s_fast)
            o2, s_eager = model.step(small[t:t + 1], s_eager)
            same += int(torch.equal(o1.reference, o2.reference))
    lines = [f"Kernels chosen (`model.fold().kernels`): "
             f"`{json.dumps(kern)}`; int8 expected on this machine: {int8_expected()}.", "",
             "| stage (batch 1) | kernel | used | us |", "|---|---|---|---|", *rows,
             f"| **whole online step**, prepared (`fold()`), inference_mode | | | "
             f"**{total:.1f}** |",
             f"| the same, CPU time of this process (`time.process_time`) | | | "
             f"**{total_cpu:.1f}** |",
             f"| whole step, eager layers (not folded) | | | {eager:.1f} |", "",
             f"Prepared online step vs eager step: {same}/{n} identical decisions on the "
             f"query."]
    return lines


def main(argv=None) -> str:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--compare", type=Path, default=ROOT.parent / "main")
    p.add_argument("--no-docs", action="store_true", help="do not update docs/results/neural.md")
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
    if args.compare.exists() and args.compare.resolve() != ROOT:
        lines += compare(args.compare.resolve(), args.rounds, args.repeats) + [""]
    lines += stages(args.repeats)
    table = "\n".join(lines)
    print(table)
    docs = ROOT / "docs" / "results" / "neural.md"
    if not args.no_docs and docs.exists():
        text = docs.read_text()
        if START in text and END in text:
            head, rest = text.split(START, 1)
            text = head + START + "\n" + table + "\n" + END + rest.split(END, 1)[1]
            write_text(docs, text)
    return table


if __name__ == "__main__":
    main()

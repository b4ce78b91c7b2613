"""Speed of one streaming step per exported variant, one CPU thread, batch 1 and 256.

    .venv/bin/python benchmarks/bench_export.py [--quick] [--doc docs/results/export.md]

Default-size Neural SeqSLAM (NeuralConfig()) fitted on the demo route (200 reference frames,
so N = 200 output units). Variants: PyTorch (``model.inference().step``, the fast form), float ONNX,
quantised ONNX, integer ONNX, NumPy integer runtime; plus single-stream traverse throughput
of ``inf.run`` (feed-forward batched over time, blocked ring scan) and of the integer
``StreamRuntime`` (the integer file's arithmetic batched over time), and the bare per-call
overhead of onnxruntime and of a PyTorch call. Prints a Markdown table and writes it into
``docs/results/export.md`` between the ``bench_export`` markers.
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper

from torchseq.demo import make_demo
from torchseq.export.int_format import encode
from torchseq.export.int_model import device_frames, integer_model
from torchseq.export.int_onnx import build_integer_onnx
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.export.int_stream import StreamRuntime
from torchseq.export.onnx_float import build_float_onnx
from torchseq.export.sessions import session
from torchseq.export.validate import quantise_onnx
from torchseq.layers import RingState
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.preprocess import resize

ROOT = Path(__file__).resolve().parents[1]


def timed(fn, min_seconds: float, min_calls: int = 3) -> float:
    """Seconds per call (median of rounds after one warm-up call)."""
    fn()
    rounds = []
    t_end = time.perf_counter() + min_seconds
    while len(rounds) < min_calls or time.perf_counter() < t_end:
        t0 = time.perf_counter()
        fn()
        rounds.append(time.perf_counter() - t0)
    return float(np.median(rounds))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="shorter timing rounds")
    ap.add_argument("--doc", default=str(ROOT / "docs" / "results" / "export.md"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    secs = 0.3 if args.quick else 1.5
    demo = make_demo()
    model = NeuralSeqSLAM(NeuralConfig())
    model.fit(demo.reference, log=False)
    inf = model.inference()  # the fast PyTorch form: its step and run
    size = model.config.input_size
    n = model.n_units
    small = resize(demo.query.float(), size)  # (Q, 24, 32) float
    im1 = integer_model(model, (1, 1))  # device frames at the input size, like the float graphs
    u8 = device_frames(demo.query, size, (1, 1))
    float_proto = build_float_onnx(model)
    quant_proto = quantise_onnx(float_proto)
    int_proto = build_integer_onnx(im1)
    sessions = {"ONNX float": session(float_proto), "ONNX quantised": session(quant_proto),
                "ONNX integer": session(int_proto)}
    runtime = IntegerRuntime(im1)
    rows = []
    for batch in (1, 256):
        idx = np.arange(batch) % small.shape[0]
        f32, f8 = small[idx].contiguous(), np.ascontiguousarray(u8[idx])
        state_t = RingState(torch.zeros(batch, n))
        feeds = {"ONNX float": {"frames": f32.numpy(), "state": np.zeros((batch, n), np.float32)},
                 "ONNX quantised": {"frames": f32.numpy(),
                                    "state": np.zeros((batch, n), np.float32)},
                 "ONNX integer": {"frames": f8, "state": np.zeros((batch, n), np.int32)}}
        with torch.inference_mode():
            t = timed(lambda: inf.step(f32, state_t), secs)
        rows.append(("PyTorch (model.inference().step)", batch, t))
        for name, sess in sessions.items():
            t = timed(lambda s=sess, f=feeds[name]: s.run(None, f), secs)
            rows.append((name, batch, t))
        state_i = runtime.initial_state(batch)
        t = timed(lambda: runtime.step(f8, state_i), secs if batch == 1 else 0.1, 1)
        rows.append(("NumPy integer runtime", batch, t))
    # single stream, whole traverse: inf.run batches the feed-forward over time; frames at
    # the input size like every variant above, then raw 96x128 frames (resize included)
    for frames, what in ((small, "frames at the input size"), (demo.query, "raw 96x128 frames")):
        t = timed(lambda f=frames: inf.run(f), secs)
        rows.append((f"PyTorch inf.run (one stream, {frames.shape[0]} {what})",
                     frames.shape[0], t))
    stream = StreamRuntime(im1)  # the integer file's arithmetic, batched over time
    t = timed(lambda: stream.run(u8), secs)
    rows.append((f"integer StreamRuntime.run (one stream, {u8.shape[0]} frames, bit-exact with "
                 f"the NumPy runtime, int8 GEMMs: {stream.l1_int8 is not None})",
                 u8.shape[0], t))
    # bare per-call overheads
    ident = helper.make_model(helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])], "id",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, n])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, n])]),
        opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    s_id = session(ident)
    x = np.zeros((1, n), np.float32)
    overhead_ort = timed(lambda: s_id.run(None, {"x": x}), secs)
    xt = torch.zeros(1, n)
    overhead_pt = timed(lambda: xt + 1, secs)
    with tempfile.TemporaryDirectory() as tmp:
        sizes = {}
        for name, proto in (("model_float.onnx", float_proto), ("model_quant.onnx", quant_proto),
                            ("model_int.onnx", int_proto)):
            onnx.save(proto, Path(tmp) / name)
            sizes[name] = (Path(tmp) / name).stat().st_size
        sizes["model_int.tsq"] = len(encode(im1))
        model.save(Path(tmp) / "ckpt.pt")
        sizes["checkpoint (.pt)"] = (Path(tmp) / "ckpt.pt").stat().st_size
    lines = ["| variant | batch | ms / call | frames/s |", "|---|---:|---:|---:|"]
    for name, batch, t in rows:
        lines.append(f"| {name} | {batch} | {t * 1e3:.3f} | {batch / t:,.0f} |")
    lines += ["", "| per-call overhead | us |", "|---|---:|",
              f"| onnxruntime `run` of an Identity graph (1, N) | {overhead_ort * 1e6:.1f} |",
              f"| PyTorch `x + 1` on (1, N) | {overhead_pt * 1e6:.1f} |",
              "", "| file | bytes |", "|---|---:|"]
    lines += [f"| {k} | {v:,} |" for k, v in sizes.items()]
    best = max(b / t for _, b, t in rows)
    best1 = max(b / t for name, b, t in rows if b == 1)
    lines += ["", f"N = {n} output units, hidden {model.config.hidden}, input {size}; "
              f"torch {torch.__version__}, one thread. Best: {best:,.0f} frames/s; best at "
              f"batch 1 (one call per frame): {best1:,.0f} frames/s."]
    table = "\n".join(lines)
    print(table)
    doc = Path(args.doc)
    if doc.is_file():
        text = doc.read_text()
        start, end = "<!-- bench_export:start -->", "<!-- bench_export:end -->"
        if start in text and end in text:
            new = re.sub(re.escape(start) + ".*?" + re.escape(end),
                         lambda _: f"{start}\n{table}\n{end}", text, flags=re.S)
            from torchseq.atomic import write_text

            write_text(doc, new)
            print(f"(table written into {doc})", file=sys.stderr)


if __name__ == "__main__":
    main()

"""Where the quantised ONNX graph loses decisions: which MatMul, and per-row weight scales.

One command (from the repository root, one thread, about a minute per route):

    .venv/bin/python experiments/quant_onnx_ablation.py [--data ../shared/data]

For the corridor and lens-davis128: ``NeuralSeqSLAM(NeuralConfig())`` fitted on the
reference (seed 0, the ``train.py`` default), its float ONNX graph quantised by onnxruntime's
``quantize_dynamic`` (int8 weights, uint8 activations with a scale per call) on both weight
``MatMul`` nodes (what ``model_quant.onnx`` holds), on L1 or L3 alone, and with per-channel
(per-output-row) weight scales; the agreement of each with the PyTorch model's decisions on
the query. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

import numpy as np
import onnx
import torch
from onnxruntime.quantization import QuantType, quantize_dynamic

from torchseq.export.onnx_float import build_float_onnx
from torchseq.export.sessions import run_float_onnx, session
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.preprocess import resize, to_grey
from torchseq.sources import load_traverse

ROUTES = {"corridor": ("corridor/ref", "corridor/query"),
          "lens-davis128": ("lens-davis128/example-reference", "lens-davis128/example-query")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="../shared/data")
    args = ap.parse_args()
    torch.set_num_threads(1)
    logging.disable(logging.WARNING)
    print("| data | quantised | per-row weight scales | agreement with PyTorch | bytes |")
    print("|---|---|---|---:|---:|")
    for route, (r, q) in ROUTES.items():
        ref = load_traverse(Path(args.data) / r, progress=False)
        qry = load_traverse(Path(args.data) / q, progress=False)
        torch.manual_seed(0)
        model = NeuralSeqSLAM(NeuralConfig())
        model.fit(ref, log=False)
        grey = to_grey(torch.as_tensor(qry)).float()
        pt = model.run(grey).matches.reference.numpy()
        small = resize(grey, tuple(model.config.input_size)).numpy()
        graph = build_float_onnx(model)
        names = {w: [n.name for n in graph.graph.node if n.op_type == "MatMul" and w in n.input]
                 for w in ("w1_t", "w3_t")}
        with tempfile.TemporaryDirectory() as tmp:
            src, dst = Path(tmp) / "f.onnx", Path(tmp) / "q.onnx"
            onnx.save(graph, src)
            for label, nodes in (("L1 and L3 (model_quant.onnx)", names["w1_t"] + names["w3_t"]),
                                 ("L1 only", names["w1_t"]), ("L3 only", names["w3_t"])):
                for per_row in (False, True):
                    quantize_dynamic(src, dst, weight_type=QuantType.QInt8,
                                     nodes_to_quantize=nodes, per_channel=per_row)
                    got = run_float_onnx(session(dst), small)[0]
                    print(f"| {route} | {label} | {'yes' if per_row else 'no'} | "
                          f"{float(np.mean(got == pt)):.3f} | {dst.stat().st_size:,} |",
                          flush=True)


if __name__ == "__main__":
    main()

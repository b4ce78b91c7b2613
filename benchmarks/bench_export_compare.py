"""Integer export speed of this tree beside another commit's, alternating in one run.

    .venv/bin/python benchmarks/bench_export_compare.py [--ref main] [--rounds 5]

``git archive REF torchseq`` is unpacked into a temporary folder; each round runs the same
measurement once with that code and once with this tree's, each in a fresh interpreter (one
thread), and the medians over rounds are printed with their ratio. Measured on the default
model (``NeuralConfig()``) fitted on the 200-frame demo route, device frames pooled 4x4:
the ``.tsq`` decode, ``StreamRuntime.run`` over the 200 query frames, the NumPy
``IntegerRuntime.step`` at batch 1, and the integer ONNX graph at batch 1 and 256. Each side
also prints the SHA-256 of its integer file and graph, so equal graphs are visible as such.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r'''
import hashlib, json, time
import numpy as np
import torch
torch.set_num_threads(1)
import torchseq
from torchseq.demo import make_demo
from torchseq.export.int_format import decode, encode
from torchseq.export.int_model import device_frames, integer_model
from torchseq.export.int_onnx import build_integer_onnx
from torchseq.export.sessions import session
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.export.int_stream import StreamRuntime
from torchseq.neural import NeuralConfig, NeuralSeqSLAM


def per_call(fn, seconds):
    fn()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        fn()
        n += 1
    return (time.perf_counter() - t0) / n


demo = make_demo(n_reference=200, size=(96, 128), seed=0)
torch.manual_seed(0)
model = NeuralSeqSLAM(NeuralConfig())
model.fit(demo.reference, log=False)
im = integer_model(model, (4, 4))
u8 = device_frames(demo.query, model.config.input_size, (4, 4))
n = im.params["n_units"]
graph = build_integer_onnx(im)
sess = session(graph)
stream, runtime = StreamRuntime(im), IntegerRuntime(im)
state1, state256 = np.zeros((1, n), np.int32), np.zeros((256, n), np.int32)
batch = np.resize(u8, (256,) + u8.shape[1:])
data = encode(im)
out = {
    "tsq decode (ms)": per_call(lambda: decode(data), 1.0) * 1e3,
    "StreamRuntime.run (frames/s)": u8.shape[0] / per_call(lambda: stream.run(u8), 2.0),
    "IntegerRuntime.step b1 (us)": per_call(lambda: runtime.step(u8[:1], state1), 1.0) * 1e6,
    "integer ONNX b1 (us)": per_call(
        lambda: sess.run(None, {"frames": u8[:1], "state": state1}), 1.0) * 1e6,
    "integer ONNX b256 (frames/s)": 256 / per_call(
        lambda: sess.run(None, {"frames": batch, "state": state256}), 2.0),
    "torchseq": torchseq.__file__,
    "sha": hashlib.sha256(data).hexdigest()[:12] + "/"
           + hashlib.sha256(graph.SerializeToString()).hexdigest()[:12],
}
print(json.dumps(out))
'''


def run_child(path: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(path), OMP_NUM_THREADS="1")
    # cwd=path: ``python -c`` puts the working directory first on sys.path, before
    # PYTHONPATH, so started from a checkout both sides would import that checkout's code
    done = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True,
                          check=False, cwd=path)
    if done.returncode:
        sys.exit(f"measurement failed with {path}:\n{done.stderr[-3000:]}")
    out = json.loads(done.stdout.strip().splitlines()[-1])
    if Path(out.pop("torchseq")).resolve() != (path / "torchseq" / "__init__.py").resolve():
        sys.exit(f"the measurement with {path} imported another torchseq")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ref", default="main", help="commit or branch to compare with")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        archive = Path(tmp) / "ref.tar"
        with open(archive, "wb") as f:
            subprocess.run(["git", "-C", str(ROOT), "archive", args.ref, "torchseq"], stdout=f,
                           check=True)
        with tarfile.open(archive) as tar:
            tar.extractall(Path(tmp) / "ref", filter="data")
        sides = {args.ref: Path(tmp) / "ref", "this tree": ROOT}
        results = {name: [] for name in sides}
        for _ in range(args.rounds):
            for name, path in sides.items():
                results[name].append(run_child(path))
    keys = [k for k in results[args.ref][0] if k != "sha"]
    print(f"| measure (median of {args.rounds}) | {args.ref} | this tree | this / {args.ref} |")
    print("|---|---:|---:|---:|")
    for key in keys:
        a = statistics.median(r[key] for r in results[args.ref])
        b = statistics.median(r[key] for r in results["this tree"])
        print(f"| {key} | {a:,.1f} | {b:,.1f} | {b / a:.3f} |")
    print(f"| .tsq / graph SHA-256 | {results[args.ref][0]['sha']} | "
          f"{results['this tree'][0]['sha']} | |")


if __name__ == "__main__":
    main()

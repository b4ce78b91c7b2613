"""The export of ``NeuralConfig.adaptive_velocity()`` models, validated (docs/results/export.md).

One command (from the repository root, under a minute):

    .venv/bin/python experiments/export_adaptive.py [--out DIR]

For the demo route at 0.8x and 1.3x (200 reference frames, seed 0) and
../shared/data/corridor (its ground truth): fit ``adaptive_velocity(seed=0)`` on the
reference, save it, run ``export_checkpoint`` on the query, and print the figures of each
``validation.json`` (float and quantised ONNX against the eager model; the integer file
(format version 3), its NumPy runtime and integer ONNX graph against the eager model on the
same uint8 frames: decisions and speed estimates; NIR is skipped for this model).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from torchseq.demo import make_demo
from torchseq.export import export_checkpoint
from torchseq.ground_truth import load_ground_truth
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.sources import load_traverse

KEYS = ("n_query", "float_onnx_agreement", "float_onnx_max_abs_error",
        "float_onnx_confidence_max_abs_error", "quant_onnx_agreement",
        "integer_format_version", "integer_agreement", "integer_onnx_agreement",
        "integer_onnx_bit_exact", "uint8_input_agreement", "integer_raw_input_agreement",
        "integer_speed_max_abs_error", "integer_speed_mean_abs_error", "recall_at_1",
        "nir", "passed")


def cases(data: Path) -> dict:
    """``{name: (reference, query, ground truth)}``."""
    out = {}
    for speed in (0.8, 1.3):
        d = make_demo(n_reference=200, speed=speed, seed=0)
        out[f"demo-{speed}x"] = (d.reference, d.query, d.ground_truth)
    corridor = data / "corridor"
    if corridor.is_dir():
        ref = load_traverse(corridor / "ref", progress=False)
        query = load_traverse(corridor / "query", progress=False)
        gt = load_ground_truth(corridor / "ground_truth.csv", len(ref), len(query))
        out["corridor"] = (ref, query, gt)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="folder for the exports (default: a temporary one)")
    ap.add_argument("--data", default="../shared/data")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out or tmp)
        out.mkdir(parents=True, exist_ok=True)
        for name, (ref, query, gt) in cases(Path(args.data)).items():
            model = NeuralSeqSLAM(NeuralConfig.adaptive_velocity(seed=0))
            model.fit(ref, log=False)
            model.save(out / f"{name}.pt")
            export_checkpoint(out / f"{name}.pt", out / name, query=query, ground_truth=gt)
            report = json.loads((out / name / "validation.json").read_text())
            print(name, json.dumps({k: report.get(k) for k in KEYS}))


if __name__ == "__main__":
    main()

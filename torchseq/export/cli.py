"""``python -m torchseq.export CHECKPOINT --out DIR``: export and validate a Neural SeqSLAM model.

Writes ``model_float.onnx``, ``model_quant.onnx``, ``model_int.tsq``, ``model_int.onnx`` and
``validation.json``; exits 0 when every check passes, 1 when a check fails, 2 on bad input.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from torchseq.atomic import write_json


class ExportError(ValueError):
    """Bad input to the exporter (unreadable checkpoint, query or ground truth)."""


def _load_model(path: Path):
    from torchseq.neural import NeuralSeqSLAM

    try:
        return NeuralSeqSLAM.load(path)
    except ValueError as err:
        raise ExportError(str(err).splitlines()[0]) from None
    except Exception as err:  # noqa: BLE001 - any unreadable checkpoint is bad input
        raise ExportError(f"{path}: cannot load checkpoint ({type(err).__name__})") from None


def export_checkpoint(checkpoint_path, out_dir, query=None, ground_truth=None) -> bool:
    """Export a Neural SeqSLAM checkpoint to every deployment format and validate them.

    Args:
        checkpoint_path: a file written by ``NeuralSeqSLAM.save``.
        out_dir: output folder (created).
        query: validation query traverse (anything ``torchseq.load_traverse`` reads, or a
            ``(T, H, W)`` array); None: the demo route (``torchseq.demo.make_demo()``).
        ground_truth: ``(R, T)`` bool array or a file ``load_ground_truth`` reads; None: no
            recall (with the demo route: the demo's exact ground truth).

    Returns:
        True when every check passes (see ``validation.json`` ``checks``).

    Raises:
        ExportError: unreadable checkpoint, query or ground truth.
    """
    from torchseq.export.validate import export_and_validate

    t0 = time.perf_counter()
    ckpt, out = Path(checkpoint_path), Path(out_dir)
    model = _load_model(ckpt)
    if query is None:
        from torchseq.demo import make_demo

        demo = make_demo()
        frames, source = demo.query, "demo: torchseq.demo.make_demo() query traverse"
        if ground_truth is None:
            ground_truth, gt_source = demo.ground_truth, "demo exact ground truth"
        else:
            gt_source = str(ground_truth) if not isinstance(ground_truth, np.ndarray) else "array"
    else:
        from torchseq.sources import load_traverse

        try:
            frames = load_traverse(query, progress=False)
        except ValueError as err:
            raise ExportError(str(err).splitlines()[0]) from None
        source = str(query) if not hasattr(query, "shape") else "array"
        gt_source = None if ground_truth is None else (
            "array" if hasattr(ground_truth, "shape") else str(ground_truth))
    if ground_truth is not None and not hasattr(ground_truth, "shape"):
        from torchseq.ground_truth import load_ground_truth

        n_ref = int(model.unit_to_reference[-1, 1])
        try:
            ground_truth = load_ground_truth(ground_truth, n_ref, int(frames.shape[0]))
        except ValueError as err:
            raise ExportError(str(err).splitlines()[0]) from None
    report = {"checkpoint": str(ckpt), "checkpoint_bytes": ckpt.stat().st_size,
              "query_source": source, "ground_truth_source": gt_source}
    report.update(export_and_validate(model, out, frames, ground_truth))
    report["seconds"] = round(time.perf_counter() - t0, 3)
    write_json(out / "validation.json", report)
    return bool(report["passed"])


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the exit status."""
    ap = argparse.ArgumentParser(prog="python -m torchseq.export", description=__doc__.split(
        "\n")[0])
    ap.add_argument("checkpoint", help="Neural SeqSLAM checkpoint (NeuralSeqSLAM.save)")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--query", help="validation query traverse (default: the demo route)")
    ap.add_argument("--ground-truth", help="ground truth for --query (.csv or .npy)")
    args = ap.parse_args(argv)
    try:
        ok = export_checkpoint(args.checkpoint, args.out, args.query, args.ground_truth)
    except ValueError as err:
        print(f"error: {str(err).splitlines()[0] if str(err) else type(err).__name__}",
              file=sys.stderr)
        return 2
    import json

    report = json.loads((Path(args.out) / "validation.json").read_text())
    for key, value in report.items():
        if key.endswith("_agreement") or key.endswith("_error") or key == "recall_at_1":
            print(f"{key}: {value}")
    failed = [k for k, v in report["checks"].items() if not v]
    print("PASS" if ok else f"FAIL: {', '.join(failed)}")
    return 0 if ok else 1

"""``torchseq export CHECKPOINT --out DIR``: the command over ``export_checkpoint``.

Exits 0 when every check passes, 1 when a check fails, 2 on bad input; prints the figures of
``validation.json`` (:func:`summary_lines`). What is written and checked: the docstring of
:mod:`torchseq.export.checkpoint` and ``docs/guide/export.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torchseq.cli.help as cli_help
from torchseq.cli.errors import UsageError
from torchseq.cli.flags import Parser, parse_size
from torchseq.cli.runs import run_folder
from torchseq.export.checkpoint import export_checkpoint
from torchseq.versions import VERSIONS_KEY, versions_line


def _first_line(err: Exception) -> str:
    return str(err).splitlines()[0] if str(err) else type(err).__name__


def summary_lines(out_dir) -> list[str]:
    """The lines the command prints from ``validation.json``: figures, then PASS or FAIL."""
    report = json.loads((Path(out_dir) / "validation.json").read_text())
    lines = [f"validated on {report['query_source']}"]
    if VERSIONS_KEY in report:  # files written before versions were recorded have none
        lines.append(f"made with {versions_line(report[VERSIONS_KEY])}")
    if "device_frame_size" in report:  # the integer device's input (none when skipped)
        lines.append(device_line(report))
    for key, value in report.items():
        if key.endswith("_agreement") or key.endswith("_error") or key == "recall_at_1":
            outside = report.get(f"{key}_outside_near_ties")
            if outside is not None and key == "float_onnx_agreement":
                value = (f"{value} (outside near-ties {outside}; "
                         f"{report.get('float_onnx_near_ties')} near-ties, "
                         f"{report.get('float_onnx_near_tie_disagreements')} decided "
                         f"otherwise; checked: outside near-ties)")
            elif outside is not None:
                value = f"{value} (outside near-ties {outside})"
            lines.append(f"{key}: {value}")
    nir = report.get("nir") or {}
    if "skipped" in nir:
        lines.append(f"nir: skipped ({nir['skipped']})")
    elif nir:
        spiking = nir.get("spiking", {})
        lines.append(f"nir: {nir['file']}, spiking model agreement with the rate model "
                     f"{spiking.get('agreement_with_rate_model')}, recall_at_1 "
                     f"{spiking.get('recall_at_1')}")
        for name, c in nir.get("consumers", {}).items():
            cut = (f" ({c['streams']} streams of {c['time_steps']} frames)"
                   if c.get("streams", 1) > 1 else "")
            lines.append(f"nir_{name}: " + (f"agreement {c['agreement']} with the spiking "
                                            f"model on the same inputs{cut}, spike agreement "
                                            f"{c.get('spike_agreement')}" if "agreement" in c
                                            else "; ".join(f"{k}: {v}" for k, v in c.items())))
        for chip, r in nir.get("chips", {}).items():  # the hardware budget, per chip
            lines.append(f"nir_chip_{chip}: " + ("fits" if r["fits"] else
                                                  "does not fit: " + "; ".join(r["exceeds"])))
        timed = nir.get("timed")
        if timed:  # the timed spiking model: figures only, no file
            lines.append(f"timed spiking model (not in model.nir: {timed['why_not_written']}): "
                         f"agreement with the rate model {timed['agreement_with_rate_model']}, "
                         f"recall_at_1 {timed['recall_at_1']}, {timed['steps_per_frame']} "
                         "time steps per frame")
            for chip, r in timed["chips"].items():
                lines.append(f"timed_chip_{chip}: " + ("fits" if r["fits"] else
                                                        "does not fit: " + "; ".join(r["exceeds"])))
    lines += [f"warning: {w}" for w in report.get("warnings", [])]
    failed = [k for k, v in report["checks"].items() if not v]
    lines.append("PASS" if report["passed"] else f"FAIL: {', '.join(failed)}")
    return lines


def device_line(report: dict) -> str:
    """What the integer device takes, and where that size came from."""
    device, camera = report["device_frame_size"], report.get("camera_frame_size")
    size, source = "x".join(map(str, device)), report["device_frame_size_source"]
    if camera is None or list(camera) == list(device):  # files before camera_frame_size: as is
        return f"device input: uint8 {size} (the camera frames' size, from {source})"
    return (f"device input: uint8 {size}: camera frames {'x'.join(map(str, camera))} (from "
            f"{source}) resized on the host (not a multiple of the model's input)")


def _nir_config(args):
    """The SpikingConfig of ``--nir-weight-bits`` / ``--nir-levels`` (ValueError when bad)."""
    from torchseq.neural.spiking import SpikingConfig

    kw = {}
    if args.nir_weight_bits:
        kw["weight_bits"] = args.nir_weight_bits
    if args.nir_levels is not None:
        kw["levels"] = args.nir_levels
    cfg = SpikingConfig(**kw)
    cfg.validate()  # SpikingError is a ValueError: exit 2 with its line
    return cfg


def build_parser(prog: str = "torchseq export") -> argparse.ArgumentParser:
    """The export command's flags."""
    ap = Parser(prog=prog, description="Export a Neural SeqSLAM checkpoint to ONNX and "
                "integer files and validate them (exit 0: every check passed, 1: one "
                "failed, 2: bad input).")
    ap.add_argument("checkpoint", help="Neural SeqSLAM checkpoint (NeuralSeqSLAM.save)")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--query", help="validation query traverse (default: the checkpoint's own "
                    "reference, recorded by train.py)")
    ap.add_argument("--ground-truth", help="ground truth for --query (.csv or .npy)")
    ap.add_argument("--frame-size", metavar="HxW", help="camera frame size the integer device "
                    "takes (default: the checkpoint's reference frame size)")
    ap.add_argument("--no-nir", action="store_true", help="do not write model.nir (the "
                    "spiking model as a NIR graph) nor run it in snnTorch and Norse")
    ap.add_argument("--nir-weight-bits", type=int, default=0, metavar="BITS",
                    help="model.nir weights as signed BITS-bit integers times a power-of-two "
                    "scale per row (2..16, 8 for Loihi 2 and Speck; default 0: float32)")
    ap.add_argument("--nir-levels", type=int, default=None, metavar="K",
                    help="ring neurons per output unit of the spiking model (default 128; "
                    "fewer fit a chip's memory: docs/guide/nir.md)")
    ap.add_argument("--overwrite", action="store_true", help="replace a previous export in "
                    "--out (one with a validation.json) instead of refusing")
    ap.add_argument("--chip-report", action="store_true", help="also check the spiking model "
                    "against each chip's published limits (Loihi 2, Speck, Xylo)")
    ap.add_argument("--timed-spiking", action="store_true", help="also run the timed spiking "
                    "model on the query and report it (no file; as long as the rest of the "
                    "export on a long query)")
    ap.add_argument("--no-progress", action="store_true", help="do not show the long steps "
                    "on stderr (bars on a terminal, one line per step otherwise)")

    cli_help.organise_help(ap, cli_help.EXPORT, cli_help.EXPORT_EXAMPLES)
    return ap


def main(argv: list[str] | None = None, prog: str = "torchseq export") -> int:
    """Command-line entry point; returns the exit status."""
    args = build_parser(prog).parse_args(argv)
    try:
        size = parse_size(args.frame_size)
        config = _nir_config(args)
        out = run_folder(args.out, "export", args.overwrite, own=("validation.json",))
        ok = export_checkpoint(args.checkpoint, out, args.query, args.ground_truth,
                               frame_size=size, nir=not args.no_nir,
                               progress=not args.no_progress, nir_config=config,
                               chips=args.chip_report, timed=args.timed_spiking)
    except (ValueError, OSError, UsageError) as err:
        print(f"{prog}: error: {_first_line(err)}", file=sys.stderr)
        return 2
    for line in summary_lines(args.out):
        print(line)
    return 0 if ok else 1

"""Export and validate a Neural SeqSLAM checkpoint: :func:`export_checkpoint`.

The library side of ``torchseq export CHECKPOINT --out DIR`` (the command:
:mod:`torchseq.cli.export`). Writes ``model_float.onnx``, ``model_quant.onnx``,
``model_int.tsq``, ``model_int.onnx``, ``model.nir`` (the spiking model, with the ``nir``
extra, calibrated on the recorded reference only; ``docs/guide/nir.md``) and
``validation.json`` (``"passed"``: every check passed). Long steps show progress on stderr.
By default the export is validated on the checkpoint's own reference (recorded by
``train.py``), replayed as the query; the integer device's camera frame size is
``frame_size`` (default: the reference's frame size), never the validation data's.
The ONNX files carry the device contract in their ``metadata_props`` (``torchseq.*``).
An adaptive-velocity checkpoint (``ring_velocity="adaptive"``) gets every file but NIR
(integer format version 3; NIR is reported as skipped: no spiking form), in
``validation.json`` and on the console.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

from torchseq.atomic import write_json
from torchseq.export.errors import ExportError
from torchseq.versions import VERSIONS_KEY, versions


def _first_line(err: Exception) -> str:
    return str(err).splitlines()[0] if str(err) else type(err).__name__


def _load_model(path: Path):
    from torchseq.neural import NeuralSeqSLAM

    try:
        return NeuralSeqSLAM.load(path)
    except ValueError as err:
        raise ExportError(_first_line(err)) from None
    except Exception as err:  # noqa: BLE001 - any unreadable checkpoint is bad input
        raise ExportError(f"{path}: cannot load checkpoint ({type(err).__name__})") from None


def recorded_reference(model) -> dict | None:
    """The reference a checkpoint learnt, as ``train.py`` records it (None: not recorded).

    ``{"source": "demo", "demo_frames", "demo_seed"}`` or ``{"source": path, "events"}``,
    with ``n_frames`` and ``frame_size`` where known (older checkpoints: from
    ``train_config``).
    """
    extra = getattr(model, "extra", None)
    if not isinstance(extra, dict):
        return None
    ref = extra.get("reference")
    if isinstance(ref, dict) and isinstance(ref.get("source"), str):
        return ref
    tc = extra.get("train_config")
    if isinstance(tc, dict) and "reference" in tc:
        if tc["reference"] is None:
            return {"source": "demo", "demo_frames": tc.get("demo_frames", 200),
                    "demo_seed": tc.get("demo_seed", 0)}
        if isinstance(tc["reference"], str):
            return {"source": tc["reference"],
                    "events": {k: tc.get(k) for k in ("window_ms", "event_count")}}
    return None


def _int(value, name: str, lo: int, hi: int) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
        raise ExportError(f"checkpoint records a bad {name}: {value!r}")
    return value


def _recorded_frames(model, ckpt: Path, rec: dict, remedy: str = ""):
    """The frames of a recorded reference file, checked against what the model learnt."""
    from torchseq.sources import EventFrameOptions, FrameSelection, load_traverse

    events = rec.get("events") if isinstance(rec.get("events"), dict) else {}
    select = rec.get("select") if isinstance(rec.get("select"), dict) else {}
    try:
        opts = EventFrameOptions(**{k: v for k, v in events.items() if v is not None})
        frames = load_traverse(rec["source"], events=opts, progress=False,
                               select=FrameSelection(**select))
    except (ValueError, TypeError, OSError) as err:
        raise ExportError(f"{ckpt}: its reference {rec['source']} cannot be loaded "
                          f"({_first_line(err)}){remedy}") from None
    n_learnt = int(model.unit_to_reference[-1, 1])
    if len(frames) != n_learnt:
        raise ExportError(f"{ckpt}: its reference {rec['source']} now has {len(frames)} "
                          f"frames, but the model learnt {n_learnt}{remedy}")
    return frames


def _own_reference(model, ckpt: Path):
    """Validation query = the checkpoint's own reference: frames, ground truth, description."""
    from torchseq.ground_truth import alignment_ground_truth

    rec = recorded_reference(model)
    if rec is None:
        raise ExportError(f"{ckpt}: the checkpoint does not record which reference it learnt "
                          f"(it was not written by train.py); give --query (and "
                          f"--ground-truth) to validate on")
    if rec["source"] == "demo":
        from torchseq.demo import make_demo

        demo = make_demo(n_reference=_int(rec.get("demo_frames"), "demo_frames", 2, 20_000),
                         seed=_int(rec.get("demo_seed"), "demo_seed", 0, 2 ** 32 - 1))
        return (demo.query, demo.ground_truth, rec,
                f"the checkpoint's own reference: demo route ({demo.reference.shape[0]} "
                f"frames), its query traverse", "demo exact ground truth")
    frames = _recorded_frames(model, ckpt, rec, "; give --query")
    n_learnt = int(model.unit_to_reference[-1, 1])
    # a replay: each frame should come back to its own place, up to a unit's span
    tol = math.ceil(n_learnt / model.n_units / 2) if n_learnt > model.n_units else 0
    gt = alignment_ground_truth(n_learnt, n_learnt, tol)
    return (frames, gt, rec, f"the checkpoint's own reference {rec['source']}, replayed",
            f"replay alignment, tolerance {tol}")


def _suggested_threshold(model, frames, gt) -> float | None:
    """The confidence at 99% precision on the validation data (None without ground truth)."""
    if gt is None:
        return None
    import torch

    from torchseq.metrics import operating_point

    matches = model.run(torch.as_tensor(frames).to(torch.float32)).matches
    op = operating_point(matches, gt, 0.99)
    return op["score_threshold"]


def export_checkpoint(checkpoint_path, out_dir, query=None, ground_truth=None,
                      frame_size: tuple[int, int] | None = None, nir: bool = True,
                      progress: bool = False, nir_config=None, chips: bool = False,
                      timed: bool = False) -> bool:
    """Export a Neural SeqSLAM checkpoint to every deployment format and validate them.

    Args:
        checkpoint_path: a file written by ``NeuralSeqSLAM.save``.
        out_dir: output folder (created).
        query: validation query traverse (anything ``torchseq.load_traverse`` reads, or a
            ``(T, H, W)`` array); None: the checkpoint's own reference as ``train.py``
            recorded it (the demo route's query, or a replay of the reference file).
        ground_truth: ``(R, T)`` bool array or a file ``load_ground_truth`` reads; None: no
            recall (with the checkpoint's own reference: its ground truth).
        frame_size: ``(H0, W0)`` camera frames the integer device takes. None: the recorded
            reference's frame size, else the validation query's (reported in
            ``validation.json`` as ``device_frame_size_source``).
        nir: also write ``model.nir`` (the spiking model, calibrated on the recorded
            reference only) and validate it in snnTorch and Norse (``docs/guide/nir.md``; needs
            the ``nir`` extra and the learnt reference, else reported as skipped).
        progress: show each long step on stderr (:mod:`torchseq.export.progress`).
        nir_config: the :class:`~torchseq.neural.spiking.SpikingConfig` of the NIR export
            (None: defaults: float32 weights, 128 levels).
        chips: also check the spiking model against each chip's limits (``nir.chips``).
        timed: also run the timed spiking model on the query (``nir.timed``).

    Returns:
        True when every check passes (see ``validation.json`` ``checks``).

    Raises:
        ExportError: unreadable checkpoint, query or ground truth, or no reference recorded
            and no query given.
    """
    from torchseq.export.contract import contract, write_contract
    from torchseq.export.progress import ExportProgress
    from torchseq.export.validate import (
        FLOAT_ONNX,
        INT_ONNX,
        NO_SPIKING_FORM,
        QUANT_ONNX,
        export_and_validate,
        spiking_form,
    )

    t0 = time.perf_counter()
    ckpt, out = Path(checkpoint_path), Path(out_dir)
    model = _load_model(ckpt)
    from torchseq.neural.search import refuse_export

    refuse_export(model, "torchseq export", ExportError,  # the flag that does it
                  hint=" (torchseq train --neural-unit-search off)")
    rec = recorded_reference(model)
    if query is None:
        frames, own_gt, rec, source, gt_source = _own_reference(model, ckpt)
        if ground_truth is None:
            ground_truth = own_gt
        else:
            gt_source = "array" if hasattr(ground_truth, "shape") else str(ground_truth)
    else:
        from torchseq.sources import load_traverse

        try:
            frames = load_traverse(query, progress=False)
        except ValueError as err:
            raise ExportError(_first_line(err)) from None
        source = str(query) if not hasattr(query, "shape") else "array"
        gt_source = None if ground_truth is None else (
            "array" if hasattr(ground_truth, "shape") else str(ground_truth))
    if ground_truth is not None and not hasattr(ground_truth, "shape"):
        from torchseq.ground_truth import load_ground_truth

        n_ref = int(model.unit_to_reference[-1, 1])
        try:
            ground_truth = load_ground_truth(ground_truth, n_ref, int(frames.shape[0]))
        except ValueError as err:
            raise ExportError(_first_line(err)) from None
    if frame_size is not None:
        size_source = "--frame-size"
    elif rec is not None and isinstance(rec.get("frame_size"), list):
        frame_size = tuple(int(v) for v in rec["frame_size"])
        size_source = "the checkpoint's reference frames"
    else:
        frame_size = tuple(int(v) for v in frames.shape[1:3])
        size_source = "the validation query's frames (give --frame-size for the camera's)"
    if len(frame_size) != 2 or not all(0 < v <= 16384 for v in frame_size):
        raise ExportError(f"frame size must be two sides in 1..16384, got {frame_size}")
    report = {VERSIONS_KEY: versions(), "checkpoint": str(ckpt),
              "checkpoint_bytes": ckpt.stat().st_size,
              "query_source": source, "ground_truth_source": gt_source,
              "camera_frame_size": list(frame_size), "device_frame_size_source": size_source}
    steps = ExportProgress(enabled=progress)
    report.update(export_and_validate(model, out, frames, ground_truth, frame_size=frame_size,
                                      progress=steps))
    threshold = _suggested_threshold(model, frames, ground_truth)
    report["suggested_confidence_threshold"] = threshold
    graphs = ((FLOAT_ONNX, "float"), (QUANT_ONNX, "float"), (INT_ONNX, "integer"))
    for name, kind in graphs:
        props = contract(kind, model, report, threshold)
        if not spiking_form(model):  # the adaptive ring: its estimator state too
            props.update(_velocity_contract(model, kind))
        write_contract(out / name, props)
        report["files_bytes"][name] = (out / name).stat().st_size
    from torchseq.export.nir_validate import calibration_frames, export_nir

    readout = getattr(model.config, "readout", "centre")
    if nir and not spiking_form(model):  # SpikingSeqSLAM.convert refuses it
        report["nir"] = {"skipped": NO_SPIKING_FORM}
    elif nir and readout != "centre":  # SpikingSeqSLAM.convert refuses it (no spiking form)
        report["nir"] = {"skipped": f"readout={readout!r} has no spiking (NIR) form; the "
                                    "ONNX and integer files hold it"}
    elif nir:  # calibrated on the learnt reference only: a device has no query
        calib, calib_source = calibration_frames(
            model, rec, replayed=frames if query is None else None,
            load=lambda: _recorded_frames(model, ckpt, rec))
        report["nir"] = export_nir(model, out, frames, ground_truth, calib, calib_source,
                                   progress=steps, config=nir_config, chips=chips,
                                   timed=timed)
    else:
        report["nir"] = {"skipped": "--no-nir"}
    if "checks" in report["nir"]:
        report["checks"].update(report["nir"]["checks"])
        report["passed"] = all(report["checks"].values())
        report["files_bytes"]["model.nir"] = report["nir"]["bytes"]
    report["seconds"] = round(time.perf_counter() - t0, 3)
    write_json(out / "validation.json", report)
    return bool(report["passed"])


def _velocity_contract(model, kind: str = "float") -> dict[str, str]:
    """A graph's extra inputs of an adaptive-velocity model (contract metadata)."""
    n, k = int(model.n_units), int(model.config.velocity_window)
    if kind == "integer":
        return {"torchseq.initial_state": (
            f"state zeros int32 (B, {n}), velocity 65536 int64 (B,) (speed on the 2**-16 "
            f"grid), positions zeros int64 (B, {k}), count zeros int64 (B,); feed new_state, "
            f"new_velocity, new_positions, new_count back")}
    return {"torchseq.initial_state": (
        f"state zeros float32 (B, {n}), velocity ones float64 (B,), positions zeros float64 "
        f"(B, {k}), count zeros int64 (B,); feed new_state, new_velocity, new_positions, "
        f"new_count back")}



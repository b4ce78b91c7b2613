"""Run every exported variant over a query traverse and compare it with the float model.

Variants: PyTorch (the reference), float ONNX, dynamically quantised ONNX, the NumPy integer
runtime and the integer ONNX graph. Decisions are compared frame by frame (the reference
frame each variant reports); the integer runtime and the integer ONNX graph must agree bit
for bit (reference, confidence and the whole ring state at every step).

The float and quantised ONNX graphs take float frames at the input size and are compared
with PyTorch on the original frames. The integer device takes uint8 frames (a camera's
pixels); its decisions are compared with PyTorch run on those same uint8 frames
(``integer_agreement``, the checked figure: what the export changes) and, for information,
with PyTorch on the original frames (``integer_raw_input_agreement``; differs only when the
query frames are not whole grey levels, e.g. the synthetic demo route).
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import numpy as np
import onnx
import torch

from torchseq.export.int_format import read_integer_model, write_integer_model
from torchseq.export.int_model import choose_pool, device_frames, integer_model
from torchseq.export.int_onnx import build_integer_onnx, run_integer_onnx, session, write_onnx
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.export.onnx_float import build_float_onnx, run_float_onnx
from torchseq.preprocess import resize, to_grey

FLOAT_ONNX = "model_float.onnx"
QUANT_ONNX = "model_quant.onnx"
INT_FILE = "model_int.tsq"
INT_ONNX = "model_int.onnx"
MIN_AGREEMENT = 0.99
# Rounding whole-grey-level frames' float copies to uint8 flips only near ties (the synthetic
# demo: 0.975-0.996); far below, the frames are not grey levels 0..255 at all (event frames
# of window means: 0.001) and the integer files cannot reproduce the model on them.
MIN_UINT8_AGREEMENT = 0.9
NO_SPIKING_FORM = "no spiking form of ring_velocity='adaptive'"


def spiking_form(model) -> bool:
    """Whether the model has the spiking (NIR) form: not the adaptive ring."""
    return getattr(model.config, "ring_velocity", "fixed") == "fixed"


def _float_speeds(model, frames: torch.Tensor) -> np.ndarray:
    """The float adaptive model's speed estimate after each frame (one stream), ``(T,)``."""
    state, out = None, []
    with torch.no_grad():
        for t in range(frames.shape[0]):
            _, state = model.step(frames[t:t + 1], state)
            out.append(float(state.velocity[0]))
    return np.asarray(out)


def quantise_onnx(model: onnx.ModelProto) -> onnx.ModelProto:
    """Dynamic int8 quantisation (onnxruntime) of the L1 and L3 weight ``MatMul`` nodes.

    The cohort normalisation and the ring stay float: quantising the recurrent state with
    per-call dynamic 8-bit scales costs decisions (measured in ``docs/results/export.md``).
    """
    from onnxruntime.quantization import QuantType, quantize_dynamic

    names = [n.name for n in model.graph.node
             if n.op_type == "MatMul" and any(i in ("w1_t", "w3_t") for i in n.input)]
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "float.onnx", Path(tmp) / "quant.onnx"
        onnx.save(model, src)
        logging.disable(logging.WARNING)  # its "consider pre-processing" advice, every call
        try:
            quantize_dynamic(src, dst, weight_type=QuantType.QInt8, nodes_to_quantize=names)
        finally:
            logging.disable(logging.NOTSET)
        quant = onnx.load(dst)
    onnx.checker.check_model(quant, full_check=True)
    return quant


def agreement(a: np.ndarray, b: np.ndarray) -> float:
    """Fraction of frames where two decision vectors are equal."""
    return float(np.mean(np.asarray(a) == np.asarray(b)))


def export_and_validate(model, out_dir: str | Path, query: torch.Tensor,
                        ground_truth: np.ndarray | None = None,
                        frame_size: tuple[int, int] | None = None) -> dict:
    """Write the four exported files and measure every variant on ``query``.

    An adaptive-velocity model (``ring_velocity="adaptive"``) is written as integer format
    version 3; the report adds the speed estimates' agreement
    (``integer_speed_max_abs_error``, ``integer_speed_mean_abs_error``, in reference frames
    per query frame, against the float model on the same uint8 frames).

    Args:
        model: a fitted :class:`torchseq.neural.NeuralSeqSLAM`.
        out_dir: folder for ``model_float.onnx``, ``model_quant.onnx``, ``model_int.tsq``,
            ``model_int.onnx``.
        query: ``(T, H, W)`` (or RGB) query frames, 0..255.
        ground_truth: ``(R, T)`` bool, or None (no recall).
        frame_size: ``(H0, W0)`` camera frames the integer device takes (sets its pooling);
            the query is resized to it for the device. None: the query's frame size.

    Returns:
        A JSON-ready dict of measurements, ``checks`` and ``passed``.
    """
    from torchseq.metrics import recall_at_k

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    grey = to_grey(torch.as_tensor(query)).to(torch.float32)
    size = tuple(model.config.input_size)
    camera = grey if frame_size is None else resize(grey, tuple(frame_size))
    pool = choose_pool(tuple(camera.shape[1:3]), size)
    # build and write
    float_onnx = build_float_onnx(model)
    quant = quantise_onnx(float_onnx)
    files = {FLOAT_ONNX: write_onnx(float_onnx, out / FLOAT_ONNX),
             QUANT_ONNX: write_onnx(quant, out / QUANT_ONNX)}
    files[INT_FILE] = write_integer_model(out / INT_FILE, integer_model(model, pool))
    stored = read_integer_model(out / INT_FILE)  # validate what was written
    files[INT_ONNX] = write_onnx(build_integer_onnx(stored), out / INT_ONNX)
    checker = {}
    for name in (FLOAT_ONNX, QUANT_ONNX, INT_ONNX):
        try:
            onnx.checker.check_model(str(out / name), full_check=True)
            checker[name] = True
        except Exception:  # noqa: BLE001 - any checker failure fails the export
            checker[name] = False
    # run every variant
    result = model.run(grey)
    ref_pt = result.matches.reference.numpy()
    act_pt = result.activity.numpy()
    conf_pt = result.matches.confidence.numpy()
    small = resize(grey, size).numpy()
    ref_f, conf_f, act_f = run_float_onnx(session(out / FLOAT_ONNX), small)
    ref_q, _, act_q = run_float_onnx(session(out / QUANT_ONNX), small)
    float_report = {
        "n_query": int(grey.shape[0]),
        "query_frame_size": list(grey.shape[1:3]),
        "input_size": list(size),
        "n_units": int(model.n_units),
        "files_bytes": files,
        "float_onnx_max_abs_error": float(np.abs(act_f - act_pt).max()),
        "float_onnx_confidence_max_abs_error": float(np.abs(conf_f - conf_pt).max()),
        "float_onnx_agreement": agreement(ref_f, ref_pt),
        "quant_onnx_max_abs_error": float(np.abs(act_q - act_pt).max()),
        "quant_onnx_agreement": agreement(ref_q, ref_pt),
    }
    frames_u8 = device_frames(camera, size, pool)
    result_u8 = model.run(torch.from_numpy(frames_u8).to(torch.float32))
    ref_u8, act_u8 = result_u8.matches.reference.numpy(), result_u8.activity.numpy()
    adaptive = stored.velocity is not None
    ref_n, conf_n, act_n, *v_n = IntegerRuntime(stored).run(frames_u8, speeds=adaptive)
    ref_o, conf_o, act_o, *v_o = run_integer_onnx(session(out / INT_ONNX), frames_u8,
                                                  speeds=adaptive)
    unit = 2.0 ** -stored.params["state_frac"]
    bit_exact = bool(np.array_equal(ref_n, ref_o) and np.array_equal(conf_n, conf_o)
                     and np.array_equal(act_n, act_o) and act_n.dtype == act_o.dtype
                     and all(np.array_equal(a, b) for a, b in zip(v_n, v_o)))
    report = {
        **float_report,
        "device_frame_size": list(frames_u8.shape[1:3]),
        "integer_pool": list(pool),
        "integer_agreement": agreement(ref_n, ref_u8),
        "integer_onnx_agreement": agreement(ref_o, ref_u8),
        "integer_raw_input_agreement": agreement(ref_n, ref_pt),
        "uint8_input_agreement": agreement(ref_u8, ref_pt),
        "integer_activity_max_abs_error": float(np.abs(act_n * unit - act_u8).max()),
        "integer_activity_scale": float(np.abs(act_u8).max()),
        "integer_onnx_bit_exact": bit_exact,
        "onnx_checker": checker,
    }
    if adaptive:  # the speed estimates, integer (2**-16 grid) against float
        diff = np.abs(v_n[0] / 2.0**16 - _float_speeds(model, torch.from_numpy(frames_u8)
                                                       .to(torch.float32)))
        report["integer_format_version"] = stored.format_version
        report["integer_speed_max_abs_error"] = float(diff.max())
        report["integer_speed_mean_abs_error"] = float(diff.mean())
    if ground_truth is not None:
        gt = np.asarray(ground_truth, dtype=bool)
        report["recall_at_1"] = {name: recall_at_k(r, gt) for name, r in (
            ("pytorch", ref_pt), ("pytorch_uint8_input", ref_u8), ("float_onnx", ref_f),
            ("quant_onnx", ref_q),
            ("integer_numpy", ref_n), ("integer_onnx", ref_o))}
    report["warnings"] = []
    if report["uint8_input_agreement"] < MIN_AGREEMENT:
        lo, hi = float(grey.min()), float(grey.max())
        report["warnings"].append(
            f"the integer device's uint8 input changes the float model's decisions on "
            f"{1 - report['uint8_input_agreement']:.1%} of the query frames: it takes whole "
            f"grey levels 0..255 and these frames span {lo:.4g}..{hi:.4g} (event frames are "
            f"event counts or means, not grey levels), so the integer files do not reproduce "
            f"this model on such frames")
    checks = {
        "float_onnx_agreement": report["float_onnx_agreement"] >= MIN_AGREEMENT,
        "integer_agreement": report["integer_agreement"] >= MIN_AGREEMENT,
        "uint8_input_agreement": report["uint8_input_agreement"] >= MIN_UINT8_AGREEMENT,
        "integer_onnx_bit_exact": bit_exact,
        "onnx_checker": all(checker.values()),
    }
    report["checks"] = checks
    report["passed"] = all(checks.values())
    return report

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
from torchseq.export.int_onnx import build_integer_onnx, write_onnx
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.export.onnx_float import build_float_onnx
from torchseq.export.sessions import run_float_onnx, run_integer_onnx, session
from torchseq.preprocess import resize, to_grey

FLOAT_ONNX = "model_float.onnx"
QUANT_ONNX = "model_quant.onnx"
INT_FILE = "model_int.tsq"
INT_ONNX = "model_int.onnx"
MIN_AGREEMENT = 0.99
# Two float32 forms of the model decide alike except where the top two scores are within
# this many units of eps * max|score| (near_ties); measured differences are 2.5 such units.
TIE_ULPS = 64
# Rounding whole-grey-level frames' float copies to uint8 flips only near ties (the synthetic
# demo: 0.975-0.996); far below, the frames are not grey levels 0..255 at all (event frames
# of window means: 0.001) and the integer files cannot reproduce the model on them.
MIN_UINT8_AGREEMENT = 0.9
NO_SPIKING_FORM = "no spiking form of ring_velocity='adaptive'"
QUANT_NOTE = (
    "approximate by design, not checked: onnxruntime's dynamic quantisation rounds each "
    "frame's L1 input to uint8 with that frame's own scale and the L1 and L3 weights to int8 "
    "with one scale per matrix, which moves L1 sums across the k-WTA threshold and shifts "
    "near-equal L3 evidence; on the corridor quantising L1 alone gives 0.901, L3 alone 0.973, "
    "per-row weight scales do not help (experiments/quant_onnx_ablation.py). The exact "
    "integer form is model_int.tsq / model_int.onnx (integer_agreement, checked)")


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


def near_ties(scores: np.ndarray, ulps: int = TIE_ULPS) -> tuple[np.ndarray, np.ndarray]:
    """Frames whose two highest scores are within float rounding of each other.

    The tolerance of frame ``t`` is ``ulps * eps(dtype) * max_u |scores[t, u]|`` (``eps``
    of the scores' floating dtype, 2**-23 for float32): two forms of the same float32
    computation (PyTorch and onnxruntime summing in another order) differ by a few units in
    the last place of the largest score (measured: 2.5 on a 500-frame nordland-b model), so
    a decision between two units closer than that is a tie either form may break.

    Args:
        scores: ``(T, N)`` the reference form's scores (ring activity), floating.
        ulps: the tolerance in units of ``eps * max |score|``.

    Returns:
        ``(near (T,) bool, tolerance (T,) float64)``.
    """
    a = np.asarray(scores)
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"scores must be floating point, got {a.dtype}")
    tol = ulps * float(np.finfo(a.dtype).eps) * np.abs(a).max(axis=1).astype(np.float64)
    if a.shape[1] < 2:
        return np.zeros(a.shape[0], dtype=bool), tol
    top2 = -np.partition(-a.astype(np.float64), 1, axis=1)[:, :2]
    return top2[:, 0] - top2[:, 1] <= tol, tol


def decision_agreement(reference: np.ndarray, other: np.ndarray, scores: np.ndarray,
                       ulps: int = TIE_ULPS) -> dict:
    """Agreement of two decision vectors, overall and outside the near-ties of ``scores``.

    Args:
        reference: ``(T,)`` the reference form's decisions (PyTorch).
        other: ``(T,)`` the exported form's decisions.
        scores: ``(T, N)`` the reference form's scores (:func:`near_ties`).
        ulps: the tie tolerance (:func:`near_ties`).

    Returns:
        ``{"agreement", "agreement_outside_near_ties", "near_ties", "near_tie_disagreements",
        "frames_outside_near_ties"}``: ``agreement_outside_near_ties`` is the raw
        agreement where every frame is a near-tie (nothing else to judge by).
    """
    same = np.asarray(reference) == np.asarray(other)
    near, _ = near_ties(scores, ulps)
    outside = same[~near]
    return {"agreement": float(same.mean()),
            "agreement_outside_near_ties": float(outside.mean() if outside.size
                                                 else same.mean()),
            "near_ties": int(near.sum()),
            "near_tie_disagreements": int((~same & near).sum()),
            "frames_outside_near_ties": int(outside.size)}


def uint8_warning(grey: torch.Tensor, camera: torch.Tensor, device: np.ndarray,
                  uint8_agreement: float) -> str:
    """The warning when the device's uint8 input changes the float model's decisions.

    Two causes, told apart by the frames: whole grey levels 0..255 (camera images) that the
    host resizes to the device input before rounding (the rounding of the resized frames
    moves near-tied decisions), or frames that are not grey levels at all (event counts or
    window means).

    Args:
        grey: ``(T, H, W)`` the validation frames, float.
        camera: ``(T, H0, W0)`` the frames at the device's camera size.
        device: ``(T, h, w)`` uint8 frames the device takes.
        uint8_agreement: the float model's agreement between the two inputs.
    """
    share = f"{1 - uint8_agreement:.1%}"
    lo, hi = float(grey.min()), float(grey.max())
    if lo >= 0 and hi <= 255 and bool(torch.equal(grey, grey.round())):
        src = "x".join(map(str, camera.shape[1:3]))
        dst = "x".join(map(str, device.shape[1:3]))
        where = (f"resized from {src} to the device input {dst} and rounded to whole grey "
                 f"levels" if src != dst else "rounded to whole grey levels")
        return (f"the integer device's uint8 input changes the float model's decisions on "
                f"{share} of the query frames: these frames hold whole levels 0..255, but "
                f"{where} they move decisions the float model takes by a narrow margin; "
                f"integer_agreement compares the integer files with the float model on those "
                f"same uint8 frames")
    return (f"the integer device's uint8 input changes the float model's decisions on "
            f"{share} of the query frames: it takes whole grey levels 0..255 and these "
            f"frames span {lo:.4g}..{hi:.4g}: not grey levels (event frames are event counts "
            f"or means), so the integer files do not reproduce this model on such frames")


def export_and_validate(model, out_dir: str | Path, query: torch.Tensor,
                        ground_truth: np.ndarray | None = None,
                        frame_size: tuple[int, int] | None = None, progress=None) -> dict:
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
        progress: an :class:`~torchseq.export.progress.ExportProgress`, or None.

    Returns:
        A JSON-ready dict of measurements, ``checks`` and ``passed``.
    """
    from torchseq.export.progress import QUIET
    from torchseq.metrics import recall_at_k

    progress = progress or QUIET
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    grey = to_grey(torch.as_tensor(query)).to(torch.float32)
    size = tuple(model.config.input_size)
    camera = grey if frame_size is None else resize(grey, tuple(frame_size))
    pool = choose_pool(tuple(camera.shape[1:3]), size)
    # build and write
    with progress.step("ONNX and integer files"):
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
    n = int(grey.shape[0])
    with progress.step("PyTorch and float ONNX runs", n):
        result = model.run(grey)
        ref_pt = result.matches.reference.numpy()
        act_pt = result.activity.numpy()
        conf_pt = result.matches.confidence.numpy()
        small = resize(grey, size).numpy()
        ref_f, conf_f, act_f = run_float_onnx(session(out / FLOAT_ONNX), small)
    with progress.step("quantised ONNX run", n):
        ref_q, _, act_q = run_float_onnx(session(out / QUANT_ONNX), small)
    float_dec = decision_agreement(ref_pt, ref_f, act_pt)
    quant_dec = decision_agreement(ref_pt, ref_q, act_pt)
    float_report = {
        "n_query": n,
        "query_frame_size": list(grey.shape[1:3]),
        "input_size": list(size),
        "n_units": int(model.n_units),
        "files_bytes": files,
        "float_onnx_max_abs_error": float(np.abs(act_f - act_pt).max()),
        "float_onnx_confidence_max_abs_error": float(np.abs(conf_f - conf_pt).max()),
        "float_onnx_agreement": float_dec["agreement"],
        "float_onnx_agreement_outside_near_ties": float_dec["agreement_outside_near_ties"],
        "float_onnx_near_ties": float_dec["near_ties"],
        "float_onnx_near_tie_disagreements": float_dec["near_tie_disagreements"],
        "near_tie_rule": (f"a frame is a near-tie when PyTorch's two highest ring activities "
                          f"differ by at most {TIE_ULPS} * eps(float32) * its largest "
                          f"|activity| ({TIE_ULPS} * 2**-23 relative): float rounding may "
                          f"break such a tie either way"),
        "quant_onnx_max_abs_error": float(np.abs(act_q - act_pt).max()),
        "quant_onnx_agreement": quant_dec["agreement"],
        "quant_onnx_agreement_outside_near_ties": quant_dec["agreement_outside_near_ties"],
        "quant_onnx_note": QUANT_NOTE,
    }
    frames_u8 = device_frames(camera, size, pool)
    with progress.step("integer runs (PyTorch on uint8, NumPy, ONNX)", n):
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
        report["warnings"].append(uint8_warning(grey, camera, frames_u8,
                                                report["uint8_input_agreement"]))
    checks = {
        # outside near-ties (near_ties): a float rounding difference that breaks a tie the
        # other way is not a fault; both figures are reported
        "float_onnx_agreement": (report["float_onnx_agreement_outside_near_ties"]
                                 >= MIN_AGREEMENT),
        "integer_agreement": report["integer_agreement"] >= MIN_AGREEMENT,
        "uint8_input_agreement": report["uint8_input_agreement"] >= MIN_UINT8_AGREEMENT,
        "integer_onnx_bit_exact": bit_exact,
        "onnx_checker": all(checker.values()),
    }
    report["checks"] = checks
    report["passed"] = all(checks.values())
    return report

"""Float ONNX export of the Neural SeqSLAM streaming step.

The exported graph takes the k-WTA winners straight from ONNX ``TopK`` (whose index set
breaks ties by the lower index, the model's rule) as a scattered 0/1 code; eager PyTorch
uses the exact :func:`torchseq.layers.functional.kwta`. Same maths, tested on tied inputs.

:class:`StreamingStep` restates ``NeuralSeqSLAM.step`` ("Step maths" in ``docs/neural.md``)
from the model's buffers with the masks folded into dense weights, for frames already at
the model's input size; :func:`export_float_onnx` writes it with a dynamic batch axis using
the TorchScript-based exporter (``dynamo=False``: the dynamo exporter needs onnxscript).
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch
from torch import nn

from torchseq.export.int_onnx import run_step_session, write_onnx
from torchseq.layers.functional import cohort_normalise, kwta
from torchseq.neural.fixed_point import block_order, quantise_input, zscore_blocks
from torchseq.neural.learning import decide
from torchseq.preprocess import patch_normalise

OPSET = 17


class StreamingStep(nn.Module):
    """``(frames (B, h, w), state (B, N)) -> (activity, new_state, reference, confidence)``.

    Args:
        model: a fitted :class:`torchseq.neural.NeuralSeqSLAM`.
    """

    def __init__(self, model) -> None:
        super().__init__()
        if not model.fitted:
            raise ValueError("the model has not learnt a route yet (fit it first)")
        cfg = model.config
        self.patch, self.mode = int(cfg.patch_size), cfg.patch_mode
        self.steps = int(getattr(cfg, "input_steps", 0))
        self.k, self.eps, self.window = int(cfg.k), float(cfg.eps), int(cfg.uniqueness_window)
        self.rectify = bool(getattr(cfg, "rectify", False))
        self.decay, self.gain = (float(v) for v in model.ring.params)
        self.input_size = tuple(cfg.input_size)
        with torch.no_grad():
            w1_t = model.l1.folded_weight().detach().float().T  # (D, M)
            self.blocks = bool(self.patch) and self.mode == "zscore"
            if self.blocks:
                w1_t = w1_t[block_order(*self.input_size, self.patch)]
            self.register_buffer("w1_t", w1_t.contiguous())
            self.register_buffer("w3_t", model.l3.folded_weight().detach().float().T.contiguous())
            self.register_buffer("shift_t", model.ring.shift.detach().float().T.contiguous())
        self.register_buffer("cohorts", model.cohorts.detach().float().clone())
        self.register_buffer("unit_centre", model.unit_centre.detach().clone())

    def forward(self, frames: torch.Tensor, state: torch.Tensor):
        """One step.

        Args:
            frames: ``(B, h, w)`` float32 grey at the input size, 0..255 (not normalised).
            state: ``(B, N)`` float32 previous activity (zeros at the start).

        Returns:
            ``activity (B, N)``, ``new_state (B, N)`` (the same values), ``reference (B,)``
            int64, ``confidence (B,)`` float32.
        """
        x = frames
        if self.blocks:  # NeuralSeqSLAM's z-scores, block-major (w1_t's rows follow)
            x = zscore_blocks(x, self.patch)
        elif self.patch:  # as NeuralSeqSLAM.encode: OpenSeqSLAM's code centred on 0
            x = patch_normalise(x, self.patch, self.mode) - 127.0
        x = quantise_input(x.reshape(x.shape[0], -1), self.steps)  # (B, D); ONNX Round
        h = x @ self.w1_t  # (B, M)
        if torch.onnx.is_in_onnx_export():
            # ONNX TopK selects ties by the lower index (TopK-11 rule) = kwta's rule, so the
            # winners' indices give the binary code.
            idx = torch.topk(h, self.k, dim=1, sorted=False).indices  # (B, k)
            code = torch.zeros_like(h).scatter(1, idx, torch.ones_like(idx, dtype=h.dtype))
            e = code @ self.w3_t  # (B, N)
        else:  # eager: torch.topk's tie order is unspecified, use the exact k-WTA
            e = kwta(h, self.k, binary=True) @ self.w3_t
        z = cohort_normalise(e, self.cohorts, self.eps)  # (B, N)
        if self.rectify:
            z = z.clamp_min(0.0)
        activity = self.decay * (state @ self.shift_t) + self.gain * z
        reference, confidence = decide(activity, self.unit_centre, self.window)
        return activity, activity.clone(), reference, confidence


def build_float_onnx(model) -> onnx.ModelProto:
    """Trace :class:`StreamingStep` into an ONNX model (dynamic batch axis ``batch``)."""
    step = StreamingStep(model).eval()
    h, w = step.input_size
    n_units = model.n_units
    frames = torch.rand(2, h, w) * 255
    state = torch.zeros(2, n_units)
    buf = io.BytesIO()
    axes = {"frames": {0: "batch"}, "state": {0: "batch"}, "activity": {0: "batch"},
            "new_state": {0: "batch"}, "reference": {0: "batch"}, "confidence": {0: "batch"}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(step, (frames, state), buf, input_names=["frames", "state"],
                          output_names=["activity", "new_state", "reference", "confidence"],
                          dynamic_axes=axes, opset_version=OPSET, dynamo=False)
    m = onnx.load_from_string(buf.getvalue())
    onnx.checker.check_model(m, full_check=True)
    return m


def export_float_onnx(model, path: str | Path) -> int:
    """Write the float streaming step to ``path`` (atomically); returns its size in bytes."""
    return write_onnx(build_float_onnx(model), path)


def run_float_onnx(sess, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stream ``(T, h, w)`` float32 frames through a float session, feeding the state back.

    Returns:
        ``(reference (T,), confidence (T,), activity (T, N))``.
    """
    return run_step_session(sess, frames)

"""Float ONNX export of the Neural SeqSLAM streaming step, traced from its inference module.

:class:`StreamingStep` is ``model.inference("portable")`` (plain torch float32 kernels,
:mod:`torchseq.neural.inference`) with the state and the outputs as plain tensors, for
frames already at the model's input size. The stages are the layers' own functions; the
k-WTA takes its export branch inside :func:`torchseq.layers.kwta` (ONNX ``TopK``'s index
set, whose tie rule is the model's). :func:`export_float_onnx` writes it with a dynamic
batch axis using the TorchScript-based exporter (``dynamo=False``: the dynamo exporter needs
onnxscript).
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch

from torchseq.export.cli import ExportError
from torchseq.export.int_onnx import run_step_session, write_onnx
from torchseq.layers import RingState
from torchseq.neural.inference import NeuralInference

OPSET = 17


class StreamingStep(NeuralInference):
    """``(frames (B, h, w), state (B, N)) -> (activity, new_state, reference, confidence)``.

    ``NeuralInference(model, "portable")`` with tensors in and out (its buffers keep their
    names in the graph: ``w1_t`` and ``w3_t`` are the two weight products).

    Args:
        model: a fitted :class:`torchseq.neural.NeuralSeqSLAM`.
    """

    def __init__(self, model) -> None:
        if not model.fitted:
            raise ValueError("the model has not learnt a route yet (fit it first)")
        if getattr(model.config, "ring_velocity", "fixed") != "fixed":
            raise ExportError(f"ring_velocity={model.config.ring_velocity!r} has no ONNX form "
                              "(the graph steps the fixed ring): export a model with "
                              "ring_velocity='fixed'")
        super().__init__(model, "portable")
        self.input_size = tuple(model.config.input_size)

    def forward(self, frames: torch.Tensor, state: torch.Tensor):
        """One step.

        Args:
            frames: ``(B, h, w)`` float grey at the input size, 0..255 (not normalised).
            state: ``(B, N)`` previous activity (zeros at the start).

        Returns:
            ``activity (B, N)``, ``new_state (B, N)`` (the same values), ``reference (B,)``
            int64, ``confidence (B,)``.
        """
        if frames.dtype != self.w3_t.dtype:  # static: no Cast node in the graph
            frames = frames.to(self.w3_t.dtype)
        out, _ = super().forward(frames, RingState(state))
        return out.activity, out.activity.clone(), out.reference, out.confidence


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

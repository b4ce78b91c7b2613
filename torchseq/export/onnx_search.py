"""Float ONNX form of a model that decides with the unit search (``unit_search``).

``(frames, state, history, filled) -> (activity, new_state, reference, confidence,
new_history, new_filled)``: the float step of :class:`~torchseq.export.onnx_float.StreamingStep`
(the portable kernels) followed by :func:`~torchseq.layers.unit_search.unit_search_step` and
:func:`~torchseq.layers.unit_search.search_decide`, traced from the same functions the model
runs. :func:`~torchseq.export.onnx_float.build_float_onnx` refuses such a model (its graph
would decide with the ring); the integer format and NIR have no form of the search.
"""

from __future__ import annotations

import io
import warnings

import numpy as np
import onnx
import torch

from torchseq.export.onnx_float import OPSET, StreamingStep
from torchseq.layers import RingState
from torchseq.layers.ring import ring_step
from torchseq.layers.unit_search import SearchHistory, search_decide, unit_search_step

SEARCH_INPUTS = ("frames", "state", "history", "filled")
SEARCH_OUTPUTS = ("activity", "new_state", "reference", "confidence", "new_history",
                  "new_filled")


class SearchStreamingStep(StreamingStep):
    """The streaming step of a searching model, tensors in and out (see the module).

    Args:
        model: a fitted :class:`torchseq.neural.NeuralSeqSLAM` whose ``search`` is set.
    """

    def __init__(self, model) -> None:
        if getattr(model, "search", None) is None:
            raise ValueError("the model does not use the unit search: use build_float_onnx")
        super().__init__(model)
        search = model.search
        self.search_config = model.config
        self.register_buffer("lines", search.lines.clone())
        self.register_buffer("search_spans", search.spans.clone())
        self.input_names, self.output_names = SEARCH_INPUTS, SEARCH_OUTPUTS

    def initial_state(self, batch: int) -> tuple[torch.Tensor, ...]:
        """``(state, history, filled)`` of ``batch`` new streams."""
        n = self.shift.shape[0]
        return (torch.zeros(batch, n, dtype=self.w3_t.dtype),
                torch.zeros(batch, self.lines.shape[1], n, dtype=self.w3_t.dtype),
                torch.zeros(batch, dtype=torch.int64))

    def forward(self, frames: torch.Tensor, state: torch.Tensor, history: torch.Tensor,
                filled: torch.Tensor):
        """One step: ``(B, h, w)`` frames, ``(B, N)`` activity, ``(B, L, N)``, ``(B,)``."""
        cfg = self.search_config
        if frames.dtype != self.w3_t.dtype:
            frames = frames.to(self.w3_t.dtype)
        with torch.no_grad():
            e = self.evidence(frames)
            activity, _ = ring_step(e, RingState(state), self.shift.to(e.dtype), self.params)
            scores, new = unit_search_step(e, activity, SearchHistory(history, filled),
                                           self.lines, cfg.search_contrast,
                                           cfg.search_ring_weight, cfg.eps)
            reference, confidence = search_decide(scores, self.search_spans,
                                                  cfg.search_phases, cfg.uniqueness_window)
        return activity, activity.clone(), reference, confidence, new.evidence, new.filled


def build_search_onnx(model) -> onnx.ModelProto:
    """Trace :class:`SearchStreamingStep` (dynamic batch axis ``batch``)."""
    step = SearchStreamingStep(model).eval()
    h, w = step.input_size
    buf = io.BytesIO()
    axes = {name: {0: "batch"} for name in step.input_names + step.output_names}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(step, (torch.rand(2, h, w) * 255, *step.initial_state(2)), buf,
                          input_names=list(step.input_names),
                          output_names=list(step.output_names), dynamic_axes=axes,
                          opset_version=OPSET, dynamo=False)
    m = onnx.load_from_string(buf.getvalue())
    onnx.checker.check_model(m, full_check=True)
    return m


def run_search_onnx(sess, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stream ``(T, h, w)`` float32 frames through a search session from empty state.

    Returns:
        ``(reference (T,), confidence (T,))``.
    """
    shapes = {i.name: i.shape for i in sess.get_inputs()}
    n, length = shapes["state"][1], shapes["history"][1]
    state = [np.zeros((1, n), np.float32), np.zeros((1, length, n), np.float32),
             np.zeros(1, np.int64)]
    refs, confs = [], []
    for t in range(frames.shape[0]):
        _, new_state, ref, conf, hist, filled = sess.run(
            None, dict(zip(SEARCH_INPUTS, [frames[t:t + 1], *state])))
        state = [new_state, hist, filled]
        refs.append(ref)
        confs.append(conf)
    return np.concatenate(refs), np.concatenate(confs)


__all__ = ["SearchStreamingStep", "build_search_onnx", "run_search_onnx"]

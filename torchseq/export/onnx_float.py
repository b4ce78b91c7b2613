"""Float ONNX export of the Neural SeqSLAM streaming step, traced from its inference module.

:class:`StreamingStep` is ``model.inference("portable")`` (plain torch float32 kernels,
:mod:`torchseq.neural.inference`) with the state and the outputs as plain tensors, for
frames already at the model's input size. The stages are the layers' own functions; the
k-WTA takes its export branch inside :func:`torchseq.layers.kwta` (ONNX ``TopK``'s index
set, whose tie rule is the model's). :func:`export_float_onnx` writes it with a dynamic
batch axis using the TorchScript-based exporter (``dynamo=False``: the dynamo exporter needs
onnxscript).

An adaptive-velocity model (``ring_velocity="adaptive"``) steps its whole
:class:`~torchseq.neural.VelocityState` through the graph: inputs ``state`` (activity),
``velocity`` (float64), ``positions`` (float64) and ``count`` (int64), returned as
``new_state``, ``new_velocity``, ``new_positions``, ``new_count``. The graph is traced from
:func:`~torchseq.neural.velocity.adaptive_step` itself (its ``ceil(velocity_max)`` shift
products summed with per-stream weights, the slope and the clamp as tensor operations), so the eager
model and the graph run the same code.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch

from torchseq.export.errors import ExportError
from torchseq.export.int_onnx import run_step_session, write_onnx
from torchseq.layers import RingState
from torchseq.neural.inference import NeuralInference
from torchseq.neural.velocity import VelocityState

OPSET = 17
FIXED_INPUTS = ("frames", "state")
FIXED_OUTPUTS = ("activity", "new_state", "reference", "confidence")
VELOCITY_INPUTS = ("velocity", "positions", "count")  # after FIXED_INPUTS
VELOCITY_OUTPUTS = ("new_velocity", "new_positions", "new_count")  # after FIXED_OUTPUTS


class StreamingStep(NeuralInference):
    """``(frames (B, h, w), state (B, N)) -> (activity, new_state, reference, confidence)``.

    ``NeuralInference(model, "portable")`` with tensors in and out (its buffers keep their
    names in the graph: ``w1_t`` and ``w3_t`` are the two weight products). With
    ``ring_velocity="adaptive"`` the rest of the :class:`~torchseq.neural.VelocityState`
    comes in after ``state`` and goes out after ``confidence`` (:attr:`input_names`,
    :attr:`output_names`).

    Args:
        model: a fitted :class:`torchseq.neural.NeuralSeqSLAM`.
    """

    def __init__(self, model) -> None:
        if not model.fitted:
            raise ValueError("the model has not learnt a route yet (fit it first)")
        velocity = getattr(model.config, "ring_velocity", "fixed")
        if velocity not in ("fixed", "adaptive"):
            raise ExportError(f"ring_velocity={velocity!r} has no ONNX form")
        super().__init__(model, "portable")
        self.input_size = tuple(model.config.input_size)
        adaptive = self.tracker is not None
        self.input_names = FIXED_INPUTS + (VELOCITY_INPUTS if adaptive else ())
        self.output_names = FIXED_OUTPUTS + (VELOCITY_OUTPUTS if adaptive else ())

    def initial_state(self, batch: int) -> tuple[torch.Tensor, ...]:
        """The state inputs of ``batch`` new streams (after ``frames``), as tensors."""
        zeros = torch.zeros(batch, self.shift.shape[0], dtype=self.w3_t.dtype)
        if self.tracker is None:
            return (zeros,)
        return tuple(self.tracker.initial(zeros))

    def forward(self, frames: torch.Tensor, state: torch.Tensor,
                velocity: torch.Tensor | None = None, positions: torch.Tensor | None = None,
                count: torch.Tensor | None = None):
        """One step.

        Args:
            frames: ``(B, h, w)`` float grey at the input size, 0..255 (not normalised).
            state: ``(B, N)`` previous activity (zeros at the start).
            velocity: adaptive models only: ``(B,)`` float64 speed estimate (1 at the start).
            positions: adaptive models only: ``(B, K)`` float64 decision window (zeros).
            count: adaptive models only: ``(B,)`` int64 frames seen (0).

        Returns:
            ``activity (B, N)``, ``new_state (B, N)`` (the same values), ``reference (B,)``
            int64, ``confidence (B,)``; adaptive models then ``new_velocity (B,)``,
            ``new_positions (B, K)``, ``new_count (B,)``.

        Raises:
            ExportError: the velocity state is missing on an adaptive model, or given to a
                fixed one.
        """
        if frames.dtype != self.w3_t.dtype:  # static: no Cast node in the graph
            frames = frames.to(self.w3_t.dtype)
        rest = (velocity, positions, count)
        if self.tracker is None:
            if any(x is not None for x in rest):
                raise ExportError("a fixed-ring model steps the activity only (no velocity "
                                  "state)")
            out, _ = super().forward(frames, RingState(state))
            return out.activity, out.activity.clone(), out.reference, out.confidence
        if any(x is None for x in rest):
            raise ExportError("an adaptive-velocity model steps with state, velocity, "
                              "positions and count")
        out, new = super().forward(frames, VelocityState(state, *rest))
        return (out.activity, out.activity.clone(), out.reference, out.confidence,
                new.velocity, new.positions, new.count)


def build_float_onnx(model) -> onnx.ModelProto:
    """Trace :class:`StreamingStep` into an ONNX model (dynamic batch axis ``batch``)."""
    step = StreamingStep(model).eval()
    h, w = step.input_size
    frames = torch.rand(2, h, w) * 255
    buf = io.BytesIO()
    axes = {name: {0: "batch"} for name in step.input_names + step.output_names}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(step, (frames, *step.initial_state(2)), buf,
                          input_names=list(step.input_names),
                          output_names=list(step.output_names),
                          dynamic_axes=axes, opset_version=OPSET, dynamo=False)
    m = onnx.load_from_string(buf.getvalue())
    onnx.checker.check_model(m, full_check=True)
    return m


def export_float_onnx(model, path: str | Path) -> int:
    """Write the float streaming step to ``path`` (atomically); returns its size in bytes."""
    return write_onnx(build_float_onnx(model), path)


def run_float_onnx(sess, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stream ``(T, h, w)`` float32 frames through a float session, feeding the state back.

    Adaptive-velocity graphs (a ``velocity`` input) run through :func:`run_velocity_onnx`.

    Returns:
        ``(reference (T,), confidence (T,), activity (T, N))``.
    """
    if "velocity" in [i.name for i in sess.get_inputs()]:
        return run_velocity_onnx(sess, frames)[:3]
    return run_step_session(sess, frames)


def run_velocity_onnx(sess, frames: np.ndarray):
    """Stream ``(T, h, w)`` float32 frames through an adaptive-velocity float session.

    The whole state (activity, velocity, positions, count) is fed back, from the start state
    of :meth:`~torchseq.neural.velocity.VelocityTracker.initial` (window read off the graph).

    Returns:
        ``(reference (T,), confidence (T,), activity (T, N), velocity (T,))``: ``velocity[t]``
        is the speed estimate after frame ``t`` (the one frame ``t + 1`` steps at).
    """
    inputs = {i.name: i for i in sess.get_inputs()}
    n_units, window = inputs["state"].shape[1], inputs["positions"].shape[1]
    state = [np.zeros((1, n_units), np.float32), np.ones(1), np.zeros((1, window)),
             np.zeros(1, np.int64)]
    names = FIXED_INPUTS[1:] + VELOCITY_INPUTS
    refs, confs, acts, vels = [], [], [], []
    for t in range(frames.shape[0]):
        act, new_state, ref, conf, *rest = sess.run(
            None, {"frames": frames[t:t + 1], **dict(zip(names, state))})
        state = [new_state, *rest]
        refs.append(ref)
        confs.append(conf)
        acts.append(act)
        vels.append(rest[0])
    return (np.concatenate(refs), np.concatenate(confs), np.concatenate(acts),
            np.concatenate(vels))

"""The integer ONNX graph: :class:`~torchseq.export.int_step.IntegerStepModule` exported.

The graph is not written by hand: it is ``torch.onnx.export`` of the one definition of the
integer step, whose export branches (the two products as ``MatMulInteger``, ``isqrt`` bit by
bit) live inside its stage functions, :mod:`torchseq.export.int_functional`. Every tensor in
the step is an integer.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import onnx
import torch

from torchseq.atomic import atomic_path
from torchseq.export.int_format import IntegerModel
from torchseq.export.int_runtime import MEMORY_BUDGET, check_dense_budget
from torchseq.export.int_step import IntegerStepModule
from torchseq.export.int_velocity import VelocityStepModule, initial_velocity_state

OPSET = 17
IR_VERSION = 8  # what onnxruntime >= 1.15 reads


class _StepGraph(torch.nn.Module):
    """The module's step with the graph's four outputs (the state output repeats activity)."""

    def __init__(self, model: IntegerModel) -> None:
        super().__init__()
        self.step = IntegerStepModule(model).eval()

    def forward(self, frames, state):
        act, ref, conf = self.step(frames, state)
        return act, act, ref, conf


class _VelocityGraph(torch.nn.Module):
    """The adaptive ring's step (format version 3) with the state outputs after the four."""

    def __init__(self, model: IntegerModel) -> None:
        super().__init__()
        self.step = VelocityStepModule(model).eval()

    def forward(self, frames, state, velocity, positions, count):
        act, ref, conf, v, pos, n = self.step(frames, state, velocity, positions, count)
        return act, act, ref, conf, v, pos, n


VELOCITY_INPUTS = ("velocity", "positions", "count")
VELOCITY_OUTPUTS = ("new_velocity", "new_positions", "new_count")


def build_integer_onnx(model: IntegerModel,
                       memory_budget: int = MEMORY_BUDGET) -> onnx.ModelProto:
    """Export the integer step (:class:`IntegerStepModule`) as an ONNX model.

    The graph is ``torch.onnx.export`` of the one definition: every tensor in the step is an
    integer (uint8 frames, int32/int64 arithmetic, the 12-bit L1 product as four int8
    ``MatMulInteger`` products, the L3 product as one, ``TopK`` k-WTA on unique keys, ``Div``
    on non-negative int64 for rounding, ``isqrt`` bit by bit). The dense product weights take
    about ``14 * n_input * hidden + 2 * hidden * n_units`` bytes to build (and the one-hot
    cohort membership ``16 * n_units * n_cohorts``), refused past
    ``memory_budget`` (``IntegerFormatError``).

    Inputs: ``frames`` uint8 ``(B, h*pool_h, w*pool_w)``, ``state`` int32 ``(B, N)``.
    Outputs: ``activity`` int32 ``(B, N)``, ``new_state`` int32 ``(B, N)``, ``reference``
    int64 ``(B,)``, ``confidence`` int64 ``(B,)`` (on the ``2**-state_frac`` grid).

    A model with the adaptive ring (format version 3) exports
    :class:`~torchseq.export.int_velocity.VelocityStepModule`: three more inputs,
    ``velocity`` int64 ``(B,)`` (``2**-16`` grid, ``2**16`` at the start), ``positions``
    int64 ``(B, K)`` and ``count`` int64 ``(B,)`` (zeros at the start), fed back from the
    outputs ``new_velocity``, ``new_positions``, ``new_count`` after the four above.
    """
    p = model.check().params
    check_dense_budget("the integer ONNX graph", 14 * p["n_input"] * p["hidden"]
                       + 2 * p["hidden"] * p["n_units"] + 16 * p["n_units"] * p["n_cohorts"],
                       int(memory_budget))
    frames = torch.zeros(2, p["height"] * p["pool_h"], p["width"] * p["pool_w"],
                         dtype=torch.uint8)
    state = torch.zeros(2, p["n_units"], dtype=torch.int32)
    names = ["activity", "new_state", "reference", "confidence"]
    inputs, graph, args = ["frames", "state"], _StepGraph, (frames, state)
    if model.velocity is not None:
        start = initial_velocity_state(2, p["n_units"], model.velocity.window)
        args = (frames, state, *(torch.from_numpy(x) for x in start[1:]))
        inputs, graph = [*inputs, *VELOCITY_INPUTS], _VelocityGraph
        names += VELOCITY_OUTPUTS
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
        torch.onnx.export(graph(model), args, buf, dynamo=False,
                          opset_version=OPSET, input_names=inputs,
                          output_names=names, do_constant_folding=True,
                          dynamic_axes={k: {0: "batch"} for k in [*inputs, *names]})
    m = onnx.load_from_string(buf.getvalue())
    used = {i for node in m.graph.node for i in node.input}
    keep = [t for t in m.graph.initializer if t.name in used]  # the products' index lists
    del m.graph.initializer[:]
    m.graph.initializer.extend(keep)
    m.graph.name, m.producer_name, m.ir_version = ("torchseq_integer_step", "torchseq.export",
                                                   IR_VERSION)
    onnx.checker.check_model(m, full_check=True)
    return m


def write_onnx(model: onnx.ModelProto, path: str | Path) -> int:
    """Write an ONNX model atomically; returns the file size in bytes."""
    data = model.SerializeToString()
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return len(data)

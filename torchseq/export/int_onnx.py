"""The integer ONNX graph: the arithmetic of the integer format with ONNX integer operators.

Built node by node (``onnx.helper``) from an :class:`IntegerModel`; every tensor in the step
is an integer (uint8 frames, int32/int64 arithmetic, the 12-bit L1 product as four int8
``MatMulInteger`` products, ``TopK`` k-WTA, ``Div`` on non-negative int64 for rounding). Must
agree bit for bit with :class:`torchseq.export.int_runtime.IntegerRuntime`.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper

from torchseq.atomic import atomic_path
from torchseq.export.int_format import INPUT_ZSCORE, X_MAX, IntegerModel
from torchseq.export.int_runtime import ISQRT_BITS, MEMORY_BUDGET, check_dense_budget
from torchseq.export.int_step import IntegerStepModule

OPSET = 17
IR_VERSION = 8  # what onnxruntime >= 1.15 reads


class _Graph:
    """A tiny node builder: fresh names, constants as initialisers."""

    def __init__(self) -> None:
        self.nodes, self.inits, self._n = [], [], 0

    def name(self, hint: str) -> str:
        self._n += 1
        return f"{hint}_{self._n}"

    def const(self, value, dtype, hint: str = "c") -> str:
        name = self.name(hint)
        self.inits.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    def i64(self, value) -> str:
        return self.const(value, np.int64, "k")

    def op(self, op: str, *inputs: str, n_out: int = 1, **attrs):
        outs = [self.name(op.lower()) for _ in range(n_out)]
        self.nodes.append(helper.make_node(op, list(inputs), outs, **attrs))
        return outs[0] if n_out == 1 else outs

    def round_div(self, a: str, b: str) -> str:
        """``a / b`` rounded half away from zero (int64, ``b > 0``)."""
        two = self.i64(2)
        num = self.op("Add", self.op("Mul", self.op("Abs", a), two), b)
        q = self.op("Div", num, self.op("Mul", b, two))  # both >= 0: truncation = floor
        return self.op("Where", self.op("Less", a, self.i64(0)), self.op("Neg", q), q)

    def isqrt(self, v: str, bits: int = ISQRT_BITS) -> str:
        """``floor(sqrt(v))`` bit by bit (int64, ``0 <= v < 4**bits``, ``bits <= 31``).

        The result is the same for any ``bits`` that covers ``v``; fewer bits, fewer nodes.
        """
        r = self.op("Mul", v, self.i64(0))
        for bit in range(min(bits, ISQRT_BITS) - 1, -1, -1):
            cand = self.op("Add", r, self.i64(1 << bit))
            ok = self.op("LessOrEqual", self.op("Mul", cand, cand), v)
            r = self.op("Where", ok, cand, r)
        return r


def _dense_t(cols: np.ndarray, values: np.ndarray, n_in: int, dtype) -> np.ndarray:
    """``(n_in, rows)`` dense transposed weights from per-row index lists."""
    rows = np.repeat(np.arange(cols.shape[0]), cols.shape[1])
    w = np.zeros((n_in, cols.shape[0]), dtype)
    w[cols.astype(np.int64).ravel(), rows] = values.ravel()
    return w


def _l1_int8(g: _Graph, x: str, w: np.ndarray) -> str:
    """``x @ w`` exactly for 12-bit ``x`` and ``w`` with four int8 ``MatMulInteger`` products.

    Each operand splits into ``64 * hi + lo`` with ``lo = v mod 64`` in 0..63 and ``hi`` in
    -32..31, so ``x @ w = 4096 hh + 64 (hl + lh) + ll``; every partial sum stays inside
    int32 for ``fan_in <= 512`` (the format's bound), so the result is exact.
    """
    w_lo = np.mod(w, 64)
    w_hi = (w - w_lo) // 64
    wh, wl = g.const(w_hi, np.int8, "l1_w_hi"), g.const(w_lo, np.int8, "l1_w_lo")
    x_lo = g.op("Mod", x, g.i64(64), fmod=0)  # 0..63 (floor modulo)
    # hi + 32 in 0..63 as uint8 with zero point 32: the fast uint8 x int8 kernels
    x_hi = g.op("Add", g.op("Div", g.op("Sub", x, x_lo), g.i64(64)), g.i64(32))
    x_hi = g.op("Cast", x_hi, to=TensorProto.UINT8)
    x_lo = g.op("Cast", x_lo, to=TensorProto.UINT8)
    zp = g.const(32, np.uint8, "zero_point")
    hh = g.op("MatMulInteger", x_hi, wh, zp)
    mid = g.op("Add", g.op("MatMulInteger", x_hi, wl, zp), g.op("MatMulInteger", x_lo, wh))
    ll = g.op("MatMulInteger", x_lo, wl)
    c = np.int32
    return g.op("Add", g.op("Add", g.op("Mul", hh, g.const(4096, c)),
                              g.op("Mul", mid, g.const(64, c))), ll)


def _build_handmade(model: IntegerModel,
                       memory_budget: int = MEMORY_BUDGET) -> onnx.ModelProto:
    """Build the integer streaming step as an ONNX model.

    The two products are dense int8 ``MatMulInteger`` weights; their build takes about
    ``14 * n_input * hidden + 2 * hidden * n_units`` bytes, refused past ``memory_budget``
    (``IntegerFormatError``).

    Inputs: ``frames`` uint8 ``(B, h*pool_h, w*pool_w)``, ``state`` int32 ``(B, N)``.
    Outputs: ``activity`` int32 ``(B, N)``, ``new_state`` int32 ``(B, N)``, ``reference``
    int64 ``(B,)``, ``confidence`` int64 ``(B,)`` (on the ``2**-state_frac`` grid).
    """
    model.check()
    p, a = model.params, model.arrays
    check_dense_budget("the integer ONNX graph", 14 * p["n_input"] * p["hidden"]
                       + 2 * p["hidden"] * p["n_units"], int(memory_budget))
    g = _Graph()
    h, w, ph, pw = p["height"], p["width"], p["pool_h"], p["pool_w"]
    n_units, d_in = p["n_units"], p["n_input"]
    # input stage: pool pixel blocks, integer patch z-score
    pix = g.op("Cast", "frames", to=TensorProto.INT64)
    pix = g.op("ReduceSum", g.op("Reshape", pix, g.i64([-1, h, ph, w, pw])), g.i64([2, 4]),
               keepdims=0)  # (B, h, w)
    if p["input_mode"] == INPUT_ZSCORE:
        s = p["patch"]
        n = g.i64(s * s)
        blocks = g.op("Reshape", pix, g.i64([-1, h // s, s, w // s, s]))
        axes = g.i64([2, 4])
        total = g.op("ReduceSum", blocks, axes, keepdims=1)
        squares = g.op("ReduceSum", g.op("Mul", blocks, blocks), axes, keepdims=1)
        var = g.op("Sub", g.op("Mul", n, squares), g.op("Mul", total, total))
        peak = s * s * 255 * ph * pw // 2 + 1  # sqrt(V) <= n * 255 * ph * pw / 2
        root = g.isqrt(g.op("Mul", var, g.i64(1 << (2 * p["sqrt_frac"]))),
                       (peak << p["sqrt_frac"]).bit_length())
        dev = g.op("Sub", g.op("Mul", n, blocks), total)
        z = g.round_div(g.op("Mul", dev, g.i64(p["norm_const"])),
                        g.op("Max", root, g.i64(1)))
        z = g.op("Clip", z, g.i64(-X_MAX), g.i64(X_MAX))
        x = g.op("Where", g.op("Greater", var, g.i64(0)), z, g.i64(0))
    else:
        x = pix
    x = g.op("Reshape", x, g.i64([-1, d_in]))  # (B, D) int64, |x| <= 2047
    # L1 -> L2 (int32 sums) and the binary k-WTA with lowest-index ties
    hid = _l1_int8(g, x, _dense_t(a["l1.cols"], a["l1.values"], d_in, np.int32))  # (B, M)
    # binary k-WTA: TopK's index set is the k largest with ties to the lower index (the ONNX
    # TopK-11 tie rule, the format's rule), scattered into a 0/1 uint8 code.
    _, win = g.op("TopK", hid, g.i64([p["k"]]), n_out=2, axis=1, largest=1, sorted=0)
    w3 = g.const(_dense_t(a["l3.cols"], a["l3.values"], p["hidden"], np.int8), np.int8, "l3_w")
    zeros = g.op("ConstantOfShape", g.op("Shape", hid),
                 value=helper.make_tensor("zero", TensorProto.UINT8, [1], [0]))
    code = g.op("ScatterElements", zeros, win,
                g.op("Expand", g.const([[1]], np.uint8, "one"), g.op("Shape", win)), axis=1)
    e = g.op("Cast", g.op("MatMulInteger", code, w3), to=TensorProto.INT64)  # (B, N)
    e = g.round_div(g.op("Mul", e, g.const(a["l3.row_scale"], np.int64, "row_scale")),
                    g.i64(1 << p["e_shift"]))
    # cohort z-score times gain
    cohort = a["cohort"].astype(np.int64)
    members = np.eye(p["n_cohorts"], dtype=np.int64)[cohort]
    mem = g.const(members, np.int64, "cohorts")
    size = g.const(members.sum(0), np.int64, "cohort_size")
    idx = g.const(cohort, np.int64, "cohort_of_unit")
    total = g.op("MatMul", e, mem)  # (B, C)
    var = g.op("Sub", g.op("Mul", size, g.op("MatMul", g.op("Mul", e, e), mem)),
               g.op("Mul", total, total))
    root = g.isqrt(var, (int(members.sum(0).max()) * 32767).bit_length())  # |E| <= 32767
    dev = g.op("Sub", g.op("Mul", g.const(members.sum(0)[cohort], np.int64, "unit_size"), e),
               g.op("Gather", total, idx, axis=1))
    div = g.op("Mul", g.op("Max", g.op("Gather", root, idx, axis=1), g.i64(1)),
               g.i64(1 << p["gain_shift"]))
    gz = g.round_div(g.op("Mul", dev, g.i64(p["gain_const"])), div)
    gz = g.op("Where", g.op("Greater", g.op("Gather", var, idx, axis=1), g.i64(0)), gz,
              g.i64(0))
    if p["rectify"]:
        gz = g.op("Max", gz, g.i64(0))
    # the ring
    prev = g.op("Gather", g.op("Cast", "state", to=TensorProto.INT64),
                g.const(a["ring.cols"], np.int64, "ring_cols"), axis=1)  # (B, N, K)
    moved = g.op("ReduceSum", g.op("Mul", prev, g.const(a["ring.values"], np.int64, "ring")),
                 g.i64([2]), keepdims=0)
    act = g.op("Add", g.round_div(moved, g.i64(1 << p["ring_frac"])), gz)
    act = g.op("Clip", act, g.i64(-(2**31 - 1)), g.i64(2**31 - 1))
    g.nodes.append(helper.make_node("Cast", [act], ["activity"], to=TensorProto.INT32))
    g.nodes.append(helper.make_node("Identity", ["activity"], ["new_state"]))
    # decision
    unit = g.op("ArgMax", "activity", axis=1, keepdims=0, select_last_index=0)  # (B,)
    unit_col = g.op("Unsqueeze", unit, g.i64([1]))
    best = g.op("Cast", g.op("GatherElements", "activity", unit_col, axis=1), to=TensorProto.INT64)
    gap = g.op("Abs", g.op("Sub", g.const(np.arange(n_units)[None, :], np.int64, "units"),
                           unit_col))
    rival = g.op("Greater", gap, g.i64(p["window"]))
    floor = g.op("ReduceMin", "activity", axes=[1], keepdims=1)
    second = g.op("ReduceMax", g.op("Where", rival, "activity", floor), axes=[1], keepdims=1)
    conf = g.op("Sub", best, g.op("Cast", second, to=TensorProto.INT64))
    g.nodes.append(helper.make_node("Squeeze", [conf, g.i64([1])], ["confidence"]))
    g.nodes.append(helper.make_node("Gather", [g.const(a["unit_centre"], np.int64, "centre"),
                                               unit], ["reference"], axis=0))
    vi = helper.make_tensor_value_info
    graph = helper.make_graph(
        g.nodes, "torchseq_integer_step",
        [vi("frames", TensorProto.UINT8, ["batch", h * ph, w * pw]),
         vi("state", TensorProto.INT32, ["batch", n_units])],
        [vi("activity", TensorProto.INT32, ["batch", n_units]),
         vi("new_state", TensorProto.INT32, ["batch", n_units]),
         vi("reference", TensorProto.INT64, ["batch"]),
         vi("confidence", TensorProto.INT64, ["batch"])],
        g.inits)
    m = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                          producer_name="torchseq.export", ir_version=IR_VERSION)
    onnx.checker.check_model(m, full_check=True)
    return m


class _StepGraph(torch.nn.Module):
    """The module's step with the graph's four outputs (the state output repeats activity)."""

    def __init__(self, model: IntegerModel) -> None:
        super().__init__()
        self.step = IntegerStepModule(model).eval()

    def forward(self, frames, state):
        act, ref, conf = self.step(frames, state)
        return act, act, ref, conf


def build_integer_onnx(model: IntegerModel,
                       memory_budget: int = MEMORY_BUDGET) -> onnx.ModelProto:
    """Export the integer step (:class:`IntegerStepModule`) as an ONNX model.

    The graph is ``torch.onnx.export`` of the one definition: every tensor in the step is an
    integer (uint8 frames, int32/int64 arithmetic, the 12-bit L1 product as four int8
    ``MatMulInteger`` products, the L3 product as one, ``TopK`` k-WTA on unique keys, ``Div``
    on non-negative int64 for rounding, ``isqrt`` bit by bit). The dense product weights take
    about ``14 * n_input * hidden + 2 * hidden * n_units`` bytes to build, refused past
    ``memory_budget`` (``IntegerFormatError``).

    Inputs: ``frames`` uint8 ``(B, h*pool_h, w*pool_w)``, ``state`` int32 ``(B, N)``.
    Outputs: ``activity`` int32 ``(B, N)``, ``new_state`` int32 ``(B, N)``, ``reference``
    int64 ``(B,)``, ``confidence`` int64 ``(B,)`` (on the ``2**-state_frac`` grid).
    """
    p = model.check().params
    check_dense_budget("the integer ONNX graph", 14 * p["n_input"] * p["hidden"]
                       + 2 * p["hidden"] * p["n_units"], int(memory_budget))
    frames = torch.zeros(2, p["height"] * p["pool_h"], p["width"] * p["pool_w"],
                         dtype=torch.uint8)
    state = torch.zeros(2, p["n_units"], dtype=torch.int32)
    names = ["activity", "new_state", "reference", "confidence"]
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
        torch.onnx.export(_StepGraph(model), (frames, state), buf, dynamo=False,
                          opset_version=OPSET, input_names=["frames", "state"],
                          output_names=names, do_constant_folding=True,
                          dynamic_axes={k: {0: "batch"} for k in ["frames", "state", *names]})
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


def session(model: onnx.ModelProto | str | Path, threads: int = 1):
    """An onnxruntime CPU session (``threads`` intra-op threads, one inter-op thread)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    src = model.SerializeToString() if isinstance(model, onnx.ModelProto) else str(model)
    return ort.InferenceSession(src, opts, providers=["CPUExecutionProvider"])


def run_step_session(sess, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stream a traverse ``(T, H, W)`` through a step graph (float or integer), frame by frame.

    The state is fed back; its dtype (int32 or float32) is read off the graph.

    Returns:
        ``(reference (T,), confidence (T,), activity (T, N))``.
    """
    state_input = sess.get_inputs()[1]
    dtype = np.int32 if state_input.type == "tensor(int32)" else np.float32
    state = np.zeros((1, state_input.shape[1]), dtype)
    refs, confs, acts = [], [], []
    for t in range(frames.shape[0]):
        act, state, ref, conf = sess.run(None, {"frames": frames[t:t + 1], "state": state})
        refs.append(ref)
        confs.append(conf)
        acts.append(act)
    return np.concatenate(refs), np.concatenate(confs), np.concatenate(acts)


def run_integer_onnx(sess, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stream a ``(T, H, W)`` uint8 traverse through an integer session (int32 state).

    Returns:
        ``(reference (T,), confidence (T,), activity (T, N) int32)``.
    """
    return run_step_session(sess, frames)

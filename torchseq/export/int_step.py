"""The integer step of ``docs/reference/integer_format.md``, written once as a torch integer module.

:class:`IntegerStepModule` holds the stages of an :class:`IntegerModel` as int64 buffers and
computes one streaming step with integer tensor operations only (no float in the
arithmetic; the one float square root inside :func:`isqrt` is a starting guess that two
exact integer comparisons correct). Run eagerly it is the definition the runtimes are tested
against: :class:`~torchseq.export.int_runtime.IntegerRuntime` (``kernel="module"`` runs it,
``kernel="numpy"`` runs the NumPy kernels tested equal to it),
:class:`~torchseq.export.int_stream.StreamRuntime` and the integer ONNX graph.

The two sparse products read the stored index lists directly (gathers of ``(B, M, F)`` and
``(B, N, F)``), so memory follows the file's size, never a dense ``(M, D)`` matrix.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from torchseq.export.int_format import INPUT_ZSCORE, READOUT_INTERPOLATE, X_MAX, IntegerModel

INT32_MAX = 2**31 - 1
ISQRT_BITS = 31  # isqrt handles 0 <= v < 2**62; result bits 30..0
_UINT8, _INT64 = 2, 7  # ONNX TensorProto data types


def round_div(a: torch.Tensor, b: torch.Tensor | int) -> torch.Tensor:
    """``a / b`` rounded half away from zero: ``sign(a) * floor((2|a| + b) / 2b)``.

    Args:
        a: int64 tensor, ``|a| < 2**61``.
        b: int64 tensor broadcastable to ``a`` (or an int), ``0 < b < 2**62``.

    Returns:
        int64 tensor of ``a``'s broadcast shape (exact: ``2|a| + b < 2**63``).
    """
    q = _TruncDiv.apply(2 * a.abs() + b, torch.as_tensor(2 * b))
    return torch.where(a < 0, -q, q)


class _TruncDiv(torch.autograd.Function):
    """``a / b`` truncated, for non-negative int64 (so also the floor): one ONNX ``Div``.

    (``torch.div(..., rounding_mode="trunc")`` exports with two extra ``Cast`` nodes.)
    """

    @staticmethod
    def forward(ctx, a, b):  # noqa: ARG004
        return torch.div(a, b, rounding_mode="trunc")

    @staticmethod
    def symbolic(g, a, b):
        return g.op("Div", a, b)


class _CohortSums(torch.autograd.Function):
    """Per-cohort sums of ``(B, N)`` int64 -> ``(B, C)``, eager and in the graph.

    Eagerly ``scatter_add`` over the cohort index; in the ONNX graph one int64 ``MatMul``
    with the one-hot ``(N, C)`` membership (fewer nodes than the exported scatter).
    """

    @staticmethod
    def forward(ctx, e, cohort, stage):  # noqa: ARG004
        zeros = torch.zeros(e.shape[0], stage.n_cohorts, dtype=torch.int64, device=e.device)
        return zeros.scatter_add(1, cohort.expand(e.shape[0], -1), e)

    @staticmethod
    def symbolic(g, e, cohort, stage):  # noqa: ARG004
        members = np.eye(stage.n_cohorts, dtype=np.int64)[stage.cohort.astype(np.int64)]
        return g.op("MatMul", e, _const(g, members))


def isqrt(v: torch.Tensor, bits: int = ISQRT_BITS) -> torch.Tensor:
    """``floor(sqrt(v))`` of int64 ``0 <= v < 4**bits`` (``bits <= 31``), exactly.

    Eagerly: the float64 square root is within one of the answer for such ``v``; one integer
    step down and one up, with exact int64 squares, make it exact. In the ONNX graph (no
    float tensor in the integer step): bit by bit from bit ``bits - 1`` down,
    ``r = 0; c = r + 2**b; r = c if c*c <= v``, the same function.
    """
    if torch.onnx.is_in_onnx_export():
        r = v * 0  # one node (zeros_like exports as Shape + ConstantOfShape)
        for bit in range(min(bits, ISQRT_BITS) - 1, -1, -1):
            cand = r + (1 << bit)
            r = torch.where(cand * cand <= v, cand, r)
        return r
    r = torch.sqrt(v.to(torch.float64)).floor().to(torch.int64).clamp_max(INT32_MAX)
    r = r - (r * r > v).long()
    return r + ((r + 1) * (r + 1) <= v).long()


def within_unit(act: torch.Tensor, unit: torch.Tensor, spans: torch.Tensor) -> torch.Tensor:
    """The interpolating read-out (step 8): the frame within each winner's span, exactly.

    With ``a0, am, ap`` the winner's and its neighbours' activity, ``D = 2 a0 - am - ap``
    and the span ``[f, l)``, ``L = l - f``: ``reference = min(f + floor(L (a0 - am) / D),
    l - 1)`` when the winner has both neighbours and ``D > 0``, else ``f + floor(L / 2)``.
    This is the float read-out ``floor((f + l - 1) / 2 + x L + 1/2)`` with the parabola's
    vertex ``x = (am - ap) / (2 (am - 2 a0 + ap))`` as an exact rational. ``0 <= a0 - am <=
    D`` (``a0`` is the maximum) keeps the quotient in ``0..L`` and non-negative, and
    ``L (a0 - am) < 2**31 * 2**32`` fits int64.

    Args:
        act: ``(B, N)`` int32 activity.
        unit: ``(B,)`` int64 winner (first index of the maximum).
        spans: ``(N, 2)`` int64 first and one-past-last frame of each unit.

    Returns:
        ``(B,)`` int64 reference frame.
    """
    n = act.shape[1]

    def at(index: torch.Tensor) -> torch.Tensor:
        return act.gather(1, index.clamp(0, n - 1)[:, None])[:, 0].to(torch.int64)

    a0, am, ap = at(unit), at(unit - 1), at(unit + 1)
    den = 2 * a0 - am - ap
    inner = (unit > 0) & (unit < n - 1) & (den > 0)
    first, last = spans[unit, 0], spans[unit, 1]
    length = last - first
    num = torch.where(inner, length * (a0 - am), length)
    quot = _TruncDiv.apply(num, torch.where(inner, den, 2))  # non-negative: the floor
    return torch.minimum(first + quot, last - 1)


def _at_least(x: torch.Tensor, v: int) -> torch.Tensor:
    """``max(x, v)`` elementwise, exported as one ONNX ``Max``.

    ``clamp_min`` exports as a one-sided ``Clip``; with three of those (and a ``Gather`` for
    the confidence's ``squeeze``) the graph took 1.03x the hand-built graph's time per step
    at batch 1 in onnxruntime, 1.00x with ``Max`` and ``Squeeze``.
    """
    return torch.maximum(x, torch.tensor(v, dtype=x.dtype, device=x.device))


def _const(g, value: np.ndarray):
    # np.array, not np.ascontiguousarray (which makes a 0-d scalar 1-d)
    return g.op("Constant", value_t=torch.from_numpy(np.array(value, order="C")))


def _dense_t(cols: np.ndarray, values: np.ndarray, n_in: int, dtype) -> np.ndarray:
    """``(n_in, rows)`` dense transposed weights from per-row index lists (graph constants)."""
    rows = np.repeat(np.arange(cols.shape[0]), cols.shape[1])
    w = np.zeros((n_in, cols.shape[0]), dtype)
    w[cols.astype(np.int64).ravel(), rows] = values.ravel()
    return w


def kwta_code(hid: torch.Tensor, k: int) -> torch.Tensor:
    """Binary k-WTA of int64 ``(B, M)``: the ``k`` largest, ties to the lowest index.

    ``topk`` runs on the unique keys ``hid * M + (M - 1 - m)`` (exact: ``|hid| < 2**31``,
    ``M < 2**15``), so its unspecified tie order never matters.

    Returns:
        ``(B, M)`` int64 0/1 code with exactly ``k`` ones per row.
    """
    m = hid.shape[1]
    key = hid * m + torch.arange(m - 1, -1, -1, dtype=torch.int64, device=hid.device)
    win = key.topk(k, dim=1, sorted=False).indices
    return torch.zeros_like(hid).scatter_(1, win, 1)


def _l1_graph(g, x, stage):
    """Step 3 in the ONNX graph: ``x @ W1`` (int32) with four int8 ``MatMulInteger`` products.

    Each 12-bit operand splits into ``64 * hi + lo`` with ``lo = v mod 64`` in 0..63 and
    ``hi`` in -32..31, so ``x @ w = 4096 hh + 64 (hl + lh) + ll``; every partial sum stays
    inside int32 for ``fan_in <= 512`` (the format's bound), so the result is exact.
    """
    w = _dense_t(stage.cols, stage.values, stage.n_input, np.int32)  # (D, M)
    w_lo = np.mod(w, 64)
    wh, wl = _const(g, ((w - w_lo) // 64).astype(np.int8)), _const(g, w_lo.astype(np.int8))
    i64 = lambda v: _const(g, np.asarray(v, np.int64))  # noqa: E731
    x_lo = g.op("Mod", x, i64(64), fmod_i=0)  # 0..63 (floor modulo)
    # hi + 32 in 0..63 as uint8 with zero point 32: the fast uint8 x int8 kernels
    x_hi = g.op("Add", g.op("Div", g.op("Sub", x, x_lo), i64(64)), i64(32))
    x_hi = g.op("Cast", x_hi, to_i=_UINT8)
    x_lo = g.op("Cast", x_lo, to_i=_UINT8)
    zp = _const(g, np.asarray(32, np.uint8))
    hh = g.op("MatMulInteger", x_hi, wh, zp)
    mid = g.op("Add", g.op("MatMulInteger", x_hi, wl, zp), g.op("MatMulInteger", x_lo, wh))
    ll = g.op("MatMulInteger", x_lo, wl)
    i32 = lambda v: _const(g, np.asarray(v, np.int32))  # noqa: E731
    return g.op("Add", g.op("Add", g.op("Mul", hh, i32(4096)), g.op("Mul", mid, i32(64))), ll)


class _SparseCore(torch.autograd.Function):
    """Steps 3-5's integer sums: L1 activity ``x`` -> L1 product -> k-WTA -> L3 sums ``e``.

    Eagerly (the definition): gathers of the stored index lists and :func:`kwta_code`. In
    the ONNX graph: the L1 product as four int8 ``MatMulInteger`` products (int32 sums),
    ``TopK`` on those sums (ONNX ``TopK`` breaks ties by the lower index, the format's rule),
    the winners scattered into a uint8 code and one ``MatMulInteger`` with the int8 L3
    weights: the same integers without int64 copies of the ``(B, M)`` tensors.
    """

    @staticmethod
    def forward(ctx, x, l1_cols, l1_values, l3_cols, l3_values, k, model):  # noqa: ARG004
        hid = (x[:, l1_cols] * l1_values).sum(-1)  # (B, M), |hid| < 2**31
        code = kwta_code(hid, k)
        return (code[:, l3_cols] * l3_values).sum(-1)  # (B, N)

    @staticmethod
    def symbolic(g, x, l1_cols, l1_values, l3_cols, l3_values, k, model):  # noqa: ARG004
        hid = _l1_graph(g, x, model.l1)  # (B, M) int32
        _, win = g.op("TopK", hid, _const(g, np.asarray([k], np.int64)), outputs=2, axis_i=1,
                      largest_i=1, sorted_i=0)
        zeros = g.op("ConstantOfShape", g.op("Shape", hid),
                     value_t=torch.zeros(1, dtype=torch.uint8))
        ones = g.op("Expand", _const(g, np.ones((1, 1), np.uint8)), g.op("Shape", win))
        code = g.op("ScatterElements", zeros, win, ones, axis_i=1)
        w3 = _const(g, _dense_t(model.l3.cols, model.l3.values, model.l3.hidden, np.int8))
        return g.op("Cast", g.op("MatMulInteger", code, w3), to_i=_INT64)


class IntegerStepModule(nn.Module):
    """One integer step of an :class:`IntegerModel` (docs/reference/integer_format.md, steps 1-8).

    Args:
        model: a checked :class:`IntegerModel` (its stages are validated when built).
    """

    def __init__(self, model: IntegerModel) -> None:
        super().__init__()
        if not isinstance(model, IntegerModel):
            raise TypeError(f"IntegerStepModule takes an IntegerModel, got {type(model).__name__}")
        p, a = model.params, model.arrays
        self.params = p
        self.stages = model  # the graph's dense weights are built from its index lists

        def buf(name: str, value) -> None:
            self.register_buffer(name, torch.from_numpy(np.array(value, dtype=np.int64)))

        buf("l1_cols", a["l1.cols"])
        buf("l1_values", a["l1.values"])
        buf("l3_cols", a["l3.cols"])
        buf("l3_values", a["l3.values"])
        buf("row_scale", a["l3.row_scale"])
        buf("cohort", a["cohort"])
        buf("cohort_size", np.bincount(a["cohort"], minlength=p["n_cohorts"]))
        # sqrt(V_c) <= n_c * 32767: the bits of the cohort isqrt
        self.cohort_bits = (int(np.bincount(a["cohort"]).max()) * 32767).bit_length()
        buf("ring_cols", a["ring.cols"])
        buf("ring_values", a["ring.values"])
        buf("unit_centre", a["unit_centre"])
        buf("unit_to_ref", a["unit_to_ref"])
        buf("units", np.arange(p["n_units"]))

    def input_stage(self, frames: torch.Tensor) -> torch.Tensor:
        """Steps 1-2: uint8 ``(B, h*ph, w*pw)`` -> L1 activity ``x`` ``(B, D)`` int64."""
        p = self.params
        h, w, ph, pw = p["height"], p["width"], p["pool_h"], p["pool_w"]
        pix = frames.to(torch.int64).reshape(-1, h, ph, w, pw).sum((2, 4))  # (B, h, w)
        if p["input_mode"] != INPUT_ZSCORE:
            return pix.reshape(-1, h * w)
        s = p["patch"]
        n = s * s
        blocks = pix.reshape(-1, h // s, s, w // s, s)
        total = blocks.sum((2, 4), keepdim=True)
        var = n * (blocks * blocks).sum((2, 4), keepdim=True) - total * total  # V >= 0
        peak = n * 255 * ph * pw // 2 + 1  # sqrt(V) <= n * 255 * ph * pw / 2
        root = isqrt(var * (1 << (2 * p["sqrt_frac"])), (peak << p["sqrt_frac"]).bit_length())
        z = round_div((n * blocks - total) * p["norm_const"], _at_least(root, 1))
        x = torch.where(var > 0, z.clamp(-X_MAX, X_MAX), 0)
        return x.reshape(-1, h * w)

    def evidence(self, x: torch.Tensor) -> torch.Tensor:
        """Steps 3-5: L1 activity ``(B, D)`` -> rescaled evidence ``E`` ``(B, N)`` int64.

        The L1 sums, the k-WTA code and the L3 sums ``e`` (:class:`_SparseCore`), then
        ``E = round_shift(e * row_scale, e_shift)``.
        """
        e = _SparseCore.apply(x, self.l1_cols, self.l1_values, self.l3_cols, self.l3_values,
                              self.params["k"], self.stages)
        return round_div(e * self.row_scale, 1 << self.params["e_shift"])

    def gain_z(self, e: torch.Tensor) -> torch.Tensor:
        """Step 6: cohort z-score times gain on the activity grid (rectified), ``(B, N)``."""
        p = self.params
        total = _CohortSums.apply(e, self.cohort, self.stages.cohort)  # (B, C)
        squares = _CohortSums.apply(e * e, self.cohort, self.stages.cohort)
        var = self.cohort_size * squares - total * total
        root = isqrt(var, self.cohort_bits)[:, self.cohort]
        dev = self.cohort_size[self.cohort] * e - total[:, self.cohort]
        g = round_div(dev * p["gain_const"], _at_least(root, 1) * (1 << p["gain_shift"]))
        g = torch.where(var[:, self.cohort] > 0, g, 0)
        return _at_least(g, 0) if p["rectify"] else g

    def drive(self, frames: torch.Tensor) -> torch.Tensor:
        """Steps 1-6, the state-free part: uint8 frames -> ``g`` ``(B, N)`` int64."""
        return self.gain_z(self.evidence(self.input_stage(frames)))

    def ring(self, state: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """Step 7: previous int32 state and ``g`` -> new activity ``(B, N)`` int32."""
        moved = (state.to(torch.int64)[:, self.ring_cols] * self.ring_values).sum(-1)
        a = round_div(moved, 1 << self.params["ring_frac"]) + g
        return a.clamp(-INT32_MAX, INT32_MAX).to(torch.int32)

    def decide(self, act: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Step 8: activity ``(B, N)`` int32 -> ``(reference, confidence)`` ``(B,)`` int64."""
        unit = act.argmax(1)  # the first index of the largest
        best = act.gather(1, unit[:, None]).to(torch.int64)
        rival = (self.units[None, :] - unit[:, None]).abs() > self.params["window"]
        floor = act.min(1, keepdim=True).values
        second = torch.where(rival, act, floor).max(1, keepdim=True).values.to(torch.int64)
        if self.params["readout"] == READOUT_INTERPOLATE:
            return within_unit(act, unit, self.unit_to_ref), (best - second).squeeze(1)
        return self.unit_centre[unit], (best - second).squeeze(1)

    def forward(self, frames: torch.Tensor,
                state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step.

        Args:
            frames: ``(B, h*pool_h, w*pool_w)`` uint8.
            state: ``(B, N)`` int32 previous activity (zeros at a stream's start).

        Returns:
            ``(activity (B, N) int32 (= the new state), reference (B,) int64,
            confidence (B,) int64)``.
        """
        act = self.ring(state, self.drive(frames))
        return (act, *self.decide(act))

"""The integer step, one function per stage: the torch definition and a ``kernel=`` choice.

``docs/reference/integer_format.md`` ("One step") defines the step's integers; each stage is
one function here, as the float side's stages are in :mod:`torchseq.layers.functional`:

=========================  =========================================================
:func:`input_stage`        steps 1-2: pooling and the integer patch z-score
:func:`l1_sums`            step 3: the L1 -> L2 masked sparse product
:func:`kwta_code`          step 4: the binary k-WTA (ties to the lowest index)
:func:`l3_sums`            step 5: the L2 -> L3 masked sparse product of the code
:func:`rescale`            step 5: ``E = round_shift(e * row_scale, e_shift)``
:func:`cohort_gain`        step 6: cohort z-score times the gain
:func:`ring_step`          step 7: the fixed-point ring
:func:`velocity_ring`      step 7v: the adaptive ring (format version 3)
:func:`decide`             step 8: the read-out (winner, margin, frame in its span)
:func:`velocity_update`    step 9: the speed estimate (format version 3)
=========================  =========================================================

``kernel="torch"`` (the default) is the definition: integer tensor operations only (the one
float square root inside :func:`isqrt` is a starting guess that two exact comparisons
correct), with the export branches of the integer ONNX graph (the two products as
``MatMulInteger`` in :class:`_SparseCore`, ``isqrt`` bit by bit); the graph is traced from
:class:`~torchseq.export.int_step.IntegerStepModule`, which calls these functions.
``kernel="numpy"`` runs the private NumPy kernels of :mod:`torchseq.export.int_kernels`,
tested bit-exact with the definition. A stage takes and returns torch tensors or NumPy arrays;
the kernel converts at its edges when it is handed the other kind (the runtimes never are).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from torchseq.export import int_kernels
from torchseq.export.int_stages import (
    INPUT_ZSCORE,
    INT32_MAX,
    READOUT_INTERPOLATE,
    SLOPE_LIMIT,
    VEL_ONE,
    X_MAX,
    CohortStage,
    IntegerInputError,
    VelocityStage,
    velocity_den,
)

KERNELS = ("torch", "numpy")
ISQRT_BITS = 31  # isqrt handles 0 <= v < 2**62; result bits 30..0
_UINT8, _INT64 = 2, 7  # ONNX TensorProto data types


def _run(kernel: str, torch_fn: Callable, numpy_fn: Callable, *args, **kwargs):
    """Run ``torch_fn`` or ``numpy_fn`` (by ``kernel``), converting arrays of the other kind.

    Arguments of the kind the kernel computes on pass as they are; when any is of the other
    kind, those are converted and so is the result (a tensor or a tuple of them), so a stage
    returns what it was given.
    """
    if kernel == "numpy":
        fn, other = numpy_fn, torch.Tensor
        here, back = (lambda t: t.detach().cpu().numpy()), _to_torch
    elif kernel == "torch":
        fn, other = torch_fn, np.ndarray
        here, back = _to_torch, (lambda t: t.detach().cpu().numpy())
    else:
        raise IntegerInputError(f"kernel must be one of {KERNELS}, got {kernel!r}")
    if not any(isinstance(a, other) for a in args):
        return fn(*args, **kwargs)
    out = fn(*(here(a) if isinstance(a, other) else a for a in args), **kwargs)
    return tuple(back(o) for o in out) if isinstance(out, tuple) else back(out)


def _to_torch(a: np.ndarray) -> torch.Tensor:
    a = np.asarray(a)
    if a.dtype.kind == "u" and a.dtype != np.uint8:
        a = a.astype(np.int64)  # torch's unsigned integer tensors lack most operations
    return torch.from_numpy(np.array(a))  # a writable copy (file sections are read-only)


# ---- the stages ----------------------------------------------------------------------------


def input_stage(frames, p: dict, kernel: str = "torch"):
    """Steps 1-2: uint8 frames ``(B, h*ph, w*pw)`` -> L1 activity ``x`` ``(B, h*w)``.

    Args:
        frames: ``(B, h * pool_h, w * pool_w)`` uint8.
        p: the model's parameters (``IntegerModel.params``).
        kernel: ``"torch"`` (int64 result) or ``"numpy"`` (int32).
    """
    return _run(kernel, _input_stage_torch, int_kernels.input_stage, frames, p)


def l1_sums(x, cols, values, kernel: str = "torch"):
    """Step 3: ``hid[b, m] = sum_f values[m, f] * x[b, cols[m, f]]`` ``(B, M)`` (exact).

    Args:
        x: ``(B, D)`` L1 activity.
        cols: ``(M, F)`` the stored index lists.
        values: ``(M, F)`` the 12-bit weights.
        kernel: ``"torch"`` (int64) or ``"numpy"`` (int32).
    """
    return _run(kernel, _l1_sums_torch, int_kernels.l1_sums, x, cols, values)


def kwta_code(hid, k: int, kernel: str = "torch"):
    """Step 4: the binary k-WTA of ``(B, M)`` integers: the ``k`` largest, ties to the lowest index.

    Returns:
        ``(B, M)`` 0/1 code with exactly ``k`` ones per row: int64 (``"torch"``) or bool
        (``"numpy"``).
    """
    return _run(kernel, _kwta_code_torch, int_kernels.kwta_code, hid, k)


def l3_sums(code, cols, values, kernel: str = "torch", w_t=None):
    """Step 5: L3 sums ``e[b, n] = sum_f values[n, f] * code[b, cols[n, f]]`` ``(B, N)`` int64.

    Args:
        code: ``(B, M)`` 0/1 k-WTA code (the same number of ones in every row).
        cols: ``(N, F)`` the stored index lists.
        values: ``(N, F)`` the int8 weights.
        kernel: ``"torch"`` (gathers of the index lists) or ``"numpy"`` (the sum of the
            winners' rows of a dense ``(M, N)`` matrix).
        w_t: the ``"numpy"`` kernel's dense ``(M, N)`` int32 matrix (built from ``cols``
            and ``values`` when not given).
    """
    if kernel == "numpy" and w_t is None:
        w_t = int_kernels.dense_t(np.asarray(cols), np.asarray(values), code.shape[1])
    return _run(kernel, _l3_sums_torch, lambda c, *_: int_kernels.l3_sums(c, w_t),
                code, cols, values)


def rescale(e, row_scale, e_shift: int, kernel: str = "torch"):
    """Step 5: ``E = round_shift(e * row_scale, e_shift)`` ``(B, N)`` int64."""
    return _run(kernel, _rescale_torch, int_kernels.rescale, e, row_scale, e_shift)


def cohort_gain(e, cohort, cohort_size, stage: CohortStage, kernel: str = "torch",
                members=None):
    """Step 6: the cohort z-score of ``E`` times the gain, on the activity grid (rectified).

    Args:
        e: ``(B, N)`` int64 evidence.
        cohort: ``(N,)`` int64 cohort of each unit.
        cohort_size: ``(C,)`` int64 units per cohort.
        stage: the :class:`~torchseq.export.int_stages.CohortStage` (gain, shift, rectify).
        kernel: ``"torch"`` or ``"numpy"``.
        members: the ``"numpy"`` kernel's one-hot ``(N, C)`` int64 membership (built from
            ``cohort`` when not given).

    Returns:
        ``(B, N)`` int64.
    """
    if kernel == "numpy" and members is None:
        members = np.eye(stage.n_cohorts, dtype=np.int64)[np.asarray(cohort, np.int64)]
    return _run(kernel, _cohort_gain_torch,
                lambda e_, c_, n_, s: int_kernels.cohort_gain(e_, c_, n_, members, s.gain_const,
                                                              s.gain_shift, s.rectify),
                e, cohort, cohort_size, stage)


def ring_step(state, g, cols, values, ring_frac: int, kernel: str = "torch"):
    """Step 7: ``a = clamp32(round_shift(sum_j values[i, j] state[cols[i, j]], ring_frac) + g)``.

    Args:
        state: ``(B, N)`` int32 previous activity.
        g: ``(B, N)`` int64 drive of this frame (:func:`cohort_gain`).
        cols: ``(N, W)`` the ring's row lists.
        values: ``(N, W)`` ``decay * shift`` at ``cols``.
        ring_frac: fractional bits of ``values``.
        kernel: ``"torch"`` or ``"numpy"``.

    Returns:
        ``(B, N)`` int32 new activity (the new state).
    """
    return _run(kernel, _ring_step_torch, int_kernels.ring_step, state, g, cols, values,
                ring_frac)


def velocity_ring(state, g, speed, cols, shift, ring_frac: int, stage: VelocityStage,
                  kernel: str = "torch"):
    """Step 7v: the adaptive ring, int32 ``state`` ``(B, N)``, ``g`` and ``speed`` ``(B,)``.

    ``P_0 = state``, ``P_k = clamp32(round_shift(sum_j shift[u, j] P_{k-1}[cols[u, j]],
    ring_frac))`` for ``k = 1..top``; ``n = speed >> 16``, ``f = speed - n 2**16``;
    ``M = round_shift((2**16 - f) P_n + f P_{n+1}, 16)`` (``P_{top+1} = 0``);
    ``a = clamp32(round_shift(decay_const M, ring_frac) + g)``. The ``"numpy"`` kernel
    computes only the powers the batch needs (the others have weight 0).

    Returns:
        ``(B, N)`` int32.
    """
    return _run(kernel, _velocity_ring_torch, int_kernels.velocity_ring, state, g, speed,
                cols, shift, ring_frac, stage)


def velocity_update(speed, positions, count, reference, stage: VelocityStage,
                    kernel: str = "torch"):
    """Step 9: push the decisions ``reference`` ``(B,)`` and re-estimate the speed.

    See :func:`_velocity_update_torch` for the integers.

    Returns:
        ``(speed (B,), positions (B, K), count (B,))`` int64.
    """
    return _run(kernel, _velocity_update_torch, int_kernels.velocity_update, speed, positions,
                count, reference, stage)


def decide(act, unit_centre, unit_to_ref, window: int, readout: int, kernel: str = "torch",
           units=None):
    """Step 8: activity ``(B, N)`` int32 -> ``(reference (B,), confidence (B,))`` int64.

    The winner is the first index of the largest activity; the confidence is its margin over
    the best unit more than ``window`` units away; the reference is the winner's
    ``unit_centre``, or with ``readout = READOUT_INTERPOLATE`` the frame within its span
    ``unit_to_ref`` read from its neighbours (:func:`within_unit`).

    Args:
        act: ``(B, N)`` int32.
        unit_centre: ``(N,)`` reference frame of each unit.
        unit_to_ref: ``(N, 2)`` first and one-past-last reference frame of each unit.
        window: units around the winner the margin ignores.
        readout: the read-out parameter.
        kernel: ``"torch"`` or ``"numpy"``.
        units: ``arange(N)`` int64 (the torch kernel's; a buffer of the module).
    """
    return _run(kernel, _decide_torch,
                lambda a, c, s, w, r, _: int_kernels.decide(a, c, s, w, r),
                act, unit_centre, unit_to_ref, window, readout, units)


# ---- the torch definition ------------------------------------------------------------------


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


def _kwta_code_torch(hid: torch.Tensor, k: int) -> torch.Tensor:
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

    Eagerly (the definition): the torch bodies of :func:`l1_sums`, :func:`kwta_code` and
    :func:`l3_sums` (gathers of the stored index lists). In the ONNX graph: the L1 product
    as four int8 ``MatMulInteger`` products (int32 sums), ``TopK`` on those sums (ONNX
    ``TopK`` breaks ties by the lower index, the format's rule), the winners scattered into
    a uint8 code and one ``MatMulInteger`` with the int8 L3 weights: the same integers
    without int64 copies of the ``(B, M)`` tensors.
    """

    @staticmethod
    def forward(ctx, x, l1_cols, l1_values, l3_cols, l3_values, k, model):  # noqa: ARG004
        code = _kwta_code_torch(_l1_sums_torch(x, l1_cols, l1_values), k)
        return _l3_sums_torch(code, l3_cols, l3_values)

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





def _input_stage_torch(frames: torch.Tensor, p: dict) -> torch.Tensor:
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


def _l1_sums_torch(x: torch.Tensor, cols: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    return (x[:, cols] * values).sum(-1)  # (B, M), |hid| < 2**31


def _l3_sums_torch(code: torch.Tensor, cols: torch.Tensor,
                   values: torch.Tensor) -> torch.Tensor:
    return (code[:, cols] * values).sum(-1)  # (B, N)


def _rescale_torch(e: torch.Tensor, row_scale: torch.Tensor, e_shift: int) -> torch.Tensor:
    return round_div(e * row_scale, 1 << e_shift)


def sparse_evidence(x: torch.Tensor, l1_cols: torch.Tensor, l1_values: torch.Tensor,
                    l3_cols: torch.Tensor, l3_values: torch.Tensor, k: int,
                    model) -> torch.Tensor:
    """Steps 3-5's sums in torch: :func:`l1_sums`, :func:`kwta_code`, :func:`l3_sums`.

    Eagerly the three stages' torch bodies; in the ONNX graph the fused integer form of
    :class:`_SparseCore` (``model`` is the :class:`IntegerModel`, for the graph's dense
    weights).

    Returns:
        ``(B, N)`` int64 L3 sums ``e``.
    """
    return _SparseCore.apply(x, l1_cols, l1_values, l3_cols, l3_values, k, model)


def _cohort_gain_torch(e: torch.Tensor, cohort: torch.Tensor, size: torch.Tensor,
                       stage: CohortStage) -> torch.Tensor:
    total = _CohortSums.apply(e, cohort, stage)  # (B, C)
    squares = _CohortSums.apply(e * e, cohort, stage)
    var = size * squares - total * total
    # sqrt(V_c) <= n_c * 32767: the bits of the cohort isqrt
    bits = (int(np.bincount(stage.cohort).max()) * 32767).bit_length()
    root = isqrt(var, bits)[:, cohort]
    dev = size[cohort] * e - total[:, cohort]
    g = round_div(dev * stage.gain_const, _at_least(root, 1) * (1 << stage.gain_shift))
    g = torch.where(var[:, cohort] > 0, g, 0)
    return _at_least(g, 0) if stage.rectify else g


def _ring_step_torch(state: torch.Tensor, g: torch.Tensor, cols: torch.Tensor,
                     values: torch.Tensor, ring_frac: int) -> torch.Tensor:
    moved = (state.to(torch.int64)[:, cols] * values).sum(-1)
    a = round_div(moved, 1 << ring_frac) + g
    return a.clamp(-INT32_MAX, INT32_MAX).to(torch.int32)


def _decide_torch(act: torch.Tensor, unit_centre: torch.Tensor, unit_to_ref: torch.Tensor,
                  window: int, readout: int, units: torch.Tensor | None):
    if units is None:
        units = torch.arange(act.shape[1], device=act.device)
    unit = act.argmax(1)  # the first index of the largest
    best = act.gather(1, unit[:, None]).to(torch.int64)
    rival = (units[None, :] - unit[:, None]).abs() > window
    floor = act.min(1, keepdim=True).values
    second = torch.where(rival, act, floor).max(1, keepdim=True).values.to(torch.int64)
    if readout == READOUT_INTERPOLATE:
        return within_unit(act, unit, unit_to_ref), (best - second).squeeze(1)
    return unit_centre[unit], (best - second).squeeze(1)


def _velocity_ring_torch(state: torch.Tensor, g: torch.Tensor, speed: torch.Tensor,
                  cols: torch.Tensor, shift: torch.Tensor, ring_frac: int,
                  stage: VelocityStage) -> torch.Tensor:
    """Step 7v: int32 ``state`` ``(B, N)``, ``g`` ``(B, N)`` and ``speed`` ``(B,)`` -> activity.

    ``P_0 = state``, ``P_k = clamp32(round_shift(sum_j shift[u, j] P_{k-1}[cols[u, j]],
    ring_frac))`` for ``k = 1..top``; ``n = speed >> 16``, ``f = speed - n 2**16``;
    ``M = round_shift((2**16 - f) P_n + f P_{n+1}, 16)`` (``P_{top+1} = 0``, weight ``f = 0``);
    ``a = clamp32(round_shift(decay_const M, ring_frac) + g)``.

    Returns:
        ``(B, N)`` int32.
    """
    one = 1 << ring_frac
    n = torch.div(speed, VEL_ONE, rounding_mode="floor")[:, None]  # (B, 1), speed >= 0
    f = speed[:, None] - n * VEL_ONE
    power = state.to(torch.int64)
    mixed = torch.where(n == 0, VEL_ONE - f, 0) * power
    for k in range(1, stage.top + 1):
        power = round_div((power[:, cols] * shift).sum(-1), one).clamp(-INT32_MAX, INT32_MAX)
        weight = torch.where(n == k, VEL_ONE - f, 0) + torch.where(n + 1 == k, f, 0)
        mixed = mixed + weight * power
    moved = round_div(mixed, VEL_ONE)
    a = round_div(stage.decay_const * moved, one) + g
    return a.clamp(-INT32_MAX, INT32_MAX).to(torch.int32)


def _velocity_update_torch(speed: torch.Tensor, positions: torch.Tensor, count: torch.Tensor,
                    reference: torch.Tensor, stage: VelocityStage):
    """Step 9: push the decisions ``reference`` ``(B,)`` and re-estimate the speed.

    ``c_i = 2 i - (K - 1)``, ``den = K (K^2 - 1) / 6``, ``num = sum c_i p_i``,
    ``P = sum p_i``; ``slope = round_div(num 2**16, den)``; residuals times ``2 K den``:
    ``R_i = 2 K den p_i - 2 den P - K num c_i``; trusted when the window is full and every
    ``|R_i| 2**16 <= tolerance 2 K den``; ``target = clamp(slope, +-2**36)`` if trusted
    else ``2**16``; ``v = v + round_shift(rate (target - v), 16)`` (``2**16`` until the
    window is full), clamped to ``[v_min, v_max]``.

    Returns:
        ``(speed (B,), positions (B, K), count (B,))`` int64.
    """
    k = stage.window
    den = velocity_den(k)
    p = torch.cat([positions[:, 1:], reference.to(torch.int64)[:, None]], dim=1)  # (B, K)
    count = torch.clamp(count + 1, max=k)
    c = torch.arange(-(k - 1), k, 2, dtype=torch.int64, device=p.device)  # 2i - (K - 1)
    num = (p * c).sum(1)  # (B,)
    total = p.sum(1)
    slope = round_div(num * VEL_ONE, den)
    resid = (2 * k * den * p - (2 * den * total)[:, None] - k * num[:, None] * c).abs()
    full = count >= k
    trusted = full & ((resid.amax(1) * VEL_ONE) <= stage.tolerance * 2 * k * den)
    target = torch.where(trusted, slope.clamp(-SLOPE_LIMIT, SLOPE_LIMIT), VEL_ONE)
    v = speed + round_div(stage.rate * (target - speed), VEL_ONE)
    v = torch.where(full, v, VEL_ONE).clamp(stage.v_min, stage.v_max)
    return v, p, count

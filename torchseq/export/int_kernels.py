"""Private NumPy kernels of the integer step, behind :mod:`torchseq.export.int_functional`.

Each kernel computes one stage of ``docs/reference/integer_format.md`` ("One step") with
NumPy, the same integers as the stage's torch definition in
:mod:`torchseq.export.int_functional` (the module the integer ONNX graph is traced from), and
is chosen there with ``kernel="numpy"``; ``tests/test_export_int_dispatch.py`` checks which
kernel ran. They are the integer side's counterpart of :mod:`torchseq.layers.kernels`.

- :func:`input_stage`: pooling and the integer patch z-score, pixel-major.
- :func:`l1_sums`, :func:`l3_sums`, :func:`rescale`: the two sparse products (L1 through the
  stored index lists, L3 as the sum of the winners' rows of a dense ``(M, N)`` matrix) and
  the evidence rescale; :func:`int8_l1_product`, :func:`int8_l3_product` (built once) with
  :func:`int8_l1_sums`, :func:`int8_l3_sums`:
  the same products through oneDNN's int8 GEMM where every sum is exact in float32.
- :func:`kwta_code`: the binary k-WTA from NumPy's introselect.
- :func:`cohort_gain`: the cohort z-score times the gain.
- :func:`ring_step`, :func:`ring_scan` (the ring over a whole sequence),
  :func:`velocity_ring`, :func:`velocity_update`: the fixed and the adaptive ring.
- :func:`decide`, :func:`within_unit`: the read-out.
- :func:`round_div`, :func:`isqrt`: the exact rounding and square root they share.
"""

from __future__ import annotations

import numpy as np
import torch

from torchseq.export.int_stages import (
    INPUT_ZSCORE,
    INT32_MAX,
    READOUT_INTERPOLATE,
    SLOPE_LIMIT,
    VEL_ONE,
    X_MAX,
    VelocityStage,
    velocity_den,
)
from torchseq.layers.kernels import Int8Linear, kwta_numpy

EXACT_F32 = 2**24  # integers below this are exact in float32


def round_div(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a / b`` rounded half away from zero, for integer ``a`` and ``b > 0`` (``|a| < 2**61``).

    ``q = floor((2|a| + b) / 2b)`` with the sign of ``a``. When every numerator
    ``N = 2|a| + b`` is below ``2**53`` the quotient runs as one float64 division, which is
    exact here: a non-integer ``N / D`` lies at least ``1 / D`` below the next integer, more
    than its rounding error ``(N / D) * 2**-53`` since ``N < 2**53`` (and much faster than
    NumPy's integer division); otherwise integer division.

    ``a`` and ``b`` are int64 (the result is int64), or float64 arrays holding integers
    whose numerators stay below ``2**53`` (the result is float64, without int64 copies;
    ``ValueError`` when a numerator is too large to be exact).
    """
    if np.asarray(a).dtype == np.float64:
        num = np.abs(a)
        num *= 2.0
        num += b
        if num.size and not num.max() < 2**53:
            raise ValueError("round_div: float64 numerators 2|a| + b must stay below 2**53")
        return _half_away_quotient(num, b, a)
    a = np.asarray(a, np.int64)
    b = np.asarray(b, np.int64)
    num = np.abs(a)
    num *= 2
    num += b  # N = 2|a| + b (in place: this runs on every pixel of every frame)
    if num.size and num.max() < 2**53:
        return _half_away_quotient(num.astype(np.float64), b, a).astype(np.int64)
    q = num // (2 * b)
    return np.where(a < 0, -q, q)


def _half_away_quotient(num: np.ndarray, b: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``floor(num / 2b)`` with the sign of ``a``, in place in float64 ``num``."""
    num /= 2.0 * b
    np.floor(num, out=num)
    return np.copysign(num, a, out=num)  # a == 0 gives 0: floor(1/2)


def isqrt(v: np.ndarray) -> np.ndarray:
    """Integer square root ``floor(sqrt(v))`` for int64 ``0 <= v < 2**62``.

    A float64 square root is within one of the answer (its error is below ``2**-20`` for
    these ``v``); one integer step down and one up, with exact int64 squares, make it exact.
    """
    v = np.asarray(v, np.int64)
    r = np.minimum(np.floor(np.sqrt(v.astype(np.float64))).astype(np.int64), 2**31 - 1)
    r -= r * r > v
    r += (r + 1) * (r + 1) <= v
    return r


def block_sums(v: np.ndarray, bh: int, bw: int) -> np.ndarray:
    """Sums of ``bh x bw`` blocks of ``(B, H, W)`` integers -> ``(B, H / bh, W / bw)``.

    Summed over contiguous axes, one direction at a time: NumPy reduces the strided block
    axes of a 5-D view several times slower (integers: the same sums).
    """
    b, h, w = v.shape
    if bh == bw == 1:
        return v
    rows = v.reshape(b, h // bh, bh, w).sum(2)  # (B, H / bh, W)
    return rows.reshape(b, h // bh, w // bw, bw).sum(3)


def input_stage(frames: np.ndarray, p: dict) -> np.ndarray:
    """Steps 1-2: uint8 frames ``(B, h*ph, w*pw)`` -> int32 L1 activity ``(B, h*w)``.

    Computed pixel-major: each pixel position of a block is one contiguous row
    ``(p*p, B * blocks)``, 2-3x faster than arithmetic broadcast over the strided block axes.
    The values are integers; they are held in float64 (exact, no int64 copies) whenever the
    file's constants keep every one of them below ``2**53``, else in int64. A flat block
    (``V = 0``) has ``d = 0`` everywhere, so its quotient is 0 as the spec says.
    """
    b, h, w = frames.shape[0], p["height"], p["width"]
    pix = block_sums(frames.astype(np.int64), p["pool_h"], p["pool_w"])  # (B, h, w)
    if p["input_mode"] != INPUT_ZSCORE:
        return pix.reshape(b, h * w).astype(np.int32)
    s = p["patch"]
    n = s * s
    peak = n * 255 * p["pool_h"] * p["pool_w"]  # bounds |S|, |d| and sqrt(V)
    exact = (n * peak * peak < 2**53
             and 2 * peak * (p["norm_const"] + 2 ** p["sqrt_frac"]) < 2**53)
    dtype = np.float64 if exact else np.int64
    rows = (pix.reshape(b, h // s, s, w // s, s).transpose(2, 4, 0, 1, 3)
            .astype(dtype).reshape(n, -1))  # (p*p, B * blocks)
    total = rows.sum(0)  # S
    var = n * np.einsum("ij,ij->j", rows, rows) - total * total  # V = n Q - S^2 >= 0
    root = isqrt(var.astype(np.int64) << (2 * p["sqrt_frac"]))  # ~ sqrt(V) * 2**F
    dev = rows * n
    dev -= total  # d = n p - S
    dev *= p["norm_const"]
    z = round_div(dev, np.maximum(root, 1).astype(dtype))
    x = np.clip(z, -X_MAX, X_MAX).astype(np.int32).reshape(s, s, b, h // s, w // s)
    return x.transpose(2, 3, 0, 4, 1).reshape(b, h * w)


def l1_sums(x: np.ndarray, cols: np.ndarray, values: np.ndarray, chunk: int = 16) -> np.ndarray:
    """Step 3: L1 sums ``(B, M)`` int32 through the stored index lists ``(M, F)``."""
    out = np.empty((x.shape[0], cols.shape[0]), np.int32)
    for lo in range(0, x.shape[0], chunk):
        g = x[lo:lo + chunk][:, cols]  # (b, M, F)
        out[lo:lo + chunk] = (g * values).sum(-1, dtype=np.int32)
    return out


def kwta_code(h: np.ndarray, k: int) -> np.ndarray:
    """Step 4: the binary k-WTA of ``(B, M)`` integers, ties to the lowest index (bool)."""
    return kwta_numpy(h, k)


def dense_t(cols: np.ndarray, values: np.ndarray, n_in: int) -> np.ndarray:
    """``(n_in, rows)`` int32 dense transposed weights from per-row index lists ``(rows, F)``."""
    w = np.zeros((n_in, cols.shape[0]), np.int32)
    w[cols.astype(np.int64).ravel(), np.repeat(np.arange(cols.shape[0]), cols.shape[1])] = \
        values.ravel()
    return w


def l3_sums(code: np.ndarray, w_t: np.ndarray) -> np.ndarray:
    """Step 5: binary code ``(B, M)`` -> L3 sums ``(B, N)`` int64 (the winners' rows of ``w_t``).

    Every row of ``code`` holds the same number of ones (the k-WTA's ``k``).
    """
    idx = np.nonzero(code)[1].reshape(code.shape[0], -1)  # (B, k)
    return w_t[idx].sum(1, dtype=np.int64)


def rescale(e: np.ndarray, row_scale: np.ndarray, e_shift: int) -> np.ndarray:
    """Step 5: ``E = round_shift(e * row_scale, e_shift)`` ``(B, N)`` int64."""
    return round_div(e * row_scale.astype(np.int64), np.int64(1) << e_shift)


def int8_l1_product(cols: np.ndarray, values: np.ndarray, n_input: int) -> Int8Linear | None:
    """The int8 GEMM (oneDNN) of the L1 weights, or None where it would not be exact.

    Built when every ``|w| <= 64`` (inputs ``x + 128`` in 1..255: pairs of products stay
    inside int16 on CPUs without VNNI) and every sum of inputs ``|x| <= 127`` stays below
    ``2**24`` (so the kernel's float32 result is the exact integer).
    """
    w1 = np.zeros((cols.shape[0], n_input), np.int64)  # (M, D) dense
    np.put_along_axis(w1, cols.astype(np.int64), values.astype(np.int64), axis=1)
    if np.abs(w1).max(initial=0) > 64 or 127 * np.abs(w1).sum(1).max(initial=0) >= EXACT_F32:
        return None
    return Int8Linear.create(torch.from_numpy(w1.astype(np.int8)), torch.ones(w1.shape[0]),
                             1.0, 128)


def int8_l3_product(w_t: np.ndarray, k: int) -> Int8Linear | None:
    """The int8 GEMM (oneDNN) of the L3 weights ``w_t`` ``(M, N)`` for a code of ``k`` ones.

    None unless every ``|w| <= 127`` and ``k * 127 < 2**24`` (exact float32 sums).
    """
    if np.abs(w_t).max(initial=0) > 127 or k * 127 >= EXACT_F32:
        return None
    return Int8Linear.create(torch.from_numpy(np.ascontiguousarray(w_t.T, np.int8)),
                             torch.ones(w_t.shape[1]), 1.0, 0, x_max=1)


def int8_l1_sums(x: np.ndarray, gemm: Int8Linear) -> np.ndarray | None:
    """Step 3 through the int8 GEMM ``(B, M)`` int32, or None when some ``|x| > 127``."""
    if x.min(initial=0) <= -128 or x.max(initial=0) >= 128:
        return None
    return gemm(torch.from_numpy((x + 128).astype(np.uint8))).numpy().astype(np.int32)


def int8_l3_sums(code: np.ndarray, gemm: Int8Linear) -> np.ndarray:
    """Step 5's sums of a bool code ``(B, M)`` through the int8 GEMM, ``(B, N)`` int64."""
    return gemm(torch.from_numpy(code.view(np.uint8))).numpy().astype(np.int64)


def cohort_sums(e: np.ndarray, members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(e @ members, (e * e) @ members)`` as int64, for int64 ``e`` ``(B, N)``.

    Through float64 matrix products (BLAS) when every sum is below ``2**53`` and so exact;
    NumPy's integer matrix product is many times slower.
    """
    sq = e * e
    if sq.size and int(sq.max()) * e.shape[1] < 2**53:
        m = members.astype(np.float64)
        return ((e.astype(np.float64) @ m).astype(np.int64),
                (sq.astype(np.float64) @ m).astype(np.int64))
    return e @ members, sq @ members


def cohort_gain(e: np.ndarray, cohort: np.ndarray, size: np.ndarray, members: np.ndarray,
                gain_const: int, gain_shift: int, rectify: int) -> np.ndarray:
    """Step 6: cohort z-score of ``E`` ``(B, N)`` times the gain (rectified), int64.

    ``members`` is the one-hot ``(N, C)`` int64 membership of the int64 ``cohort`` ``(N,)``,
    ``size`` its column sums ``(C,)``.
    """
    total, squares = cohort_sums(e, members)  # (B, C) each
    var = size * squares - total * total  # (B, C)
    root = isqrt(var)
    dev = size[cohort] * e - total[:, cohort]  # (B, N)
    div = np.maximum(root[:, cohort], 1) << gain_shift
    g = np.where(var[:, cohort] > 0, round_div(dev * gain_const, div), 0)
    return np.maximum(g, 0) if rectify else g


def ring_step(state: np.ndarray, g: np.ndarray, cols: np.ndarray, values: np.ndarray,
              ring_frac: int) -> np.ndarray:
    """Step 7: int32 ``state`` ``(B, N)`` and ``g`` -> the new activity ``(B, N)`` int32."""
    moved = (state.astype(np.int64)[:, cols] * values).sum(-1)
    a = np.clip(round_div(moved, np.int64(1) << ring_frac) + g, -INT32_MAX, INT32_MAX)
    return a.astype(np.int32)


def ring_scan(g: np.ndarray, cols: np.ndarray, values: np.ndarray,
              ring_frac: int) -> np.ndarray:
    """Step 7 over a sequence: ``g`` ``(T, N)`` int64 from a zero start -> ``(T, N)`` int32.

    ``a_t = clip(round_half_away(sum_j R[i, j] a_{t-1}[j] / 2**ring_frac) + g_t)``,
    :func:`ring_step` frame by frame; the division by a power of two rounds with one shift:
    ``(m + 2**(f-1) - [m < 0]) >> f`` (``f = 0``: ``m`` itself).
    """
    f = ring_frac
    half = (np.int64(1) << f) >> 1  # f = 0: no rounding at all (m itself)
    # one 1-D gather per column of the row lists: much faster in NumPy than a 2-D gather
    # and a sum over the short last axis
    cols_t = [np.ascontiguousarray(c) for c in cols.T]
    vals_t = [np.ascontiguousarray(v) for v in values.T]
    # |a_t| <= rho |a_{t-1}| + 1/2 + max|g| with rho the largest row sum of |R| / 2**f,
    # so from a zero start |a| never exceeds (max|g| + 1) / (1 - rho): when that fits
    # int32 the saturation cannot act and is skipped (np.clip costs microseconds a call)
    rho = np.abs(values).sum(1).max(initial=0) / 2.0**f
    bound = (np.abs(g).max(initial=0) + 1) / (1 - rho) if rho < 1 else np.inf
    saturate = not bound < INT32_MAX
    out = np.empty(g.shape, np.int32)
    a = np.zeros(g.shape[1], np.int64)
    for t in range(g.shape[0]):
        m = a[cols_t[0]] * vals_t[0]
        for c, v in zip(cols_t[1:], vals_t[1:]):
            m += a[c] * v
        a = (((m + half - (m < 0)) >> f) if f else m) + g[t]
        if saturate:
            np.clip(a, -INT32_MAX, INT32_MAX, out=a)
        out[t] = a
    return out


def velocity_ring(state: np.ndarray, g: np.ndarray, speed: np.ndarray, cols: np.ndarray,
                  shift: np.ndarray, ring_frac: int, stage: VelocityStage) -> np.ndarray:
    """Step 7v: the adaptive ring ``(B, N)`` int32 (the powers of the shift, mixed by speed).

    The powers are computed only up to the largest ``n + 1`` the batch needs (the same
    integers: the others have weight 0), and each stream takes its two by indexing.
    """
    f = ring_frac
    n = speed // VEL_ONE  # (B,)
    frac = speed - n * VEL_ONE
    need = min(int(n.max()) + int((frac > 0).any()), stage.top)
    powers = [state.astype(np.int64)]
    for _ in range(need):
        m = (powers[-1][:, cols] * shift).sum(-1)
        powers.append(np.clip(round_div(m, np.int64(1) << f), -INT32_MAX, INT32_MAX))
    stack = np.stack(powers + [np.zeros_like(powers[0])], 1)  # (B, need + 2, N)
    rows = np.arange(state.shape[0])
    hi = stack[rows, np.minimum(n + 1, need + 1)]
    mixed = (VEL_ONE - frac)[:, None] * stack[rows, n] + frac[:, None] * hi
    moved = round_div(mixed, np.int64(VEL_ONE))
    a = round_div(stage.decay_const * moved, np.int64(1) << f) + g
    return np.clip(a, -INT32_MAX, INT32_MAX).astype(np.int32)


def velocity_update(speed: np.ndarray, positions: np.ndarray, count: np.ndarray,
                    reference: np.ndarray, stage: VelocityStage):
    """Step 9: push the decisions ``(B,)`` and re-estimate the speed.

    Returns:
        ``(speed (B,), positions (B, K), count (B,))`` int64.
    """
    k, den = stage.window, velocity_den(stage.window)
    p = np.concatenate([positions[:, 1:], reference.astype(np.int64)[:, None]], 1)
    count = np.minimum(count + 1, k)
    c = np.arange(-(k - 1), k, 2, dtype=np.int64)
    num = p @ c
    resid = np.abs(2 * k * den * p - (2 * den * p.sum(1))[:, None] - k * num[:, None] * c)
    full = count >= k
    trusted = full & (resid.max(1) * VEL_ONE <= stage.tolerance * 2 * k * den)
    slope = np.clip(round_div(num * VEL_ONE, np.int64(den)), -SLOPE_LIMIT, SLOPE_LIMIT)
    target = np.where(trusted, slope, VEL_ONE)
    v = speed + round_div(stage.rate * (target - speed), np.int64(VEL_ONE))
    v = np.clip(np.where(full, v, VEL_ONE), stage.v_min, stage.v_max).astype(np.int64)
    return v, p, count


def within_unit(a: np.ndarray, unit: np.ndarray, spans: np.ndarray) -> np.ndarray:
    """The interpolating read-out of :func:`torchseq.export.int_functional.within_unit`.

    ``min(f + floor(L (a0 - am) / D), l - 1)`` for a winner with both neighbours and
    ``D = 2 a0 - am - ap > 0``, else ``f + L // 2`` (int64 floor division: exact).

    Args:
        a: ``(B, N)`` int32 activity.
        unit: ``(B,)`` winners.
        spans: ``(N, 2)`` int64 ``[first, last)`` of each unit.

    Returns:
        ``(B,)`` int64 reference frame.
    """
    n = a.shape[1]
    rows = np.arange(a.shape[0])
    a0 = a[rows, unit].astype(np.int64)
    am = a[rows, np.maximum(unit - 1, 0)].astype(np.int64)
    ap = a[rows, np.minimum(unit + 1, n - 1)].astype(np.int64)
    den = 2 * a0 - am - ap
    inner = (unit > 0) & (unit < n - 1) & (den > 0)
    first, last = spans[unit, 0], spans[unit, 1]
    length = last - first
    quot = np.where(inner, length * (a0 - am), length) // np.where(inner, den, 2)
    return np.minimum(first + quot, last - 1)


def decide(act: np.ndarray, unit_centre: np.ndarray, unit_to_ref: np.ndarray, window: int,
           readout: int) -> tuple[np.ndarray, np.ndarray]:
    """Step 8: activity ``(B, N)`` int32 -> ``(reference (B,), confidence (B,))`` int64."""
    unit = act.argmax(1)  # first index on ties
    best = act[np.arange(act.shape[0]), unit].astype(np.int64)
    rival = np.abs(np.arange(act.shape[1])[None, :] - unit[:, None]) > window
    second = np.where(rival, act, act.min(1, keepdims=True)).max(1).astype(np.int64)
    if readout == READOUT_INTERPOLATE:
        return within_unit(act, unit, unit_to_ref.astype(np.int64)), best - second
    return unit_centre[unit].astype(np.int64), best - second

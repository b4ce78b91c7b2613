"""Single-stream integer runtime: the integer format's arithmetic, batched over time.

:class:`StreamRuntime` computes exactly what :meth:`IntegerRuntime.run
<torchseq.export.int_runtime.IntegerRuntime.run>` computes (same integers, bit for bit) for
one stream of frames, but runs every state-free stage (input stage, L1, k-WTA, L3, cohort
z-score and gain) on all frames at once and only the fixed-point ring frame by frame. The
two products use oneDNN's int8 GEMM (:class:`torchseq.neural.fast.Int8Linear`) where their
integers fit int8 and every sum stays below ``2**24`` (so the float32 result of the kernel is
the exact integer); otherwise the NumPy runtime's own integer products.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from torchseq.export.int_format import INPUT_ZSCORE, X_MAX, IntegerModel
from torchseq.export.int_runtime import (
    INT32_MAX,
    IntegerRuntime,
    input_stage,
    isqrt,
    kwta_int,
    round_div,
)

EXACT_F32 = 2**24  # integers below this are exact in float32
EXACT_DIV = 2**50  # |a| below this: round_div(a, b) is exact through one float64 division


def input_stage_fast(frames: np.ndarray, p: dict) -> np.ndarray:
    """:func:`~torchseq.export.int_runtime.input_stage`, the same integers, faster.

    Block sums run over contiguous axes, and the per-pixel rounded division
    ``round_div(d * norm_const, root)`` runs as one float64 division: with ``|a| < 2**50``
    and ``b < 2**32`` the quotient ``(2|a| + b) / 2b`` is never within a float64 rounding
    of an integer unless it is one, so its floor is exact. Larger values (not produced by
    the format's own bit widths) fall back to the integer version.

    Args:
        frames: uint8 ``(B, h * pool_h, w * pool_w)``.
        p: the model's parameters.

    Returns:
        ``(B, h * w)`` int32.
    """
    b, h, w = frames.shape[0], p["height"], p["width"]
    ph, pw = p["pool_h"], p["pool_w"]
    pix = frames.astype(np.int64)
    if ph > 1 or pw > 1:
        pix = pix.reshape(b, h, ph, w * pw).sum(2).reshape(b, h, w, pw).sum(3)  # (B, h, w)
    if p["input_mode"] != INPUT_ZSCORE:
        return pix.reshape(b, h * w).astype(np.int32)
    s = p["patch"]
    n = s * s

    def block_sums(v: np.ndarray) -> np.ndarray:  # (B, h, w) -> (B, h/s, 1, w/s, 1)
        t = v.reshape(b, h // s, s, w).sum(2).reshape(b, h // s, w // s, s).sum(3)
        return t[:, :, None, :, None]

    total = block_sums(pix)
    var = n * block_sums(pix * pix) - total * total
    root = np.maximum(isqrt(var << (2 * p["sqrt_frac"])), 1)
    a = (n * pix.reshape(b, h // s, s, w // s, s) - total) * p["norm_const"]
    if np.abs(a).max(initial=0) >= EXACT_DIV or root.max(initial=1) >= 2**32:
        return input_stage(frames, p)
    af = a.astype(np.float64)
    q = np.abs(af)
    q *= 2.0
    q += root
    q /= 2.0 * root
    np.floor(q, out=q)
    np.copysign(q, af, out=q)  # round_div(a, root), exactly; a flat block has a == 0 -> 0
    np.clip(q, -X_MAX, X_MAX, out=q)
    return q.reshape(b, h * w).astype(np.int32)


class StreamRuntime(IntegerRuntime):
    """Run an integer model over one stream, batched over time (bit-exact with ``run``).

    Args:
        model: an :class:`IntegerModel` or a path to a ``.tsq`` file.
        chunk: frames per batch of the state-free stages (memory bound, not a result change).
    """

    def __init__(self, model: IntegerModel | str | Path, chunk: int = 256) -> None:
        super().__init__(model)
        self.chunk = int(chunk)
        p = self.params
        w1 = np.zeros((p["hidden"], p["n_input"]), np.int64)  # (M, D) dense
        np.put_along_axis(w1, self.l1_cols, self.l1_values.astype(np.int64), axis=1)
        self.l1_int8 = None  # used for chunks whose |x| <= 127 (checked per chunk)
        if np.abs(w1).max(initial=0) <= 64 and 127 * np.abs(w1).sum(1).max(initial=0) < EXACT_F32:
            from torchseq.neural.fast import Int8Linear

            self.l1_int8 = Int8Linear.create(torch.from_numpy(w1.astype(np.int8)),
                                             torch.ones(p["hidden"]), 1.0, 128)
        w3 = self.l3_t.T  # (N, M)
        self.l3_int8 = None
        if np.abs(w3).max(initial=0) <= 127 and p["k"] * 127 < EXACT_F32:
            from torchseq.neural.fast import Int8Linear

            self.l3_int8 = Int8Linear.create(torch.from_numpy(np.ascontiguousarray(w3, np.int8)),
                                             torch.ones(p["n_units"]), 1.0, 0)

    def evidence_stage(self, frames: np.ndarray) -> np.ndarray:
        """uint8 frames ``(T, H, W)`` -> ``gain * z`` ``(T, N)`` int64 (state-free stages)."""
        p = self.params
        x = input_stage_fast(frames, p)  # (T, D) int32
        if self.l1_int8 is not None and -128 < x.min() and x.max() < 128:
            xq = torch.from_numpy((x + 128).astype(np.uint8))
            hidden = self.l1_int8(xq).numpy().astype(np.int32)  # exact: sums < 2**24
        else:
            hidden = self.hidden(x)
        win = kwta_int(hidden, p["k"])  # (T, M) bool
        if self.l3_int8 is not None:
            sums = self.l3_int8(torch.from_numpy(win.view(np.uint8))).numpy().astype(np.int64)
            e = round_div(sums * self.row_scale, np.int64(1) << p["e_shift"])
        else:
            e = self.evidence(win)
        return self.gain_z(e)

    def run(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stream a traverse ``(T, h * pool_h, w * pool_w)`` uint8 (one stream, zero start).

        Returns:
            ``(reference (T,) int64, confidence (T,) int64, activity (T, N) int32)``, the
            same integers as :meth:`IntegerRuntime.run`.
        """
        frames = self.check_frames(frames)
        g = np.concatenate([self.evidence_stage(frames[lo:lo + self.chunk])
                            for lo in range(0, frames.shape[0], self.chunk)])  # (T, N)
        act = self.ring_scan(g)
        return (*self.decide(act), act)

    def ring_scan(self, g: np.ndarray) -> np.ndarray:
        """The fixed-point ring over ``gain * z`` ``(T, N)`` int64 -> activity ``(T, N)`` int32.

        ``a_t = clip(round_half_away(sum_j R[i, j] a_{t-1}[j] / 2**ring_frac) + g_t)``, the
        runtime's step; the division by a power of two rounds with one shift:
        ``(m + 2**(f-1) - [m < 0]) >> f``.
        """
        f = self.params["ring_frac"]
        half = np.int64(1) << (f - 1)
        # one 1-D gather per column of the row lists: much faster in NumPy than a 2-D gather
        # and a sum over the short last axis
        cols = [np.ascontiguousarray(c) for c in self.ring_cols.T]
        vals = [np.ascontiguousarray(v) for v in self.ring_values.T]
        # |a_t| <= rho |a_{t-1}| + 1/2 + max|g| with rho the largest row sum of |R| / 2**f,
        # so from a zero start |a| never exceeds (max|g| + 1) / (1 - rho): when that fits
        # int32 the saturation cannot act and is skipped (np.clip costs microseconds a call)
        rho = np.abs(self.ring_values).sum(1).max(initial=0) / 2.0**f
        bound = (np.abs(g).max(initial=0) + 1) / (1 - rho) if rho < 1 else np.inf
        saturate = not bound < INT32_MAX
        out = np.empty(g.shape, np.int32)
        a = np.zeros(g.shape[1], np.int64)
        for t in range(g.shape[0]):
            m = a[cols[0]] * vals[0]
            for c, v in zip(cols[1:], vals[1:]):
                m += a[c] * v
            a = ((m + half - (m < 0)) >> f) + g[t]
            if saturate:
                np.clip(a, -INT32_MAX, INT32_MAX, out=a)
            out[t] = a
        return out

    def decide(self, act: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The runtime's decision for every row of ``act`` ``(T, N)`` int32."""
        unit = act.argmax(1)  # first index on ties
        best = act[np.arange(act.shape[0]), unit].astype(np.int64)
        rival = np.abs(np.arange(self.n_units)[None, :] - unit[:, None]) > self.params["window"]
        second = np.where(rival, act, act.min(1, keepdims=True)).max(1).astype(np.int64)
        return self.unit_centre[unit], best - second

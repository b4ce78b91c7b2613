"""Single-stream integer runtime: the integer format's arithmetic, batched over time.

:class:`StreamRuntime` computes exactly what :meth:`IntegerRuntime.run
<torchseq.export.int_runtime.IntegerRuntime.run>` computes (same integers, bit for bit) for
one stream of frames, but runs every state-free stage (:meth:`IntegerRuntime.drive`: input
stage, L1, k-WTA, L3, cohort z-score and gain) on all frames at once and only the fixed-point
ring frame by frame. The two products use oneDNN's int8 GEMM
(:class:`torchseq.layers.kernels.Int8Linear`) where their integers fit int8 and every sum stays
below ``2**24`` (so the float32 result of the kernel is the exact integer); otherwise the
NumPy runtime's own integer products. A model with the adaptive ring (format version 3)
batches the same state-free stages; its ring, decision and speed estimate run frame by frame
(:meth:`StreamRuntime.velocity_scan`: each decision sets the next frame's speed).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from torchseq.export.int_format import IntegerModel, read_integer_model
from torchseq.export.int_runtime import (
    INT32_MAX,
    MEMORY_BUDGET,
    IntegerRuntime,
    check_dense_budget,
)
from torchseq.export.int_stages import IntegerInputError
from torchseq.layers.kernels import Int8Linear

EXACT_F32 = 2**24  # integers below this are exact in float32


class StreamRuntime(IntegerRuntime):
    """Run an integer model over one stream, batched over time (bit-exact with ``run``).

    Args:
        model: an :class:`IntegerModel` or a path to a ``.tsq`` file.
        chunk: frames per batch of the state-free stages (memory bound, not a result change).
        memory_budget: bytes of dense weights it may build (``IntegerFormatError`` past it).
    """

    def __init__(self, model: IntegerModel | str | Path, chunk: int = 256,
                 memory_budget: int = MEMORY_BUDGET) -> None:
        if not isinstance(model, IntegerModel):
            model = read_integer_model(model)
        p = model.params
        # the L3 matrix of the NumPy kernels plus the dense int64 L1 matrix and the int8 copies
        check_dense_budget("StreamRuntime", 5 * p["hidden"] * p["n_units"]
                           + 9 * p["hidden"] * p["n_input"], int(memory_budget))
        super().__init__(model, kernel="numpy", memory_budget=memory_budget)
        self.chunk = int(chunk)
        w1 = np.zeros((p["hidden"], p["n_input"]), np.int64)  # (M, D) dense
        np.put_along_axis(w1, self.l1_cols, self.l1_values.astype(np.int64), axis=1)
        self.l1_int8 = None  # used for chunks whose |x| <= 127 (checked per chunk)
        if np.abs(w1).max(initial=0) <= 64 and 127 * np.abs(w1).sum(1).max(initial=0) < EXACT_F32:
            self.l1_int8 = Int8Linear.create(torch.from_numpy(w1.astype(np.int8)),
                                             torch.ones(p["hidden"]), 1.0, 128)
        w3 = self.l3_t.T  # (N, M)
        self.l3_int8 = None
        if np.abs(w3).max(initial=0) <= 127 and p["k"] * 127 < EXACT_F32:
            self.l3_int8 = Int8Linear.create(torch.from_numpy(np.ascontiguousarray(w3, np.int8)),
                                             torch.ones(p["n_units"]), 1.0, 0, x_max=1)

    def hidden(self, x: np.ndarray, chunk: int = 16) -> np.ndarray:
        """L1 sums ``(B, M)`` int32: the int8 GEMM when every ``|x| <= 127``, else NumPy's."""
        if self.l1_int8 is None or x.min(initial=0) <= -128 or x.max(initial=0) >= 128:
            return super().hidden(x, chunk)
        xq = torch.from_numpy((x + 128).astype(np.uint8))
        return self.l1_int8(xq).numpy().astype(np.int32)  # exact: sums < 2**24

    def l3_sums(self, win: np.ndarray) -> np.ndarray:
        """L3 sums ``(B, N)`` int64 of a binary code: the int8 GEMM when it was built."""
        if self.l3_int8 is None:
            return super().l3_sums(win)
        return self.l3_int8(torch.from_numpy(win.view(np.uint8))).numpy().astype(np.int64)

    def run(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stream a traverse ``(T, h * pool_h, w * pool_w)`` uint8 (one stream, zero start).

        Returns:
            ``(reference (T,) int64, confidence (T,) int64, activity (T, N) int32)``, the
            same integers as :meth:`IntegerRuntime.run`.
        """
        g = self.drive_all(frames)
        if self.velocity is not None:
            return self.velocity_scan(g)[:3]
        act = self.ring_scan(g)
        return (*self.decide(act), act)

    def run_speeds(self, frames: np.ndarray) -> tuple[np.ndarray, ...]:
        """:meth:`run` of an adaptive-ring model (format version 3) with its speeds.

        Returns:
            ``(reference (T,), confidence (T,), activity (T, N) int32, speed (T,) int64)``
            (the speed estimate after each frame, ``2**-16`` grid), the same integers as
            :meth:`IntegerRuntime.run` with ``speeds=True``.
        """
        if self.velocity is None:
            raise IntegerInputError("run_speeds: the model has the fixed ring (no speed estimate)")
        return self.velocity_scan(self.drive_all(frames))

    def drive_all(self, frames: np.ndarray) -> np.ndarray:
        """``gain * z`` ``(T, N)`` of a checked traverse, ``chunk`` frames at a time."""
        frames = self.check_frames(frames)
        return np.concatenate([self.drive(frames[lo:lo + self.chunk])
                               for lo in range(0, frames.shape[0], self.chunk)])

    def velocity_scan(self, g: np.ndarray) -> tuple[np.ndarray, ...]:
        """The adaptive ring over ``gain * z`` ``(T, N)``: steps 7v, 8 and 9 frame by frame.

        The decisions feed the speed of the next frame, so only the state-free stages batch.
        """
        state = self.initial_state(1)
        refs, confs, vs = [], [], []
        act = np.empty(g.shape, np.int32)
        for t in range(g.shape[0]):
            a = self.velocity_ring(state.activity, g[t:t + 1], state.velocity)
            ref, conf = self.decide(a)
            state = self.velocity_update(state, ref, a)
            act[t] = a[0]
            refs.append(ref)
            confs.append(conf)
            vs.append(state.velocity)
        return np.concatenate(refs), np.concatenate(confs), act, np.concatenate(vs)

    def ring_scan(self, g: np.ndarray) -> np.ndarray:
        """The fixed-point ring over ``gain * z`` ``(T, N)`` int64 -> activity ``(T, N)`` int32.

        ``a_t = clip(round_half_away(sum_j R[i, j] a_{t-1}[j] / 2**ring_frac) + g_t)``, the
        runtime's step; the division by a power of two rounds with one shift:
        ``(m + 2**(f-1) - [m < 0]) >> f`` (``f = 0``: ``m`` itself).
        """
        f = self.params["ring_frac"]
        half = (np.int64(1) << f) >> 1  # f = 0: no rounding at all (m itself)
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
            a = (((m + half - (m < 0)) >> f) if f else m) + g[t]
            if saturate:
                np.clip(a, -INT32_MAX, INT32_MAX, out=a)
            out[t] = a
        return out

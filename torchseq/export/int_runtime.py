"""Integer runtime of the integer format: the step's definition or its NumPy kernels.

The arithmetic of ``docs/reference/integer_format.md`` ("One step") is defined once, by
:class:`torchseq.export.int_step.IntegerStepModule`. :class:`IntegerRuntime` runs either that
module eagerly (``kernel="module"``) or private NumPy kernels of the same integers
(``kernel="numpy"``, the default: 2.5x faster per step at batch 1 on a 1024-unit L2), chosen at
construction and tested bit-exact with the module; the integer ONNX graph
(:mod:`torchseq.export.int_onnx`) must agree with both bit for bit.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from torchseq.export.int_format import (
    INPUT_ZSCORE,
    READOUT_INTERPOLATE,
    X_MAX,
    IntegerFormatError,
    IntegerModel,
    read_integer_model,
)
from torchseq.export.int_stages import SLOPE_LIMIT, VEL_ONE, IntegerInputError, velocity_den
from torchseq.export.int_step import IntegerStepModule
from torchseq.export.int_velocity import (
    IntVelocityState,
    VelocityStepModule,
    initial_velocity_state,
)
from torchseq.layers.kernels import kwta_numpy

ISQRT_BITS = 31  # isqrt handles 0 <= v < 2**62; result bits 30..0
INT32_MAX = 2**31 - 1
MEMORY_BUDGET = 2**30  # bytes of dense weight matrices a runtime or graph may build
KERNELS = ("numpy", "module")


def check_dense_budget(what: str, n_bytes: int, budget: int) -> None:
    """Refuse to build ``n_bytes`` of dense weights past ``budget`` (``IntegerFormatError``).

    The file stores the sparse products as index lists, so a small legal file (e.g.
    ``n_input = hidden = n_units = 32767``, every fan-in 1: under 1 MB) can ask a dense kernel
    for gigabytes.
    """
    if n_bytes > budget:
        raise IntegerFormatError(
            f"{what} needs {n_bytes / 2**20:,.0f} MiB of dense weights, over the memory budget "
            f"of {budget / 2**20:,.0f} MiB (pass a larger memory_budget, or use "
            f"IntegerRuntime(model, kernel='module'), whose memory follows the file's size)")


class IntegerStep(NamedTuple):
    """Output of one integer step.

    Attributes:
        reference: ``(B,)`` int64 reference frame of the winning unit.
        confidence: ``(B,)`` int64 winner minus best rival, on the ``2**-state_frac`` grid.
        activity: ``(B, N)`` int32 ring activity (also the new state).
    """

    reference: np.ndarray
    confidence: np.ndarray
    activity: np.ndarray


class IntegerVelocityStep(NamedTuple):
    """Output of one integer step of the adaptive ring (format version 3).

    Attributes:
        reference: ``(B,)`` int64 reference frame of the winning unit.
        confidence: ``(B,)`` int64 winner minus best rival, on the ``2**-state_frac`` grid.
        activity: ``(B, N)`` int32 ring activity.
        speed: ``(B,)`` int64 the new speed estimate on the ``2**-16`` grid.
    """

    reference: np.ndarray
    confidence: np.ndarray
    activity: np.ndarray
    speed: np.ndarray


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
    (The ONNX graph computes the same function bit by bit.)
    """
    v = np.asarray(v, np.int64)
    r = np.minimum(np.floor(np.sqrt(v.astype(np.float64))).astype(np.int64), 2**31 - 1)
    r -= r * r > v
    r += (r + 1) * (r + 1) <= v
    return r


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
    """uint8 frames ``(B, h*ph, w*pw)`` -> int32 L1 activity ``(B, h*w)`` (patch z-scores).

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


def within_unit(a: np.ndarray, unit: np.ndarray, spans: np.ndarray) -> np.ndarray:
    """The interpolating read-out of :func:`torchseq.export.int_step.within_unit` in NumPy.

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


class IntegerRuntime:
    """Run an integer model step by step (integer dtypes only).

    Args:
        model: an :class:`IntegerModel` or a path to a ``.tsq`` file.
        kernel: ``"numpy"`` (default): the private NumPy kernels, with a dense ``(M, N)``
            int32 L3 matrix; ``"module"``: :class:`IntegerStepModule` run eagerly (the
            definition; memory follows the file's size).
        memory_budget: bytes of dense weights the NumPy kernels may build
            (``IntegerFormatError`` past it).
    """

    def __init__(self, model: IntegerModel | str | Path, kernel: str = "numpy",
                 memory_budget: int = MEMORY_BUDGET) -> None:
        if kernel not in KERNELS:
            raise IntegerInputError(f"kernel must be one of {KERNELS}, got {kernel!r}")
        if not isinstance(model, IntegerModel):
            model = read_integer_model(model)
        self.model = model.check()
        p, a = model.params, model.arrays
        self.params = p
        self.kernel = kernel
        self.memory_budget = int(memory_budget)
        self.velocity = model.velocity  # the adaptive ring (version 3), or None
        kind = IntegerStepModule if self.velocity is None else VelocityStepModule
        self.module = kind(model).eval() if kernel == "module" else None
        if kernel == "module":
            return
        check_dense_budget("the NumPy L3 kernel", 4 * p["hidden"] * p["n_units"],
                           self.memory_budget)
        self.l1_cols = a["l1.cols"].astype(np.int64)
        self.l1_values = a["l1.values"].astype(np.int32)
        w3 = np.zeros((p["hidden"], p["n_units"]), np.int32)  # (M, N) dense for row gathers
        rows = np.repeat(np.arange(p["n_units"]), p["l3_fan_in"])
        w3[a["l3.cols"].astype(np.int64).ravel(), rows] = a["l3.values"].ravel()
        self.l3_t = w3
        self.row_scale = a["l3.row_scale"].astype(np.int64)
        self.cohort = a["cohort"].astype(np.int64)
        self.members = np.eye(p["n_cohorts"], dtype=np.int64)[self.cohort]  # (N, C)
        self.cohort_size = self.members.sum(0)  # (C,)
        self.ring_cols = a["ring.cols"].astype(np.int64)
        self.ring_values = a["ring.values"].astype(np.int64)
        self.unit_centre = a["unit_centre"].astype(np.int64)
        self.unit_to_ref = a["unit_to_ref"].astype(np.int64)
        if self.velocity is not None:
            self.ring_shift = self.velocity.shift.astype(np.int64)

    @property
    def n_units(self) -> int:
        """Output units ``N``."""
        return self.params["n_units"]

    def check_frames(self, frames: np.ndarray) -> np.ndarray:
        """``frames`` as a uint8 ``(B, h * pool_h, w * pool_w)`` array, or ``ValueError``."""
        p = self.params
        frames = np.asarray(frames)
        size = (p["height"] * p["pool_h"], p["width"] * p["pool_w"])
        if frames.dtype != np.uint8 or frames.ndim != 3 or frames.shape[1:] != size:
            raise IntegerInputError(f"frames must be uint8 (B, {size[0]}, {size[1]}), got "
                                    f"{frames.dtype} {frames.shape}")
        if frames.shape[0] == 0:
            raise IntegerInputError("frames are empty (no frame in the batch)")
        return frames

    def initial_state(self, batch: int) -> np.ndarray | IntVelocityState:
        """The start of ``batch`` streams: zero activity ``(batch, N)`` int32.

        With the adaptive ring an :class:`~torchseq.export.int_velocity.IntVelocityState`
        (zero activity, speed 1, empty window).
        """
        if self.velocity is not None:
            return initial_velocity_state(batch, self.n_units, self.velocity.window)
        return np.zeros((batch, self.n_units), np.int32)

    def velocity_ring(self, state: np.ndarray, g: np.ndarray, speed: np.ndarray) -> np.ndarray:
        """Step 7v in NumPy (the module's :func:`~torchseq.export.int_velocity.velocity_ring`).

        The powers are computed only up to the largest ``n + 1`` the batch needs (the same
        integers: the others have weight 0), and each stream takes its two by indexing.
        """
        st, f = self.velocity, self.params["ring_frac"]
        n = speed // VEL_ONE  # (B,)
        frac = speed - n * VEL_ONE
        need = min(int(n.max()) + int((frac > 0).any()), st.top)
        powers = [state.astype(np.int64)]
        for _ in range(need):
            m = (powers[-1][:, self.ring_cols] * self.ring_shift).sum(-1)
            powers.append(np.clip(round_div(m, np.int64(1) << f), -INT32_MAX, INT32_MAX))
        stack = np.stack(powers + [np.zeros_like(powers[0])], 1)  # (B, need + 2, N)
        rows = np.arange(state.shape[0])
        hi = stack[rows, np.minimum(n + 1, need + 1)]
        mixed = (VEL_ONE - frac)[:, None] * stack[rows, n] + frac[:, None] * hi
        moved = round_div(mixed, np.int64(VEL_ONE))
        a = round_div(st.decay_const * moved, np.int64(1) << f) + g
        return np.clip(a, -INT32_MAX, INT32_MAX).astype(np.int32)

    def velocity_update(self, state: IntVelocityState, reference: np.ndarray,
                        activity: np.ndarray) -> IntVelocityState:
        """Step 9 in NumPy (the module's :func:`~torchseq.export.int_velocity.velocity_update`)."""
        st = self.velocity
        k, den = st.window, velocity_den(st.window)
        p = np.concatenate([state.positions[:, 1:], reference.astype(np.int64)[:, None]], 1)
        count = np.minimum(state.count + 1, k)
        c = np.arange(-(k - 1), k, 2, dtype=np.int64)
        num = p @ c
        resid = np.abs(2 * k * den * p - (2 * den * p.sum(1))[:, None] - k * num[:, None] * c)
        full = count >= k
        trusted = full & (resid.max(1) * VEL_ONE <= st.tolerance * 2 * k * den)
        slope = np.clip(round_div(num * VEL_ONE, np.int64(den)), -SLOPE_LIMIT, SLOPE_LIMIT)
        target = np.where(trusted, slope, VEL_ONE)
        v = state.velocity + round_div(st.rate * (target - state.velocity), np.int64(VEL_ONE))
        v = np.clip(np.where(full, v, VEL_ONE), st.v_min, st.v_max).astype(np.int64)
        return IntVelocityState(activity, v, p, count)

    def check_velocity_state(self, state, batch: int) -> IntVelocityState:
        """``state`` if it is this model's :class:`IntVelocityState` for ``batch`` streams.

        Raises:
            ValueError: another type, dtype or shape, or a speed outside ``[v_min, v_max]``.
        """
        k = self.velocity.window
        want = ((np.int32, (batch, self.n_units)), (np.int64, (batch,)),
                (np.int64, (batch, k)), (np.int64, (batch,)))
        if not isinstance(state, IntVelocityState) or any(
                np.asarray(x).dtype != d or np.shape(x) != s for x, (d, s) in zip(state, want)):
            raise IntegerInputError(
                f"an adaptive-ring model steps with an IntVelocityState of int32 "
                f"({batch}, {self.n_units}) activity and int64 ({batch},) speed, "
                f"({batch}, {k}) positions and ({batch},) count")
        v = state.velocity
        if (v < self.velocity.v_min).any() or (v > self.velocity.v_max).any():
            raise IntegerInputError("speeds must lie in [v_min, v_max] of the model")
        return state

    def hidden(self, x: np.ndarray, chunk: int = 16) -> np.ndarray:
        """L1 -> L2 sums ``(B, M)`` int32 through the stored index lists."""
        out = np.empty((x.shape[0], self.params["hidden"]), np.int32)
        for lo in range(0, x.shape[0], chunk):
            g = x[lo:lo + chunk][:, self.l1_cols]  # (b, M, fan_in)
            out[lo:lo + chunk] = (g * self.l1_values).sum(-1, dtype=np.int32)
        return out

    def l3_sums(self, win: np.ndarray) -> np.ndarray:
        """Binary code ``(B, M)`` -> L3 sums ``(B, N)`` int64 (the winners' weight rows)."""
        idx = np.nonzero(win)[1].reshape(win.shape[0], self.params["k"])  # (B, k)
        return self.l3_t[idx].sum(1, dtype=np.int64)

    def evidence(self, win: np.ndarray) -> np.ndarray:
        """Binary code ``(B, M)`` -> per-row rescaled evidence ``E`` ``(B, N)`` int64."""
        e = self.l3_sums(win)  # (B, N)
        return round_div(e * self.row_scale, np.int64(1) << self.params["e_shift"])

    def gain_z(self, e: np.ndarray) -> np.ndarray:
        """Cohort z-score times gain on the activity grid (rectified), ``(B, N)`` int64."""
        p = self.params
        total, squares = cohort_sums(e, self.members)  # (B, C) each
        var = self.cohort_size * squares - total * total  # (B, C)
        root = isqrt(var)
        dev = self.cohort_size[self.cohort] * e - total[:, self.cohort]  # (B, N)
        div = np.maximum(root[:, self.cohort], 1) << p["gain_shift"]
        g = np.where(var[:, self.cohort] > 0, round_div(dev * p["gain_const"], div), 0)
        return np.maximum(g, 0) if p["rectify"] else g

    def drive(self, frames: np.ndarray) -> np.ndarray:
        """The state-free stages: checked uint8 frames -> ``gain * z`` ``(B, N)`` int64."""
        p = self.params
        win = kwta_numpy(self.hidden(input_stage(frames, p)), p["k"])
        return self.gain_z(self.evidence(win))

    def decide(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Activity ``(B, N)`` int32 -> ``(reference (B,), confidence (B,))`` int64."""
        unit = a.argmax(1)  # first index on ties
        best = a[np.arange(a.shape[0]), unit].astype(np.int64)
        rival = np.abs(np.arange(self.n_units)[None, :] - unit[:, None]) > self.params["window"]
        second = np.where(rival, a, a.min(1, keepdims=True)).max(1).astype(np.int64)
        if self.params["readout"] == READOUT_INTERPOLATE:
            return within_unit(a, unit, self.unit_to_ref), best - second
        return self.unit_centre[unit], best - second

    def step(self, frames: np.ndarray,
             state: np.ndarray | None = None) -> tuple[IntegerStep, np.ndarray]:
        """One streaming step.

        Args:
            frames: ``(B, h * pool_h, w * pool_w)`` uint8.
            state: ``(B, N)`` int32 previous activity (None: zeros); with the adaptive ring
                (format version 3) an :class:`IntVelocityState` (None: its start).

        Returns:
            ``(IntegerStep, new state (B, N) int32)``; with the adaptive ring
            ``(IntegerVelocityStep, new IntVelocityState)``.
        """
        p = self.params
        frames = self.check_frames(frames)
        if state is None:
            state = self.initial_state(frames.shape[0])
        if self.velocity is not None:
            return self._velocity_step(frames, self.check_velocity_state(state, frames.shape[0]))
        if state.dtype != np.int32 or state.shape != (frames.shape[0], self.n_units):
            raise IntegerInputError(f"state must be int32 ({frames.shape[0]}, {self.n_units}), "
                                    f"got {state.dtype} {state.shape}")
        if self.module is not None:
            with torch.inference_mode():
                act, ref, conf = self.module(torch.tensor(frames), torch.tensor(state))
            a = act.numpy()
            return IntegerStep(ref.numpy(), conf.numpy(), a), a
        g = self.drive(frames)
        moved = (state.astype(np.int64)[:, self.ring_cols] * self.ring_values).sum(-1)
        a = np.clip(round_div(moved, np.int64(1) << p["ring_frac"]) + g, -INT32_MAX, INT32_MAX)
        a = a.astype(np.int32)
        return IntegerStep(*self.decide(a), a), a

    def _velocity_step(self, frames: np.ndarray,
                       state: IntVelocityState) -> tuple[IntegerVelocityStep, IntVelocityState]:
        """One step of the adaptive ring (format version 3): steps 1-6, 7v, 8 and 9."""
        if self.module is not None:
            with torch.inference_mode():
                out = self.module(torch.tensor(frames), *(torch.tensor(x) for x in state))
            act, ref, conf, v, pos, count = (x.numpy() for x in out)
            return IntegerVelocityStep(ref, conf, act, v), IntVelocityState(act, v, pos, count)
        a = self.velocity_ring(state.activity, self.drive(frames), state.velocity)
        ref, conf = self.decide(a)
        new = self.velocity_update(state, ref, a)
        return IntegerVelocityStep(ref, conf, a, new.velocity), new

    def run(self, frames: np.ndarray, speeds: bool = False) -> tuple[np.ndarray, ...]:
        """Stream a traverse ``(T, h * pool_h, w * pool_w)`` uint8 (one stream).

        Args:
            frames: the traverse.
            speeds: also return the adaptive ring's speed estimate after each frame
                (``(T,)`` int64, ``2**-16`` grid; ``ValueError`` for a fixed-ring model).

        Returns:
            ``(reference (T,) int64, confidence (T,) int64, activity (T, N) int32)``, and
            ``speed (T,)`` with ``speeds``.
        """
        if speeds and self.velocity is None:
            raise IntegerInputError("speeds: the model has the fixed ring (no speed estimate)")
        state = self.initial_state(1)
        refs, confs, acts, vs = [], [], [], []
        for t in range(frames.shape[0]):
            out, state = self.step(frames[t:t + 1], state)
            refs.append(out.reference)
            confs.append(out.confidence)
            acts.append(out.activity)
            vs.append(out.speed if speeds else None)
        out = np.concatenate(refs), np.concatenate(confs), np.concatenate(acts)
        return (*out, np.concatenate(vs)) if speeds else out

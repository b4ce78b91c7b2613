"""Single-stream integer runtime: the integer format's arithmetic, batched over time.

:class:`StreamRuntime` computes exactly what :meth:`IntegerRuntime.run
<torchseq.export.int_runtime.IntegerRuntime.run>` computes (same integers, bit for bit) for
one stream of frames, but runs every state-free stage (input stage, L1, k-WTA, L3, cohort
z-score and gain) on all frames at once and only the fixed-point ring frame by frame
(:func:`torchseq.export.int_kernels.ring_scan`). It is composed, not derived: it holds a
NumPy :class:`~torchseq.export.int_runtime.IntegerRuntime` for the model's operands and the
stages it does not batch, and calls the stage functions of
:mod:`torchseq.export.int_functional`. The two products use oneDNN's int8 GEMM
(:func:`~torchseq.export.int_kernels.int8_l1_product`,
:func:`~torchseq.export.int_kernels.int8_l3_product`) where their integers fit int8 and every
sum stays below ``2**24`` (so the float32 result of the kernel is the exact integer);
otherwise the NumPy kernels. :attr:`StreamRuntime.kernels` says which ran last. A model
with the adaptive ring (format version 3) batches the same state-free stages; its ring,
decision and speed estimate run frame by frame (:meth:`StreamRuntime.velocity_scan`: each
decision sets the next frame's speed).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from torchseq.export import int_functional as F
from torchseq.export import int_kernels
from torchseq.export.int_format import IntegerModel, read_integer_model
from torchseq.export.int_runtime import MEMORY_BUDGET, IntegerRuntime, check_dense_budget
from torchseq.export.int_stages import IntegerInputError


class StreamRuntime:
    """Run an integer model over one stream, batched over time (bit-exact with ``run``).

    Args:
        model: an :class:`IntegerModel` or a path to a ``.tsq`` file.
        chunk: frames per batch of the state-free stages (memory bound, not a result change).
        memory_budget: bytes of dense weights it may build (``IntegerFormatError`` past it).

    Attributes:
        runtime: the NumPy :class:`IntegerRuntime` whose operands and stages it uses.
        l1_int8, l3_int8: the int8 GEMMs of the two products, or None (NumPy kernels).
        kernels: ``{"l1": ..., "l3": ...}``, the kernels the last :meth:`drive_all` ran
            (``"int8"``, ``"numpy"``, or both for L1 when some chunks had ``|x| > 127``).
    """

    def __init__(self, model: IntegerModel | str | Path, chunk: int = 256,
                 memory_budget: int = MEMORY_BUDGET) -> None:
        if not isinstance(model, IntegerModel):
            model = read_integer_model(model)
        p = model.params
        # the L3 matrix of the NumPy kernels plus the dense int64 L1 matrix and the int8 copies
        check_dense_budget("StreamRuntime", 5 * p["hidden"] * p["n_units"]
                           + 9 * p["hidden"] * p["n_input"], int(memory_budget))
        self.runtime = rt = IntegerRuntime(model, kernel="numpy", memory_budget=memory_budget)
        self.chunk = int(chunk)
        self.l1_int8 = int_kernels.int8_l1_product(rt.l1_cols, rt.l1_values, p["n_input"])
        self.l3_int8 = int_kernels.int8_l3_product(rt.l3_t, p["k"])
        self.kernels: dict[str, set[str]] = {"l1": set(), "l3": set()}

    @property
    def params(self) -> dict:
        """The model's parameters."""
        return self.runtime.params

    @property
    def n_units(self) -> int:
        """Output units ``N``."""
        return self.runtime.n_units

    @property
    def velocity(self):
        """The adaptive ring's :class:`~torchseq.export.int_stages.VelocityStage`, or None."""
        return self.runtime.velocity

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
        return (*self.runtime.decide(act), act)

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

    def drive(self, frames: np.ndarray) -> np.ndarray:
        """Steps 1-6 of checked frames ``(B, ...)`` -> ``g`` ``(B, N)`` int64, int8 GEMMs first."""
        rt, p = self.runtime, self.params
        x = F.input_stage(frames, p, kernel="numpy")
        hid = None if self.l1_int8 is None else int_kernels.int8_l1_sums(x, self.l1_int8)
        self.kernels["l1"].add("numpy" if hid is None else "int8")
        if hid is None:
            hid = rt.l1_sums(x)
        code = F.kwta_code(hid, p["k"], kernel="numpy")
        if self.l3_int8 is None:
            self.kernels["l3"].add("numpy")
            e = rt.l3_sums(code)
        else:
            self.kernels["l3"].add("int8")
            e = int_kernels.int8_l3_sums(code, self.l3_int8)
        return rt.gain(F.rescale(e, rt.row_scale, p["e_shift"], kernel="numpy"))

    def drive_all(self, frames: np.ndarray) -> np.ndarray:
        """``gain * z`` ``(T, N)`` of a checked traverse, ``chunk`` frames at a time."""
        frames = self.runtime.check_frames(frames)
        self.kernels = {"l1": set(), "l3": set()}
        return np.concatenate([self.drive(frames[lo:lo + self.chunk])
                               for lo in range(0, frames.shape[0], self.chunk)])

    def velocity_scan(self, g: np.ndarray) -> tuple[np.ndarray, ...]:
        """The adaptive ring over ``gain * z`` ``(T, N)``: steps 7v, 8 and 9 frame by frame.

        The decisions feed the speed of the next frame, so only the state-free stages batch.
        """
        rt = self.runtime
        state = rt.initial_state(1)
        refs, confs, vs = [], [], []
        act = np.empty(g.shape, np.int32)
        for t in range(g.shape[0]):
            a = rt.velocity_ring(state.activity, g[t:t + 1], state.velocity)
            ref, conf = rt.decide(a)
            state = rt.velocity_update(state, ref, a)
            act[t] = a[0]
            refs.append(ref)
            confs.append(conf)
            vs.append(state.velocity)
        return np.concatenate(refs), np.concatenate(confs), act, np.concatenate(vs)

    def ring_scan(self, g: np.ndarray) -> np.ndarray:
        """The fixed-point ring over ``gain * z`` ``(T, N)`` int64 -> activity ``(T, N)`` int32.

        :func:`torchseq.export.int_kernels.ring_scan`: the ring stage frame by frame from a
        zero start (the same integers as :func:`~torchseq.export.int_functional.ring_step`).
        """
        rt = self.runtime
        return int_kernels.ring_scan(g, rt.ring_cols, rt.ring_values, self.params["ring_frac"])

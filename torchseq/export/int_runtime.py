"""The integer runtime: the stage functions of the integer step, called with one kernel.

The arithmetic of ``docs/reference/integer_format.md`` ("One step") is defined once, by the
stage functions of :mod:`torchseq.export.int_functional` (their torch definition is
:class:`torchseq.export.int_step.IntegerStepModule`, which the integer ONNX graph is traced
from). :class:`IntegerRuntime` holds a model's operands and calls those stages with the
kernel chosen at construction: ``kernel="numpy"`` (the default: the NumPy kernels of
:mod:`torchseq.export.int_kernels`, 2.5x faster per step at batch 1 on a 1024-unit L2) or
``kernel="torch"`` (the module, run eagerly). The two are tested bit-exact with each other,
with a plain-Python oracle and with the integer ONNX graph.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from torchseq.export import int_functional as F
from torchseq.export import int_kernels
from torchseq.export.int_format import IntegerFormatError, IntegerModel, read_integer_model
from torchseq.export.int_stages import IntegerInputError
from torchseq.export.int_step import IntegerStepModule
from torchseq.export.int_velocity import (
    IntVelocityState,
    VelocityStepModule,
    initial_velocity_state,
)

MEMORY_BUDGET = 2**30  # bytes of dense weight matrices a runtime or graph may build
KERNELS = ("numpy", "torch")


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
            f"IntegerRuntime(model, kernel='torch'), whose memory follows the file's size)")


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


class IntegerRuntime:
    """Run an integer model step by step (integer dtypes only).

    Args:
        model: an :class:`IntegerModel` or a path to a ``.tsq`` file.
        kernel: ``"numpy"`` (default): the stages' NumPy kernels, with a dense ``(M, N)``
            int32 L3 matrix; ``"torch"``: :class:`IntegerStepModule` run eagerly (the
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
        self.module = kind(model).eval() if kernel == "torch" else None
        if kernel == "torch":
            return
        check_dense_budget("the NumPy L3 kernel", 4 * p["hidden"] * p["n_units"],
                           self.memory_budget)
        self.l1_cols = a["l1.cols"].astype(np.int64)
        self.l1_values = a["l1.values"].astype(np.int32)
        self.l3_cols, self.l3_values = a["l3.cols"], a["l3.values"]
        self.l3_t = int_kernels.dense_t(a["l3.cols"], a["l3.values"], p["hidden"])  # (M, N)
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

    # ---- the stages, with the NumPy kernels (kernel="numpy") ----

    def l1_sums(self, x: np.ndarray) -> np.ndarray:
        """Step 3: L1 activity ``(B, D)`` -> L1 sums ``(B, M)`` int32."""
        return F.l1_sums(x, self.l1_cols, self.l1_values, kernel="numpy")

    def l3_sums(self, code: np.ndarray) -> np.ndarray:
        """Step 5: binary code ``(B, M)`` -> L3 sums ``(B, N)`` int64."""
        return F.l3_sums(code, self.l3_cols, self.l3_values, kernel="numpy", w_t=self.l3_t)

    def drive(self, frames: np.ndarray) -> np.ndarray:
        """Steps 1-6, the state-free stages: checked uint8 frames -> ``g`` ``(B, N)`` int64."""
        return self.gain(self.evidence(F.input_stage(frames, self.params, kernel="numpy")))

    def evidence(self, x: np.ndarray) -> np.ndarray:
        """Steps 3-5: L1 activity ``(B, D)`` -> rescaled evidence ``E`` ``(B, N)`` int64."""
        code = F.kwta_code(self.l1_sums(x), self.params["k"], kernel="numpy")
        return F.rescale(self.l3_sums(code), self.row_scale, self.params["e_shift"],
                         kernel="numpy")

    def gain(self, e: np.ndarray) -> np.ndarray:
        """Step 6: cohort z-score times gain (rectified), ``(B, N)`` int64."""
        return F.cohort_gain(e, self.cohort, self.cohort_size, self.model.cohort,
                             kernel="numpy", members=self.members)

    def ring(self, state: np.ndarray, g: np.ndarray) -> np.ndarray:
        """Step 7: int32 state ``(B, N)`` and ``g`` -> new activity ``(B, N)`` int32."""
        return F.ring_step(state, g, self.ring_cols, self.ring_values, self.params["ring_frac"],
                           kernel="numpy")

    def velocity_ring(self, state: np.ndarray, g: np.ndarray, speed: np.ndarray) -> np.ndarray:
        """Step 7v: the adaptive ring ``(B, N)`` int32 at the streams' speeds ``(B,)``."""
        return F.velocity_ring(state, g, speed, self.ring_cols, self.ring_shift,
                               self.params["ring_frac"], self.velocity, kernel="numpy")

    def velocity_update(self, state: IntVelocityState, reference: np.ndarray,
                        activity: np.ndarray) -> IntVelocityState:
        """Step 9: the new :class:`IntVelocityState` after the decisions ``reference``."""
        v, p, count = F.velocity_update(state.velocity, state.positions, state.count, reference,
                                        self.velocity, kernel="numpy")
        return IntVelocityState(activity, v, p, count)

    def decide(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Step 8: activity ``(B, N)`` int32 -> ``(reference (B,), confidence (B,))`` int64."""
        return F.decide(a, self.unit_centre, self.unit_to_ref, self.params["window"],
                        self.params["readout"], kernel="numpy")

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
        a = self.ring(state, self.drive(frames))
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

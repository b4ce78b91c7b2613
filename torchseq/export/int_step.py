"""The integer step of ``docs/reference/integer_format.md`` as one torch ``nn.Module``.

:class:`IntegerStepModule` holds the stages of an :class:`IntegerModel` as int64 buffers and
calls the stage functions of :mod:`torchseq.export.int_functional` with ``kernel="torch"``
(the definition: integer tensor operations only). The integer ONNX graph
(:mod:`torchseq.export.int_onnx`) is traced from it; run eagerly it is what
:class:`~torchseq.export.int_runtime.IntegerRuntime` runs with ``kernel="torch"``, and the
NumPy kernels (``kernel="numpy"``) and :class:`~torchseq.export.int_stream.StreamRuntime`
are tested equal to it.

The two sparse products read the stored index lists directly (gathers of ``(B, M, F)`` and
``(B, N, F)``), so memory follows the file's size, never a dense ``(M, D)`` matrix.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from torchseq.export import int_functional as F
from torchseq.export.int_format import IntegerModel


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
        buf("ring_cols", a["ring.cols"])
        buf("ring_values", a["ring.values"])
        buf("unit_centre", a["unit_centre"])
        buf("unit_to_ref", a["unit_to_ref"])
        buf("units", np.arange(p["n_units"]))

    def input_stage(self, frames: torch.Tensor) -> torch.Tensor:
        """Steps 1-2: uint8 ``(B, h*ph, w*pw)`` -> L1 activity ``x`` ``(B, D)`` int64."""
        return F.input_stage(frames, self.params)

    def evidence(self, x: torch.Tensor) -> torch.Tensor:
        """Steps 3-5: L1 activity ``(B, D)`` -> rescaled evidence ``E`` ``(B, N)`` int64.

        The L1 sums, the k-WTA code and the L3 sums ``e`` (:func:`F.sparse_evidence`), then
        ``E = round_shift(e * row_scale, e_shift)``.
        """
        e = F.sparse_evidence(x, self.l1_cols, self.l1_values, self.l3_cols, self.l3_values,
                              self.params["k"], self.stages)
        return F.rescale(e, self.row_scale, self.params["e_shift"])

    def gain_z(self, e: torch.Tensor) -> torch.Tensor:
        """Step 6: cohort z-score times gain on the activity grid (rectified), ``(B, N)``."""
        return F.cohort_gain(e, self.cohort, self.cohort_size, self.stages.cohort)

    def drive(self, frames: torch.Tensor) -> torch.Tensor:
        """Steps 1-6, the state-free part: uint8 frames -> ``g`` ``(B, N)`` int64."""
        return self.gain_z(self.evidence(self.input_stage(frames)))

    def ring(self, state: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """Step 7: previous int32 state and ``g`` -> new activity ``(B, N)`` int32."""
        return F.ring_step(state, g, self.ring_cols, self.ring_values, self.params["ring_frac"])

    def decide(self, act: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Step 8: activity ``(B, N)`` int32 -> ``(reference, confidence)`` ``(B,)`` int64."""
        return F.decide(act, self.unit_centre, self.unit_to_ref, self.params["window"],
                        self.params["readout"], units=self.units)

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

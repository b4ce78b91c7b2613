"""The adaptive ring's step module and state (format version 3).

docs/reference/integer_format.md, steps 7v and 9: the ring moves by the fixed-point speed ``v``
(``2**-16`` grid) as the mix of two integer powers of the stored shift, and after each
decision the speed is re-estimated from the window of the last ``K`` reported frames. The two
stages are :func:`~torchseq.export.int_functional.velocity_ring` and
:func:`~torchseq.export.int_functional.velocity_update` (no branch reads a value, so their
torch definition is also the integer ONNX graph). :class:`VelocityStepModule` is
:class:`~torchseq.export.int_step.IntegerStepModule` with this ring and estimator.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from torchseq.export import int_functional as F
from torchseq.export.int_stages import VEL_ONE
from torchseq.export.int_step import IntegerStepModule


class IntVelocityState(NamedTuple):
    """State of ``B`` integer streams of the adaptive ring.

    Attributes:
        activity: ``(B, N)`` int32 ring activity (``2**-state_frac`` grid).
        velocity: ``(B,)`` int64 speed on the ``2**-16`` grid (``2**16`` at the start).
        positions: ``(B, K)`` int64 the last ``K`` reported reference frames, oldest first.
        count: ``(B,)`` int64 decisions seen, saturating at ``K``.
    """

    activity: np.ndarray
    velocity: np.ndarray
    positions: np.ndarray
    count: np.ndarray


def initial_velocity_state(batch: int, n_units: int, window: int) -> IntVelocityState:
    """The start of ``batch`` streams: zero activity, speed 1, empty window (NumPy)."""
    return IntVelocityState(np.zeros((batch, n_units), np.int32),
                            np.full(batch, VEL_ONE, np.int64),
                            np.zeros((batch, window), np.int64), np.zeros(batch, np.int64))


class VelocityStepModule(IntegerStepModule):
    """One integer step of a version-3 model: steps 1-6, the adaptive ring 7v, 8 and 9.

    Args:
        model: a checked :class:`~torchseq.export.int_format.IntegerModel` with a
            :class:`VelocityStage`.
    """

    def __init__(self, model) -> None:
        super().__init__(model)
        if model.velocity is None:
            raise TypeError("VelocityStepModule takes a model with the adaptive ring "
                            "(format version 3)")
        self.velocity = model.velocity
        self.register_buffer("ring_shift",
                             torch.from_numpy(np.array(model.velocity.shift, np.int64)))

    def forward(self, frames: torch.Tensor, state: torch.Tensor, speed: torch.Tensor,
                positions: torch.Tensor, count: torch.Tensor):
        """One step.

        Args:
            frames: ``(B, h*pool_h, w*pool_w)`` uint8.
            state: ``(B, N)`` int32 previous activity.
            speed: ``(B,)`` int64 speed on the ``2**-16`` grid.
            positions: ``(B, K)`` int64 window of reported frames.
            count: ``(B,)`` int64 decisions seen (saturating at ``K``).

        Returns:
            ``(activity (B, N) int32, reference (B,), confidence (B,), speed (B,),
            positions (B, K), count (B,))``, the last three the new estimator state.
        """
        act = F.velocity_ring(state, self.drive(frames), speed, self.ring_cols, self.ring_shift,
                              self.params["ring_frac"], self.velocity)
        ref, conf = self.decide(act)
        return (act, ref, conf, *F.velocity_update(speed, positions, count, ref, self.velocity))

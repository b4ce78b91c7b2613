"""The adaptive ring in integers (format version 3), written once as torch integer operations.

docs/reference/integer_format.md, steps 7v and 9: the ring moves by the fixed-point speed ``v``
(``2**-16`` grid) as the mix of two integer powers of the stored shift, and after each
decision the speed is re-estimated from the window of the last ``K`` reported frames (the
least-squares slope, an exact rational residual test, the rate step and the clamp). No
branch reads a value (the powers are weighted, not indexed), so the same code is the eager
definition and the integer ONNX graph. :class:`VelocityStepModule` is
:class:`~torchseq.export.int_step.IntegerStepModule` with this ring and estimator.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from torchseq.export.int_stages import (
    INT32_MAX,
    SLOPE_LIMIT,
    VEL_ONE,
    VelocityStage,
    velocity_den,
)
from torchseq.export.int_step import IntegerStepModule, round_div


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


def velocity_ring(state: torch.Tensor, g: torch.Tensor, speed: torch.Tensor,
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


def velocity_update(speed: torch.Tensor, positions: torch.Tensor, count: torch.Tensor,
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
        act = velocity_ring(state, self.drive(frames), speed, self.ring_cols, self.ring_shift,
                            self.params["ring_frac"], self.velocity)
        ref, conf = self.decide(act)
        return (act, ref, conf, *velocity_update(speed, positions, count, ref, self.velocity))

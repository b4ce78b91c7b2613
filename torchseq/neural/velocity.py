"""The adaptive ring (``ring_velocity="adaptive"``): an online speed estimate from the decisions.

Each stream keeps the reference positions it reported over the last ``K`` frames
(``velocity_window``). Its speed estimate (reference frames per query frame) is the
least-squares slope of those positions against time,

``s = sum_i (t_i - mean t) p_i / sum_i (t_i - mean t)^2``, residuals ``r_i = p_i - fit_i``,

trusted only when the positions lie on that line: every ``|r_i| <= tolerance`` (in reference
frames, times the frames per unit when units hold several frames). A relocalisation jump or
scattered decisions leave the window untrusted, and the target speed is 1 (the learnt
shift's); a trusted slope is the target. The estimate then moves towards the target,
``v_t = v_{t-1} + rate (target - v_{t-1})``, and is clamped to ``[velocity_min,
velocity_max]``. Until ``K`` decisions are in, ``v = 1``. The ring of the next frame moves
by ``P_v`` (:func:`~torchseq.layers.ring_velocity.ring_step_velocity`).

One frame of the adaptive model (:func:`adaptive_step`): ring at the previous estimate, read
out the place, push it into the window, update the estimate. Every step computes the
``ceil(velocity_max)`` shift products and sums them weighted (``1 - f``, ``f``, zeros), and
the estimator is tensor operations only (no branch reads a value): the same code traces
into the float ONNX graph (:class:`torchseq.export.onnx_float.StreamingStep`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, NamedTuple

import torch

from torchseq.layers import RingParams
from torchseq.layers.ring_velocity import ring_step_velocity
from torchseq.neural.config import NeuralError


class VelocityState(NamedTuple):
    """State of the adaptive ring for ``B`` streams.

    Attributes:
        activity: ``(B, N)`` ring activity after the last step.
        velocity: ``(B,)`` float64 speed estimate for the next step (1: the reference's).
        positions: ``(B, K)`` float64 reported reference frames, oldest first.
        count: ``(B,)`` int64 frames seen (the window is full from ``K`` on).
    """

    activity: torch.Tensor
    velocity: torch.Tensor
    positions: torch.Tensor
    count: torch.Tensor


@dataclass(frozen=True)
class VelocityTracker:
    """The estimator's settings (from :class:`~torchseq.neural.NeuralConfig`).

    Attributes:
        window: ``K`` decisions in the fit.
        v_min: smallest speed.
        v_max: largest speed.
        tolerance: largest residual of a trusted window, in reference frames.
        rate: step of the estimate towards its target (1: jump to it).
    """

    window: int
    v_min: float
    v_max: float
    tolerance: float
    rate: float

    @classmethod
    def from_model(cls, model) -> VelocityTracker:
        """Settings of a fitted model; the tolerance is scaled by its frames per unit."""
        cfg = model.config
        spans = model.unit_to_reference
        per_unit = max(1.0, float(spans[-1, 1] - spans[0, 0]) / spans.shape[0])
        return cls(cfg.velocity_window, cfg.velocity_min, cfg.velocity_max,
                   cfg.velocity_tolerance * per_unit, cfg.velocity_rate)

    def initial(self, activity: torch.Tensor) -> VelocityState:
        """Start of ``B`` streams: zero activity like ``activity`` ``(B, N)``, speed 1."""
        b = activity.shape[0]
        dev = activity.device
        return VelocityState(torch.zeros_like(activity),
                             torch.ones(b, dtype=torch.float64, device=dev),
                             torch.zeros(b, self.window, dtype=torch.float64, device=dev),
                             torch.zeros(b, dtype=torch.int64, device=dev))

    def check(self, state, batch: int, n_units: int) -> None:
        """Raise :class:`NeuralError` unless ``state`` is this tracker's state for the batch."""
        if not isinstance(state, VelocityState):
            raise NeuralError(f"an adaptive-velocity model steps with a VelocityState (or None "
                              f"at the start), got {type(state).__name__}")
        shapes = (tuple(state.activity.shape), tuple(state.velocity.shape),
                  tuple(state.positions.shape), tuple(state.count.shape))
        if shapes != ((batch, n_units), (batch,), (batch, self.window), (batch,)):
            raise NeuralError(f"VelocityState shapes {shapes} do not fit {batch} streams, "
                              f"{n_units} units and a window of {self.window}")

    def update(self, state: VelocityState, reference: torch.Tensor,
               activity: torch.Tensor) -> VelocityState:
        """Push the new decisions ``reference`` ``(B,)`` and re-estimate the speed."""
        p = torch.cat([state.positions[:, 1:],
                       reference.to(state.positions)[:, None]], dim=1)  # (B, K)
        count = state.count + 1
        k = self.window
        t = torch.arange(k, dtype=torch.float64, device=p.device) - (k - 1) / 2.0
        centred = p - p.mean(dim=1, keepdim=True)
        slope = (centred * t).sum(dim=1) / (k * (k * k - 1) / 12.0)  # sum t^2, exact
        resid = (centred - slope[:, None] * t).abs().amax(dim=1)
        trusted = (count >= k) & (resid <= self.tolerance)
        target = torch.where(trusted, slope, torch.ones_like(slope))
        v = state.velocity + self.rate * (target - state.velocity)
        v = torch.where(count >= k, v, torch.ones_like(v)).clamp(self.v_min, self.v_max)
        return VelocityState(activity, v, p, count)


def adaptive_step(evidence: torch.Tensor, state: VelocityState, shift: torch.Tensor,
                  params: RingParams, diagonals: torch.Tensor | None,
                  read: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
                  tracker: VelocityTracker):
    """One frame of the adaptive ring for ``B`` streams.

    Args:
        evidence: ``(B, N)`` normalised evidence of the new frames.
        state: :class:`VelocityState` before them.
        shift: ``(N, N)`` the learnt shift.
        params: ring decay and gain.
        diagonals: banded kernel of the shift (None: dense).
        read: the read-out, ``activity (B, N) -> (reference (B,), confidence (B,))``.
        tracker: the estimator.

    Returns:
        ``(activity (B, N), reference (B,), confidence (B,), new state)``.
    """
    activity = ring_step_velocity(evidence, state.activity, shift, params,
                                  state.velocity.to(evidence.device), diagonals,
                                  top=math.ceil(tracker.v_max))
    reference, confidence = read(activity)
    return activity, reference, confidence, tracker.update(state, reference, activity)

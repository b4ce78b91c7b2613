"""``OutputRing``: the recurrent output layer whose activity moves along the learnt route."""

from __future__ import annotations

import torch
from torch import nn

from torchseq.layers.functional import RingParams, RingState, learn_shift_matrix, ring_step


class OutputRing(nn.Module):
    """Output units on a ring: activity shifts through a learnt matrix and integrates evidence.

    ``activity_t = decay * activity_{t-1} @ shift.T + gain * evidence_t``. The shift matrix
    ``shift[next, current]`` is a buffer learnt by :meth:`learn` from the order in which
    units won during a training traverse (see
    :func:`torchseq.layers.functional.learn_shift_matrix`).

    Args:
        n_units: ``N``.
        decay: weight of the shifted old activity.
        gain: weight of the new evidence (None: ``1 - decay``).
        spread: largest lag that learns.
        spread_decay: weight ratio between successive lags.
        stay: weight of lag 0 (a unit onto itself).
        wrap: the route is a closed loop.
        device: device of the buffer.
        dtype: dtype of the buffer.
    """

    def __init__(self, n_units: int, decay: float = 0.9, gain: float | None = None,
                 spread: int = 2, spread_decay: float = 0.5, stay: float = 0.5,
                 wrap: bool = False, device=None, dtype=None) -> None:
        super().__init__()
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"decay must be in [0, 1), got {decay}")
        self.n_units = int(n_units)
        self.params = RingParams(float(decay), float(1.0 - decay if gain is None else gain))
        self.spread, self.spread_decay, self.stay, self.wrap = spread, spread_decay, stay, wrap
        self.register_buffer("shift", torch.zeros(n_units, n_units, device=device, dtype=dtype))

    def learn(self, winners: torch.Tensor) -> None:
        """Learn the shift matrix from a winner sequence.

        Args:
            winners: ``(T,)`` int64 unit indices in firing order.
        """
        shift = learn_shift_matrix(winners, self.n_units, self.spread, self.spread_decay,
                                   self.stay, self.wrap)
        self.shift.copy_(shift.to(self.shift))

    def initial_state(self, batch: int, like: torch.Tensor) -> RingState:
        """Zero activity ``(batch, N)`` on ``like``'s device and dtype."""
        return RingState(torch.zeros(batch, self.n_units, device=like.device, dtype=like.dtype))

    def forward(self, evidence: torch.Tensor,
                state: RingState | None = None) -> tuple[torch.Tensor, RingState]:
        """One step.

        Args:
            evidence: ``(B, N)``.
            state: previous state (None: zeros).

        Returns:
            ``(activity (B, N), state)``.
        """
        if state is None:
            state = self.initial_state(evidence.shape[0], evidence)
        return ring_step(evidence, state, self.shift.to(evidence.dtype), self.params)

    def extra_repr(self) -> str:
        """Summary for print(module)."""
        return (f"n_units={self.n_units}, decay={self.params.decay}, gain={self.params.gain}, "
                f"spread={self.spread}, spread_decay={self.spread_decay}, stay={self.stay}, "
                f"wrap={self.wrap}")

"""The output ring at a per-stream speed: :func:`ring_step` with the shift applied ``v`` times.

The learnt shift ``S`` moves the activity as fast as the reference traverse (one reference
frame per query frame on average). A stream whose query runs at ``v`` times that speed moves
its activity by the fractional power of ``S`` mixed from its two neighbouring integer powers:

``n = floor(v)``, ``f = v - n``, ``P_v(a) = (1 - f) S^n a + f S^(n + 1) a`` (``S^0 = I``),

``a_t = decay * P_v(a_{t-1}) + gain * evidence_t``.

``v = 1`` is :func:`~torchseq.layers.ring_step` exactly (``n = 1``, ``f = 0``: the same
product, then ``1 * x + 0 * y = x``), and the mean displacement of ``P_v`` is ``v`` times
``S``'s (``(1 - f) n + f (n + 1) = v`` applications).
"""

from __future__ import annotations

import torch

from torchseq.layers.ring import RingParams, ring_move

MAX_VELOCITY = 8.0  # at most 9 shift products per frame: a bound on the work a setting asks


def ring_step_velocity(evidence: torch.Tensor, activity: torch.Tensor, shift: torch.Tensor,
                       params: RingParams, velocity: torch.Tensor,
                       diagonals: torch.Tensor | None = None) -> torch.Tensor:
    """One ring step of ``B`` streams, each at its own speed ``velocity[b]``.

    Args:
        evidence: ``(B, N)`` feed-forward evidence of the new frame.
        activity: ``(B, N)`` activity after the previous step.
        shift: ``(N, N)`` ``S[next, current]``.
        params: :class:`~torchseq.layers.RingParams` (decay, gain).
        velocity: ``(B,)`` speeds in ``[0, MAX_VELOCITY]`` (1: the reference's).
        diagonals: ``(L + 1, N)`` from :func:`~torchseq.layers.ring.band_diagonals` (the
            banded kernel of :func:`~torchseq.layers.ring.ring_move`); None: dense.

    Returns:
        ``(B, N)`` the new activity.
    """
    v = velocity.to(torch.float64)
    if v.shape != (activity.shape[0],) or not bool(((v >= 0) & (v <= MAX_VELOCITY)).all()):
        raise ValueError(f"velocity must be ({activity.shape[0]},) in [0, {MAX_VELOCITY:g}], "
                         f"got {tuple(velocity.shape)}")
    n = torch.floor(v)
    frac = (v - n).to(activity.dtype)[:, None]  # (B, 1)
    n = n.to(torch.int64)
    top = int(n.max()) + (1 if bool((frac > 0).any()) else 0)
    powers = [activity]  # S^k a for k = 0..top
    for _ in range(top):
        powers.append(ring_move(powers[-1], shift, diagonals))
    stack = torch.stack(powers + [powers[-1]])  # (top + 2, B, N); the extra copy has f = 0
    rows = torch.arange(activity.shape[0], device=activity.device)
    low, high = stack[n.to(activity.device), rows], stack[(n + 1).to(activity.device), rows]
    moved = (1 - frac) * low + frac * high
    return params.decay * moved + params.gain * evidence


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
                       diagonals: torch.Tensor | None = None,
                       top: int | None = None) -> torch.Tensor:
    """One ring step of ``B`` streams, each at its own speed ``velocity[b]``.

    The powers ``S^k a``, ``k = 0..top``, are weighted per stream by ``1 - f`` at ``k = n``,
    ``f`` at ``k = n + 1`` and 0 elsewhere, and summed (two non-zero terms: the same value
    as indexing the two powers and mixing them): no branch reads the velocities once ``top``
    is given, so the step traces into a graph (the float ONNX export of the adaptive model).

    Args:
        evidence: ``(B, N)`` feed-forward evidence of the new frame.
        activity: ``(B, N)`` activity after the previous step.
        shift: ``(N, N)`` ``S[next, current]``.
        params: :class:`~torchseq.layers.RingParams` (decay, gain).
        velocity: ``(B,)`` speeds in ``[0, top]`` (``[0, MAX_VELOCITY]`` without ``top``;
            1: the reference's).
        diagonals: ``(L + 1, N)`` from :func:`~torchseq.layers.ring.band_diagonals` (the
            banded kernel of :func:`~torchseq.layers.ring.ring_move`); None: dense.
        top: shift products to compute (at most ``MAX_VELOCITY``), a bound on every speed
            known before the step (the adaptive model's ``ceil(velocity_max)``); None: the
            fewest these velocities need (read off their values: no graph form).

    Returns:
        ``(B, N)`` the new activity.

    Raises:
        ValueError: a velocity outside ``[0, top]`` (checked in eager runs; a traced graph
            takes the speeds it returned itself).
    """
    v = velocity.to(torch.float64)
    bound = MAX_VELOCITY if top is None else float(top)
    if top is not None and not 0 <= top <= MAX_VELOCITY:
        raise ValueError(f"top must be in 0..{MAX_VELOCITY:g}, got {top}")
    if v.shape != (activity.shape[0],) or (
            not torch.jit.is_tracing() and not bool(((v >= 0) & (v <= bound)).all())):
        raise ValueError(f"velocity must be ({activity.shape[0]},) in [0, {bound:g}], "
                         f"got {tuple(velocity.shape)}")
    n = torch.floor(v)
    frac = (v - n).to(activity.dtype)[:, None]  # (B, 1)
    if top is None:
        top = int(n.max()) + (1 if bool((frac > 0).any()) else 0)
    powers = [activity]  # S^k a for k = 0..top
    for _ in range(top):
        powers.append(ring_move(powers[-1], shift, diagonals))
    k = torch.arange(top + 1, dtype=torch.float64, device=activity.device)
    n = n.to(activity.device)[:, None]  # (B, 1)
    zero = torch.zeros_like(frac)
    # (B, top + 1): 1 - f at k = n, f at k = n + 1 (none where n = top: then f = 0), else 0
    weight = torch.where(n == k, 1 - frac, zero) + torch.where(n + 1 == k, frac, zero)
    # two non-zero terms per row: the sum is (1 - f) S^n a + f S^(n + 1) a in any order
    moved = (weight[:, :, None] * torch.stack(powers, dim=1)).sum(dim=1)
    return params.decay * moved + params.gain * evidence

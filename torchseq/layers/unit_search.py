"""A short sequence search over unit evidence, beside the output ring (SeqSLAM's search).

When the route is longer than the ring (each output unit stands for several frames) the
learnt shift matrix moves activity like a random walk and blurs the sequence it integrates
(``docs/results/neural-long-routes.md``). This stage scores straight lines through the last
``L`` frames of L3 evidence instead, as SeqSLAM scores trajectories through its difference
matrix, at a few speeds, in units per frame:

1. ``c_t = contrast_units(e_t, w)``: each unit's evidence against its ``2w + 1``
   neighbouring units (mean and standard deviation over the window, shrunk at the ends of
   the route), as SeqSLAM enhances its differences;
2. ``s_t[m] = max_v mean_{j < min(t + 1, L)} c_{t-j}[floor(x_m - v u j)]``: lines ending at
   position ``x_m = (m + 1/2) / P`` (``P`` phases per unit), moving at ``v`` times the
   reference's ``u`` units per frame (``u = N / R``), unit indices clamped at 0;
3. ``q_t[m] = s_t[m] + lambda z(a_t)[floor(x_m)]``: the ring's activity, standardised over
   units, is one input;
4. the place is the best position's frame within its unit, the confidence its margin over
   positions more than ``window`` units away; candidates past the first are ranked by each
   unit's best position (:func:`search_units`), one frame per unit.

State: the last ``L`` contrast-enhanced evidence vectors, ``(B, L, N)``: bounded by the
unit count, not the route. :func:`unit_search_step` is the definition;
:func:`unit_search_scan` is its sequence form over one stream (tested against it).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

VELOCITIES = (0.8, 0.9, 1.0, 1.1, 1.2)  # line speeds, times the reference's (SeqSLAM's)


class SearchHistory(NamedTuple):
    """State of the unit search.

    Attributes:
        evidence: ``(B, L, N)`` the last ``L`` contrast-enhanced evidence vectors, newest
            first (zeros before the stream's start).
        filled: ``(B,)`` int64 frames seen, capped at ``L``.
    """

    evidence: torch.Tensor
    filled: torch.Tensor


def contrast_units(evidence: torch.Tensor, window: int, eps: float = 1e-6) -> torch.Tensor:
    """Each unit's evidence z-scored against its ``2 window + 1`` neighbouring units.

    ``c[b, u] = (e[b, u] - mean_W e[b]) / sqrt(max(var_W e[b], eps ** 2))`` over the units
    ``W = [u - window, u + window]`` clipped to ``0..N-1`` (fewer units at the ends).

    Args:
        evidence: ``(B, N)``.
        window: units on each side (0: the evidence unchanged).
        eps: floor of the standard deviation.

    Returns:
        ``(B, N)``.
    """
    if window <= 0:
        return evidence
    n, k = evidence.shape[1], 2 * window + 1
    ones = torch.ones(1, 1, n, dtype=evidence.dtype, device=evidence.device)
    count = F.avg_pool1d(F.pad(ones, (window, window)), k, 1)[0] * k  # (1, N)
    x = F.pad(evidence[:, None], (window, window))  # (B, 1, N + 2w), zeros outside
    mean = F.avg_pool1d(x, k, 1)[:, 0] * k / count
    square = F.avg_pool1d(x * x, k, 1)[:, 0] * k / count
    sd = (square - mean * mean).clamp_min(eps * eps).sqrt()
    return (evidence - mean) / sd


def search_lines(n_units: int, n_frames: int, length: int, phases: int,
                 velocities: tuple[float, ...] = VELOCITIES,
                 device=None) -> torch.Tensor:
    """Unit index of every line at every lag: ``floor(x_m - v (N / R) j)`` clamped at 0.

    Args:
        n_units: ``N``.
        n_frames: reference frames ``R`` the units stand for.
        length: lags ``L`` (frames of a line).
        phases: positions per unit ``P``.
        velocities: speeds, times the reference's.
        device: where the table lives.

    Returns:
        ``(V, L, N * P)`` int64.
    """
    x = (torch.arange(n_units * phases, dtype=torch.float64) + 0.5) / phases  # (M,)
    v = torch.tensor(velocities, dtype=torch.float64)[:, None, None] * (n_units / n_frames)
    j = torch.arange(length, dtype=torch.float64)[None, :, None]
    return torch.floor(x[None, None] - v * j).clamp_min(0).to(torch.int64).to(device)


def unit_search_step(evidence: torch.Tensor, activity: torch.Tensor, state: SearchHistory,
                     lines: torch.Tensor, window: int, ring_weight: float,
                     eps: float = 1e-6) -> tuple[torch.Tensor, SearchHistory]:
    """One step of the search: push the new evidence, score every line ending now.

    Args:
        evidence: ``(B, N)`` L3 evidence of the new frame (before the ring).
        activity: ``(B, N)`` the ring's activity after this frame.
        state: :class:`SearchHistory` before the frame.
        lines: ``(V, L, M)`` from :func:`search_lines`.
        window: :func:`contrast_units`' window.
        ring_weight: ``lambda``, the weight of the standardised ring activity.
        eps: numerical floor.

    Returns:
        ``(scores (B, M), new state)``.
    """
    n_lags = lines.shape[1]
    c = contrast_units(evidence, window, eps)
    hist = torch.cat([c[:, None], state.evidence[:, :n_lags - 1]], 1)  # (B, L, N)
    filled = (state.filled + 1).clamp_max(n_lags)
    lag = torch.arange(n_lags, device=hist.device)
    picked = hist[:, lag[None, :, None], lines]  # (B, V, L, M)
    seen = (lag[None, :] < filled[:, None]).to(hist.dtype)  # (B, L)
    sums = (picked * seen[:, None, :, None]).sum(2)  # (B, V, M)
    lines_score = sums.amax(1) / filled[:, None].to(hist.dtype)
    return (combine(lines_score, activity, lines.shape[2] // activity.shape[1], ring_weight, eps),
            SearchHistory(hist, filled))


def unit_search_scan(evidence: torch.Tensor, activity: torch.Tensor, lines: torch.Tensor,
                     window: int, ring_weight: float, eps: float = 1e-6) -> torch.Tensor:
    """:func:`unit_search_step` over one whole stream from an empty history.

    Args:
        evidence: ``(T, N)``.
        activity: ``(T, N)`` the ring's activity.
        lines: ``(V, L, M)``.
        window: :func:`contrast_units`' window.
        ring_weight: ``lambda``.
        eps: numerical floor.

    Returns:
        ``(T, M)`` scores.
    """
    n_frames = evidence.shape[0]
    c = contrast_units(evidence, window, eps)  # (T, N)
    n_vel, n_lags, m = lines.shape
    best = torch.full((n_frames, m), -torch.inf, dtype=c.dtype, device=c.device)
    for v in range(n_vel):
        total = torch.zeros(n_frames, m, dtype=c.dtype, device=c.device)
        for j in range(min(n_lags, n_frames)):
            total[j:] += c[:n_frames - j][:, lines[v, j]]
        best = torch.maximum(best, total)
    filled = torch.arange(1, n_frames + 1, device=c.device).clamp_max(n_lags)
    return combine(best / filled[:, None].to(c.dtype), activity, m // activity.shape[1],
                   ring_weight, eps)


def combine(line_scores: torch.Tensor, activity: torch.Tensor, phases: int,
            ring_weight: float, eps: float = 1e-6) -> torch.Tensor:
    """``line_scores + ring_weight * z(activity)`` at each position's unit.

    Args:
        line_scores: ``(B, N * P)``.
        activity: ``(B, N)``; z-scored over units (standard deviation floored at ``eps``).
        phases: ``P``.
        ring_weight: ``lambda`` (0: the lines alone).
        eps: numerical floor.

    Returns:
        ``(B, N * P)``.
    """
    if ring_weight == 0:
        return line_scores
    mean = activity.mean(1, keepdim=True)
    sd = (activity - mean).square().mean(1, keepdim=True).clamp_min(eps * eps).sqrt()
    z = (activity - mean) / sd
    return line_scores + ring_weight * z.repeat_interleave(phases, 1)


def search_decide(scores: torch.Tensor, spans: torch.Tensor, phases: int,
                  window: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The place of the best position, and its margin as confidence.

    Position ``m`` is unit ``u = m // P``, phase ``p = m % P``: reference frame
    ``f_u + floor((p + 1/2) (l_u - f_u) / P)`` of the unit's frames ``[f_u, l_u)``.
    ``confidence = q[m*] - max_{|u - u*| > window} q`` (minus ``min q`` when every unit is
    within the window). First position on ties.

    Args:
        scores: ``(B, M)``.
        spans: ``(N, 2)`` int64 first and one-past-last frame of each unit.
        phases: ``P``.
        window: units on each side of the winner that are not rivals.

    Returns:
        ``(reference (B,) int64, confidence (B,))``.
    """
    best, m = scores.max(1)
    unit, phase = m // phases, m % phases
    first, last = spans[unit, 0], spans[unit, 1]
    reference = first + ((2 * phase + 1) * (last - first)) // (2 * phases)
    units = torch.arange(scores.shape[1], device=scores.device) // phases  # (M,)
    near = (units[None] - unit[:, None]).abs() <= window  # (B, M)
    rival = scores.masked_fill(near, -torch.inf).amax(1)
    rival = torch.where(torch.isfinite(rival), rival, scores.amin(1))
    return reference, best - rival


def search_units(scores: torch.Tensor, spans: torch.Tensor,
                 phases: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Each unit's best position: its score and its frame (the search's ranked candidates).

    ``score[b, u] = max_p q[b, u P + p]`` and the frame of that phase, as
    :func:`search_decide` reads it: the best unit here holds the decision.

    Args:
        scores: ``(B, N * P)``.
        spans: ``(N, 2)`` int64 first and one-past-last frame of each unit.
        phases: ``P``.

    Returns:
        ``(scores (B, N), frames (B, N) int64)``.
    """
    best, phase = scores.reshape(scores.shape[0], -1, phases).max(2)
    first, last = spans[:, 0], spans[:, 1]
    return best, first + ((2 * phase + 1) * (last - first)) // (2 * phases)

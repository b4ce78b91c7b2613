"""Read-out of Neural SeqSLAM: the place is the most active ring unit, with a margin.

:func:`rank` turns any decision stage's per-unit scores into its ranked candidates.
"""

from __future__ import annotations

import numpy as np
import torch

DECIDE_KERNELS = ("torch", "numpy")


def decide(activity: torch.Tensor, unit_centre: torch.Tensor, window: int,
           kernel: str = "torch",
           spans: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Read the place out of the ring: the most active unit, and a margin as confidence.

    ``u* = argmax_u a_u`` (first index on ties); ``reference = unit_centre[u*]``;
    ``confidence = a_{u*} - max_{|v - u*| > window} a_v`` (minus ``min_v a_v`` when every
    unit is inside the window).

    With ``spans`` (readout ``"interpolate"``) the reference is read *within* the winner's
    stretch of frames ``[f, l)`` from its neighbours' activity: the vertex of the parabola
    through ``(-1, a_{u*-1}), (0, a_{u*}), (1, a_{u*+1})``,
    ``x = (a_{u*-1} - a_{u*+1}) / (2 (a_{u*-1} - 2 a_{u*} + a_{u*+1}))`` (``|x| <= 1/2``
    since ``a_{u*}`` is the maximum; ``x = 0`` when the denominator is 0 and at the first and
    last unit), then ``reference = clamp(floor((f + l - 1) / 2 + x (l - f) + 1/2), f,
    l - 1)``: a unit of one frame reports that frame whatever ``x``.

    Kernels: ``"torch"`` (any device, traceable: no data-dependent branch while tracing or
    exporting) and ``"numpy"`` (CPU, no gradients: the same numbers with a fraction of the
    per-call overhead).

    Args:
        activity: ``(B, N)``.
        unit_centre: ``(N,)`` int64 reference frame each unit stands for.
        window: units on each side of the winner that are not rivals.
        kernel: ``"torch"`` or ``"numpy"``.
        spans: ``(N, 2)`` int64 first and one-past-last reference frame of each unit
            (``unit_to_reference``); None: report ``unit_centre``.

    Returns:
        ``(reference (B,) int64, confidence (B,) float)``.
    """
    # a window reaching past the ring changes nothing (every unit is inside already); clamped
    # so a hostile checkpoint's 10**9 cannot size an index tensor
    window = min(int(window), activity.shape[1])
    if kernel not in DECIDE_KERNELS:
        raise ValueError(f"kernel must be one of {DECIDE_KERNELS}, got {kernel!r}")
    if spans is not None:
        _, confidence = decide(activity, unit_centre, window, kernel)
        unit = activity.argmax(dim=1)
        if kernel == "numpy":
            pos = _within_unit_numpy(activity.numpy(), unit.numpy(), spans.numpy())
            return torch.from_numpy(pos), confidence
        return _within_unit(activity, unit, spans), confidence
    if kernel == "numpy":
        return _decide_numpy(activity, unit_centre, window)
    tracing = torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()  # no data-dependence
    unit = activity.argmax(dim=1)
    best = activity.gather(1, unit[:, None])[:, 0]
    n = activity.shape[1]
    near = (unit[:, None] + torch.arange(-window, window + 1, device=activity.device))
    masked = activity.scatter(1, near.clamp(0, n - 1), float("-inf"))  # (B, N)
    second = masked.amax(dim=1)  # -inf: every unit is inside the window
    inside = torch.isinf(second)
    if tracing or bool(inside.any()):
        second = torch.where(inside, activity.amin(dim=1), second)
    return unit_centre[unit], best - second


def rank(scores: torch.Tensor, frames: torch.Tensor, reference: torch.Tensor,
         k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The best ``k`` candidates of a decision stage, the first its decision.

    Units ranked by their score, each standing for its frame; the first candidate is the
    stage's own decision ``reference`` (inside the best unit's stretch: the interpolating
    read-out and the search's phases read a frame finer than the unit).

    Args:
        scores: ``(T, N)`` the stage's score per unit, higher is better (the ring: activity).
        frames: ``(N,)`` or ``(T, N)`` int64 frame each unit stands for.
        reference: ``(T,)`` int64 the stage's decisions.
        k: candidates (at most ``N``).

    Returns:
        ``(ranked (T, k) int64, ranked_score (T, k))``, best first.
    """
    top = scores.topk(min(k, scores.shape[1]), dim=1)
    ranked = (frames[top.indices] if frames.dim() == 1
              else frames.gather(1, top.indices))
    ranked[:, 0] = reference
    return ranked, top.values


def _decide_numpy(activity: torch.Tensor, unit_centre: torch.Tensor,
                  window: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Kernel of :func:`decide` in NumPy (NumPy's argmax also takes the first index on ties)."""
    if activity.device.type != "cpu" or activity.requires_grad:
        raise ValueError("decide's numpy kernel needs a CPU tensor without gradients")
    a = activity.numpy()
    b, n = a.shape
    if b == 1:  # one stream: scalar work on slices, no masked copy
        row = a[0]
        u = int(row.argmax())
        lo, hi = max(u - window, 0), min(u + window + 1, n)
        if lo == 0 and hi == n:
            second = row.min()
        else:
            second = max(row[:lo].max() if lo else -np.inf, row[hi:].max() if hi < n else -np.inf)
        conf = np.array([row[u] - second], a.dtype)
        return unit_centre[u:u + 1], torch.from_numpy(conf)
    unit = a.argmax(axis=1)  # (B,)
    best = a[np.arange(b), unit]
    near = np.clip(unit[:, None] + np.arange(-window, window + 1), 0, n - 1)  # (B, 2w + 1)
    masked = a.copy()
    np.put_along_axis(masked, near, -np.inf, axis=1)
    second = masked.max(axis=1)  # -inf: every unit is inside the window
    inside = np.isinf(second)
    if inside.any():
        second[inside] = a[inside].min(axis=1)
    return unit_centre[torch.from_numpy(unit)], torch.from_numpy(best - second)


def _within_unit(activity: torch.Tensor, unit: torch.Tensor, spans: torch.Tensor) -> torch.Tensor:
    """``(B,)`` int64 reference within each winner's stretch (see :func:`decide`), in torch."""
    n = activity.shape[1]

    def at(index: torch.Tensor) -> torch.Tensor:  # gather: no batch size frozen when traced
        return activity.gather(1, index.clamp(0, n - 1)[:, None])[:, 0].to(torch.float64)

    a0, am, ap = at(unit), at(unit - 1), at(unit + 1)
    den = am - 2.0 * a0 + ap
    inner = (unit > 0) & (unit < n - 1) & (den < 0)
    x = torch.where(inner, (am - ap) / (2.0 * torch.where(inner, den, -1.0)), 0.0)
    first, last = spans[unit, 0], spans[unit, 1]
    pos = torch.floor((first + last - 1).to(torch.float64) / 2.0 + x * (last - first) + 0.5)
    return torch.minimum(torch.maximum(pos.to(torch.int64), first), last - 1)


def _within_unit_numpy(a: np.ndarray, unit: np.ndarray, spans: np.ndarray) -> np.ndarray:
    """Kernel of :func:`_within_unit` in NumPy (the same float64 operations)."""
    n = a.shape[1]
    rows = np.arange(a.shape[0])
    a0 = a[rows, unit].astype(np.float64)
    am = a[rows, np.clip(unit - 1, 0, n - 1)].astype(np.float64)
    ap = a[rows, np.clip(unit + 1, 0, n - 1)].astype(np.float64)
    den = am - 2.0 * a0 + ap
    inner = (unit > 0) & (unit < n - 1) & (den < 0)
    x = np.where(inner, (am - ap) / (2.0 * np.where(inner, den, -1.0)), 0.0)
    first, last = spans[unit, 0], spans[unit, 1]
    pos = np.floor((first + last - 1).astype(np.float64) / 2.0 + x * (last - first) + 0.5)
    return np.minimum(np.maximum(pos.astype(np.int64), first), last - 1)

"""Read-out of Neural SeqSLAM: the place is the most active ring unit, with a margin."""

from __future__ import annotations

import numpy as np
import torch

DECIDE_KERNELS = ("torch", "numpy")


def decide(activity: torch.Tensor, unit_centre: torch.Tensor, window: int,
           kernel: str = "torch") -> tuple[torch.Tensor, torch.Tensor]:
    """Read the place out of the ring: the most active unit, and a margin as confidence.

    ``u* = argmax_u a_u`` (first index on ties); ``reference = unit_centre[u*]``;
    ``confidence = a_{u*} - max_{|v - u*| > window} a_v`` (minus ``min_v a_v`` when every
    unit is inside the window).

    Kernels: ``"torch"`` (any device, traceable: no data-dependent branch while tracing or
    exporting) and ``"numpy"`` (CPU, no gradients: the same numbers with a fraction of the
    per-call overhead).

    Args:
        activity: ``(B, N)``.
        unit_centre: ``(N,)`` int64 reference frame each unit stands for.
        window: units on each side of the winner that are not rivals.
        kernel: ``"torch"`` or ``"numpy"``.

    Returns:
        ``(reference (B,) int64, confidence (B,) float)``.
    """
    # a window reaching past the ring changes nothing (every unit is inside already); clamped
    # so a hostile checkpoint's 10**9 cannot size an index tensor
    window = min(int(window), activity.shape[1])
    if kernel == "numpy":
        return _decide_numpy(activity, unit_centre, window)
    if kernel != "torch":
        raise ValueError(f"kernel must be one of {DECIDE_KERNELS}, got {kernel!r}")
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

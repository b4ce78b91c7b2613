"""Input checks shared by the whole library: one helper per kind of mistake."""

from __future__ import annotations

from typing import Sequence

import torch


def check_shape(x: torch.Tensor, dims: Sequence[str | int], name: str = "input") -> None:
    """Raise a clear ``ValueError`` when ``x`` does not have the named shape.

    Args:
        x: tensor to check.
        dims: one entry per dimension: an int for a fixed size, a string for a free one
            (used only in the message), e.g. ``("T", "H", "W")`` or ``("B", 768)``.
        name: what the tensor is, for the message.
    """
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    want = "(" + ", ".join(str(d) for d in dims) + ")"
    if x.dim() != len(dims):
        raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")
    for size, d in zip(x.shape, dims):
        if isinstance(d, int) and size != d:
            raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")


def check_finite(x: torch.Tensor, name: str = "input") -> None:
    """Raise ``ValueError`` when ``x`` holds NaN or infinite values."""
    if x.is_floating_point() and not bool(torch.isfinite(x).all()):
        bad = int((~torch.isfinite(x)).sum())
        raise ValueError(f"{name} holds {bad} NaN or infinite value(s)")


def check_not_empty(x: torch.Tensor, name: str = "input") -> None:
    """Raise ``ValueError`` when ``x`` has no elements along its first axis."""
    if x.dim() == 0 or x.shape[0] == 0:
        raise ValueError(f"{name} is empty (shape {tuple(x.shape)})")

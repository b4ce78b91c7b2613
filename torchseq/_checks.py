"""Input checks shared by the whole library: one helper per kind of mistake."""

from __future__ import annotations

from typing import Sequence

import numpy as np
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


def torch_numbers(x: np.ndarray, name: str, error: type[Exception] = TypeError) -> np.ndarray:
    """``x`` in native byte order, refused unless its dtype is one torch holds.

    Numbers and bools of at most 8 bytes (complex: 16) pass; a big-endian array is copied to
    native order (torch refuses other byte orders); structured, text, date, object and
    long-double arrays raise ``error`` naming ``name`` and the dtype.
    """
    kind, size = x.dtype.kind, x.dtype.itemsize
    if x.dtype.names is not None or kind not in "biufc" or size > (16 if kind == "c" else 8):
        raise error(f"{name}: dtype {x.dtype} is not a number type torch holds")
    if not x.dtype.isnative:
        x = x.astype(x.dtype.newbyteorder("="))
    return x


def as_frames(x: torch.Tensor | np.ndarray, name: str = "frames") -> torch.Tensor:
    """A traverse of frames as a tensor: a tensor as it is, a NumPy array as one.

    A NumPy array shares its memory where it can (contiguous and writable) and is copied
    otherwise; nested lists of numbers become a tensor as ``torch.as_tensor`` makes it; anything
    else is a ``TypeError`` naming the accepted kinds.
    """
    if isinstance(x, torch.Tensor):
        return x
    if isinstance(x, np.ndarray):
        if not (np.issubdtype(x.dtype, np.number) or x.dtype == np.bool_):
            raise TypeError(f"{name} must hold numbers, got a NumPy array of {x.dtype}")
        x = torch_numbers(x, name)
        if not (x.flags.c_contiguous and x.flags.writeable):
            x = np.array(x, order="C")  # torch cannot wrap negative strides or read-only memory
        return torch.from_numpy(x)
    try:  # nested lists of numbers, as torch.as_tensor reads them
        return torch.as_tensor(x)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"{name} must be a torch.Tensor or a NumPy array, got "
                        f"{type(x).__name__}") from None

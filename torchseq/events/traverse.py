"""Event files as traverses: grey, non-negative ``(T, H, W)`` frames for place recognition."""

from __future__ import annotations

from pathlib import Path

import torch

from torchseq.events.frames import accumulate
from torchseq.events.io import read_events


def load_event_frames(path: str | Path, window_ms: float = 10.0, event_count: int | None = None,
                      frame_size: tuple[int, int] | None = None,
                      sensor_size: tuple[int, int] | None = None, mode: str = "count",
                      anchor: str | int = "first", **options) -> torch.Tensor:
    """Read an event file and accumulate it into grey frames.

    Each pixel of a frame is the number of events (both polarities) it fired in the window
    (``mode="count"``, like the event-count images of the LENS data), or ``|ON - OFF|``
    (``mode="signed"``), clipped to 0..255 and then area-pooled to ``frame_size``. Empty
    windows give zero frames. Events whose time goes backwards are reordered (with a warning).

    Args:
        path: ``.aedat``, ``.aedat4``, ``.raw``, ``.csv``/``.txt``, ``.npz`` or structured ``.npy``.
        window_ms: window length in milliseconds (ignored when ``event_count`` is set).
        event_count: events per frame instead of time windows.
        frame_size: ``(H, W)`` to area-pool the frames to, or None for the sensor size.
        sensor_size: ``(W, H)`` override of the file's sensor size.
        mode: ``"count"`` or ``"signed"`` (its absolute value).
        anchor: where window 0 starts: ``"first"`` (the first event, default), ``"zero"``
            (sensor time 0) or an int sensor time in microseconds; frame ``k`` covers
            ``[origin + k * window, origin + (k + 1) * window)``. Events before the anchor
            are dropped (see :func:`torchseq.events.accumulate`).
        **options: reader options (see :func:`torchseq.events.iter_events`).

    Returns:
        ``(T, H, W)`` float32 frames in 0..255.
    """
    if mode not in ("count", "signed"):
        raise ValueError(f"mode must be 'count' or 'signed', got {mode!r}")
    if event_count is None and not window_ms > 0:
        raise ValueError(f"window_ms must be > 0, got {window_ms}")
    stream = read_events(path, sensor_size=sensor_size, sort=True, **options)
    window_us = None if event_count is not None else max(1, int(round(window_ms * 1000)))
    frames = accumulate(stream, window_us=window_us, event_count=event_count, mode=mode,
                        anchor=anchor)
    frames = frames.abs().clamp_(0, 255)
    if frame_size is not None:
        frames = accumulate_pool(frames, frame_size)
    return frames.to(torch.float32)


def accumulate_pool(frames: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Area-pool ``(T, H, W)`` frames to ``size`` ``(H', W')``."""
    h, w = size
    if not (0 < h <= frames.shape[-2] and 0 < w <= frames.shape[-1]):
        raise ValueError(f"frame_size {size} must be within the {tuple(frames.shape[-2:])} frame")
    return torch.nn.functional.adaptive_avg_pool2d(frames[:, None], (int(h), int(w)))[:, 0]

"""Frames from events: time-window or event-count accumulation, downsampled by area pooling.

Event ``i`` falls into window ``(t_i - t_start) // window_us`` (or ``i // event_count``) and
lands at flat index ``window * H * W + y * W + x`` (``((window * 2 + p) * H + y) * W + x``
for two channels); one ``torch.bincount`` builds all frames, on the CPU or CUDA. Windows
without events give zero frames (they are kept, so frame ``k`` always covers
``[t_start + k * window_us, t_start + (k + 1) * window_us)``). A last, partial event-count
window is kept.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from torchseq.events.filters import check_events_present, hot_pixel_mask, refractory_mask
from torchseq.events.stream import EventStream, as_event_array, infer_sensor_size

MODES = ("signed", "two_channel", "binary", "count")


def window_index(t: np.ndarray, window_us: int | None, event_count: int | None,
                 t_start: int | None = None) -> tuple[np.ndarray, int]:
    """``(N,)`` window of each event and the number of windows ``T``."""
    if (window_us is None) == (event_count is None):
        raise ValueError("give exactly one of window_us and event_count")
    if event_count is not None:
        if event_count < 1:
            raise ValueError(f"event_count must be >= 1, got {event_count}")
        idx = np.arange(len(t), dtype=np.int64) // int(event_count)
    else:
        if window_us <= 0:
            raise ValueError(f"window_us must be > 0, got {window_us}")
        t0 = int(t.min()) if t_start is None else int(t_start)
        if t0 > t.min():
            raise ValueError(f"t_start {t0} is after the first event ({int(t.min())} us)")
        idx = (t.astype(np.int64) - t0) // int(window_us)
    return idx, int(idx.max()) + 1


def accumulate(events: EventStream | np.ndarray, sensor_size: tuple[int, int] | None = None,
               window_us: int | None = 10_000, event_count: int | None = None,
               mode: str = "signed", hot_pixel: float | None = None,
               refractory_us: int | None = None, downsample: tuple[int, int] | None = None,
               t_start: int | None = None, device: torch.device | str | None = None,
               dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Accumulate events into frames.

    Args:
        events: an :class:`EventStream` or a structured array with ``t, x, y, p``.
        sensor_size: ``(W, H)``; default the stream's (arrays: inferred from coordinates).
        window_us: window length in microseconds (used when ``event_count`` is None).
        event_count: events per frame instead of time windows (sets ``window_us`` aside).
        mode: ``"signed"`` (ON - OFF), ``"two_channel"`` (channel 0 OFF, 1 ON counts),
            ``"binary"`` (1 where any event) or ``"count"`` (events of both polarities).
        hot_pixel: drop pixels with more than this many times the median count of active
            pixels (None: off).
        refractory_us: drop events within this time of the pixel's last kept event.
        downsample: ``(H', W')`` output size by area pooling (mean over each block).
        t_start: time of the first window's start (default the first event's time).
        device: where to build the frames.
        dtype: output float dtype.

    Returns:
        ``(T, H, W)`` frames, or ``(T, 2, H, W)`` for ``"two_channel"``.

    Raises:
        EventFormatError: no events.
        ValueError: bad mode, window or size.
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if isinstance(events, EventStream):
        sensor_size = sensor_size or events.sensor_size
        events = events.events
    events = as_event_array(events)
    check_events_present(events)
    sensor_size = tuple(sensor_size) if sensor_size else infer_sensor_size(events)
    EventStream(events[:0], sensor_size)  # checks the size
    win, n_frames = window_index(events["t"], window_us if event_count is None else None,
                                 event_count, t_start)
    keep = None
    if hot_pixel is not None:
        keep = hot_pixel_mask(events, sensor_size, hot_pixel)
    if refractory_us is not None:
        mask = refractory_mask(events, sensor_size, refractory_us)
        keep = mask if keep is None else keep & mask
    w, h = sensor_size
    x, y, p = events["x"], events["y"], events["p"]
    if x.min() < 0 or y.min() < 0 or x.max() >= w or y.max() >= h:
        raise ValueError(f"events outside the {w}x{h} sensor: wrong sensor_size?")
    if keep is not None:
        x, y, p, win = x[keep], y[keep], p[keep], win[keep]
    channels = 2 if mode == "two_channel" else 1
    flat = win * (channels * h * w)  # int64
    if channels == 2:
        flat += p.astype(np.int64) * (h * w)
    flat += y.astype(np.int64) * w
    flat += x
    dev = torch.device(device) if device is not None else torch.device("cpu")
    acc = torch.float64 if dtype == torch.float64 else torch.float32  # exact below 2**24
    weights = None
    if mode == "signed":
        weights = torch.from_numpy(p).to(dev).to(acc).mul_(2).sub_(1)
    size = n_frames * channels * h * w
    frames = torch.bincount(torch.from_numpy(flat).to(dev), weights=weights,
                            minlength=size).to(dtype)
    if mode == "binary":
        frames = (frames > 0).to(dtype)
    frames = frames.reshape(n_frames, channels, h, w)
    if downsample is not None:
        dh, dw = downsample
        if not (0 < dh <= h and 0 < dw <= w):
            raise ValueError(f"downsample size {downsample} must be within the {h}x{w} frame")
        frames = F.adaptive_avg_pool2d(frames, (int(dh), int(dw)))
    return frames if channels == 2 else frames[:, 0]

"""Events from frames: log-intensity threshold crossings between linearly interpolated frames.

Each pixel keeps a reference log intensity (initially the first frame's). Between two
frames the log intensity ``L = log(I + eps)`` moves linearly in time; every time it crosses
``reference + k * C_on`` (up) or ``reference - k * C_off`` (down) an ON / OFF event fires at
the interpolated crossing time and the reference moves to that level, so several events per
pixel per frame interval are possible and the reference never lags by a threshold or more.
Thresholds can vary per pixel (Gaussian ``threshold_noise``, as in ESIM/v2e), a refractory
period drops events that follow a pixel's last kept event too closely (the reference still
moves), and uniform background-activity noise can be added. The loop runs over frame
intervals; everything inside is vectorised over pixels.
"""

from __future__ import annotations

import numpy as np
import torch

from torchseq.events.filters import refractory_mask
from torchseq.events.stream import EventStream, make_events


def _frame_times(n: int, timestamps_us, fps: float | None, speed: float) -> np.ndarray:
    if speed <= 0:
        raise ValueError(f"speed must be > 0, got {speed}")
    if timestamps_us is not None:
        t = np.asarray(timestamps_us, dtype=np.float64).reshape(-1)
        if len(t) != n:
            raise ValueError(f"{len(t)} timestamps for {n} frames")
        if (np.diff(t) <= 0).any():
            raise ValueError("frame timestamps must increase strictly")
    elif fps is not None and fps > 0:
        t = np.arange(n, dtype=np.float64) * (1e6 / fps)
    else:
        raise ValueError("give timestamps_us or fps > 0")
    return (t - t[0]) / speed + t[0]


def frames_to_events(frames: np.ndarray | torch.Tensor, timestamps_us=None,
                     fps: float | None = None, contrast_threshold: float = 0.2,
                     speed: float = 1.0, threshold_noise: float = 0.0,
                     refractory_us: int = 0, noise_rate_hz: float = 0.0, eps: float = 1.0,
                     seed: int = 0) -> EventStream:
    """Simulate an event camera watching a frame sequence.

    Args:
        frames: ``(T, H, W)`` intensities in 0..255, T >= 2.
        timestamps_us: ``(T,)`` frame times in microseconds (strictly increasing), or None
            with ``fps``.
        fps: frame rate when ``timestamps_us`` is None (first frame at t = 0).
        contrast_threshold: ``C``, the log-intensity step per event (both polarities).
        speed: playback speed factor: frame times are divided by it (2 = twice as fast).
        threshold_noise: std of the per-pixel Gaussian spread of ``C`` (clipped at 0.01).
        refractory_us: per-pixel refractory period for output events (0: off).
        noise_rate_hz: background-activity events per pixel per second (random polarity).
        eps: offset in ``log(I + eps)`` so that black pixels stay finite.
        seed: random seed for threshold and background noise.

    Returns:
        An :class:`EventStream` of sensor size ``(W, H)``, time-ordered (ties by pixel).
    """
    frames = torch.as_tensor(frames).detach().cpu().to(torch.float64).numpy()
    if frames.ndim != 3 or frames.shape[0] < 2:
        raise ValueError(f"frames must be (T, H, W) with T >= 2, got {frames.shape}")
    if not np.isfinite(frames).all() or frames.min() < 0:
        raise ValueError("frames must be finite and non-negative")
    if contrast_threshold <= 0:
        raise ValueError(f"contrast_threshold must be > 0, got {contrast_threshold}")
    n, h, w = frames.shape
    times = _frame_times(n, timestamps_us, fps, speed)
    rng = np.random.default_rng(seed)
    c_on = np.full(h * w, contrast_threshold)
    c_off = np.full(h * w, contrast_threshold)
    if threshold_noise > 0:
        c_on = np.maximum(c_on + rng.normal(0, threshold_noise, h * w), 0.01)
        c_off = np.maximum(c_off + rng.normal(0, threshold_noise, h * w), 0.01)
    log = np.log(frames.reshape(n, h * w) + eps)
    ref = log[0].copy()
    parts = []
    for k in range(n - 1):
        a, b = log[k], log[k + 1]
        up = np.floor((b - ref) / c_on).clip(min=0).astype(np.int64)
        down = np.floor((ref - b) / c_off).clip(min=0).astype(np.int64)
        count = up + down
        total = int(count.sum())
        if total:
            pix = np.repeat(np.arange(h * w), count)
            j = np.arange(total) - np.repeat(np.cumsum(count) - count, count) + 1  # 1..count
            on = up[pix] > 0
            level = ref[pix] + np.where(on, j * c_on[pix], -j * c_off[pix])
            step = b[pix] - a[pix]
            frac = np.clip((level - a[pix]) / np.where(step != 0, step, 1.0), 0.0, 1.0)
            t = times[k] + frac * (times[k + 1] - times[k])
            order = np.lexsort((pix, t))
            parts.append((t[order], pix[order], on[order]))
        ref = ref + up * c_on - down * c_off
    if parts:
        t, pix, on = (np.concatenate(v) for v in zip(*parts))
    else:
        t, pix, on = np.zeros(0), np.zeros(0, np.int64), np.zeros(0, bool)
    events = make_events(np.round(t).astype(np.int64), pix % w, pix // w, on)
    if noise_rate_hz > 0:
        span = times[-1] - times[0]
        m = rng.poisson(noise_rate_hz * h * w * span * 1e-6)
        noise = make_events(rng.uniform(times[0], times[-1], m).round().astype(np.int64),
                            rng.integers(0, w, m), rng.integers(0, h, m), rng.integers(0, 2, m))
        events = np.concatenate([events, noise])
        events = events[np.argsort(events["t"], kind="stable")]
    if refractory_us > 0:
        events = events[refractory_mask(events, (w, h), refractory_us)]
    return EventStream(events, (w, h))

"""Event filters: hot pixels and a per-pixel refractory period (NumPy, vectorised)."""

from __future__ import annotations

import numpy as np

from torchseq.events.stream import EventFormatError


def hot_pixel_mask(events: np.ndarray, sensor_size: tuple[int, int],
                   factor: float = 10.0) -> np.ndarray:
    """``(N,)`` bool, True for events of pixels that are not hot.

    A pixel is hot when its event count exceeds ``factor`` times the median count of the
    pixels that fired at all. Memory follows the events, not the sensor: a dense count per
    pixel only when the sensor has at most about four pixels per event.
    """
    if factor <= 0:
        raise ValueError(f"hot pixel factor must be > 0, got {factor}")
    w, h = sensor_size
    pix = events["y"].astype(np.int64) * w + events["x"]
    if w * h <= 4 * len(events) + (1 << 16):  # dense per-pixel counts: one bincount
        counts = np.bincount(pix, minlength=w * h)
        active = counts[counts > 0]
        per_event = counts[pix]
    else:  # a large sensor with few events: counts of the pixels that fired only
        _, inverse, active = np.unique(pix, return_inverse=True, return_counts=True)
        per_event = active[inverse]
    if not len(active):
        return np.ones(len(events), bool)
    return per_event <= factor * np.median(active)


def refractory_mask(events: np.ndarray, sensor_size: tuple[int, int],
                    period_us: int) -> np.ndarray:
    """``(N,)`` bool, True for events kept by a per-pixel refractory period.

    An event is dropped when the last *kept* event of the same pixel (either polarity) is
    less than ``period_us`` earlier. Events of one pixel are visited in runs: an event at
    least ``period_us`` after its predecessor is always kept; inside a run of closer events
    the decision is made offset by offset, vectorised over all runs at once.
    """
    if period_us < 0:
        raise ValueError(f"refractory period must be >= 0, got {period_us}")
    n = len(events)
    keep = np.ones(n, bool)
    if n < 2 or period_us == 0:
        return keep
    w, _ = sensor_size
    pix = events["y"].astype(np.int64) * w + events["x"]
    order = np.lexsort((np.arange(n), events["t"], pix))  # by pixel, then time, then index
    p, t = pix[order], events["t"][order]
    close = np.r_[False, (p[1:] == p[:-1]) & (t[1:] - t[:-1] < period_us)]
    if not close.any():
        return keep
    # runs of consecutive "close" events; the event before each run is kept
    start = np.nonzero(close & ~np.r_[False, close[:-1]])[0]
    end = np.nonzero(close & ~np.r_[close[1:], False])[0] + 1
    last_kept = t[start - 1].copy()
    kept_sorted = np.ones(n, bool)
    for k in range(int((end - start).max())):
        live = start + k < end
        i = (start + k)[live]
        ok = t[i] - last_kept[live] >= period_us
        kept_sorted[i] = ok
        last_kept[live] = np.where(ok, t[i], last_kept[live])
    keep[order] = kept_sorted
    return keep


def check_events_present(events: np.ndarray) -> None:
    """Raise :class:`EventFormatError` when there are no events to accumulate."""
    if len(events) == 0:
        raise EventFormatError("no events to accumulate into frames")

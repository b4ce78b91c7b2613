"""Frames from events: time-window or event-count accumulation, downsampled by area pooling.

Windows start at an *anchor* (see :func:`window_origin`): the first event (default), sensor
time zero, or a given sensor time; events before the anchor are dropped. Event ``i`` falls
into window ``(t_i - origin) // window_us`` (or ``i // event_count`` among the kept events)
and lands at flat index ``(window * C + c) * H * W + y * W + x`` (channel ``c = p`` for two
channels, else 0); one scatter-add (``torch.bincount``) builds all frames. Windows without
events give zero frames (they are kept, so frame ``k`` always covers
``[origin + k * window_us, origin + (k + 1) * window_us)``). A last, partial event-count
window is kept.

Two kernels compute the flat indices, chosen by the device the frames are built on
(:func:`_kernel_for`): on the CPU NumPy does the index arithmetic in int32 where it fits and
uses the time order (window bounds by ``searchsorted`` instead of a division per event); on
other devices (CUDA) the same arithmetic runs in torch on the device.
"""

from __future__ import annotations

import numbers
import warnings

import numpy as np
import torch
import torch.nn.functional as F

from torchseq.events.filters import check_events_present, hot_pixel_mask, refractory_mask
from torchseq.events.stream import (
    EventFormatError,
    EventStream,
    as_event_array,
    infer_sensor_size,
)

MODES = ("signed", "two_channel", "binary", "count")
MAX_TIME_US = 2**62  # an int anchor (sensor time, us) lies within +-this: int64 with room
MAX_FRAME_ELEMENTS = 2**32  # bound on T * C * H * W of one accumulation (16 GiB float32)
# bound on C * H * W of one frame as built (64 MiB float32): 16x the largest event sensors
# made (1280x960, two channels); a header declaring a 32768x32768 sensor is refused
MAX_FRAME_PIXELS = 2**24
# a time anchor that leaves at least this many empty windows before the first event, and
# more empty windows than full ones, is warned about (e.g. anchor='zero' on a late recording)
EMPTY_LEAD_WARN = 100
# frames whose windows are mostly empty (two events far apart: a pause, a damaged time stamp)
# are refused beyond this many elements in all (1 GiB float32) before anything is allocated:
# their size follows the time span, not the events the file holds
MAX_SPARSE_ELEMENTS = 2**28


def window_origin(t: np.ndarray, anchor: str | int = "first") -> int:
    """Sensor time (us) where window 0 starts.

    Args:
        t: ``(N,)`` event times in microseconds (N >= 1 for ``"first"``).
        anchor: ``"first"`` (the earliest event), ``"zero"`` (sensor time 0) or an int
            sensor time in microseconds.

    Returns:
        The origin; frame ``k`` of a time-window accumulation covers
        ``[origin + k * window_us, origin + (k + 1) * window_us)``.
    """
    if isinstance(anchor, str):
        if anchor == "first":
            if len(t) == 0:
                raise ValueError("anchor='first' needs at least one event")
            return int(t.min())
        if anchor == "zero":
            return 0
        raise ValueError(f"anchor must be 'first', 'zero' or an int time in us, got {anchor!r}")
    if (isinstance(anchor, bool) or not isinstance(anchor, numbers.Integral)
            or not -MAX_TIME_US <= anchor <= MAX_TIME_US):
        raise ValueError(f"anchor must be 'first', 'zero' or an int time in us within "
                         f"+-2**62, got {anchor!r}")
    return int(anchor)


def sensor_wh(size) -> tuple[int, int]:
    """``(W, H)`` from a sensor size given as ``(W, H)`` or tonic's ``(W, H, P)``.

    Raises:
        ValueError: any other length (``P``, the polarity count, must be 1 or 2).
    """
    size = tuple(int(v) for v in size)
    if len(size) == 3 and size[2] in (1, 2):
        return size[:2]
    if len(size) != 2:
        raise ValueError(f"sensor_size must be (W, H) or tonic's (W, H, P), got {size}")
    return size


def _check_window(window_us, event_count) -> None:
    if (window_us is None) == (event_count is None):
        raise ValueError("give exactly one of window_us and event_count")
    if event_count is not None and event_count < 1:
        raise ValueError(f"event_count must be >= 1, got {event_count}")
    if window_us is not None and window_us <= 0:
        raise ValueError(f"window_us must be > 0, got {window_us}")


def accumulate(events: EventStream | np.ndarray, sensor_size: tuple[int, int] | None = None,
               window_us: int | None = 10_000, event_count: int | None = None,
               mode: str = "count", hot_pixel: float | None = None,
               refractory_us: int | None = None, downsample: tuple[int, int] | None = None,
               t_start: int | None = None, device: torch.device | str | None = None,
               dtype: torch.dtype = torch.float32, anchor: str | int = "first") -> torch.Tensor:
    """Accumulate events into frames.

    Args:
        events: an :class:`EventStream` or a structured array with ``t, x, y, p``.
        sensor_size: ``(W, H)`` (or tonic's ``(W, H, P)``); default the stream's (arrays:
            inferred from coordinates).
        window_us: window length in microseconds (used when ``event_count`` is None).
        event_count: events per frame instead of time windows (sets ``window_us`` aside).
        mode: ``"signed"`` (ON - OFF), ``"two_channel"`` (channel 0 OFF, 1 ON counts),
            ``"binary"`` (1 where any event) or ``"count"`` (events of both polarities).
        hot_pixel: drop pixels with more than this many times the median count of active
            pixels (None: off).
        refractory_us: drop events within this time of the pixel's last kept event.
        downsample: ``(H', W')`` output size by area pooling (mean over each block). When
            ``H'``, ``W'`` divide the sensor size (and the mode is not ``"binary"``) events
            are binned straight into the pooled pixels: same frames, no full-size buffer.
        t_start: older spelling of an int ``anchor`` that raises when events precede it.
        device: where to build the frames (picks the kernel, see the module docstring).
        dtype: output float dtype (float64 accumulates in float64, others in float32: exact
            up to 2**24 events per pixel and window).
        anchor: where window 0 starts: ``"first"`` (the first event, default), ``"zero"``
            (sensor time 0, so frame ``k`` covers ``[k * window_us, (k + 1) * window_us)``)
            or an int sensor time in microseconds. **Events before the anchor are dropped**
            (also with ``event_count``, which then counts from the first kept event).

    Returns:
        ``(T, H, W)`` frames, or ``(T, 2, H, W)`` for ``"two_channel"``.

    Raises:
        EventFormatError: no events (or none at or after the anchor).
        ValueError: bad mode, window, anchor or size, polarity not 0/1, frames of more
            than ``MAX_FRAME_ELEMENTS`` elements in all (a far anchor, tiny windows), or a
            frame buffer of more than ``MAX_FRAME_PIXELS`` elements (``C * H * W`` as built:
            the pooled size when ``downsample`` divides the sensor, else the sensor's), as
            from a header declaring a far larger sensor than its events use, or frames of
            more than ``MAX_SPARSE_ELEMENTS`` elements whose windows are mostly empty (the
            message names the time span, the window and the windows holding events).
    """
    frames, _, _ = accumulate_windows(
        events, sensor_size, window_us, event_count, mode, hot_pixel, refractory_us,
        downsample, t_start, device, dtype, anchor, occupied_only=False)
    return frames


def accumulate_windows(events, sensor_size, window_us, event_count, mode, hot_pixel,
                       refractory_us, downsample, t_start, device, dtype, anchor,
                       occupied_only: bool, frame_elements: int | None = None
                       ) -> tuple[torch.Tensor, np.ndarray, int]:
    """:func:`accumulate`, optionally building only the windows that hold events.

    Args:
        events: as :func:`accumulate`.
        sensor_size: as :func:`accumulate`.
        window_us: as :func:`accumulate`.
        event_count: as :func:`accumulate`.
        mode: as :func:`accumulate`.
        hot_pixel: as :func:`accumulate`.
        refractory_us: as :func:`accumulate`.
        downsample: as :func:`accumulate`.
        t_start: as :func:`accumulate`.
        device: as :func:`accumulate`.
        dtype: as :func:`accumulate`.
        anchor: as :func:`accumulate`.
        occupied_only: build only the ``K`` windows holding events (the others are zero
            frames), so memory follows the events, not the time span.
        frame_elements: elements of one frame as the caller will hold it (for the
            mostly-empty bound; default the frame as built here).

    Returns:
        ``(frames, windows, T)``: ``frames`` ``(K, ...)`` of the windows ``windows`` ``(K,)``
        (increasing window indices) out of ``T`` windows in all; ``K == T`` and ``windows``
        is ``arange(T)`` unless ``occupied_only``.
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if event_count is not None:
        window_us = None
    _check_window(window_us, event_count)
    if isinstance(events, EventStream):
        sensor_size = sensor_size or events.sensor_size
        events = events.events
    events = as_event_array(events)
    check_events_present(events)
    sensor_size = sensor_wh(sensor_size) if sensor_size else infer_sensor_size(events)
    EventStream(events[:0], sensor_size)  # checks the size
    w, h = sensor_size
    t = events["t"]
    ordered = len(t) < 2 or bool((t[1:] >= t[:-1]).all())  # one pass; spares min/max passes
    t_first = int(t[0]) if ordered else int(t.min())
    if t_start is not None:
        if not (isinstance(anchor, str) and anchor == "first"):
            raise ValueError("give anchor or t_start, not both")
        if int(t_start) > t_first:
            raise ValueError(f"t_start {int(t_start)} is after the first event ({t_first} us)")
        anchor = int(t_start)
    origin = t_first if isinstance(anchor, str) and anchor == "first" else window_origin(
        t, anchor)
    if origin > t_first:  # events before the anchor are dropped
        t_last = int(t[-1]) if ordered else int(t.max())
        events = events[np.searchsorted(t, origin):] if ordered else events[t >= origin]
        if len(events) == 0:
            raise EventFormatError(
                f"no events to accumulate into frames: the windows start at {origin} us (the "
                f"anchor), after the last event; the recording spans {t_first}..{t_last} us "
                f"({(t_last - t_first) / 1000:g} ms)")
    _check_fields(events, w, h)
    keep = None
    if hot_pixel is not None:
        keep = hot_pixel_mask(events, sensor_size, hot_pixel)
    if refractory_us is not None:
        mask = refractory_mask(events, sensor_size, refractory_us)
        keep = mask if keep is None else keep & mask
    if keep is not None:
        events = events[keep]
        if len(events) == 0:
            raise EventFormatError(f"no events left: the hot_pixel ({hot_pixel}) and "
                                   f"refractory_us ({refractory_us}) filters dropped all "
                                   f"{len(keep):,}")
    channels = 2 if mode == "two_channel" else 1
    out_h, out_w, fh, fw = h, w, 1, 1
    if downsample is not None:
        dh, dw = (int(v) for v in downsample)
        if not (0 < dh <= h and 0 < dw <= w):
            raise ValueError(f"downsample size {downsample} must be within the {h}x{w} frame")
        if mode != "binary" and h % dh == 0 and w % dw == 0:
            out_h, out_w, fh, fw = dh, dw, h // dh, w // dw
    _check_frame_pixels(channels, out_h, out_w, w, h, len(events))
    dev = torch.device(device) if device is not None else torch.device("cpu")
    acc = torch.float64 if dtype == torch.float64 else torch.float32
    geometry = _Geometry(out_w, out_h, fw, fh, channels)
    t_last = int(events["t"][-1]) if ordered else int(events["t"].max())
    n_frames = _count_windows(len(events), t_last, origin, window_us, event_count)
    windows = None  # (K,) the windows built, None: all n_frames
    elements = channels * out_h * out_w if frame_elements is None else frame_elements
    if window_us is not None and (occupied_only or n_frames * elements > MAX_SPARSE_ELEMENTS):
        wid = np.floor_divide(events["t"] - origin, int(window_us))  # (N,) window of each event
        occupied = (wid[np.concatenate(([True], wid[1:] != wid[:-1]))] if ordered
                    else np.unique(wid))
        check_window_span(n_frames, len(occupied), elements, origin,
                          int(events["t"][0]) if ordered else int(events["t"].min()), t_last,
                          window_us)
        if occupied_only and len(occupied) < n_frames:  # close the gaps: window k -> rank k
            events = events.copy()
            events["t"] -= (wid - np.searchsorted(occupied, wid)) * int(window_us)
            windows = occupied
    n_built = n_frames if windows is None else len(windows)
    size = n_built * channels * out_h * out_w
    if size > MAX_FRAME_ELEMENTS:
        raise ValueError(
            f"{n_built} windows of {channels}x{out_h}x{out_w} would need {size:,} elements "
            f"(> {MAX_FRAME_ELEMENTS:,}): use a later anchor, longer windows or downsample")
    if window_us is not None and origin < t_first:
        empty = (t_first - origin) // window_us  # windows that end before the first event
        if empty >= EMPTY_LEAD_WARN and 2 * empty > n_frames:
            warnings.warn(f"anchor {anchor!r}: {empty:,} of the {n_frames:,} windows "
                          f"({(t_first - origin) / 1e6:.1f} s) end before the first event (at "
                          f"{t_first} us) and are empty frames; anchor='first' starts at the "
                          f"first event", stacklevel=2)
    if windows is None:
        windows = np.arange(n_built)
    _, kernel = _kernel_for(dev)
    frames = kernel(events, origin, window_us, event_count, n_built, geometry,
                    mode == "signed", acc, dev, ordered)
    frames = frames.reshape(n_built, channels, out_h, out_w)
    if mode == "binary":
        frames = (frames > 0).to(acc)
    if fh * fw > 1:
        frames = frames / (fh * fw)
    elif downsample is not None and (out_h, out_w) != (int(downsample[0]), int(downsample[1])):
        frames = F.adaptive_avg_pool2d(frames, (int(downsample[0]), int(downsample[1])))
    frames = frames.to(dtype)
    return (frames if channels == 2 else frames[:, 0]), windows, n_frames


def check_window_span(n_frames: int, occupied: int, frame_elements: int, origin: int,
                      t_first: int, t_last: int, window_us: int) -> None:
    """Refuse frames that are mostly empty windows and too many to hold.

    Args:
        n_frames: windows in all.
        occupied: windows holding events.
        frame_elements: elements of one frame as it will be held.
        origin: sensor time (us) where window 0 starts.
        t_first: the first event's time (us).
        t_last: the last event's time (us).
        window_us: the window length (us).

    Raises:
        ValueError: more than ``MAX_SPARSE_ELEMENTS`` elements in ``n_frames`` frames of
            ``frame_elements`` each while fewer than half the windows hold events; the
            message names the time span, the window and the remedies.
    """
    size = n_frames * frame_elements
    if size > MAX_SPARSE_ELEMENTS and 2 * occupied < n_frames:
        lead = (f"the window origin at {origin} us is {(t_first - origin) / 1e6:,.1f} s before "
                f"the first event (use a later anchor); " if origin < t_first else "")
        raise ValueError(
            f"{n_frames:,} windows of {window_us / 1000:g} ms span {(t_last - origin) / 1e6:,.1f}"
            f" s (events at {t_first}..{t_last} us) but only {occupied:,} of them hold events: "
            f"the frames would need {size:,} elements ({size * 4 / 2**30:,.1f} GiB float32); "
            f"{lead}crop the recording (start_ms/duration_ms, --t-start/--duration), use "
            f"longer windows (--window-ms) or a fixed number of events per frame "
            f"(--event-count)")


class _Geometry:
    """Output layout: ``(C, H', W')`` and the integer pooling factors ``(fh, fw)``."""

    def __init__(self, w: int, h: int, fw: int, fh: int, channels: int) -> None:
        self.w, self.h, self.fw, self.fh, self.channels = w, h, fw, fh, channels
        self.plane = w * h


def _check_fields(events: np.ndarray, w: int, h: int) -> None:
    # int16 seen as uint16: negative coordinates become >= 32768, so one max checks both ends
    if len(events) == 0:
        return
    if (int(events["x"].view(np.uint16).max()) >= w
            or int(events["y"].view(np.uint16).max()) >= h):
        raise ValueError(f"events outside the {w}x{h} sensor: wrong sensor_size?")
    if int(events["p"].max()) > 1:
        raise ValueError(f"polarity must be 0 or 1, found {int(events['p'].max())}")


def _check_frame_pixels(channels: int, out_h: int, out_w: int, w: int, h: int, n: int) -> None:
    pixels = channels * out_h * out_w
    if pixels > MAX_FRAME_PIXELS:
        raise ValueError(
            f"frames of {channels}x{out_h}x{out_w} = {pixels:,} elements each for a {w}x{h} "
            f"sensor (> MAX_FRAME_PIXELS = {MAX_FRAME_PIXELS:,}) from {n:,} events: check "
            f"sensor_size (a file header may declare a larger sensor than the events use) or "
            f"pass downsample=(H', W') dividing {h}x{w}, which bins events straight into the "
            f"pooled pixels")


def _count_windows(n: int, t_last: int, origin: int, window_us, event_count) -> int:
    if event_count is not None:
        return max(1, -(-n // int(event_count)))
    return (t_last - origin) // int(window_us) + 1


def _kernel_for(device: torch.device):
    """``(name, kernel)`` that builds frames on ``device``.

    ``"numpy"`` on the CPU, else ``"torch"`` (the index arithmetic on the device).
    """
    if device.type == "cpu":
        return "numpy", _bins_numpy
    return "torch", _bins_torch


def _bins_numpy(events, origin, window_us, event_count, n_frames, g: _Geometry, signed, acc,
                device, ordered) -> torch.Tensor:
    t, x, y, p = events["t"], events["x"], events["y"], events["p"]
    n = len(t)
    stride = g.channels * g.plane
    itype = np.int32 if n_frames * stride < 2**31 else np.int64
    if event_count is not None:
        counts = np.full(n_frames, int(event_count), np.int64)
        counts[-1] = n - (n_frames - 1) * int(event_count)
        flat = np.repeat(np.arange(n_frames, dtype=itype) * itype(stride), counts)
    elif ordered:  # time-ordered: window bounds by searchsorted, no division per event
        bounds = np.searchsorted(t, origin + np.arange(1, n_frames) * int(window_us))
        counts = np.diff(np.concatenate(([0], bounds, [n])))
        flat = np.repeat(np.arange(n_frames, dtype=itype) * itype(stride), counts)
    else:
        flat = np.subtract(t, origin)
        np.floor_divide(flat, int(window_us), out=flat)
        flat = flat.astype(itype, copy=False)
        flat *= itype(stride)
    if g.fh > 1:
        flat += np.floor_divide(y, g.fh, dtype=itype) * itype(g.w)
    else:
        flat += np.multiply(y, itype(g.w), dtype=itype)
    flat += np.floor_divide(x, g.fw, dtype=itype) if g.fw > 1 else x
    if g.channels == 2:
        flat += np.multiply(p, itype(g.plane), dtype=itype)
    ftype = np.float64 if acc == torch.float64 else np.float32
    if signed:
        weights = np.multiply(p, ftype(2), dtype=ftype)
        weights -= 1
    else:
        weights = np.ones(n, ftype)
    frames = torch.bincount(torch.from_numpy(flat), torch.from_numpy(weights),
                            minlength=n_frames * stride)
    return frames.to(device)


def _bins_torch(events, origin, window_us, event_count, n_frames, g: _Geometry, signed, acc,
                device, ordered) -> torch.Tensor:
    t, x, y, p = (torch.from_numpy(events[f]).to(device) for f in "txyp")
    stride = g.channels * g.plane
    if event_count is not None:
        flat = torch.arange(len(t), device=device).div_(int(event_count), rounding_mode="floor")
    else:
        flat = (t - origin).div_(int(window_us), rounding_mode="floor")
    flat *= stride
    flat += y.long().div_(g.fh, rounding_mode="floor") * g.w
    flat += x.long().div_(g.fw, rounding_mode="floor")
    if g.channels == 2:
        flat += p.long() * g.plane
    weights = p.to(acc).mul_(2).sub_(1) if signed else torch.ones(len(t), dtype=acc,
                                                                  device=device)
    return torch.bincount(flat, weights, minlength=n_frames * stride)

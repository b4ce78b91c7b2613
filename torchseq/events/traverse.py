"""Event files as traverses: grey, non-negative ``(T, H, W)`` frames for place recognition."""

from __future__ import annotations

import math
import numbers
from pathlib import Path

import numpy as np
import torch

from torchseq.events.frames import accumulate_windows, sensor_wh, window_origin
from torchseq.events.io import read_events
from torchseq.events.stream import EventFormatError, EventStream

TRAVERSE_MODES = ("count", "signed", "two_channel", "binary")
MAX_TIME_MS = 2.0**52 / 1000  # windows, crops: at most 143 years, exact in int64 us


def _time_ms(value, lo: float, closed: bool = False) -> bool:
    """Whether ``value`` is a real number of ms in ``(lo, MAX_TIME_MS]`` (``[lo, ...]``)."""
    return (isinstance(value, numbers.Real) and not isinstance(value, bool)
            and (lo <= value if closed else lo < value) and value <= MAX_TIME_MS)


def load_event_frames(path: str | Path, window_ms: float = 10.0, event_count: int | None = None,
                      frame_size: tuple[int, int] | None = None,
                      sensor_size: tuple[int, int] | None = None, mode: str = "count",
                      anchor: str | int = "first", start_ms: float = 0.0,
                      duration_ms: float | None = None, hot_pixel: float | None = None,
                      refractory_us: int | None = None, centred_ms: float | None = None,
                      **options) -> torch.Tensor:
    """Read an event file and accumulate it into grey frames.

    Pixel values per ``mode``, each clipped to 0..255 and then area-pooled to ``frame_size``:

    - ``"count"``: events of both polarities (like the event-count images of the LENS data);
    - ``"signed"``: ``|ON - OFF|``;
    - ``"binary"``: 255 where the pixel fired at all in the window, else 0;
    - ``"two_channel"``: OFF and ON counts **side by side**: frame ``[:, :, :W]`` holds the
      OFF counts and ``[:, :, W:]`` the ON counts, so the engines, which read one grey image
      per frame, see a ``(H, 2W)`` image (``frame_size`` is the size of each half).

    Empty windows give zero frames. Events whose time goes backwards are reordered (with a
    warning).

    Args:
        path: ``.aedat``, ``.aedat4``, ``.raw``, ``.csv``/``.txt``, ``.npz``, structured
            ``.npy``, ``.h5``/``.hdf5`` or ``.parquet``.
        window_ms: window length in milliseconds (ignored when ``event_count`` is set).
        event_count: events per frame instead of time windows.
        frame_size: ``(H, W)`` to area-pool the frames to, or None for the sensor size.
        sensor_size: ``(W, H)`` (or tonic's ``(W, H, P)``) override of the file's sensor size.
        mode: ``"count"``, ``"signed"``, ``"binary"`` or ``"two_channel"`` (see above).
        anchor: where window 0 starts: ``"first"`` (the first event, default), ``"zero"``
            (sensor time 0) or an int sensor time in microseconds; frame ``k`` covers
            ``[origin + k * window, origin + (k + 1) * window)``. Events before the anchor
            are dropped (see :func:`torchseq.events.accumulate`).
        start_ms: time crop: skip this many milliseconds after the anchor's origin; windows
            then start at ``origin + start_ms`` (so frame ``k`` covers
            ``[origin + start + k * window, origin + start + (k + 1) * window)``).
        duration_ms: time crop: keep only events before ``origin + start_ms + duration_ms``
            (None: to the end of the recording).
        hot_pixel: drop the events of pixels firing more than this many times the median
            count of active pixels (None: off), counted over the cropped events.
        refractory_us: drop events within this many microseconds of the pixel's last kept
            event (None: off).
        centred_ms: a member of a temporal-window ensemble: frame ``k`` still stands for
            window ``k`` of ``window_ms``, but counts the events of the ``centred_ms`` long
            window centred on it (:func:`~torchseq.events.ensemble.accumulate_ensemble`;
            ``centred_ms - window_ms`` must be a whole, even number of microseconds). None:
            plain windows. Not with ``event_count``.
        **options: reader options (see :func:`torchseq.events.iter_events`).

    Returns:
        ``(T, H, W)`` float32 frames in 0..255 (``(T, H, 2W)`` for ``"two_channel"``).

    Raises:
        EventFormatError: no events in the crop (the message gives the recording's span).
        ValueError: bad mode, window or crop.
    """
    return load_event_windows(path, window_ms, event_count, frame_size, sensor_size, mode,
                              anchor, start_ms, duration_ms, hot_pixel, refractory_us,
                              centred_ms, **options).dense()


class WindowFrames:
    """``(T, H, W)`` event frames of which only the windows holding events are stored.

    A recording with long pauses (or two events far apart) has many empty windows; they are
    zero frames made when asked for, so memory follows the events, not the time span.
    ``len()`` is ``T`` and ``frames[i]`` is frame ``i`` ``(H, W)``, as from a tensor.

    Args:
        frames: ``(K, H, W)`` float32 frames of the windows holding events.
        windows: ``(K,)`` their increasing window indices.
        n_frames: ``T``, the windows in all.
    """

    def __init__(self, frames: torch.Tensor, windows: np.ndarray, n_frames: int) -> None:
        self.frames, self.windows, self.n_frames = frames, np.asarray(windows), int(n_frames)
        self._zero = torch.zeros(frames.shape[1:], dtype=frames.dtype)

    def __len__(self) -> int:
        return self.n_frames

    def __getitem__(self, i: int) -> torch.Tensor:
        i = int(i)
        if not -self.n_frames <= i < self.n_frames:
            raise IndexError(f"frame {i} of {self.n_frames}")
        i %= self.n_frames
        k = int(np.searchsorted(self.windows, i))
        if k < len(self.windows) and self.windows[k] == i:
            return self.frames[k]
        return self._zero

    def dense(self) -> torch.Tensor:
        """All ``T`` frames as one ``(T, H, W)`` tensor."""
        if len(self.windows) == self.n_frames:
            return self.frames
        out = torch.zeros((self.n_frames, *self.frames.shape[1:]), dtype=self.frames.dtype)
        out[torch.from_numpy(self.windows.astype(np.int64))] = self.frames
        return out


def load_event_windows(path: str | Path, window_ms: float = 10.0,
                       event_count: int | None = None,
                       frame_size: tuple[int, int] | None = None,
                       sensor_size: tuple[int, int] | None = None, mode: str = "count",
                       anchor: str | int = "first", start_ms: float = 0.0,
                       duration_ms: float | None = None, hot_pixel: float | None = None,
                       refractory_us: int | None = None, centred_ms: float | None = None,
                       **options) -> WindowFrames:
    """:func:`load_event_frames`, keeping the empty windows sparse (:class:`WindowFrames`).

    Raises:
        EventFormatError: as :func:`load_event_frames`.
        ValueError: as :func:`load_event_frames`, and frames of more than
            ``MAX_SPARSE_ELEMENTS`` elements (``T`` frames at their output size) whose
            windows are mostly empty (see :func:`torchseq.events.frames.check_window_span`).
    """
    if mode not in TRAVERSE_MODES:
        raise ValueError(f"mode must be one of {', '.join(TRAVERSE_MODES)}, got {mode!r}")
    if event_count is None and not _time_ms(window_ms, 0):
        raise ValueError(f"window_ms must be a time in (0, {MAX_TIME_MS:g}] ms, got "
                         f"{window_ms!r}")
    if event_count is not None and (isinstance(event_count, bool) or not isinstance(
            event_count, numbers.Integral) or not 1 <= event_count <= MAX_TIME_MS):
        raise ValueError(f"event_count must be an integer >= 1, got {event_count!r}")
    if not _time_ms(start_ms, 0, True):
        raise ValueError(f"start_ms must be a time in [0, {MAX_TIME_MS:g}] ms, got {start_ms!r}")
    if duration_ms is not None and not _time_ms(duration_ms, 0):
        raise ValueError(f"duration_ms must be a time in (0, {MAX_TIME_MS:g}] ms, got "
                         f"{duration_ms!r}")
    if frame_size is not None and (
            not isinstance(frame_size, (tuple, list)) or len(frame_size) != 2
            or not all(isinstance(v, numbers.Integral) and not isinstance(v, bool)
                       and 1 <= v <= 2**16 for v in frame_size)):
        raise ValueError(f"frame_size must be (H, W), two sizes of 1..65536, got "
                         f"{frame_size!r}")
    if sensor_size is not None:
        sensor_size = sensor_wh(sensor_size)
    stream = read_events(path, sensor_size=sensor_size, sort=True, **options)
    if start_ms or duration_ms is not None:
        stream, anchor = crop_events(stream, anchor, start_ms, duration_ms, path)
    window_us = None if event_count is not None else max(1, int(round(window_ms * 1000)))
    if centred_ms is not None:  # an ensemble member: every window, dense (ensemble.py)
        if event_count is not None:
            raise ValueError("centred_ms (an ensemble member) needs time windows, not "
                             "event_count")
        frames = _centred_frames(stream, window_us, centred_ms, mode, anchor, hot_pixel,
                                 refractory_us)
        n_frames = frames.shape[0]
        windows = np.arange(n_frames)
    else:
        channels = 2 if mode == "two_channel" else 1
        elements = (None if frame_size is None
                    else channels * int(frame_size[0]) * int(frame_size[1]))
        frames, windows, n_frames = accumulate_windows(
            stream, None, window_us, event_count, mode, hot_pixel, refractory_us, None, None,
            None, torch.float32, anchor, occupied_only=True, frame_elements=elements)
    if mode == "binary":
        frames = frames * 255
    frames = frames.abs().clamp_(0, 255)
    if mode == "two_channel":  # (T, 2, H, W): pool each channel, then OFF | ON side by side
        if frame_size is not None:
            frames = accumulate_pool(frames.flatten(0, 1), frame_size).unflatten(0, (-1, 2))
        frames = torch.cat([frames[:, 0], frames[:, 1]], dim=-1)
    elif frame_size is not None:
        frames = accumulate_pool(frames, frame_size)
    return WindowFrames(frames.to(torch.float32), windows, n_frames)


def crop_events(stream: EventStream, anchor: str | int, start_ms: float,
                duration_ms: float | None, name: object = "events"
                ) -> tuple[EventStream, int]:
    """The events of a time crop and the sensor time (us) where its windows start.

    Args:
        stream: time-ordered events.
        anchor: as :func:`torchseq.events.window_origin`.
        start_ms: the crop starts this long after the anchor's origin.
        duration_ms: the crop's length (None: to the end).
        name: what to call the events in an error (the file).

    Returns:
        ``(cropped stream, crop start in us)``; the crop start is the new anchor.

    Raises:
        EventFormatError: no events in the crop; the message says what the recording spans.
    """
    t = stream.events["t"]
    if len(t) == 0:
        raise EventFormatError(f"{name}: no events")
    origin = window_origin(t, anchor)
    begin = origin + int(round(start_ms * 1000))
    end = None if duration_ms is None else begin + max(1, int(round(duration_ms * 1000)))
    lo = int(np.searchsorted(t, begin, side="left"))
    hi = len(t) if end is None else int(np.searchsorted(t, end, side="left"))
    if hi <= lo:
        span = f"[{begin}, {'end' if end is None else end}) us"
        raise EventFormatError(
            f"{name}: no events in the time crop {span} (it starts {start_ms:g} ms after "
            f"the window origin, {origin} us); the recording spans "
            f"{int(t[0])}..{int(t[-1])} us ({(int(t[-1]) - int(t[0])) / 1000:g} ms)")
    return EventStream(stream.events[lo:hi], stream.sensor_size), begin


def accumulate_pool(frames: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Area-pool ``(T, H, W)`` frames to ``size`` ``(H', W')``."""
    h, w = size
    if not (0 < h <= frames.shape[-2] and 0 < w <= frames.shape[-1]):
        raise ValueError(f"frame_size {size} must be within the {tuple(frames.shape[-2:])} frame")
    return torch.nn.functional.adaptive_avg_pool2d(frames[:, None], (int(h), int(w)))[:, 0]


def _centred_frames(stream: EventStream, window_us: int, centred_ms: float, mode: str,
                    anchor: str | int, hot_pixel: float | None,
                    refractory_us: int | None) -> torch.Tensor:
    """One ensemble member: ``accumulate``'s windows and filters, windows centred and widened.

    Events before the anchor are dropped and the pixel filters applied as :func:`accumulate`
    does, then :func:`accumulate_ensemble` counts the ``centred_ms`` window around each
    ``window_us`` step (``(T, H, W)``, or ``(T, 2, H, W)`` for ``"two_channel"``).
    """
    from torchseq.events.ensemble import accumulate_ensemble
    from torchseq.events.filters import hot_pixel_mask, refractory_mask

    if not (math.isfinite(centred_ms) and centred_ms > 0):
        raise ValueError(f"centred_ms must be > 0, got {centred_ms}")
    events = stream.events
    origin = window_origin(events["t"], anchor)
    events = events[events["t"] >= origin]
    keep = np.ones(len(events), dtype=bool)
    if hot_pixel is not None:
        keep &= hot_pixel_mask(events, stream.sensor_size, hot_pixel)
    if refractory_us is not None:
        keep &= refractory_mask(events, stream.sensor_size, refractory_us)
    if not keep.all():
        events = events[keep]
    members = accumulate_ensemble(EventStream(events, stream.sensor_size),
                                  [max(1, int(round(centred_ms * 1000)))], step_us=window_us,
                                  mode=mode, anchor=origin)
    return members[0]

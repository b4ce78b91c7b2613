"""The event representation: a structured NumPy array plus the sensor size.

Events are rows of :data:`EVENT_DTYPE` with the field names tonic uses: ``t`` (int64,
microseconds), ``x`` and ``y`` (int16, pixel column and row, origin top-left, ``y`` down),
``p`` (uint8 polarity, 1 = ON = brighter, 0 = OFF = darker).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

EVENT_DTYPE = np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")], align=True)


class EventFormatError(ValueError):
    """An event file or array is malformed; the message says why in one line."""


def make_events(t, x, y, p) -> np.ndarray:
    """Pack equally long ``t, x, y, p`` sequences into an ``(N,)`` :data:`EVENT_DTYPE` array."""
    t, x, y, p = (np.asarray(v).reshape(-1) for v in (t, x, y, p))
    if not len(t) == len(x) == len(y) == len(p):
        raise EventFormatError(f"t, x, y, p lengths differ: {len(t)}, {len(x)}, {len(y)}, {len(p)}")
    out = np.empty(len(t), EVENT_DTYPE)
    out["t"], out["x"], out["y"], out["p"] = t, x, y, p
    return out


def as_event_array(events: np.ndarray, name: str = "events") -> np.ndarray:
    """Convert any structured array with fields ``t, x, y, p`` to :data:`EVENT_DTYPE`.

    Polarity given as -1/+1 (or any signed values) becomes 0/1 (``p > 0``).
    """
    events = np.asarray(events)
    if events.dtype.names and "t" in events.dtype.names and events["t"].dtype.kind == "f":
        from torchseq.events.times import with_us_times  # tonic's float seconds

        events = with_us_times(events, name)
    names = events.dtype.names or ()
    missing = [f for f in "txyp" if f not in names]
    if missing:
        raise EventFormatError(f"{name} lacks field(s) {', '.join(missing)} (has {names})")
    if events.dtype == EVENT_DTYPE:
        return events.reshape(-1)
    p = events["p"]
    if p.dtype.kind in "if" and (p < 0).any():
        p = p > 0
    return make_events(events["t"], events["x"], events["y"], p)


def infer_sensor_size(events: np.ndarray) -> tuple[int, int]:
    """``(W, H)`` as one more than the largest coordinates (a guess: edges may be unused)."""
    if len(events) == 0:
        raise EventFormatError("cannot infer the sensor size from zero events; pass sensor_size")
    return int(events["x"].max()) + 1, int(events["y"].max()) + 1


@dataclass
class EventStream:
    """Events of one recording and the size of the sensor that made them.

    Attributes:
        events: ``(N,)`` structured array of :data:`EVENT_DTYPE`, time-ordered.
        sensor_size: ``(W, H)`` in pixels (width first, as tonic).
    """

    events: np.ndarray
    sensor_size: tuple[int, int]

    def __post_init__(self) -> None:
        self.events = as_event_array(self.events)
        w, h = (int(v) for v in self.sensor_size)
        if w <= 0 or h <= 0:
            raise EventFormatError(f"sensor_size must be positive (W, H), got {self.sensor_size}")
        self.sensor_size = (w, h)

    def __len__(self) -> int:
        return len(self.events)

    @property
    def duration_us(self) -> int:
        """Time from the first to the last event, in microseconds (0 when empty)."""
        return int(self.events["t"][-1] - self.events["t"][0]) if len(self.events) else 0

    def validate(self) -> EventStream:
        """Check field dtypes, coordinates inside the sensor, polarity 0/1, monotonic time.

        Returns:
            ``self``, so that ``EventStream(...).validate()`` chains.

        Raises:
            EventFormatError: with the first problem found.
        """
        validate_events(self.events, self.sensor_size)
        return self

    def to_tensors(self, device: torch.device | str | None = None) -> dict[str, torch.Tensor]:
        """Fields as tensors ``{"t": (N,) int64, "x", "y": (N,) int16, "p": (N,) uint8}``.

        On the CPU these share memory with :attr:`events` (strided views, no copy).
        """
        return {f: torch.from_numpy(self.events[f]).to(device) for f in "txyp"}


def validate_events(events: np.ndarray, sensor_size: tuple[int, int]) -> None:
    """Raise :class:`EventFormatError` unless ``events`` are well-formed for ``sensor_size``."""
    if events.dtype != EVENT_DTYPE:
        raise EventFormatError(f"events must have dtype {EVENT_DTYPE.descr}, got {events.dtype}")
    if len(events) == 0:
        return
    w, h = sensor_size
    x, y, t, p = events["x"], events["y"], events["t"], events["p"]
    bad = (x < 0) | (x >= w) | (y < 0) | (y >= h)
    if bad.any():
        i = int(np.argmax(bad))
        raise EventFormatError(
            f"{int(bad.sum())} event(s) outside the {w}x{h} sensor, first #{i} at "
            f"x={x[i]}, y={y[i]}: wrong sensor_size?")
    if (p > 1).any():
        raise EventFormatError(f"polarity must be 0 or 1, found {int(p.max())}")
    back = np.diff(t) < 0
    if back.any():
        i = int(np.argmax(back)) + 1
        raise EventFormatError(
            f"timestamps go backwards at event #{i} ({t[i - 1]} -> {t[i]} us); pass "
            f"sort=True to reorder")


def order_events(events: np.ndarray, sort: bool, source: str = "events") -> np.ndarray:
    """Return ``events`` time-ordered: stable sort when ``sort``, else error if out of order."""
    back = np.diff(events["t"]) < 0
    if not back.any():
        return events
    if not sort:
        i = int(np.argmax(back)) + 1
        raise EventFormatError(
            f"{source}: timestamps go backwards at event #{i} ({events['t'][i - 1]} -> "
            f"{events['t'][i]} us); pass sort=True to reorder")
    warnings.warn(f"{source}: {int(back.sum())} backward time steps, events sorted by time",
                  stacklevel=3)
    return events[np.argsort(events["t"], kind="stable")]


def iter_records(f, path, dtype: np.dtype, body_bytes: int, chunk: int, truncated: str,
                 unit: str) -> Iterator[np.ndarray]:
    """Read a body of fixed-size binary records in chunks, after checking it is whole.

    Args:
        f: binary file positioned at the first record.
        path: the file's path, for messages.
        dtype: one record.
        body_bytes: bytes from the first record to the end of the file.
        chunk: records per yielded array.
        truncated: ``"error"`` or ``"drop"`` (warn and ignore a partial last record).
        unit: what a record is called in messages (e.g. ``"8-byte record"``).

    Yields:
        ``(n,)`` arrays of ``dtype``; at least one (empty for an empty body).
    """
    spare = body_bytes % dtype.itemsize
    if spare:
        msg = (f"{path}: truncated, {spare} trailing byte(s) after "
               f"{body_bytes // dtype.itemsize} whole {unit}s")
        if truncated != "drop":
            raise EventFormatError(msg + "; pass truncated='drop' to ignore them")
        warnings.warn(msg + ", dropped", stacklevel=3)
    n_left = body_bytes // dtype.itemsize
    while True:
        n = min(chunk, n_left)
        records = np.fromfile(f, dtype, n)
        if len(records) < n:
            raise EventFormatError(f"{path}: file shrank while reading")
        n_left -= n
        yield records
        if n_left == 0:
            return

"""The event representation: a structured NumPy array plus the sensor size.

Events are rows of :data:`EVENT_DTYPE` with the field names tonic uses: ``t`` (int64,
microseconds), ``x`` and ``y`` (int16, pixel column and row, origin top-left, ``y`` down),
``p`` (uint8 polarity, 1 = ON = brighter, 0 = OFF = darker).

Invariants every reader guarantees (and :func:`validate_events` checks): ``t`` int64 and
non-decreasing, ``0 <= x < W``, ``0 <= y < H``, ``p`` in {0, 1}, ``1 <= W, H <= 32768``
(``x`` and ``y`` are int16). Conversions into this form never wrap or round: a value that
does not fit (a coordinate above 32767, a time that is not an integer or not below 2**63, a
polarity other than -1, 0, 1) is an :class:`EventFormatError`.
"""

from __future__ import annotations

import operator
import warnings
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from torchseq.events.errors import EventFormatError, file_error

EVENT_DTYPE = np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")], align=True)
MAX_SENSOR_SIDE = 1 << 15  # x, y are int16: the largest column index is 32767
_T_RANGE = (-(1 << 63), (1 << 63) - 1)
_XY_RANGE = (-(1 << 15), (1 << 15) - 1)


def _checked_ints(v, name: str, lo: int, hi: int) -> np.ndarray:
    """``v`` as an integer array, exactly: error on non-integers or values outside [lo, hi]."""
    v = np.asarray(v).reshape(-1)
    kind = v.dtype.kind
    if kind == "b" or len(v) == 0:
        return v
    if kind in "iu":
        info = np.iinfo(v.dtype)
        if info.min >= lo and info.max <= hi:
            return v
        bad = (v < lo) | (v > hi) if info.min < lo else v > hi
    elif kind == "f":
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(v) | (np.floor(v) != v) | (v < lo) | (v >= float(hi) + 1)
    else:
        raise EventFormatError(f"{name} must be integers, got dtype {v.dtype}")
    if bad.any():
        i = int(np.argmax(bad))
        raise EventFormatError(f"{name}[{i}] = {v[i]!r} is not an integer in [{lo}, {hi}]")
    return v


def make_events(t, x, y, p) -> np.ndarray:
    """Pack equally long ``t, x, y, p`` sequences into an ``(N,)`` :data:`EVENT_DTYPE` array.

    Values are converted exactly: ``t`` integers (any integer or integral float dtype) in
    the int64 range, ``x``/``y`` integers in the int16 range, ``p`` in {-1, 0, 1} or bool
    (1/True = ON; 0 and -1 = OFF). Anything else raises :class:`EventFormatError`.
    """
    t = _checked_ints(t, "t", *_T_RANGE)
    x = _checked_ints(x, "x", *_XY_RANGE)
    y = _checked_ints(y, "y", *_XY_RANGE)
    p = _checked_ints(p, "p", -1, 1)
    if not len(t) == len(x) == len(y) == len(p):
        raise EventFormatError(f"t, x, y, p lengths differ: {len(t)}, {len(x)}, {len(y)}, {len(p)}")
    out = np.empty(len(t), EVENT_DTYPE)
    out["t"], out["x"], out["y"] = t, x, y
    out["p"] = p > 0
    return out


def as_event_array(events: np.ndarray, name: str = "events") -> np.ndarray:
    """Convert any structured array with fields ``t, x, y, p`` to :data:`EVENT_DTYPE`.

    Polarity given as -1/+1 becomes 0/1 (the rule of :func:`make_events`, element by element,
    so a file gives the same events whole or in chunks).
    """
    events = np.asarray(events)
    if events.dtype.names and "t" in events.dtype.names and events["t"].dtype.kind == "f":
        from torchseq.events.times import with_us_times  # tonic's float seconds

        events = with_us_times(events, name)
    names = events.dtype.names or ()
    missing = [f for f in "txyp" if f not in names]
    if missing:
        raise EventFormatError(f"{name} lacks field(s) {', '.join(missing)} (has {names})")
    if events.ndim == 0:
        raise EventFormatError(f"{name} is a single record (0-d array), not an event array")
    if events.dtype == EVENT_DTYPE:
        return events.reshape(-1)
    return make_events(events["t"], events["x"], events["y"], events["p"])


def check_sensor_size(size, source: str = "sensor_size") -> tuple[int, int]:
    """``(W, H)`` as two Python ints in ``1..32768``, else :class:`EventFormatError`."""
    try:
        w, h = (operator.index(v) if not isinstance(v, (float, np.floating)) or
                not float(v).is_integer() else int(v) for v in size)
    except (TypeError, ValueError, OverflowError):
        raise EventFormatError(f"{source} must be two integers (W, H), got {size!r}") from None
    if not (1 <= w <= MAX_SENSOR_SIDE and 1 <= h <= MAX_SENSOR_SIDE):
        raise EventFormatError(f"{source} must be positive (W, H) of at most {MAX_SENSOR_SIDE} "
                               f"each, got {w}x{h}")
    return w, h


def infer_sensor_size(events: np.ndarray) -> tuple[int, int]:
    """``(W, H)`` as one more than the largest coordinates (a guess: edges may be unused)."""
    if len(events) == 0:
        raise EventFormatError("cannot infer the sensor size from zero events; pass sensor_size")
    return check_sensor_size((int(events["x"].max()) + 1, int(events["y"].max()) + 1),
                             "the sensor size implied by the largest coordinates")


@dataclass
class EventStream:
    """Events of one recording and the size of the sensor that made them.

    Attributes:
        events: ``(N,)`` structured array of :data:`EVENT_DTYPE`, time-ordered.
        sensor_size: ``(W, H)`` in pixels (width first, as tonic), each 1..32768.
    """

    events: np.ndarray
    sensor_size: tuple[int, int]

    def __post_init__(self) -> None:
        self.events = as_event_array(self.events)
        self.sensor_size = check_sensor_size(self.sensor_size)

    def __len__(self) -> int:
        return len(self.events)

    @property
    def duration_us(self) -> int:
        """Time from the first to the last event, in microseconds (0 when empty)."""
        return int(self.events["t"][-1]) - int(self.events["t"][0]) if len(self.events) else 0

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


@dataclass
class Chunk(EventStream):
    """An :class:`EventStream` read from a file, with where it came from (for messages).

    Attributes:
        offset: byte offset in the file of the first record this chunk was decoded from
            (``None`` when unknown).
    """

    offset: int | None = None


def concat_events(parts: list[np.ndarray]) -> np.ndarray:
    """Concatenate :data:`EVENT_DTYPE` arrays into one new array, as raw 16-byte rows.

    Same result as ``np.concatenate(parts)``, about 5x faster: NumPy copies a structured
    dtype with padding field by field, so the rows are copied as pairs of uint64 instead.

    Args:
        parts: ``(N_i,)`` :data:`EVENT_DTYPE` arrays.

    Returns:
        ``(sum N_i,)`` :data:`EVENT_DTYPE` array (a fresh, writeable array).
    """
    if any(part.dtype != EVENT_DTYPE for part in parts):
        raise EventFormatError("concat_events takes EVENT_DTYPE arrays only")
    words = [np.ascontiguousarray(part).view(np.uint64) for part in parts]
    if not words:
        return np.empty(0, EVENT_DTYPE)
    return np.concatenate(words).view(EVENT_DTYPE)


def check_contents(events: np.ndarray, sensor_size: tuple[int, int]) -> None:
    """Raise :class:`EventFormatError` unless dtype, coordinates and polarity are valid."""
    if events.dtype != EVENT_DTYPE:
        raise EventFormatError(f"events must have dtype {EVENT_DTYPE.descr}, got {events.dtype}")
    if len(events) == 0:
        return
    w, h = check_sensor_size(sensor_size)
    x, y, p = events["x"], events["y"], events["p"]
    # one pass each: an int16 viewed as uint16 is >= w exactly when it is < 0 or >= w
    bad = (x.view(np.uint16) >= w) | (y.view(np.uint16) >= h)
    if bad.any():
        i = int(np.argmax(bad))
        raise EventFormatError(
            f"{int(bad.sum())} event(s) outside the {w}x{h} sensor, first #{i} at "
            f"x={x[i]}, y={y[i]}: wrong sensor_size?")
    if p.max() > 1:
        raise EventFormatError(f"polarity must be 0 or 1, found {int(p.max())}")


def first_backward(t: np.ndarray) -> int | None:
    """Index ``i`` of the first ``t[i] < t[i - 1]`` (no subtraction, so no overflow), or None."""
    back = t[1:] < t[:-1]
    return int(np.argmax(back)) + 1 if back.any() else None


def validate_events(events: np.ndarray, sensor_size: tuple[int, int]) -> None:
    """Raise :class:`EventFormatError` unless ``events`` are well-formed for ``sensor_size``."""
    check_contents(events, sensor_size)
    t = events["t"]
    i = first_backward(t)
    if i is not None:
        raise EventFormatError(
            f"timestamps go backwards at event #{i} ({t[i - 1]} -> {t[i]} us); pass "
            f"sort=True to reorder")


def order_events(events: np.ndarray, sort: bool, source: str = "events") -> np.ndarray:
    """Return ``events`` time-ordered: stable sort when ``sort``, else error if out of order."""
    t = events["t"]
    i = first_backward(t)
    if i is None:
        return events
    if not sort:
        raise EventFormatError(
            f"{source}: timestamps go backwards at event #{i} ({t[i - 1]} -> {t[i]} us); pass "
            f"sort=True to reorder")
    n_back = int((t[1:] < t[:-1]).sum())
    warnings.warn(f"{source}: {n_back} backward time steps, events sorted by time", stacklevel=3)
    return events[np.argsort(t, kind="stable")]


def check_truncated(truncated: str) -> str:
    """Validate the ``truncated=`` option (``"error"`` or ``"drop"``)."""
    if truncated not in ("error", "drop"):
        raise ValueError(f"truncated must be 'error' or 'drop', got {truncated!r}")
    return truncated


def iter_records(f, path, dtype: np.dtype, body_bytes: int, chunk: int, truncated: str,
                 unit: str) -> Iterator[tuple[int, np.ndarray]]:
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
        ``(byte offset, (n,) array of dtype)``; at least one (empty for an empty body).
    """
    check_truncated(truncated)
    start = f.tell()
    spare = body_bytes % dtype.itemsize
    if spare:
        end = start + body_bytes - spare
        msg = (f"truncated, {spare} trailing byte(s) after "
               f"{body_bytes // dtype.itemsize} whole {unit}s")
        if truncated != "drop":
            raise file_error(path, end, msg + "; pass truncated='drop' to ignore them")
        warnings.warn(f"{path}: {msg} (at byte {end}), dropped", stacklevel=3)
    n_left = body_bytes // dtype.itemsize
    pos = start
    while True:
        n = min(chunk, n_left)
        records = np.fromfile(f, dtype, n)
        if len(records) < n:
            raise file_error(path, pos + len(records) * dtype.itemsize, "file shrank while reading")
        n_left -= n
        yield pos, records
        pos += n * dtype.itemsize
        if n_left == 0:
            return

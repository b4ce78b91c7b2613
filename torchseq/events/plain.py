"""Plain event files: ``.npy`` / ``.npz`` structured arrays and ``t,x,y,p`` CSV / text.

``.npz`` files written by :func:`write_npz` hold ``events`` (structured) and
``sensor_size`` ``(W, H)``; ``.npz`` files with separate ``t``, ``x``, ``y``, ``p`` arrays
are read too. CSV/text: one event per line, ``t,x,y,p`` (commas or whitespace), an optional
header line naming the columns in any order; polarity -1/+1 becomes 0/1.
"""

from __future__ import annotations

import io
import re
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from torchseq.atomic import atomic_open
from torchseq.events.stream import (
    EventFormatError,
    EventStream,
    as_event_array,
    infer_sensor_size,
    make_events,
)


def _with_size(events: np.ndarray, sensor_size, path: Path) -> EventStream:
    if sensor_size is None:
        sensor_size = infer_sensor_size(events)
        warnings.warn(f"{path}: no sensor size stored; using {sensor_size[0]}x{sensor_size[1]} "
                      f"from the largest coordinates (pass sensor_size= to set it)", stacklevel=3)
    return EventStream(events, tuple(sensor_size))


def iter_npy(path: str | Path, chunk_events: int = 1 << 20,
             sensor_size: tuple[int, int] | None = None) -> Iterator[EventStream]:
    """Stream a structured ``.npy`` event array through a memory map, ``chunk_events`` at a time.

    The sensor size, when not given, comes from a first pass over the coordinates (cheap:
    memory-mapped) so that every chunk carries the same size.
    """
    path = Path(path)
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except ValueError as err:
        raise EventFormatError(f"{path}: not a readable .npy file ({err})") from None
    if arr.dtype.names is None:
        raise EventFormatError(f"{path}: not a structured event array (dtype {arr.dtype})")
    if sensor_size is None:
        if len(arr) == 0:
            raise EventFormatError(f"{path}: no events and no sensor size; pass sensor_size=")
        w = max(int(arr["x"][i : i + chunk_events].max()) for i in range(0, len(arr), chunk_events))
        h = max(int(arr["y"][i : i + chunk_events].max()) for i in range(0, len(arr), chunk_events))
        warnings.warn(f"{path}: no sensor size stored; using {w + 1}x{h + 1} from the largest "
                      f"coordinates (pass sensor_size= to set it)", stacklevel=2)
        sensor_size = (w + 1, h + 1)
    for i in range(0, max(len(arr), 1), chunk_events):
        yield EventStream(as_event_array(np.array(arr[i : i + chunk_events]), str(path)),
                          sensor_size)


def read_npz(path: str | Path, sensor_size: tuple[int, int] | None = None) -> EventStream:
    """Read events from a ``.npz`` (``events`` + ``sensor_size``, or ``t, x, y, p`` arrays)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            files = set(z.files)
            if "events" in files:
                events = as_event_array(z["events"], str(path))
            elif {"t", "x", "y", "p"} <= files:
                events = as_event_array(np.rec.fromarrays([z[k] for k in "txyp"], names="t,x,y,p"))
            else:
                raise EventFormatError(f"{path}: no 'events' or 't, x, y, p' arrays in the .npz")
            if sensor_size is None and "sensor_size" in files:
                sensor_size = tuple(int(v) for v in z["sensor_size"])
    except (ValueError, OSError) as err:
        if isinstance(err, EventFormatError):
            raise
        raise EventFormatError(f"{path}: not a readable .npz file ({err})") from None
    return _with_size(events, sensor_size, path)


def write_npz(path: str | Path, stream: EventStream) -> None:
    """Write events and sensor size to a ``.npz`` atomically (read back by :func:`read_npz`)."""
    stream.validate()
    with atomic_open(path) as f:
        np.savez(f, events=stream.events, sensor_size=np.asarray(stream.sensor_size, np.int64))


def read_csv(path: str | Path, sensor_size: tuple[int, int] | None = None) -> EventStream:
    """Read ``t,x,y,p`` text (comma/whitespace separated, optional header naming the columns)."""
    path = Path(path)
    text = path.read_text(encoding="utf-8", errors="replace")
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise EventFormatError(f"{path}: empty event text file")
    order = list("txyp")
    first = [c.strip().lower() for c in re.split(r"[,\s;]+", lines[0].strip())]
    if not re.match(r"^-?\d", first[0]):  # a header line
        alias = {"timestamp": "t", "time": "t", "ts": "t", "polarity": "p", "pol": "p", "on": "p"}
        first = [alias.get(c, c) for c in first]
        if sorted(first) != sorted(order):
            raise EventFormatError(f"{path}: header must name t, x, y, p, got {lines[0]!r}")
        order, lines = first, lines[1:]
    try:
        data = np.loadtxt(io.StringIO("\n".join(re.sub(r"[,;]", " ", ln) for ln in lines)),
                          dtype=np.float64, ndmin=2)
    except ValueError as err:
        raise EventFormatError(f"{path}: malformed event line ({err})") from None
    if data.shape[1] != 4:
        raise EventFormatError(f"{path}: need 4 columns t, x, y, p, found {data.shape[1]}")
    cols = {name: data[:, i] for i, name in enumerate(order)}
    if any((np.round(v) != v).any() for v in cols.values()):
        raise EventFormatError(f"{path}: t, x, y, p must be integers (t in microseconds)")
    p = cols["p"] > 0
    events = make_events(cols["t"].astype(np.int64), cols["x"], cols["y"], p)
    return _with_size(events, sensor_size, path)


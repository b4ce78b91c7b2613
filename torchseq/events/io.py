"""One entry point for event files: :func:`read_events` and the chunked :func:`iter_events`.

The format is found from the file's first bytes (magic), then its suffix:

| format | detected by | streams in chunks |
|---|---|---|
| jAER AEDAT 2.0 | ``#!AER-DAT2.0`` | yes |
| AEDAT 4.0 | ``#!AER-DAT4.0`` | yes (whole packets) |
| Prophesee EVT 3.0 / 2.0 ``.raw`` | ``%`` header naming ``evt 3.0`` / ``evt 2.0`` | yes |
| NumPy ``.npy`` structured array | NumPy magic | yes (memory map) |
| NumPy ``.npz`` | zip magic | no |
| CSV / text ``t,x,y,p`` | ``.csv`` / ``.txt`` suffix | no |
| HDF5 ``events/{t,x,y,p}`` (NSAVP, DSEC, ...; needs h5py) | HDF5 magic | yes |
| Parquet ``t,x,y,p`` table (needs pyarrow) | ``PAR1`` magic | yes |
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from torchseq.events.aedat2 import iter_aedat2
from torchseq.events.aedat4 import iter_aedat4
from torchseq.events.plain import iter_npy, read_csv, read_npz
from torchseq.events.prophesee import iter_raw
from torchseq.events.stream import (
    EVENT_DTYPE,
    EventFormatError,
    EventStream,
    check_contents,
    concat_events,
    file_error,
    first_backward,
    order_events,
)

DEFAULT_CHUNK = 1 << 20
# the format options each format takes (a format not listed takes none); a new format
# registers its options here beside its detect_format and _chunks lines
FORMAT_OPTIONS = {"aedat2": {"layout", "flip_y", "truncated"}, "aedat4": {"truncated"},
                  "raw": {"truncated", "evt3_time", "evt3_kernel"},
                  "hdf5": {"group", "columns", "time_unit"}, "parquet": {"columns", "time_unit"},
                  "csv": {"time_unit"}}


def _check_options(path: Path, fmt: str, options: dict) -> None:
    """Check the format options against the file's format.

    TypeError for options no format takes; EventFormatError when the file's format (found
    from its first bytes, so perhaps not the one the caller expected) does not take them.
    """
    known = set().union(*FORMAT_OPTIONS.values())
    unknown = sorted(set(options) - known)
    if unknown:
        raise TypeError(f"unknown event file option(s) {unknown} (known: {sorted(known)})")
    foreign = sorted(set(options) - FORMAT_OPTIONS.get(fmt, set()))
    if foreign:
        raise file_error(path, 0, f"the file is {fmt} (by its first bytes); option(s) {foreign} "
                         f"do not apply to it")


def detect_format(path: str | Path) -> str:
    """Name the event format of ``path``: aedat2, aedat4, raw, npy, npz, csv, hdf5, parquet."""
    path = Path(path)
    if not path.is_file():
        raise EventFormatError(f"no such event file: {path}")
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError as err:
        raise EventFormatError(f"{path}: cannot read ({err.strerror})") from None
    if not head:
        raise file_error(path, 0, "empty file")
    if head.startswith(b"#!AER-DAT2"):
        return "aedat2"
    if head.startswith(b"#!AER-DAT4"):
        return "aedat4"
    if head.startswith(b"#!AER-DAT"):
        raise file_error(path, 0, f"unsupported AEDAT version {head[:13]!r}")
    if head.startswith(b"%"):
        return "raw"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    if head.startswith(b"PK"):
        return "npz"
    if head.startswith(b"\x89HDF\r\n\x1a\n"):
        return "hdf5"
    if head.startswith(b"PAR1"):
        return "parquet"
    if path.suffix.lower() in (".csv", ".txt"):
        return "csv"
    raise file_error(path, 0, f"unknown event file format (starts {head[:12]!r})")


def _chunks(path: Path, fmt: str, chunk_events: int, sensor_size, options: dict):
    if fmt == "aedat2":
        return iter_aedat2(path, chunk_events, sensor_size, **options)
    if fmt == "aedat4":
        return iter_aedat4(path, chunk_events, sensor_size, **options)
    if fmt == "raw":
        return iter_raw(path, chunk_events, sensor_size, **options)
    if fmt == "hdf5":
        from torchseq.events.hdf5 import iter_hdf5

        return iter_hdf5(path, chunk_events, sensor_size, **options)
    if fmt == "parquet":
        from torchseq.events.parquet import iter_parquet

        return iter_parquet(path, chunk_events, sensor_size, **options)
    if fmt == "csv":
        return iter([read_csv(path, sensor_size, **options)])
    if options:
        raise TypeError(f"options {sorted(options)} do not apply to {fmt} files")
    if fmt == "npy":
        return iter_npy(path, chunk_events, sensor_size)
    return iter([read_npz(path, sensor_size)])


def _checked(path: Path, fmt: str, chunk_events: int, sensor_size, options: dict,
             check_order: bool) -> Iterator[EventStream]:
    """The chunks of ``path``, each checked (contents; time order within and across chunks).

    Every failure is an :class:`EventFormatError` naming the file and, where the reader
    knows it, the byte offset of the chunk (see :class:`~torchseq.events.stream.Chunk`).
    """
    if chunk_events < 1:
        raise ValueError(f"chunk_events must be >= 1, got {chunk_events}")
    _check_options(path, fmt, options)
    last, seen = None, 0
    for chunk in _chunks(path, fmt, chunk_events, sensor_size, options):
        offset = getattr(chunk, "offset", None)
        where = f" (in the chunk read from byte {offset})" if offset is not None else ""
        try:
            check_contents(chunk.events, chunk.sensor_size)
        except EventFormatError as err:
            raise EventFormatError(f"{path}: {err}{where}") from None
        t = chunk.events["t"]
        if check_order and len(t):
            i = first_backward(t)
            if i is not None:
                raise EventFormatError(
                    f"{path}: timestamps go backwards at event #{seen + i} ({t[i - 1]} -> {t[i]} "
                    f"us){where}; use read_events(sort=True)")
            if last is not None and t[0] < last:
                raise EventFormatError(
                    f"{path}: timestamps go backwards at event #{seen} ({last} -> {t[0]} us)"
                    f"{where}; use read_events(sort=True)")
        if len(t):
            last = t[-1]
        seen += len(t)
        yield chunk


def iter_events(path: str | Path, chunk_events: int = DEFAULT_CHUNK,
                sensor_size: tuple[int, int] | None = None,
                **options) -> Iterator[EventStream]:
    """Stream an event file in chunks without loading it whole (see the module table).

    Every chunk is checked by the same rules as :func:`read_events`: coordinates inside
    the sensor, polarity 0/1, and time never going backwards, within and across chunks
    (reorder with ``read_events(..., sort=True)``).

    Args:
        path: the event file.
        chunk_events: about how many events (or raw records/words) per chunk.
        sensor_size: ``(W, H)`` override of the size the file states or implies.
        **options: format options: ``layout``, ``flip_y`` (AEDAT 2.0), ``truncated``
            (``"error"``/``"drop"``; AEDAT 2.0/4.0, ``.raw``), ``evt3_time`` and
            ``evt3_kernel`` (``.raw``; the kernel changes speed, never the events).

    Yields:
        :class:`EventStream` chunks with the same ``sensor_size``.

    Raises:
        EventFormatError: unknown or malformed file, events outside the sensor, time going
            backwards; the message names the file and, where known, the byte offset.
    """
    path = Path(path)
    yield from _checked(path, detect_format(path), chunk_events, sensor_size, options, True)


def read_events(path: str | Path, sensor_size: tuple[int, int] | None = None,
                sort: bool = False, chunk_events: int = DEFAULT_CHUNK,
                **options) -> EventStream:
    """Read a whole event file (any format of the module table) as one :class:`EventStream`.

    Args:
        path: the event file.
        sensor_size: ``(W, H)`` override.
        sort: reorder events whose timestamps go backwards (stable, with a warning) instead
            of raising.
        chunk_events: read granularity (memory peak is about the output plus one chunk).
        **options: format options, see :func:`iter_events`.

    Returns:
        The events, time-ordered and checked against the sensor size.
    """
    path = Path(path)
    events, size = _gather(_checked(path, detect_format(path), chunk_events, sensor_size,
                                    options, not sort), path.stat().st_size)
    if sort:
        events = order_events(events, True, str(path))
    return EventStream(events, size)


def _gather(chunks: Iterator[EventStream], file_bytes: int) -> tuple[np.ndarray, tuple[int, int]]:
    """All events of ``chunks`` in one writeable array, and their sensor size.

    From the second chunk on, chunks are copied (as raw 16-byte rows, see
    :func:`concat_events`) into one output sized from the events per file byte of the
    first chunk (plus 1/8 and a chunk; two chunks' room if the system refuses that much),
    allocated anew with twice the room when that runs out and cut to size at the end. Each
    chunk is released before the next is read, so the peak is about the output plus one
    chunk.
    """
    first = next(chunks, None)
    if first is None:  # every reader yields at least one (perhaps empty) chunk
        raise EventFormatError("the reader yielded no chunk")
    events, size, start = first.events, first.sensor_size, getattr(first, "offset", None)
    del first
    out, n = None, 0
    for chunk in chunks:
        ev, offset = chunk.events, getattr(chunk, "offset", None)
        del chunk
        if out is None:  # a second chunk: from here on, one buffer of our own
            m = len(events)
            guess = m + len(ev)
            if start is not None and offset is not None and offset > start:
                guess = max(guess, int(m * (file_bytes - start) / (offset - start) * 1.125))
            try:
                out = np.empty(guess + len(ev), EVENT_DTYPE)
            except MemoryError:  # a first chunk far denser than the rest: grow as needed
                out = np.empty(m + 2 * len(ev), EVENT_DTYPE)
            _put(out, 0, events)
            n, events = m, None
        if n + len(ev) > len(out):
            grown = np.empty(2 * (n + len(ev)), EVENT_DTYPE)
            _put(grown, 0, out[:n])
            out = grown
        _put(out, n, ev)
        n += len(ev)
    if out is None:
        return (events if events.flags.writeable else concat_events([events])), size
    out.resize(n, refcheck=False)
    return out, size


def _put(out: np.ndarray, at: int, events: np.ndarray) -> None:
    """Copy ``events`` into ``out[at:]`` as raw 16-byte rows (see :func:`concat_events`)."""
    rows = np.ascontiguousarray(events).view(np.uint64)
    out.view(np.uint64)[2 * at : 2 * at + len(rows)] = rows

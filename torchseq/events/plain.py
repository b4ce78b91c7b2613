"""Plain event files: ``.npy`` / ``.npz`` structured arrays and ``t,x,y,p`` CSV / text.

``.npz`` files written by :func:`write_npz` hold ``events`` (structured) and
``sensor_size`` ``(W, H)``; ``.npz`` files with separate ``t``, ``x``, ``y``, ``p`` arrays
are read too. CSV/text: one event per line, ``t,x,y,p`` (commas or whitespace), an optional
header line naming the columns in any order; polarity -1/+1 becomes 0/1.

NumPy headers are parsed by the library's one bounded reader (:mod:`torchseq.npyfile`, not
``np.load``) so that a damaged or hostile header is a clear :class:`EventFormatError` with
the byte offset: the declared shape must fit in the bytes that follow (a 300-byte file cannot
make the reader allocate gigabytes), object dtypes are refused, and ``.npz`` members are
read in bounded pieces, so memory never exceeds what the archive really decompresses to.
A large ``.npy`` is streamed through a memory map, ``chunk_events`` at a time.
Values are converted exactly (:func:`~torchseq.events.stream.make_events`): CSV integers
are parsed as int64, never through float64. CSV times written with fractions follow the
one float-time rule (:mod:`torchseq.events.times`: under 1e5 they are seconds, with a
warning; beyond, refused); whole numbers, however written (``10``, ``10.0``, ``1e3``), are
exact integer microseconds, with the rule's warning when written as floats below 1e5.
"""

from __future__ import annotations

import io
import lzma
import re
import warnings
import zipfile
from collections.abc import Iterator
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from torchseq.atomic import atomic_open
from torchseq.events.columns import check_unit, to_microseconds
from torchseq.events.stream import (
    Chunk,
    EventFormatError,
    EventStream,
    as_event_array,
    check_sensor_size,
    file_error,
    make_events,
)
from torchseq.events.times import (
    FloatTimeRule,
    float_time_unit,
    float_times_to_us,
    with_us_times,
)
from torchseq.npyfile import ZIP_ERRORS, NpyHeader, check_size, read_header, read_member

_ZIP_ERRORS = ZIP_ERRORS + (lzma.LZMAError,)


def _events_header(f, path, where: int, available, what: str) -> tuple[NpyHeader, int]:
    """A shared-parser ``.npy`` header of a 1-D array and its element count, bounded."""
    header = read_header(f, path, EventFormatError, where)
    if len(header.shape) != 1:
        raise file_error(path, where, f"{what} must be a 1-D array, got shape {header.shape}")
    check_size(header, available - header.size, path, EventFormatError, where, what)
    return header, header.shape[0]


def _with_size(events: np.ndarray, sensor_size, path: Path) -> EventStream:
    if sensor_size is None:
        if len(events) == 0:
            raise file_error(path, None, "no events and no sensor size; pass sensor_size=")
        try:
            sensor_size = check_sensor_size(
                (int(events["x"].max()) + 1, int(events["y"].max()) + 1),
                "the sensor size implied by the largest coordinates")
        except EventFormatError as err:
            raise file_error(path, None, str(err)) from None
        warnings.warn(f"{path}: no sensor size stored; using {sensor_size[0]}x{sensor_size[1]} "
                      f"from the largest coordinates (pass sensor_size= to set it)", stacklevel=3)
    return EventStream(events, sensor_size)


def _convert(arr: np.ndarray, path, offset: int | None,
             rule: FloatTimeRule | None = None) -> np.ndarray:
    try:
        if arr.dtype.names and "t" in arr.dtype.names:  # float times: warnings name the file
            arr = with_us_times(arr, str(path), rule)
        return as_event_array(arr, "the array")
    except EventFormatError as err:
        msg = str(err).removeprefix(f"{path}: ")
        raise file_error(path, offset, msg) from None


def iter_npy(path: str | Path, chunk_events: int = 1 << 20,
             sensor_size: tuple[int, int] | None = None) -> Iterator[EventStream]:
    """Stream a structured ``.npy`` event array through a memory map, ``chunk_events`` at a time.

    The sensor size, when not given, comes from a first pass over the coordinates (cheap:
    memory-mapped) so that every chunk carries the same size.
    """
    path = Path(path)
    if sensor_size is not None:
        sensor_size = check_sensor_size(sensor_size)
    with open(path, "rb") as f:
        header, n = _events_header(f, path, 0, path.stat().st_size, "the event array")
    dtype, data = header.dtype, header.size
    if dtype.names is None or any(k not in dtype.names for k in "txyp"):
        raise file_error(path, 0, f"not a structured event array with fields t, x, y, p "
                         f"(dtype {dtype})")
    arr = (np.memmap(path, dtype, "r", offset=data, shape=(n,)) if n
           else np.empty(0, dtype))

    rule = FloatTimeRule(str(path))  # float times: one decision per file

    def pieces():
        for i in range(0, max(n, 1), chunk_events):
            at = data + i * dtype.itemsize
            yield at, _convert(np.array(arr[i : i + chunk_events]), path, at, rule)

    if sensor_size is None:
        if n == 0:
            raise file_error(path, None, "no events and no sensor size; pass sensor_size=")
        w = h = -1
        for _, ev in pieces():
            w, h = max(w, int(ev["x"].max())), max(h, int(ev["y"].max()))
        try:
            sensor_size = check_sensor_size((w + 1, h + 1), "the sensor size implied by the "
                                            "largest coordinates")
        except EventFormatError as err:
            raise file_error(path, None, str(err)) from None
        warnings.warn(f"{path}: no sensor size stored; using {w + 1}x{h + 1} from the largest "
                      f"coordinates (pass sensor_size= to set it)", stacklevel=2)
    for offset, ev in pieces():
        yield Chunk(ev, sensor_size, offset)


def _read_member(zf: zipfile.ZipFile, name: str, path) -> np.ndarray:
    """One 1-D ``.npy`` member of an archive (the shared bounded reader)."""
    info = zf.getinfo(name)
    array = read_member(zf, info, path, EventFormatError)
    if array.ndim != 1:
        raise file_error(path, info.header_offset, f"member {name} must be a 1-D array, got "
                         f"shape {array.shape}")
    return array


def read_npz(path: str | Path, sensor_size: tuple[int, int] | None = None) -> EventStream:
    """Read events from a ``.npz`` (``events`` + ``sensor_size``, or ``t, x, y, p`` arrays)."""
    path = Path(path)
    if sensor_size is not None:
        sensor_size = check_sensor_size(sensor_size)
    # where a zip failure sits: the central directory (end of the file), then each member
    where = [max(path.stat().st_size - 22, 0)]

    def member(zf, name):
        where[0] = zf.getinfo(name).header_offset
        return _read_member(zf, name, path)

    try:
        with zipfile.ZipFile(path) as zf:
            files = {n[:-4] for n in zf.namelist() if n.endswith(".npy")}
            if "events" in files:
                events = _convert(member(zf, "events.npy"), path, where[0])
            elif {"t", "x", "y", "p"} <= files:
                cols = [member(zf, f"{k}.npy") for k in "txyp"]
                if cols[0].dtype.kind == "f":  # the float-time rule; messages name the file
                    try:
                        cols[0] = float_times_to_us(cols[0], str(path))
                    except EventFormatError as err:
                        raise file_error(path, zf.getinfo("t.npy").header_offset,
                                         "t.npy: " + str(err).removeprefix(f"{path}: ")
                                         ) from None
                try:
                    events = make_events(*cols)
                except EventFormatError as err:  # point at the member the message names
                    name = f"{str(err)[0]}.npy"
                    at = zf.getinfo(name).header_offset if name in zf.namelist() else None
                    raise file_error(path, at if at is not None else where[0], str(err)
                                     ) from None
            else:
                raise file_error(path, where[0], "no 'events' or 't, x, y, p' arrays in the "
                                 ".npz's directory")
            if sensor_size is None and "sensor_size" in files:
                stored = member(zf, "sensor_size.npy")
                try:
                    sensor_size = check_sensor_size(stored.tolist(), "the stored sensor_size")
                except EventFormatError as err:
                    raise file_error(path, where[0], str(err)) from None
    except _ZIP_ERRORS as err:
        if isinstance(err, EventFormatError):
            raise
        raise file_error(path, where[0], f"not a readable .npz file ({type(err).__name__}: "
                         f"{err})") from None
    return _with_size(events, sensor_size, path)


def write_npz(path: str | Path, stream: EventStream) -> None:
    """Write events and sensor size to a ``.npz`` atomically (read back by :func:`read_npz`)."""
    stream.validate()
    with atomic_open(path) as f:
        np.savez(f, events=stream.events, sensor_size=np.asarray(stream.sensor_size, np.int64))


def _exact_ints(rows: list[list[str]], first_line: list[int], path) -> np.ndarray:
    """Slow path: every token an exact integer (``1.0``, ``1e3`` allowed when integral)."""
    out = np.empty((len(rows), 4), np.int64)
    for r, row in enumerate(rows):
        for c, tok in enumerate(row):
            try:
                v = int(tok)
            except ValueError:
                try:
                    d = Decimal(tok)
                    v = int(d) if d.is_finite() and d == d.to_integral_value() else None
                except (InvalidOperation, ValueError):
                    v = None
            if v is None or not -(1 << 63) <= v < (1 << 63):
                raise file_error(path, None, f"line {first_line[r]}: {tok!r} is not an integer "
                                 f"in the int64 range")
            out[r, c] = v
    return out


_PLAIN_INT = re.compile(r"[-+]?\d+")


def _csv_float_times(tokens: list[str], lines: list[int], path, unit: str | None = None
                     ) -> np.ndarray | None:
    """``(N,)`` int64 us from a ``t`` column written with fractions, in ``unit`` or by the rule.

    None when every time is a plain integer, or (no ``unit``) a whole number such as ``10.0``
    (the rule reads those as microseconds, warning below 1e5): the caller then parses them
    exactly instead of through float64 and scales them by ``unit``.
    """
    if all(_PLAIN_INT.fullmatch(tok) for tok in tokens):
        return None
    t = np.empty(len(tokens), np.float64)
    for i, (k, tok) in enumerate(zip(lines, tokens)):
        try:
            t[i] = float(tok)
        except ValueError:
            raise file_error(path, None, f"line {k}: time {tok!r} is not a number") from None
    try:
        if unit is None:
            unit = float_time_unit(t, str(path))
            if unit == "us":
                return None
        return float_times_to_us(t, str(path), unit)
    except EventFormatError as err:
        raise file_error(path, None, str(err).removeprefix(f"{path}: ")) from None


def read_csv(path: str | Path, sensor_size: tuple[int, int] | None = None,
             time_unit: str | None = None) -> EventStream:
    """Read ``t,x,y,p`` text (comma/whitespace separated, optional header naming the columns).

    Args:
        path: the text file.
        sensor_size: ``(W, H)``; default from the largest coordinates (with a warning).
        time_unit: the ``t`` column's unit, ``"s"``, ``"ms"``, ``"us"`` or ``"ns"``; None:
            integers are microseconds, fractions follow the float-time rule (times.py).
    """
    path = Path(path)
    check_unit(time_unit)
    if sensor_size is not None:
        sensor_size = check_sensor_size(sensor_size)
    text = path.read_text(encoding="utf-8", errors="replace")
    numbered = [(i + 1, ln) for i, ln in enumerate(text.splitlines())
                if ln.strip() and not ln.lstrip().startswith("#")]
    if not numbered:
        raise file_error(path, None, "empty event text file")
    order = list("txyp")
    first = [c.strip().lower() for c in re.split(r"[,\s;]+", numbered[0][1].strip())]
    if not re.match(r"^[-+]?\d", first[0]):  # a header line
        alias = {"timestamp": "t", "time": "t", "ts": "t", "polarity": "p", "pol": "p", "on": "p"}
        first = [alias.get(c, c) for c in first]
        if sorted(first) != sorted(order):
            raise file_error(path, None, f"line {numbered[0][0]}: header must name t, x, y, p, "
                             f"got {numbered[0][1]!r}")
        order, numbered = first, numbered[1:]
    rows = [re.split(r"[,;\s]+", ln.strip()) for _, ln in numbered]
    for (k, ln), row in zip(numbered, rows):
        if len(row) != 4:
            raise file_error(path, None, f"line {k}: need 4 columns t, x, y, p, found "
                             f"{len(row)}: {ln[:60]!r}")
    lines, tc = [k for k, _ in numbered], order.index("t")
    t_us = _csv_float_times([r[tc] for r in rows], lines, path, time_unit)
    if t_us is not None:  # the times are parsed; the integer columns stay exact
        rows = [r[:tc] + ["0"] + r[tc + 1:] for r in rows]
    try:
        data = np.loadtxt(io.StringIO("\n".join(" ".join(r) for r in rows)), dtype=np.int64,
                          ndmin=2) if rows else np.empty((0, 4), np.int64)
    except ValueError:
        data = _exact_ints(rows, lines, path)
    cols = {name: data[:, i] for i, name in enumerate(order)}
    if t_us is not None:
        cols["t"] = t_us
    elif time_unit is not None:
        try:
            cols["t"] = to_microseconds(cols["t"], time_unit, str(path))
        except EventFormatError as err:
            raise file_error(path, None, str(err).removeprefix(f"{path}: ")) from None
    try:
        events = make_events(cols["t"], cols["x"], cols["y"], cols["p"])
    except EventFormatError as err:
        raise file_error(path, None, str(err)) from None
    return _with_size(events, sensor_size, path)

"""Parquet event tables: columns ``t, x, y, p`` (and their spellings), one row per event.

The layout of Brisbane-Event-VPR's published Parquet conversion and of event tables written
with pandas/polars/pyarrow. Columns are found by the names in
:data:`torchseq.events.columns.ALIASES` (``columns=`` overrides). Times: an Arrow
``timestamp``/``duration`` column carries its unit; otherwise integers are microseconds and
floats by times.py (``time_unit=`` overrides). The sensor size comes from ``sensor_size=``, else
the file's key-value metadata (``sensor_size`` as ``"W,H"`` or ``width``/``height``), else
the largest coordinates (with a warning). Rows are read in batches of ``chunk_events``;
a declared row count needing more than ``MAX_EXPANSION`` times the file's bytes is
rejected before anything is read. Needs ``pyarrow`` (``pip install torchseq[parquet]``).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from torchseq.atomic import atomic_open
from torchseq.events.columns import MAX_EXPANSION, check_unit, find_columns, pack
from torchseq.events.stream import EVENT_DTYPE, EventFormatError, EventStream, as_event_array
from torchseq.events.times import FloatTimeRule

PARQUET_MAGIC = b"PAR1"


def _pyarrow():
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:  # pragma: no cover - exercised where pyarrow is absent
        raise ImportError("reading Parquet event files needs pyarrow: "
                          "pip install 'torchseq[parquet]'") from None
    return pa, pq


def _size_from_metadata(meta) -> tuple[int, int] | None:
    if not meta:
        return None
    meta = {k.decode("utf-8", "replace").lower(): v.decode("utf-8", "replace")
            for k, v in meta.items()}
    try:
        if "sensor_size" in meta:
            w, h = (int(v) for v in meta["sensor_size"].replace("x", ",").split(","))
            return w, h
        if "width" in meta and "height" in meta:
            return int(meta["width"]), int(meta["height"])
    except ValueError:
        raise EventFormatError(f"unreadable sensor size in the metadata: {meta}") from None
    return None


def _arrow_unit(field_type, pa) -> str | None:
    if pa.types.is_timestamp(field_type) or pa.types.is_duration(field_type):
        return field_type.unit
    return None


def _column(batch, name, pa):
    col = batch.column(name)
    if col.null_count:
        raise EventFormatError(f"column {name!r} has {col.null_count} missing value(s)")
    if pa.types.is_timestamp(col.type) or pa.types.is_duration(col.type):
        col = col.cast(pa.int64())
    if pa.types.is_boolean(col.type):
        return col.to_numpy(zero_copy_only=False).astype(np.uint8)
    if not (pa.types.is_integer(col.type) or pa.types.is_floating(col.type)):
        raise EventFormatError(f"column {name!r} must hold numbers, has {col.type}")
    return col.to_numpy(zero_copy_only=False)


def iter_parquet(path: str | Path, chunk_events: int = 1 << 20,
                 sensor_size: tuple[int, int] | None = None, columns: dict | None = None,
                 time_unit: str | None = None) -> Iterator[EventStream]:
    """Stream a Parquet event table in batches.

    Args:
        path: the ``.parquet`` file.
        chunk_events: rows per batch.
        sensor_size: ``(W, H)`` override.
        columns: ``{"t": name, ...}`` for columns the aliases miss.
        time_unit: ``"s"``, ``"ms"``, ``"us"`` or ``"ns"`` override.

    Yields:
        :class:`EventStream` chunks (at least one, empty for an empty table).

    Raises:
        EventFormatError: unreadable file, missing columns, sizes the file cannot hold, bad
            values.
    """
    pa, pq = _pyarrow()
    check_unit(time_unit)
    path = Path(path)
    try:
        f = pq.ParquetFile(path)
        schema = f.schema_arrow
        n = int(f.metadata.num_rows)
    except (OSError, ValueError, pa.ArrowException) as err:
        raise EventFormatError(f"{path}: not a readable Parquet file ({err})") from None
    try:
        names = find_columns(schema.names, columns, str(path))
        if n * EVENT_DTYPE.itemsize > MAX_EXPANSION * path.stat().st_size + 4096:
            raise EventFormatError(f"{path}: declares {n} rows in a {path.stat().st_size}-byte "
                                   f"file (more than {MAX_EXPANSION}x)")
        unit = time_unit or _arrow_unit(schema.field(names["t"]).type, pa)
        unit = FloatTimeRule(str(path), unit)  # float times: one decision per file
        if sensor_size is None:
            sensor_size = _size_from_metadata(schema.metadata)
        order = [names[k] for k in "txyp"]

        def batches(cols):
            yield from f.iter_batches(batch_size=chunk_events, columns=cols)

        if sensor_size is None:
            if n == 0:
                raise EventFormatError(f"{path}: no events and no sensor size; pass sensor_size=")
            w = h = 0
            for b in batches([names["x"], names["y"]]):
                w = max(w, int(np.max(_column(b, names["x"], pa))))
                h = max(h, int(np.max(_column(b, names["y"], pa))))
            sensor_size = (w + 1, h + 1)
            warnings.warn(f"{path}: no sensor size stored; using {w + 1}x{h + 1} from the "
                          f"largest coordinates (pass sensor_size= to set it)", stacklevel=2)
        done = 0
        for b in batches(order):
            cols = [_column(b, c, pa) for c in order]
            yield EventStream(pack(*cols, unit, f"{path} rows {done}.."), tuple(sensor_size))
            done += b.num_rows
        if done != n:
            raise EventFormatError(f"{path}: {done} rows read, {n} declared")
        if n == 0:
            yield EventStream(np.zeros(0, EVENT_DTYPE), tuple(sensor_size))
    except EventFormatError as err:
        msg = str(err)
        raise EventFormatError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    except (OSError, ValueError, TypeError, pa.ArrowException) as err:
        raise EventFormatError(f"{path}: cannot read the event columns ({err})") from None


def write_parquet(path: str | Path, stream: EventStream) -> None:
    """Write events as a Parquet table ``t`` (int64 us), ``x``, ``y`` (int16), ``p`` (uint8).

    The sensor size goes into the key-value metadata (``sensor_size = "W,H"``). Atomic.
    """
    pa, pq = _pyarrow()
    ev = as_event_array(stream.events)
    w, h = stream.sensor_size
    table = pa.table({f: np.ascontiguousarray(ev[f]) for f in "txyp"})
    table = table.replace_schema_metadata({"sensor_size": f"{w},{h}", "time_unit": "us"})
    with atomic_open(Path(path), "wb") as out:
        pq.write_table(table, out)

"""HDF5 event files: one dataset per field (``events/{t,x,y,p}`` and its spellings).

Layouts read (found by walking the file for the first group that holds a dataset for each
of ``t, x, y, p`` under one of the names in :data:`torchseq.events.columns.ALIASES`):

- NSAVP ``*_dvxplorer_*.h5``: ``/events`` with ``timestamps`` (uint64 ns, ``units``
  attribute), ``x_coordinates``, ``y_coordinates``, ``polarities``; ``width``/``height``
  attributes.
- DSEC, and DDD20 or other recordings exported to ``events/{t,x,y,p}``: int us, plus a root
  ``t_offset``.
- ``events/{ts,xs,ys,ps}`` (Stoffregen et al.'s layout): float seconds.
- a compound ``events`` dataset with named fields, or an ``(N, 4)`` ``events`` dataset with
  columns ``t, x, y, p``.
- DDD20's original recordings: raw libcaer packets, one per row of ``/dvs/data``
  (:mod:`torchseq.events.libcaer`; found first, at ``dvs`` or ``group=``).

Units come from a ``units``/``unit`` attribute of the time dataset, else int = us and
float by times.py; ``time_unit=`` overrides. A root dataset or attribute ``t_offset`` (DSEC, in us)
is added. The sensor size comes from ``sensor_size=``, else ``width``/``height`` attributes
of the group or the root, else the largest coordinates (with a warning).

Nothing is read before the declared sizes are checked against the bytes the file stores:
an unfiltered dataset must store all its elements, a compressed one at most
``MAX_EXPANSION`` times its stored bytes. Reads go in chunks of ``chunk_events``.
Needs ``h5py`` (``pip install torchseq[hdf5]``).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from torchseq.events.columns import (
    ALIASES,
    MAX_EXPANSION,
    check_unit,
    find_columns,
    pack,
    to_microseconds,
    unit_from_text,
)
from torchseq.events.libcaer import PacketRows, find_packet_dataset, iter_packet_events
from torchseq.events.stream import EventFormatError, EventStream
from torchseq.events.times import FloatTimeRule

HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


def _h5py():
    try:
        import h5py
    except ImportError:  # pragma: no cover - exercised where h5py is absent
        raise ImportError("reading HDF5 event files needs h5py: pip install 'torchseq[hdf5]'") \
            from None
    return h5py


def _fields_in(group, h5py, columns=None) -> dict | None:
    names = [k for k, v in group.items() if isinstance(v, h5py.Dataset)]
    lower = {n.lower() for n in names}
    columns = columns or {}
    if all(columns.get(f) in names or any(a in lower for a in ALIASES[f]) for f in "txyp"):
        return {"kind": "columns", "names": names}
    if "events" in group and isinstance(group["events"], h5py.Dataset):
        d = group["events"]
        if d.dtype.names:
            return {"kind": "compound", "names": list(d.dtype.names)}
        if d.ndim == 2 and d.shape[1] == 4:
            return {"kind": "matrix", "names": ["t", "x", "y", "p"]}
    return None


def _locate(f, group: str | None, h5py, columns=None):
    if group is not None:
        if group not in f or not isinstance(f[group], h5py.Group):
            raise EventFormatError(f"no group {group!r} in the file")
        found = _fields_in(f[group], h5py, columns)
        if found is None:
            raise EventFormatError(f"group {group!r} holds no t, x, y, p datasets")
        return f[group], found
    candidates = [f["events"]] if "events" in f and isinstance(f["events"], h5py.Group) else []
    candidates.append(f)
    groups = []
    f.visit(lambda name: groups.append(name) if isinstance(f.get(name), h5py.Group) else None)
    candidates += [f[g] for g in groups]
    for g in candidates:
        found = _fields_in(g, h5py, columns)
        if found is not None:
            return g, found
    raise EventFormatError("no group with t, x, y, p datasets (or an (N, 4) 'events' dataset) "
                           "found; pass group=")


def _event_length(d, where: str) -> int:
    if d.ndim < 1 or (d.ndim == 2 and (d.dtype.names or d.shape[1] != 4)) or d.ndim > 2:
        raise EventFormatError(f"{where}: dataset {d.name} has shape {d.shape}")
    check_storage(d, where)
    return int(d.shape[0])


def check_storage(d, where: str, error: type[Exception] = EventFormatError) -> None:
    """Refuse an HDF5 dataset declaring more bytes than the file stores (or can inflate to)."""
    declared = int(np.prod(d.shape, dtype=np.float64) * d.dtype.itemsize)
    stored = int(d.id.get_storage_size())
    filtered = d.chunks is not None and d.id.get_create_plist().get_nfilters() > 0
    if declared and not filtered and stored < declared:
        raise error(f"{where}: dataset {d.name} declares {declared} bytes but the file "
                    f"stores {stored}")
    if declared and filtered and declared > MAX_EXPANSION * stored + 4096:
        raise error(f"{where}: dataset {d.name} declares {declared} bytes from "
                    f"{stored} stored (more than {MAX_EXPANSION}x)")


def _size_from_attrs(*objs) -> tuple[int, int] | None:
    for o in objs:
        a = o.attrs
        for wk, hk in (("width", "height"), ("sensor_width", "sensor_height")):
            if wk in a and hk in a:
                try:
                    return int(np.asarray(a[wk]).reshape(-1)[0]), int(
                        np.asarray(a[hk]).reshape(-1)[0])
                except (TypeError, ValueError, IndexError):
                    raise EventFormatError(f"unreadable {wk}/{hk} attributes") from None
        if "sensor_size" in a:
            v = np.asarray(a["sensor_size"]).reshape(-1)
            if len(v) != 2 or v.dtype.kind not in "iu":
                raise EventFormatError(f"sensor_size attribute must be (W, H), got {v}")
            return int(v[0]), int(v[1])
    return None


def _t_offset(f) -> int:
    raw = f["t_offset"][()] if "t_offset" in f else f.attrs.get("t_offset", 0)
    v = np.asarray(raw).reshape(-1)
    if len(v) != 1 or v.dtype.kind not in "iu" or abs(int(v[0])) >= 2**62:
        raise EventFormatError(f"t_offset must be one integer (us), got {raw!r}")
    return int(v[0])


def iter_hdf5(path: str | Path, chunk_events: int = 1 << 20,
              sensor_size: tuple[int, int] | None = None, group: str | None = None,
              columns: dict | None = None, time_unit: str | None = None
              ) -> Iterator[EventStream]:
    """Stream an HDF5 event file (layouts in the module docstring) in chunks.

    Args:
        path: the ``.h5``/``.hdf5`` file.
        chunk_events: events per chunk.
        sensor_size: ``(W, H)`` override.
        group: the group holding the datasets (default: found by walking the file).
        columns: ``{"t": name, ...}`` to name datasets the aliases miss.
        time_unit: ``"s"``, ``"ms"``, ``"us"`` or ``"ns"`` override.

    Yields:
        :class:`EventStream` chunks (at least one, empty for an empty file).

    Raises:
        EventFormatError: unreadable file, no event datasets, sizes the file does not hold,
            bad values.
    """
    h5py = _h5py()
    check_unit(time_unit)
    path = Path(path)
    try:
        f = h5py.File(path, "r")
    except (OSError, ValueError) as err:
        raise EventFormatError(f"{path}: not a readable HDF5 file ({err})") from None
    with f:
        try:
            yield from _iter_open(f, path, chunk_events, sensor_size, group, columns,
                                  time_unit, h5py)
        except EventFormatError as err:
            msg = str(err)
            raise EventFormatError(msg if msg.startswith(str(path)) else f"{path}: {msg}") \
                from None
        except (OSError, KeyError, TypeError, ValueError, RuntimeError) as err:
            raise EventFormatError(f"{path}: cannot read the event datasets ({err})") from None


def _reader(kind: str, data, names):
    """``read(a, b) -> (t, x, y, p)`` arrays of events ``a..b`` for one layout."""
    if kind == "columns":
        def read(a, b):
            return tuple(data[k][a:b] for k in "txyp")
    elif kind == "compound":
        def read(a, b):
            block = data[a:b]
            return tuple(block[names[k]] for k in "txyp")
    else:  # (N, 4) matrix, columns t, x, y, p
        def read(a, b):
            return tuple(data[a:b].T)
    return read


def _iter_open(f, path, chunk_events, sensor_size, group, columns, time_unit, h5py):
    packets = find_packet_dataset(f, group, h5py)
    if packets is not None:  # libcaer packets (DDD20): times are us by definition
        where = f"{path}:{packets.name}"
        if columns or time_unit:
            raise EventFormatError(f"{where}: libcaer packets; columns= and time_unit= do not "
                                   f"apply")
        size = sensor_size if sensor_size is not None else _size_from_attrs(packets.parent, f)
        yield from iter_packet_events(PacketRows(packets, where), chunk_events, size)
        return
    g, found = _locate(f, group, h5py, columns)
    where = f"{path}:{g.name}"
    if found["kind"] == "columns":
        names = find_columns(found["names"], columns, where)
        ds = {k: g[v] for k, v in names.items()}
        lengths = {k: _event_length(d, where) for k, d in ds.items()}
        if any(d.ndim != 1 for d in ds.values()):
            raise EventFormatError(f"{where}: t, x, y, p datasets must be one-dimensional")
        if len(set(lengths.values())) != 1:
            raise EventFormatError(f"{where}: dataset lengths differ: {lengths}")
        n = lengths["t"]
        t_attrs = ds["t"].attrs
        read = _reader("columns", ds, names)
    else:
        d = g["events"]
        n = _event_length(d, where)
        t_attrs = d.attrs
        names = find_columns(found["names"], columns, where) if found["kind"] == "compound" \
            else None
        read = _reader(found["kind"], d, names)
    unit = time_unit or unit_from_text(t_attrs.get("units", t_attrs.get("unit")))
    unit = FloatTimeRule(where, unit)  # float times: one decision per file
    offset = _t_offset(f)
    if sensor_size is None:
        sensor_size = _size_from_attrs(g, f)
    if sensor_size is None:
        if n == 0:
            raise EventFormatError("no events and no sensor size; pass sensor_size=")
        w = h = 0
        for a in range(0, n, chunk_events):
            _, x, y, _ = read(a, a + chunk_events)
            w, h = max(w, int(np.max(x))), max(h, int(np.max(y)))
        sensor_size = (w + 1, h + 1)
        warnings.warn(f"{path}: no sensor size stored; using {w + 1}x{h + 1} from the largest "
                      f"coordinates (pass sensor_size= to set it)", stacklevel=3)
    for a in range(0, max(n, 1), chunk_events):
        events = pack(*read(a, a + chunk_events), unit, f"{where} events {a}..")
        if offset:
            events["t"] += offset
        yield EventStream(events, tuple(sensor_size))


def read_hdf5_positions(path: str | Path, group: str | None = None,
                        time_unit: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Timed positions from HDF5 (NSAVP ``*_applanix.h5``: ``pose_base_link``).

    Looks for a group with ``positions`` ``(N, D)`` and ``timestamps`` ``(N,)`` datasets.

    Returns:
        ``times_us (N,)`` int64 and ``positions (N, D)`` float64 (metres in NSAVP's ECEF).
    """
    h5py = _h5py()
    check_unit(time_unit)
    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            names = [group] if group else ["pose_base_link", "/"]
            extra = []
            f.visit(lambda k: extra.append(k) if isinstance(f.get(k), h5py.Group) else None)
            for name in names + extra:
                g = f[name] if name in f else None
                if g is None or "positions" not in g or "timestamps" not in g:
                    continue
                pos, ts = g["positions"], g["timestamps"]
                for d in (pos, ts):
                    check_storage(d, f"{path}:{g.name}")
                if pos.ndim != 2 or ts.ndim != 1 or pos.shape[0] != ts.shape[0]:
                    raise EventFormatError(f"{path}:{g.name}: positions {pos.shape} do not "
                                           f"match timestamps {ts.shape}")
                unit = time_unit or unit_from_text(ts.attrs.get("units"))
                t = to_microseconds(ts[()], unit, f"{path}:{g.name}")
                p = np.asarray(pos[()], dtype=np.float64)
                if not np.isfinite(p).all():
                    raise EventFormatError(f"{path}:{g.name}: positions not finite")
                return t, p
    except (OSError, KeyError, TypeError, ValueError) as err:
        if isinstance(err, EventFormatError):
            raise
        raise EventFormatError(f"{path}: cannot read positions ({err})") from None
    raise EventFormatError(f"{path}: no group with 'positions' and 'timestamps' datasets")


def write_hdf5(path: str | Path, stream: EventStream) -> None:
    """Write ``/events/{t,x,y,p}`` (int64 us, int16, int16, uint8), ``width``/``height`` attrs.

    Atomic (temporary file, then rename).
    """
    from torchseq.atomic import atomic_path

    h5py = _h5py()
    ev = stream.events
    with atomic_path(Path(path)) as tmp, h5py.File(tmp, "w") as f:
        g = f.create_group("events")
        g.attrs["width"], g.attrs["height"] = stream.sensor_size
        for k in "txyp":
            g.create_dataset(k, data=np.ascontiguousarray(ev[k]))
        g["t"].attrs["units"] = "microseconds"

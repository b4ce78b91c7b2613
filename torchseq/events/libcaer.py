"""libcaer event packets stored row by row in HDF5: DDD20's original recordings.

The DDD20 recorder (ddd20-utils, Binas et al. 2017) stores every libcaer packet it receives
from a DAVIS346B as one row of the ``(N, 3)`` variable-length ``uint8`` dataset
``/dvs/data``: ``[decimal text of the host time in us, 28-byte packet header, packet body]``,
with the host times again in ``/dvs/timestamp``. The dataset grows in blocks, so rows after
the last packet are empty (all three fields zero-length) and are skipped.

The packet header is eight little-endian fields: ``int16 eventType, int16 eventSource,
int32 eventSize, eventTSOffset, eventTSOverflow, eventCapacity, eventNumber, eventValid``;
the body holds ``eventCapacity`` events of ``eventSize`` bytes, the first ``eventNumber`` of
them in use. A polarity event (type 1, 8 bytes) is ``uint32 data, int32 timestamp``: bit 0
of ``data`` marks the event valid, bit 1 is the polarity, bits 2-16 ``y`` and bits 17-31
``x`` (15 bits each); the 64-bit time in us is ``eventTSOverflow << 31 | timestamp``.

Read here: polarity events whose valid bit is set, in file order; packets of other types
(special, APS frames, IMU) are checked and skipped. Any row whose header or body breaks
these rules (sizes, counts, offsets, a negative timestamp or overflow) is an
:class:`EventFormatError` naming the row and the byte inside it. The sensor size comes
from ``sensor_size=``, else ``width``/``height`` attributes, else the extent of the first
valid APS frame (a DAVIS frame covers the same pixel array as its events: 346x260 for
DDD20's DAVIS346B), else the largest coordinates (with a warning).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator

import numpy as np

from torchseq.events.h5vlen import VlenReader
from torchseq.events.stream import EVENT_DTYPE, EventFormatError, EventStream, check_sensor_size

HEADER_BYTES = 28
HEADER_DTYPE = np.dtype([("type", "<i2"), ("source", "<i2"), ("size", "<i4"),
                         ("ts_offset", "<i4"), ("ts_overflow", "<i4"), ("capacity", "<i4"),
                         ("number", "<i4"), ("valid", "<i4")])
HEADER_FIELD_AT = {name: HEADER_DTYPE.fields[name][1] for name in HEADER_DTYPE.names}
POLARITY_EVENT, FRAME_EVENT = 1, 2
POLARITY_BYTES = 8
FRAME_HEADER_BYTES = 36  # uint32 info, 4 x int32 times, int32 lengthX, lengthY, posX, posY
TS_OVERFLOW_SHIFT = 31
ROWS_PER_READ = 128  # DDD20's own HDF5 chunk length
VLEN_REF_BYTES = 16  # a variable-length element as HDF5 stores it: length + global heap id


def is_packet_dataset(d, h5py) -> bool:
    """True when ``d`` is an ``(N, 3)`` variable-length ``uint8`` dataset (``/dvs/data``)."""
    if not isinstance(d, h5py.Dataset) or d.ndim != 2 or d.shape[1] != 3:
        return False
    base = h5py.check_vlen_dtype(d.dtype)
    return base is not None and np.dtype(base) == np.uint8


def find_packet_dataset(f, group: str | None, h5py):
    """The ``data`` packet dataset of ``group`` (default ``dvs``) if it is one, else None."""
    name = group if group is not None else "dvs"
    g = f.get(name)
    if isinstance(g, h5py.Group) and is_packet_dataset(g.get("data"), h5py):
        return g["data"]
    return None


def stored_rows(d, where: str) -> int:
    """Rows of ``d`` that the file stores.

    Up to the last allocated chunk for a chunked dataset (DDD20 grows its datasets in
    blocks; unwritten chunks read as empty rows), all of them otherwise.

    Raises:
        EventFormatError: an unchunked dataset declaring more rows than it stores.
    """
    n = int(d.shape[0])
    if d.chunks is None:
        stored = int(d.id.get_storage_size())
        if stored < n * 3 * VLEN_REF_BYTES:
            raise EventFormatError(f"{where}: declares {n} rows but stores {stored} bytes "
                                   f"(less than {VLEN_REF_BYTES} per element)")
        return n
    ends = [d.id.get_chunk_info(i).chunk_offset[0] + d.chunks[0]
            for i in range(d.id.get_num_chunks())]
    return min(n, max(ends, default=0))


def parse_header(raw: np.ndarray, where: str) -> dict[str, int]:
    """The checked fields of one 28-byte packet header.

    Args:
        raw: ``(28,)`` uint8 header bytes.
        where: the packet, for messages.

    Raises:
        EventFormatError: wrong length, negative fields, ``eventNumber > eventCapacity``,
            ``eventValid > eventNumber``, a time-stamp offset outside the event.
    """
    if len(raw) != HEADER_BYTES:
        raise EventFormatError(f"{where}: packet header has {len(raw)} bytes, not "
                               f"{HEADER_BYTES} (at header byte {min(len(raw), HEADER_BYTES)})")
    h = np.frombuffer(raw.tobytes(), HEADER_DTYPE)[0]
    fields = {name: int(h[name]) for name in HEADER_DTYPE.names}
    for name in HEADER_DTYPE.names:
        if fields[name] < 0:
            raise EventFormatError(f"{where}: negative {name} {fields[name]} in the packet "
                                   f"header (at header byte {HEADER_FIELD_AT[name]})")
    rules = (("size", fields["size"] < 4, "event size below 4 bytes"),
             ("ts_offset", fields["ts_offset"] > fields["size"] - 4,
              f"time-stamp offset {fields['ts_offset']} outside a {fields['size']}-byte event"),
             ("number", fields["number"] > fields["capacity"],
              f"eventNumber {fields['number']} > eventCapacity {fields['capacity']}"),
             ("valid", fields["valid"] > fields["number"],
              f"eventValid {fields['valid']} > eventNumber {fields['number']}"))
    for name, bad, msg in rules:
        if bad:
            raise EventFormatError(f"{where}: {msg} (at header byte {HEADER_FIELD_AT[name]})")
    return fields


def decode_polarity(header: dict[str, int], body: np.ndarray, where: str
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The valid events of one polarity packet.

    Args:
        header: its :func:`parse_header` fields (type 1).
        body: ``(eventCapacity * 8,)`` uint8 packet body.
        where: the packet, for messages.

    Returns:
        ``t (M,)`` int64 us, ``x (M,)``, ``y (M,)`` uint32, ``p (M,)`` uint32 (0/1): the events
        among the first ``eventNumber`` whose valid bit is set, in packet order.

    Raises:
        EventFormatError: not 8-byte events with the time stamp at byte 4, or a valid event
            with a negative time stamp.
    """
    if header["size"] != POLARITY_BYTES or header["ts_offset"] != 4:
        raise EventFormatError(f"{where}: polarity packet with {header['size']}-byte events and "
                               f"time stamp at byte {header['ts_offset']} (expected 8 and 4; at "
                               f"header byte {HEADER_FIELD_AT['size']})")
    n = header["number"]
    words = np.frombuffer(body, "<u4", count=2 * n).reshape(n, 2)
    data = words[:, 0]
    keep = (data & 1).astype(bool)
    data = data[keep]
    ts = words[keep, 1].view("<i4")
    if len(ts) and ts.min() < 0:
        i = int(np.flatnonzero(keep)[np.argmax(ts < 0)])
        raise EventFormatError(f"{where}: negative time stamp {int(ts.min())} in event #{i} "
                               f"(at body byte {i * POLARITY_BYTES + 4})")
    t = (np.int64(header["ts_overflow"]) << TS_OVERFLOW_SHIFT) | ts.astype(np.int64)
    return t, (data >> 17) & 0x7FFF, (data >> 2) & 0x7FFF, (data >> 1) & 1


def _frame_extent(header: dict[str, int], body: np.ndarray) -> tuple[int, int] | None:
    """``(W, H)`` covered by the packet's first valid frame event, if it is plausible."""
    size = header["size"]
    if size < FRAME_HEADER_BYTES:
        return None
    for i in range(header["number"]):
        f = np.frombuffer(body[i * size: i * size + FRAME_HEADER_BYTES].tobytes(), "<i4")
        if f[0] & 1:  # valid mark
            lx, ly, px, py = (int(v) for v in f[5:9])
            w, h = lx + px, ly + py
            ok = min(lx, ly, px, py) >= 0 and 1 <= w <= 1 << 15 and 1 <= h <= 1 << 15
            return (w, h) if ok else None
    return None


class PacketRows:
    """The packet rows of one ``/dvs/data`` dataset, read ``ROWS_PER_READ`` at a time.

    Args:
        d: the ``(N, 3)`` variable-length uint8 dataset.
        where: ``"<file>:<dataset>"`` for messages.
    """

    def __init__(self, d, where: str) -> None:
        self.d, self.where_file = d, where
        self.n = stored_rows(d, where)
        self.reader = VlenReader(d, where)

    def where(self, row: int) -> str:
        """The row, for messages."""
        return f"{self.where_file} row {row}"

    def packets(self, headers_only: bool = False
                ) -> Iterator[tuple[int, dict[str, int], np.ndarray | None]]:
        """``(row, header fields, body)`` of every non-empty row, checked.

        ``body`` is None when ``headers_only``.
        """
        for a in range(0, self.n, ROWS_PER_READ):
            b = min(a + ROWS_PER_READ, self.n)
            block = self.reader.rows(a, b, (1,) if headers_only else (0, 1, 2))
            for i, row in enumerate(block):
                where = self.where(a + i)
                head = row[0] if headers_only else row[1]
                if headers_only:
                    if len(head) == 0:
                        continue
                elif not any(len(v) for v in row):
                    continue  # the dataset's unused tail (DDD20 grows it in blocks)
                header = parse_header(head, where)
                if headers_only:
                    yield a + i, header, None
                    continue
                body = row[2]
                need = header["capacity"] * header["size"]
                if len(body) != need:
                    raise EventFormatError(
                        f"{where}: packet body has {len(body)} bytes, the header declares "
                        f"{header['capacity']} x {header['size']} = {need} (at body byte "
                        f"{min(len(body), need)})")
                yield a + i, header, body

    def frame_size(self) -> tuple[int, int] | None:
        """The ``(W, H)`` of the first valid, plausible APS frame in the file, or None."""
        for row, header, _ in self.packets(headers_only=True):
            if header["type"] == FRAME_EVENT and header["number"]:
                body = self.reader.rows(row, row + 1, (2,))[0][0]
                size = _frame_extent(header, body) \
                    if len(body) == header["capacity"] * header["size"] else None
                if size is not None:
                    return size
        return None


def iter_packet_events(rows: PacketRows, chunk_events: int,
                       sensor_size: tuple[int, int] | None) -> Iterator[EventStream]:
    """Stream the valid polarity events of ``rows`` in chunks of ``chunk_events``.

    Args:
        rows: the packet rows.
        chunk_events: events per chunk (the last may be shorter).
        sensor_size: ``(W, H)`` from the caller or the file's attributes; None: the first
            APS frame's extent, else the largest coordinates (with a warning).

    Yields:
        :class:`EventStream` chunks (at least one, empty for a file without events).
    """
    if sensor_size is None:
        sensor_size = rows.frame_size()
    if sensor_size is None:
        w = h = -1
        for t, x, y, _ in _decoded(rows):
            if len(t):
                w, h = max(w, int(x.max())), max(h, int(y.max()))
        if w < 0:
            raise EventFormatError(f"{rows.where_file}: no events, no APS frame and no sensor "
                                   f"size; pass sensor_size=")
        warnings.warn(f"{rows.where_file}: no sensor size stored and no APS frame; using "
                      f"{w + 1}x{h + 1} from the largest coordinates (DDD20's DAVIS346B is "
                      f"346x260; pass sensor_size= to set it)", stacklevel=4)
        sensor_size = (w + 1, h + 1)
    sensor_size = check_sensor_size(sensor_size)
    pending, held, sent = [], 0, False
    for t, x, y, p in _decoded(rows):
        if not len(t):
            continue
        ev = np.empty(len(t), EVENT_DTYPE)
        ev["t"], ev["x"], ev["y"], ev["p"] = t, x, y, p
        pending.append(ev)
        held += len(ev)
        if held >= chunk_events:
            buf = np.concatenate(pending)
            cut = len(buf) - len(buf) % chunk_events
            for a in range(0, cut, chunk_events):
                yield EventStream(buf[a:a + chunk_events], sensor_size)
                sent = True
            pending, held = [buf[cut:]], len(buf) - cut
    if held or not sent:
        yield EventStream(np.concatenate(pending) if pending else np.empty(0, EVENT_DTYPE),
                          sensor_size)


def _decoded(rows: PacketRows):
    for row, header, body in rows.packets():
        if header["type"] == POLARITY_EVENT:
            yield decode_polarity(header, body, rows.where(row))

"""AEDAT 4.0 (iniVation DV) reader, hand-written, with no flatbuffers dependency.

Layout: the line ``#!AER-DAT4.0`` (CR LF), a size-prefixed IOHeader flatbuffer, then packets
``(int32 stream id, int32 size, payload)`` up to the data table.

The IOHeader gives the payload compression (0 none, 1/2 LZ4, 3/4 Zstd) and an XML info node
naming each stream's type (``EVTS`` for polarity events) and size (``sizeX``/``sizeY``). An
``EVTS`` payload is a flatbuffer table whose first field is a vector of 16-byte structs
``(int64 timestamp us, int16 x, int16 y, bool polarity, 3 padding bytes)``. Other streams
(frames, IMU, triggers) are skipped. The flatbuffers are parsed by hand (a few offsets), LZ4
uses the ``lz4`` package when installed (pure-Python fallback otherwise), Zstd needs the
``zstandard`` package.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from torchseq.events.lz4frame import LZ4Error
from torchseq.events.lz4frame import decompress as lz4_decompress
from torchseq.events.stream import EventFormatError, EventStream, make_events

MAGIC = b"#!AER-DAT4.0\r\n"
EVENT = np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1"), ("pad", "V3")])


def _table_field(buf: bytes, table: int, field: int) -> int | None:
    """Absolute position of ``field`` of the flatbuffer table at ``table`` (None if absent)."""
    vtable = table - struct.unpack_from("<i", buf, table)[0]
    vt_size = struct.unpack_from("<H", buf, vtable)[0]
    slot = 4 + 2 * field
    if slot + 2 > vt_size:
        return None
    off = struct.unpack_from("<H", buf, vtable + slot)[0]
    return table + off if off else None


def _deref(buf: bytes, pos: int) -> int:
    return pos + struct.unpack_from("<I", buf, pos)[0]


def parse_io_header(buf: bytes) -> tuple[int, int, str]:
    """``(compression, data table position or -1, info XML)`` from an IOHeader flatbuffer."""
    root = _deref(buf, 0)
    pos = _table_field(buf, root, 0)
    compression = struct.unpack_from("<i", buf, pos)[0] if pos is not None else 0
    pos = _table_field(buf, root, 1)
    table_pos = struct.unpack_from("<q", buf, pos)[0] if pos is not None else -1
    pos = _table_field(buf, root, 2)
    info = ""
    if pos is not None:
        s = _deref(buf, pos)
        n = struct.unpack_from("<I", buf, s)[0]
        info = buf[s + 4 : s + 4 + n].decode("utf-8", "replace")
    return compression, table_pos, info


def parse_streams(info: str) -> dict[int, dict[str, str]]:
    """Stream id -> attributes (``typeIdentifier``, ``compression``, ``sizeX``, ``sizeY``)."""
    streams = {}
    for m in re.finditer(r'<node name="(\d+)" path="[^"]*/outInfo/\d+/">(.*?)</node>\s*</node>',
                         info, re.S):
        attrs = dict(re.findall(r'<attr key="(\w+)" type="\w+">([^<]*)</attr>', m.group(2)))
        streams[int(m.group(1))] = attrs
    return streams


def _decompress(payload: bytes, compression: int) -> bytes:
    if compression == 0:
        return payload
    if compression in (1, 2):
        try:
            return lz4_decompress(payload)
        except (LZ4Error, RuntimeError) as err:
            raise EventFormatError(f"corrupt LZ4 packet: {err}") from None
    if compression in (3, 4):
        try:
            import zstandard
        except ImportError:
            raise EventFormatError("this AEDAT4 file is Zstd-compressed: pip install zstandard"
                                   ) from None
        return zstandard.ZstdDecompressor().decompressobj().decompress(payload)
    raise EventFormatError(f"unknown AEDAT4 compression type {compression}")


def decode_events_packet(buf: bytes) -> np.ndarray:
    """Events of one decompressed ``EVTS`` packet flatbuffer (size-prefixed or not)."""
    if len(buf) >= 8 and struct.unpack_from("<I", buf, 0)[0] == len(buf) - 4:
        buf = buf[4:]
    if len(buf) < 8 or buf[4:8] != b"EVTS":
        raise EventFormatError("AEDAT4 events packet lacks its 'EVTS' identifier")
    root = _deref(buf, 0)
    pos = _table_field(buf, root, 0)
    if pos is None:
        return make_events([], [], [], [])
    vec = _deref(buf, pos)
    n = struct.unpack_from("<I", buf, vec)[0]
    if vec + 4 + n * EVENT.itemsize > len(buf):
        raise EventFormatError("AEDAT4 events packet is shorter than its event count")
    raw = np.frombuffer(buf, EVENT, n, vec + 4)
    return make_events(raw["t"], raw["x"], raw["y"], raw["p"] != 0)


def iter_aedat4(path: str | Path, chunk_events: int = 1 << 20,
                sensor_size: tuple[int, int] | None = None,
                truncated: str = "error") -> Iterator[EventStream]:
    """Stream the polarity events of an AEDAT 4.0 file, about ``chunk_events`` at a time.

    Args:
        path: the ``.aedat4`` file.
        chunk_events: events gathered (from whole packets) before a chunk is yielded.
        sensor_size: ``(W, H)`` override; default from the events stream's info node.
        truncated: a partial last packet: ``"error"`` (default) or ``"drop"`` with a warning.

    Yields:
        :class:`EventStream` chunks, time order not yet checked.
    """
    import warnings

    path = Path(path)
    with open(path, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise EventFormatError(f"{path}: not an AEDAT 4.0 file")
        head = f.read(4)
        if len(head) < 4:
            raise EventFormatError(f"{path}: truncated AEDAT4 header")
        size = struct.unpack("<i", head)[0]
        buf = f.read(size)
        if len(buf) < size:
            raise EventFormatError(f"{path}: truncated AEDAT4 header")
        compression, table_pos, info = parse_io_header(buf)
        end = table_pos if table_pos >= 0 else path.stat().st_size  # packets stop at the table
        streams = {k: v for k, v in parse_streams(info).items()
                   if v.get("typeIdentifier") == "EVTS"}
        if not streams:
            raise EventFormatError(f"{path}: no polarity-event (EVTS) stream in the AEDAT4 file")
        sid = min(streams)
        if sensor_size is None:
            try:
                sensor_size = (int(streams[sid]["sizeX"]), int(streams[sid]["sizeY"]))
            except KeyError:
                raise EventFormatError(f"{path}: no sizeX/sizeY in the header; pass sensor_size="
                                       ) from None
        pending, count = [], 0
        while f.tell() < end:
            head = f.read(min(8, end - f.tell()))
            stream_id, size = struct.unpack("<ii", head) if len(head) == 8 else (-1, 0)
            payload = f.read(size) if len(head) == 8 and 0 <= size <= end - f.tell() else b""
            if len(head) < 8 or len(payload) < size:
                msg = f"{path}: truncated, the last packet is cut short"
                if truncated != "drop":
                    raise EventFormatError(msg + "; pass truncated='drop' to ignore it")
                warnings.warn(msg + ", dropped", stacklevel=2)
                break
            if stream_id != sid:
                continue
            pending.append(decode_events_packet(_decompress(payload, compression)))
            count += len(pending[-1])
            if count >= chunk_events:
                yield EventStream(np.concatenate(pending), sensor_size)
                pending, count = [], 0
        if pending or count == 0:
            yield EventStream(np.concatenate(pending) if pending else make_events([], [], [], []),
                              sensor_size)

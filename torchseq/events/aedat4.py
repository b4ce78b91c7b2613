"""AEDAT 4.0 (iniVation DV) reader and writer, hand-written, with no flatbuffers dependency.

Layout: the line ``#!AER-DAT4.0`` (CR LF), a size-prefixed IOHeader flatbuffer, then packets
``(int32 stream id, int32 size, payload)`` up to the data table.

The IOHeader gives the payload compression (0 none, 1/2 LZ4, 3/4 Zstd) and an XML info node
naming each stream's type (``EVTS`` for polarity events) and size (``sizeX``/``sizeY``). An
``EVTS`` payload is a flatbuffer table whose first field is a vector of 16-byte structs
``(int64 timestamp us, int16 x, int16 y, bool polarity, 3 padding bytes)``. Other streams
(frames, IMU, triggers) are skipped. The flatbuffers are parsed by hand (a few offsets, each
checked against the buffer before use); the event structs have the memory layout of
:data:`~torchseq.events.stream.EVENT_DTYPE`, so a packet is read without per-field work.
LZ4 uses the ``lz4`` package when installed (pure-Python fallback otherwise), Zstd needs the
``zstandard`` package. A packet may decompress to at most :data:`PACKET_LIMIT` bytes.
"""

from __future__ import annotations

import importlib.util
import re
import struct
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from torchseq.atomic import atomic_open
from torchseq.events.lz4frame import LZ4Error, decompress_frames
from torchseq.events.stream import (
    EVENT_DTYPE,
    Chunk,
    EventFormatError,
    EventStream,
    check_sensor_size,
    check_truncated,
    concat_events,
    file_error,
)

MAGIC = b"#!AER-DAT4.0\r\n"
EVENT = np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1"), ("pad", "V3")])
PACKET_LIMIT = 1 << 28  # bytes one packet may decompress to (16.7 M events)
COMPRESSION = {"none": 0, "lz4": 1, "zstd": 3}
assert EVENT.itemsize == EVENT_DTYPE.itemsize == 16 and all(
    EVENT.fields[f][1] == EVENT_DTYPE.fields[f][1] for f in "txyp")


class _Flat:
    """Bounds-checked little-endian reads from a flatbuffer (errors name file and byte)."""

    def __init__(self, buf: bytes, path, offset: int, what: str):
        self.buf, self.path, self.offset, self.what = buf, path, offset, what

    def error(self, msg: str) -> EventFormatError:
        return file_error(self.path, self.offset, f"{self.what}: {msg}")

    def read(self, fmt: str, pos: int) -> int:
        size = struct.calcsize(fmt)
        if pos < 0 or pos + size > len(self.buf):
            raise self.error(f"offset {pos} (+{size}) outside its {len(self.buf)} bytes")
        return struct.unpack_from(fmt, self.buf, pos)[0]

    def deref(self, pos: int) -> int:
        return pos + self.read("<I", pos)

    def field(self, table: int, field: int) -> int | None:
        """Absolute position of ``field`` of the table at ``table`` (None if absent)."""
        vtable = table - self.read("<i", table)
        vt_size = self.read("<H", vtable)
        slot = 4 + 2 * field
        if slot + 2 > vt_size:
            return None
        off = self.read("<H", vtable + slot)
        return table + off if off else None


def parse_io_header(buf: bytes, path=None, offset: int = 0) -> tuple[int, int, str]:
    """``(compression, data table position or -1, info XML)`` from an IOHeader flatbuffer."""
    fb = _Flat(buf, path, offset, "AEDAT4 IOHeader")
    root = fb.deref(0)
    pos = fb.field(root, 0)
    compression = fb.read("<i", pos) if pos is not None else 0
    pos = fb.field(root, 1)
    table_pos = fb.read("<q", pos) if pos is not None else -1
    pos = fb.field(root, 2)
    info = ""
    if pos is not None:
        s = fb.deref(pos)
        n = fb.read("<I", s)
        if s + 4 + n > len(buf):
            raise fb.error(f"info string of {n} bytes runs past the header's end")
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


def _lz4_package(payload: bytes, limit: int) -> bytes:
    """LZ4 frames through the ``lz4`` package (C), at most ``limit`` bytes out.

    A frame that states its content size (DV and torchseq write it) is decompressed in one
    call into a buffer of that size, once the size is checked against ``limit``; otherwise
    in pieces of at most 1 MiB, so the output never grows past what the frame holds.
    """
    import lz4.frame

    out, data, total = [], payload, 0
    while data:
        size = lz4.frame.get_frame_info(data[:32])["content_size"]
        if 0 < size <= limit - total:
            d = lz4.frame.LZ4FrameDecompressor()
            out.append(d.decompress(data, max_length=size + 1))
            if len(out[-1]) != size or not d.eof:
                raise LZ4Error(f"frame holds {len(out[-1])} bytes, its header says {size}")
            total += size
            data = d.unused_data
            continue
        if size > limit - total:
            raise LZ4Error(f"decompresses to more than {limit} bytes")
        d = lz4.frame.LZ4FrameDecompressor()
        piece = d.decompress(data, max_length=min(1 << 20, limit - total + 1))
        while True:
            out.append(piece)
            total += len(piece)
            if total > limit:
                raise LZ4Error(f"decompresses to more than {limit} bytes")
            if d.eof or d.needs_input:
                break
            piece = d.decompress(b"", max_length=min(1 << 20, limit - total + 1))
        if not d.eof:
            raise LZ4Error("truncated LZ4 frame")
        data = d.unused_data
    return b"".join(out) if len(out) != 1 else out[0]


# the LZ4 kernel, chosen once here: the C package when installed, else pure Python; found
# without importing it (a run that reads no AEDAT 4 file never loads lz4)
lz4_decompress = (_lz4_package if importlib.util.find_spec("lz4") is not None
                  else decompress_frames)


def _zstd(payload: bytes, limit: int) -> bytes:
    import zstandard

    out, total = [], 0
    with zstandard.ZstdDecompressor().stream_reader(payload, read_across_frames=True) as r:
        while True:
            block = r.read(1 << 20)
            if not block:
                break
            out.append(block)
            total += len(block)
            if total > limit:
                raise zstandard.ZstdError(f"decompresses to more than {limit} bytes")
    return b"".join(out)


def _decompress(payload: bytes, compression: int, limit: int = PACKET_LIMIT) -> bytes:
    """Decompress one packet (at most ``limit`` bytes out); errors are EventFormatError."""
    if compression == 0:
        return payload
    if compression in (1, 2):
        try:
            return lz4_decompress(payload, limit)
        except (LZ4Error, RuntimeError) as err:
            raise EventFormatError(f"corrupt LZ4 packet: {err}") from None
    if compression in (3, 4):
        try:
            import zstandard
        except ImportError:
            raise EventFormatError("this AEDAT4 file is Zstd-compressed: pip install zstandard"
                                   ) from None
        try:
            return _zstd(payload, limit)
        except zstandard.ZstdError as err:
            raise EventFormatError(f"corrupt Zstd packet: {err}") from None
    raise EventFormatError(f"unknown AEDAT4 compression type {compression}")


def decode_events_packet(buf: bytes, path=None, offset: int | None = None) -> np.ndarray:
    """Events of one decompressed ``EVTS`` packet flatbuffer (size-prefixed or not).

    Returns:
        ``(N,)`` :data:`EVENT_DTYPE` array, read-only (a view of ``buf``) unless a polarity
        byte other than 0/1 had to be normalised (a flatbuffers bool: non-zero = ON).
    """
    if len(buf) >= 8 and struct.unpack_from("<I", buf, 0)[0] == len(buf) - 4:
        buf = memoryview(buf)[4:]
    fb = _Flat(buf, path, offset, "AEDAT4 events packet")
    if len(buf) < 8 or bytes(buf[4:8]) != b"EVTS":
        raise fb.error("lacks its 'EVTS' identifier")
    pos = fb.field(fb.deref(0), 0)
    if pos is None:
        return np.empty(0, EVENT_DTYPE)
    vec = fb.deref(pos)
    n = fb.read("<I", vec)
    if vec + 4 + n * EVENT.itemsize > len(buf):
        raise fb.error(f"declares {n} events, more than its {len(buf)} bytes hold")
    events = np.frombuffer(buf, EVENT_DTYPE, n, vec + 4)
    if n and events["p"].max() > 1:
        events = events.copy()
        events["p"] = events["p"] != 0
    return events


def _read_header(f, path) -> tuple[int, int, dict]:
    if f.read(len(MAGIC)) != MAGIC:
        raise file_error(path, 0, "not an AEDAT 4.0 file")
    head = f.read(4)
    file_size = path.stat().st_size
    if len(head) < 4:
        raise file_error(path, len(MAGIC), "truncated AEDAT4 header")
    size = struct.unpack("<i", head)[0]
    if not 0 < size <= file_size - f.tell():
        raise file_error(path, len(MAGIC), f"truncated AEDAT4 header (declares {size} bytes, "
                         f"{file_size - f.tell()} follow)")
    buf = f.read(size)
    if len(buf) < size:
        raise file_error(path, len(MAGIC), "truncated AEDAT4 header")
    compression, table_pos, info = parse_io_header(buf, path, len(MAGIC) + 4)
    return compression, table_pos, parse_streams(info)


def iter_aedat4(path: str | Path, chunk_events: int = 1 << 20,
                sensor_size: tuple[int, int] | None = None,
                truncated: str = "error") -> Iterator[EventStream]:
    """Stream the polarity events of an AEDAT 4.0 file, about ``chunk_events`` at a time.

    Args:
        path: the ``.aedat4`` file.
        chunk_events: events gathered (from whole packets) before a chunk is yielded.
        sensor_size: ``(W, H)`` override; default from the events stream's info node.
        truncated: a partial last packet (or a data table position past the end of the
            file): ``"error"`` (default) or ``"drop"`` with a warning.

    Yields:
        :class:`~torchseq.events.stream.Chunk` pieces, time order not yet checked.
    """
    path = Path(path)
    check_truncated(truncated)
    if sensor_size is not None:
        sensor_size = check_sensor_size(sensor_size)
    file_size = path.stat().st_size
    with open(path, "rb") as f:
        compression, table_pos, streams = _read_header(f, path)
        data_start = f.tell()
        if table_pos >= 0 and table_pos < data_start:
            raise file_error(path, len(MAGIC) + 4, f"data table position {table_pos} lies "
                             f"inside the header (which ends at byte {data_start})")
        end = table_pos if 0 <= table_pos <= file_size else file_size
        cut = 0 <= file_size < table_pos  # the data table lies past the end: truncated
        streams = {k: v for k, v in streams.items() if v.get("typeIdentifier") == "EVTS"}
        if not streams:
            raise file_error(path, len(MAGIC) + 4,
                             "no polarity-event (EVTS) stream in the AEDAT4 file")
        sid = min(streams)
        if sensor_size is None:
            attrs = streams[sid]
            if "sizeX" not in attrs or "sizeY" not in attrs:
                raise file_error(path, len(MAGIC) + 4,
                                 "no sizeX/sizeY in the header; pass sensor_size=")
            try:
                sensor_size = check_sensor_size(
                    (int(attrs["sizeX"]), int(attrs["sizeY"])), "the header's sizeX/sizeY")
            except ValueError as err:
                raise file_error(path, len(MAGIC) + 4, f"bad sizeX/sizeY in the header "
                                 f"({err})") from None
        pending, count, chunk_start = [], 0, data_start
        pos = data_start
        while pos < end:
            head = f.read(min(8, end - pos))
            stream_id, size = struct.unpack("<ii", head) if len(head) == 8 else (-1, 0)
            if len(head) == 8 and size < 0:
                raise file_error(path, pos, f"packet with a negative size {size}")
            if len(head) < 8 or size > end - pos - 8:
                msg = f"truncated, the packet at byte {pos} is cut short"
                if truncated != "drop":
                    raise file_error(path, pos, msg + "; pass truncated='drop' to ignore it")
                warnings.warn(f"{path}: {msg}, dropped", stacklevel=2)
                cut = False
                break
            if stream_id != sid:
                f.seek(size, 1)
                pos += 8 + size
                continue
            payload = f.read(size)
            if len(payload) < size:
                raise file_error(path, pos, "file shrank while reading")
            try:
                data = _decompress(payload, compression)
            except EventFormatError as err:
                raise file_error(path, pos, f"packet: {err}") from None
            pending.append(decode_events_packet(data, path, pos))
            pos += 8 + size
            count += len(pending[-1])
            if count >= chunk_events:
                yield Chunk(concat_events(pending), sensor_size, chunk_start)
                pending, count, chunk_start = [], 0, pos
        if cut:
            msg = f"truncated: the data table position {table_pos} lies past the end"
            if truncated != "drop":
                raise file_error(path, file_size, msg + "; pass truncated='drop' to ignore it")
            warnings.warn(f"{path}: {msg}, ignored", stacklevel=2)
        if pending or count == 0:
            yield Chunk(concat_events(pending), sensor_size, chunk_start)


# ---------------------------------------------------------------- writer


def _io_header(compression: int, info: str) -> bytes:
    """IOHeader flatbuffer (identifier ``IOHE``): compression, data table -1, info string."""
    text = info.encode("utf-8")
    vtable = struct.pack("<HHHHH", 10, 20, 4, 8, 16) + b"\0\0"  # at 8..20
    table = struct.pack("<iiqI", 20 - 8, compression, -1, 40 - 36)  # at 20..40
    string = struct.pack("<I", len(text)) + text + b"\0"
    buf = struct.pack("<I", 20) + b"IOHE" + vtable + table + string
    return buf + b"\0" * (-len(buf) % 4)


def _events_packet(events: np.ndarray) -> bytes:
    """Size-prefixed ``EVTS`` flatbuffer of ``events`` (struct vector 8-byte aligned)."""
    body = (struct.pack("<I", 16) + b"EVTS" + struct.pack("<HHH", 6, 8, 4) + b"\0\0"
            + struct.pack("<iII", 8, 4, len(events)))  # table at 16 (prefix excluded), vec 24
    raw = np.zeros(len(events), EVENT)
    for name in "txyp":
        raw[name] = events[name]
    return struct.pack("<I", len(body) + raw.nbytes) + body + raw.tobytes()


def write_aedat4(path: str | Path, stream: EventStream, compression: str = "lz4",
                 packet_events: int = 8192) -> None:
    """Write events as AEDAT 4.0 (atomically): one ``EVTS`` stream, packets of events.

    Args:
        path: output ``.aedat4`` file.
        stream: events (validated first).
        compression: ``"lz4"`` (as DV records), ``"zstd"`` or ``"none"``.
        packet_events: events per packet.
    """
    stream.validate()
    if compression not in COMPRESSION:
        raise ValueError(f"compression must be one of {sorted(COMPRESSION)}, got {compression!r}")
    if packet_events < 1:
        raise ValueError(f"packet_events must be >= 1, got {packet_events}")
    (w, h), code = stream.sensor_size, COMPRESSION[compression]
    info = ('<dv version="2.0">\n    <node name="outInfo" path="/mainloop/Recorder/outInfo/">\n'
            '        <node name="0" path="/mainloop/Recorder/outInfo/0/">\n'
            f'            <attr key="compression" type="string">{compression.upper()}</attr>\n'
            '            <attr key="originalOutputName" type="string">events</attr>\n'
            '            <attr key="typeIdentifier" type="string">EVTS</attr>\n'
            '            <node name="info" path="/mainloop/Recorder/outInfo/0/info/">\n'
            f'                <attr key="sizeX" type="int">{w}</attr>\n'
            f'                <attr key="sizeY" type="int">{h}</attr>\n'
            '                <attr key="source" type="string">torchseq</attr>\n'
            '            </node>\n        </node>\n    </node>\n</dv>\n')
    header = _io_header(code, info)
    if compression == "lz4":
        import lz4.frame

        def pack(data):
            return lz4.frame.compress(data)
    elif compression == "zstd":
        import zstandard

        cctx = zstandard.ZstdCompressor()

        def pack(data):
            return cctx.compress(data)
    else:
        def pack(data):
            return data
    ev = stream.events
    with atomic_open(path) as f:
        f.write(MAGIC + struct.pack("<i", len(header)) + header)
        for i in range(0, len(ev), packet_events):
            payload = pack(_events_packet(ev[i : i + packet_events]))
            f.write(struct.pack("<ii", 0, len(payload)) + payload)

"""LZ4 frame decompression: the ``lz4`` package when installed, else a pure-Python decoder.

The pure-Python fallback follows the published LZ4 frame and block format descriptions
(magic ``0x184D2204``, frame descriptor, size-prefixed blocks, optional checksums, which are
skipped, not verified). It is about 10-50x slower than the C library but needs nothing.
"""

from __future__ import annotations

import struct

MAGIC = 0x184D2204


class LZ4Error(ValueError):
    """Malformed LZ4 data."""


def decompress_block(src: bytes | memoryview, out: bytearray, limit: int | None = None) -> None:
    """Append the decoded LZ4 block ``src`` to ``out`` (matches may reach into earlier data).

    Raises :class:`LZ4Error` before ``out`` would grow beyond ``limit`` bytes.
    """
    limit = float("inf") if limit is None else limit
    i, n = 0, len(src)
    while i < n:
        token = src[i]
        i += 1
        lit = token >> 4
        if lit == 15:
            while True:
                b = src[i]
                i += 1
                lit += b
                if b != 255:
                    break
        if len(out) + lit > limit:
            raise LZ4Error(f"decompresses to more than {limit} bytes")
        out += src[i : i + lit]
        i += lit
        if i >= n:  # the last sequence has literals only
            break
        offset = src[i] | (src[i + 1] << 8)
        i += 2
        mlen = (token & 15) + 4
        if token & 15 == 15:
            while True:
                b = src[i]
                i += 1
                mlen += b
                if b != 255:
                    break
        if len(out) + mlen > limit:
            raise LZ4Error(f"decompresses to more than {limit} bytes")
        if offset == 0 or offset > len(out):
            raise LZ4Error(f"bad LZ4 match offset {offset} at output byte {len(out)}")
        start = len(out) - offset
        if mlen <= offset:
            out += out[start : start + mlen]
        else:  # overlapping copy repeats the last `offset` bytes
            pattern = bytes(out[start:])
            reps, rest = divmod(mlen, offset)
            out += pattern * reps + pattern[:rest]


def decompress_frames(data: bytes, limit: int | None = None) -> bytes:
    """Decompress one or more concatenated LZ4 frames (pure Python), to at most ``limit`` bytes."""
    out = bytearray()
    mv, i = memoryview(data), 0
    while i < len(data):
        if len(data) - i < 7:
            raise LZ4Error("truncated LZ4 frame header")
        (magic,) = struct.unpack_from("<I", data, i)
        if 0x184D2A50 <= magic <= 0x184D2A5F:  # skippable frame
            if len(data) - i < 8:
                raise LZ4Error("truncated skippable LZ4 frame")
            (size,) = struct.unpack_from("<I", data, i + 4)
            i += 8 + size
            continue
        if magic != MAGIC:
            raise LZ4Error(f"not an LZ4 frame (magic {magic:#x})")
        flg = data[i + 4]
        if flg >> 6 != 1:
            raise LZ4Error(f"unsupported LZ4 frame version {flg >> 6}")
        block_checksum, content_size, content_checksum, dict_id = (
            flg & 0x10, flg & 0x08, flg & 0x04, flg & 0x01)
        i += 6 + (8 if content_size else 0) + (4 if dict_id else 0) + 1  # ... + header checksum
        while True:
            if i + 4 > len(data):
                raise LZ4Error("truncated LZ4 frame: missing end mark")
            (size,) = struct.unpack_from("<I", data, i)
            i += 4
            if size == 0:
                break
            raw, size = size & 0x80000000, size & 0x7FFFFFFF
            if i + size > len(data):
                raise LZ4Error("truncated LZ4 block")
            if raw:
                if limit is not None and len(out) + size > limit:
                    raise LZ4Error(f"decompresses to more than {limit} bytes")
                out += mv[i : i + size]
            else:
                try:
                    decompress_block(mv[i : i + size], out, limit)
                except IndexError:
                    raise LZ4Error("malformed LZ4 block (reads past its end)") from None
            i += size + (4 if block_checksum else 0)
        i += 4 if content_checksum else 0
    return bytes(out)


def decompress(data: bytes) -> bytes:
    """Decompress LZ4 frame data with the ``lz4`` package if present, else in pure Python."""
    try:
        import lz4.frame
    except ImportError:
        return decompress_frames(data)
    return lz4.frame.decompress(data)

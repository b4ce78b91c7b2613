"""jAER AEDAT 2.0: ``#`` text header lines, then big-endian (int32 address, int32 time in us).

Address layouts (jAER's own extractors; x is mirrored by jAER, y counts up from the bottom):

- DVS128: ``x_raw = (a >> 1) & 0x7F``, ``y_raw = (a >> 8) & 0x7F``, bit 0 set = OFF;
  bit 15 marks external/sync events, which are skipped.
- DAVIS: bit 31 clear = DVS event (bit 31 set = APS sample or IMU sample, skipped; bit 10 set
  with bit 31 clear = external input event, skipped); ``y_raw`` bits 22..30, ``x_raw`` bits
  12..21, bit 11 set = ON.

torchseq stores ``x = W - 1 - x_raw`` (jAER's mirror) and ``y = H - 1 - y_raw`` (rows counted
from the top, as in images) unless ``flip_y=False``. Timestamps are read as unsigned 32-bit
and unwrapped: a backward jump of more than 2**31 us is a counter wrap and adds 2**32.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from torchseq.atomic import atomic_open
from torchseq.events.stream import (
    EVENT_DTYPE,
    Chunk,
    EventFormatError,
    EventStream,
    check_sensor_size,
    file_error,
    iter_records,
)

MAGIC = b"#!AER-DAT2.0"
RECORD = np.dtype([("a", ">u4"), ("t", ">u4")])
WRAP = 1 << 32
CHIPS = {  # AEChip/HardwareInterface name fragment -> (layout, (W, H))
    "DVS128": ("dvs128", (128, 128)),
    "DAVIS240": ("davis", (240, 180)),
    "DAVIS346": ("davis", (346, 260)),
    "DAVIS128": ("davis", (128, 128)),
    "DAVIS640": ("davis", (640, 480)),
}


# one header line: '#', printable ASCII (tab, CR allowed), newline; at most 65536 bytes. A
# binary record that happens to start with '#' (0x23) fails this, so it is not swallowed.
_HEADER_LINES = re.compile(rb"(?:#[\t\r\x20-\x7e]{0,65534}\n)*")
_BLOCK = 1 << 20


def read_header(f) -> tuple[int, list[str]]:
    """Read the ``#`` header lines of an open binary file; returns (byte length, lines).

    The lines are matched in blocks of 1 MiB by one regular expression (jAER files carry
    headers of thousands of lines); the file is left at the first byte after the header.
    """
    start = f.tell()
    buf, end = b"", 0
    while True:
        block = f.read(_BLOCK)
        buf += block
        end = _HEADER_LINES.match(buf, end).end()
        # done when the match stopped at a whole non-header line or at the end of the file
        # (a header line is at most 65536 bytes, so one cut by the block is within that)
        if not block or len(buf) - end > 65536:
            break
    f.seek(start + end)
    lines = buf[:end].decode("ascii").split("\n")[:-1]
    return end, [line.rstrip("\r") for line in lines]


def detect_chip(lines: list[str], path=None) -> tuple[str, tuple[int, int]] | None:
    """``(layout, (W, H))`` from the header's torchseq/AEChip/HardwareInterface lines."""
    text = "\n".join(lines)
    m = re.search(r"^#\s*torchseq layout: (\w+) sensor_size: (\d+)x(\d+)", text, re.M)
    if m:
        try:
            size = check_sensor_size((int(m.group(2)), int(m.group(3))),
                                     "the header's sensor_size")
        except EventFormatError as err:
            raise file_error(path, 0, str(err)) from None
        return m.group(1), size
    for key in ("AEChip", "HardwareInterface"):
        for m in re.finditer(rf"^#\s*{key}\s*:.*$", text, re.M):
            for frag, chip in CHIPS.items():
                if frag.lower() in m.group(0).lower():
                    return chip
    return None


def decode(records: np.ndarray, layout: str, sensor_size: tuple[int, int],
           flip_y: bool, state: dict) -> np.ndarray:
    """Decode ``(N,)`` :data:`RECORD` rows to events; ``state`` carries the time unwrap.

    Works on uint32 columns and writes straight into the output fields (one byte swap per
    column, no int64 temporaries unless the 32-bit time actually wraps).
    """
    if layout not in ("dvs128", "davis"):
        raise EventFormatError(f"unknown AEDAT 2.0 layout {layout!r} (use 'dvs128' or 'davis')")
    a = records["a"].astype(np.uint32)
    t = records["t"].astype(np.uint32)
    if layout == "dvs128":
        keep = a < 0x8000
        x_raw = (a >> 1) & 0x7F
        y_raw = (a >> 8) & 0x7F
        p = ~a & 1
    else:
        keep = (a & ((1 << 31) | (1 << 10))) == 0
        x_raw = (a >> 12) & 0x3FF
        y_raw = (a >> 22) & 0x1FF
        p = (a >> 11) & 1
    if not keep.all():
        t, x_raw, y_raw, p = t[keep], x_raw[keep], y_raw[keep], p[keep]
    w, h = sensor_size
    out = np.empty(len(t), EVENT_DTYPE)
    if len(t):
        last = state.get("last", int(t[0]))
        wraps0 = state.get("wraps", 0)
        state["last"] = int(t[-1])
        if (last - int(t[0]) > (1 << 31)) or (t[1:] < t[:-1]).any():
            t64 = t.astype(np.int64)
            prev = np.empty_like(t64)
            prev[0], prev[1:] = last, t64[:-1]
            wraps = np.cumsum(t64 - prev < -(1 << 31)) + wraps0
            state["wraps"] = int(wraps[-1])
            out["t"] = t64 + wraps * WRAP
        else:
            out["t"] = t
            if wraps0:
                out["t"] += wraps0 * WRAP
    # W - 1 - x_raw in int32: a raw column beyond the sensor gives a negative x (an error
    # later), never a wrapped one; |values| < 2**15 because W <= 32768 and x_raw < 1024
    out["x"] = np.subtract(w - 1, x_raw, dtype=np.int32)
    out["y"] = np.subtract(h - 1, y_raw, dtype=np.int32) if flip_y else y_raw
    out["p"] = p
    return out


def iter_aedat2(path: str | Path, chunk_events: int = 1 << 20,
                sensor_size: tuple[int, int] | None = None, layout: str | None = None,
                flip_y: bool = True, truncated: str = "error") -> Iterator[EventStream]:
    """Stream an AEDAT 2.0 file in chunks of ``chunk_events`` records (APS/IMU dropped).

    Args:
        path: the ``.aedat`` file.
        chunk_events: records read per chunk.
        sensor_size: ``(W, H)`` override (needed when the header names no known chip).
        layout: ``"dvs128"`` or ``"davis"``; default from the header.
        flip_y: store rows from the top (image convention) instead of jAER's bottom-up rows.
        truncated: a partial last record: ``"error"`` (default) or ``"drop"`` with a warning.

    Yields:
        :class:`~torchseq.events.stream.Chunk` pieces (EventStreams carrying the byte
        offset they were read from), time order not yet checked (see ``read_events``).
    """
    path = Path(path)
    if sensor_size is not None:
        sensor_size = check_sensor_size(sensor_size)
    if layout is not None and layout not in ("dvs128", "davis"):
        raise EventFormatError(f"unknown AEDAT 2.0 layout {layout!r} (use 'dvs128' or 'davis')")
    with open(path, "rb") as f:
        head = f.read(len(MAGIC))
        if head != MAGIC:
            raise file_error(path, 0, f"not an AEDAT 2.0 file (starts {head!r})")
        f.seek(0)
        header_len, lines = read_header(f)
        chip = detect_chip(lines, path)
        if layout is None:
            if chip is None and sensor_size is None:
                raise file_error(path, 0, "header names no known chip; pass layout= "
                                 "('dvs128' or 'davis') and sensor_size=")
            layout = chip[0] if chip else ("dvs128" if sensor_size == (128, 128) else "davis")
            if layout not in ("dvs128", "davis"):
                raise file_error(path, 0, f"the header names an unknown layout {layout!r}")
        size = sensor_size if sensor_size is not None else (
            chip[1] if chip else (128, 128) if layout == "dvs128" else None)
        if size is None:
            raise file_error(path, 0, "pass sensor_size= for a DAVIS file of unknown chip")
        body = path.stat().st_size - header_len
        state: dict = {}
        foreign, first, total = 0, None, 0  # DVS128 words use bits 0-15: others are not events
        for offset, records in iter_records(f, path, RECORD, body, chunk_events, truncated,
                                            "8-byte record"):
            total += len(records)
            if layout == "dvs128":
                bad = np.flatnonzero(records["a"] >= 0x10000)
                foreign += len(bad)
                if first is None and len(bad):
                    first = offset + RECORD.itemsize * int(bad[0])
            yield Chunk(decode(records, layout, size, flip_y, state), size, offset)
        if foreign:
            warnings.warn(f"{path}: skipped {foreign} of {total} records that are not DVS128 "
                          f"events (address bits 16-31 set), the first at byte {first}: the "
                          f"file may be corrupt there", stacklevel=2)


def write_aedat2(path: str | Path, stream: EventStream, layout: str = "dvs128",
                 flip_y: bool = True) -> None:
    """Write events as AEDAT 2.0 (atomically), inverting :func:`iter_aedat2`'s conventions.

    Args:
        path: output ``.aedat`` file.
        stream: events; ``t`` must be >= 0 and is stored modulo 2**32 (the reader unwraps it).
        layout: ``"dvs128"`` (needs a 128x128 sensor) or ``"davis"`` (up to 1024x512).
        flip_y: the events' rows count from the top (as :func:`iter_aedat2` returns them).
    """
    ev, (w, h) = stream.events, stream.sensor_size
    stream.validate()
    if len(ev) and ev["t"][0] < 0:
        raise EventFormatError("AEDAT 2.0 timestamps must be >= 0")
    x_raw = (w - 1 - ev["x"]).astype(np.int64)
    y_raw = (h - 1 - ev["y"] if flip_y else ev["y"]).astype(np.int64)
    p = ev["p"].astype(np.int64)
    if layout == "dvs128":
        if (w, h) != (128, 128):
            raise EventFormatError(f"the DVS128 layout needs a 128x128 sensor, got {w}x{h}")
        addr = (y_raw << 8) | (x_raw << 1) | (1 - p)
        chip = "ch.unizh.ini.jaer.chip.retina.DVS128"
    elif layout == "davis":
        if w > 1024 or h > 512:
            raise EventFormatError(f"the DAVIS layout holds at most 1024x512, got {w}x{h}")
        addr = (y_raw << 22) | (x_raw << 12) | (p << 11)
        chip = "eu.seebetter.ini.chips.davis.DAVIS240C" if (w, h) == (240, 180) else "unknown"
    else:
        raise EventFormatError(f"unknown AEDAT 2.0 layout {layout!r} (use 'dvs128' or 'davis')")
    records = np.empty(len(ev), RECORD)
    records["a"], records["t"] = addr, ev["t"] % WRAP
    header = "".join(f"{line}\r\n" for line in (
        MAGIC.decode(), "# This is a raw AE data file written by torchseq",
        "# Data format is int32 address, int32 timestamp (8 bytes total), repeated for each event",
        "# Timestamps tick is 1 us", f"# AEChip: {chip}",
        f"# torchseq layout: {layout} sensor_size: {w}x{h}"))
    with atomic_open(path) as f:
        f.write(header.encode("ascii"))
        f.write(records.tobytes())

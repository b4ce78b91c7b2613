"""Prophesee ``.raw`` files: ``%`` text header lines, then EVT 3.0 or EVT 2.0 words.

EVT 3.0 packs events in little-endian 16-bit words whose top 4 bits give the type:
``0x0`` EVT_ADDR_Y (sets the row), ``0x2`` EVT_ADDR_X (one event at the current row and time,
polarity bit 11), ``0x3`` VECT_BASE_X (sets the column base and polarity for vectors),
``0x4`` VECT_12 / ``0x5`` VECT_8 (a bit mask of events at base+i; the base then moves by 12 / 8),
``0x6`` EVT_TIME_LOW (low 12 bits of the time), ``0x8`` EVT_TIME_HIGH (bits 12..23),
``0xA`` EXT_TRIGGER, ``0xE`` OTHERS, ``0xF`` CONTINUED (skipped). The 24-bit time wraps every
16.8 s; a decreasing TIME_HIGH is taken as a wrap and adds 2**24 us.

The decoder is vectorised: each word's state (row, time, vector base) is the value of the
latest word of the matching type, found with ``np.maximum.accumulate`` over word indices;
state carries across chunks, so files stream in bounded memory.

EVT 2.0 packs each event in a little-endian 32-bit word: type ``w >> 28`` (0 CD_OFF, 1 CD_ON,
8 EV_TIME_HIGH with ``t >> 6`` in bits 0..27), CD events hold ``t & 63`` in bits 22..27,
``x`` in bits 11..21 and ``y`` in bits 0..10.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from torchseq.events.stream import (
    Chunk,
    EventFormatError,
    EventStream,
    check_sensor_size,
    check_truncated,
    file_error,
    iter_records,
    make_events,
)

PLUGIN_SIZES = {"gen41": (1280, 720), "imx636": (1280, 720), "gen31": (640, 480),
                "gen3": (640, 480), "imx646": (1280, 720), "genx320": (320, 320)}
_TEXT = set(range(0x20, 0x7F)) | {0x09, 0x0D}


def read_header(f) -> tuple[str, tuple[int, int] | None]:
    """Read ``%`` header lines; returns (format ``"evt3"``/``"evt2"``, ``(W, H)`` or None)."""
    lines = []
    while True:
        pos = f.tell()
        line = f.readline(65536)
        if not line.startswith(b"%") or not line.endswith(b"\n") or not set(line[:-1]) <= _TEXT:
            f.seek(pos)
            break
        lines.append(line.decode("ascii").strip())
        if lines[-1] == "% end":
            break
    text = "\n".join(lines).lower()
    if re.search(r"evt ?3|format evt3", text):
        fmt = "evt3"
    elif re.search(r"evt ?2|format evt2", text):
        fmt = "evt2"
    else:
        raise EventFormatError("Prophesee header names no supported format (EVT 2.0 or 3.0)"
                               if lines else "not a Prophesee .raw file (no '%' header)")
    size = None
    m = re.search(r"geometry (\d+)x(\d+)", text) or re.search(r"width=(\d+).*height=(\d+)", text)
    if m:
        size = (int(m.group(1)), int(m.group(2)))
    m = re.search(r"height=(\d+);width=(\d+)", text)
    if m and size is None:
        size = (int(m.group(2)), int(m.group(1)))
    if size is None:
        for name, wh in PLUGIN_SIZES.items():
            if re.search(rf"plugin_name \S*{name}", text):
                size = wh
                break
    return fmt, size


def _ffill(mask: np.ndarray, values: np.ndarray, init: int) -> tuple[np.ndarray, np.ndarray]:
    """Value of the latest masked word at or before each word (``init`` before any)."""
    idx = np.arange(len(mask))
    last = np.maximum.accumulate(np.where(mask, idx, -1))
    return np.where(last >= 0, values[np.maximum(last, 0)], init), last


def decode_evt3(words: np.ndarray, state: dict, time_mode: str = "spec") -> np.ndarray:
    """Decode ``(N,)`` uint16 EVT 3.0 words; ``state`` (row, time, base, wraps) carries over.

    ``time_mode="carry"`` also adds 4096 us at every decrease of TIME_LOW, as some third-party
    decoders do (it reproduces ``evt3_sample.npy``); ``"spec"`` follows the format.
    """
    if time_mode not in ("spec", "carry"):
        raise EventFormatError(f"unknown EVT 3.0 time mode {time_mode!r} ('spec' or 'carry')")
    w = words.astype(np.int64)
    typ, val = w >> 12, w & 0xFFF
    # time: TIME_HIGH words with wrap counting, TIME_LOW words
    is_high = typ == 0x8
    high = val[is_high]
    prev = np.r_[state.get("high", high[0] if len(high) else 0), high[:-1]]
    loops = np.cumsum(high < prev) + state.get("loops", 0)
    high_full = np.zeros(len(w), np.int64)
    high_full[is_high] = high + (loops << 12)
    high_t, _ = _ffill(is_high, high_full, state.get("high_full", -1))
    high_raw = high_t
    low_t, _ = _ffill(typ == 0x6, val, state.get("low", 0))
    if time_mode == "carry":
        is_low = typ == 0x6
        low = val[is_low]
        prev_low = np.r_[state.get("low", low[0] if len(low) else 0), low[:-1]]
        carry = np.zeros(len(w), np.int64)
        carry[is_low] = np.cumsum(low < prev_low) + state.get("carry", 0)
        carry, _ = _ffill(is_low, carry, state.get("carry", 0))
        if len(w):
            state["carry"] = int(carry[-1])
        high_t = np.where(high_t >= 0, high_t + carry, high_t)
    t = high_t * 4096 + low_t
    row, _ = _ffill(typ == 0x0, val & 0x7FF, state.get("y", -1))
    # vector base: VECT_BASE_X value plus the 12/8 steps of the vectors since it
    is_base = typ == 0x3
    step = np.where(typ == 0x4, 12, np.where(typ == 0x5, 8, 0))
    done = np.cumsum(step) - step  # steps taken before each word
    base0, last = _ffill(is_base, val & 0x7FF, -1)
    pol, _ = _ffill(is_base, val >> 11, state.get("pol", 0))
    base = np.where(last >= 0, base0 + done - done[np.maximum(last, 0)],
                    state.get("base", 0) + done)
    # events: single (ADDR_X) and vectors (VECT_12 / VECT_8), in word then bit order
    single = np.nonzero(typ == 0x2)[0]
    vec = np.nonzero((typ == 0x4) | (typ == 0x5))[0]
    mask = np.where(typ[vec] == 0x4, val[vec], val[vec] & 0xFF)
    k, bit = np.nonzero((mask[:, None] >> np.arange(12)) & 1)
    k = vec[k]
    word = np.r_[single, k]
    order = np.argsort(word * 16 + np.r_[np.zeros(len(single), np.int64), bit], kind="stable")
    word = word[order]
    x = np.r_[val[single] & 0x7FF, base[k] + bit][order]
    p = np.r_[val[single] >> 11, pol[k]][order]
    ok = (high_t[word] >= 0) & (row[word] >= 0)  # nothing before the first time and row
    if len(w):
        state.update(y=int(row[-1]), low=int(low_t[-1]), high_full=int(high_raw[-1]),
                     pol=int(pol[-1]), base=int(base[-1] + step[-1]))
        if len(high):
            state.update(high=int(high[-1]), loops=int(loops[-1]))
    return make_events(t[word][ok], x[ok], row[word][ok], p[ok])


def decode_evt2(words: np.ndarray, state: dict) -> np.ndarray:
    """Decode ``(N,)`` uint32 EVT 2.0 words; ``state`` carries the time high bits."""
    w = words.astype(np.int64)
    typ = w >> 28
    is_high = typ == 0x8
    high = w[is_high] & 0x0FFFFFFF
    prev = np.r_[state.get("high", high[0] if len(high) else 0), high[:-1]]
    loops = np.cumsum(high < prev) + state.get("loops", 0)
    high_full = np.zeros(len(w), np.int64)
    high_full[is_high] = high + (loops << 28)
    high_t, _ = _ffill(is_high, high_full, state.get("high_full", -1))
    if len(w):
        state["high_full"] = int(high_t[-1])
        if len(high):
            state.update(high=int(high[-1]), loops=int(loops[-1]))
    cd = ((typ == 0) | (typ == 1)) & (high_t >= 0)
    wc = w[cd]
    return make_events(high_t[cd] * 64 + ((wc >> 22) & 0x3F), (wc >> 11) & 0x7FF, wc & 0x7FF,
                       typ[cd])


def iter_raw(path: str | Path, chunk_events: int = 1 << 20,
             sensor_size: tuple[int, int] | None = None, truncated: str = "error",
             evt3_time: str = "spec") -> Iterator[EventStream]:
    """Stream a Prophesee EVT 3.0 / 2.0 ``.raw`` file in chunks of ``chunk_events`` words.

    Args:
        path: the ``.raw`` file.
        chunk_events: words decoded per chunk (EVT 3.0 needs about 1-2 words per event).
        sensor_size: ``(W, H)``; default from the header (``geometry``, ``format`` or the
            plugin name), else an error.
        truncated: a partial last word: ``"error"`` (default) or ``"drop"`` with a warning.
        evt3_time: ``"spec"`` (default) or ``"carry"`` (see :func:`decode_evt3`).

    Yields:
        :class:`EventStream` chunks, time order not yet checked.
    """
    path = Path(path)
    check_truncated(truncated)
    if evt3_time not in ("spec", "carry"):
        raise EventFormatError(f"unknown EVT 3.0 time mode {evt3_time!r} ('spec' or 'carry')")
    if sensor_size is not None:
        sensor_size = check_sensor_size(sensor_size)
    with open(path, "rb") as f:
        try:
            fmt, size = read_header(f)
            size = sensor_size if sensor_size is not None else (
                check_sensor_size(size, "the header's geometry") if size is not None else None)
        except EventFormatError as err:
            raise file_error(path, 0, str(err)) from None
        if size is None:
            raise file_error(path, 0, "header gives no sensor geometry; pass sensor_size=")
        if fmt == "evt3":
            dtype = np.dtype("<u2")
            def decode(words, state):
                return decode_evt3(words, state, evt3_time)
        else:
            dtype, decode = np.dtype("<u4"), decode_evt2
        body = path.stat().st_size - f.tell()
        state: dict = {}
        for offset, words in iter_records(f, path, dtype, body, chunk_events, truncated, "word"):
            yield Chunk(decode(words, state), size, offset)

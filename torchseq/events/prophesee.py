"""Prophesee ``.raw`` files: ``%`` text header lines, then EVT 3.0 or EVT 2.0 words.

EVT 3.0 packs events in little-endian 16-bit words whose top 4 bits give the type:
``0x0`` EVT_ADDR_Y (sets the row), ``0x2`` EVT_ADDR_X (one event at the current row and time,
polarity bit 11), ``0x3`` VECT_BASE_X (sets the column base and polarity for vectors),
``0x4`` VECT_12 / ``0x5`` VECT_8 (a bit mask of events at base+i; the base then moves by 12 / 8),
``0x6`` EVT_TIME_LOW (low 12 bits of the time), ``0x8`` EVT_TIME_HIGH (bits 12..23),
``0xA`` EXT_TRIGGER, ``0xE`` OTHERS, ``0xF`` CONTINUED (skipped). The 24-bit time wraps every
16.8 s; a decreasing TIME_HIGH is taken as a wrap and adds 2**24 us.

:func:`decode_evt3` has two kernels, chosen by its ``kernel`` argument (``iter_raw`` /
``read_events``: ``evt3_kernel=``), both exact and interchangeable mid-stream (they carry the
same state across chunks, so files stream in bounded memory):

- ``"numba"`` (``pip install numba``): one compiled pass over the words, a state
  machine as the format is meant to be read; about 2.8x the NumPy kernel's rate, but loading
  numba costs about a second once per process.
- ``"numpy"``: vectorised; each event word's state (row, time, vector base) is the value
  of the latest word of the matching type, found from cumulative counts of each type.

:func:`default_evt3_kernel` picks the kernel when none is given: numba for inputs of at
least :data:`EVT3_NUMBA_MIN_BYTES` (where its rate repays its start-up) when numba is
installed, else NumPy. ``iter_raw`` decides once per file from the file's size.

EVT 2.0 packs each event in a little-endian 32-bit word: type ``w >> 28`` (0 CD_OFF, 1 CD_ON,
8 EV_TIME_HIGH with ``t >> 6`` in bits 0..27), CD events hold ``t & 63`` in bits 22..27,
``x`` in bits 11..21 and ``y`` in bits 0..10.
"""

from __future__ import annotations

import importlib.util
import re
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


_EVENT_WORD = np.zeros(16, bool)
_EVENT_WORD[[0x2, 0x4, 0x5]] = True  # ADDR_X, VECT_12, VECT_8
_VECTOR_STEP = np.zeros(16, np.int32)
_VECTOR_STEP[0x4], _VECTOR_STEP[0x5] = 12, 8


def _latest(is_kind: np.ndarray, values: np.ndarray, at: np.ndarray, init) -> np.ndarray:
    """Value of the latest word of one kind at or before each word index in ``at``.

    Args:
        is_kind: ``(N,)`` bool, the words of that kind.
        values: ``(K,)`` their values, in word order.
        at: ``(E,)`` word indices asking.
        init: the value carried in from before the chunk.
    """
    ext = np.empty(len(values) + 1, values.dtype if len(values) else np.int64)
    ext[0], ext[1:] = init, values
    return ext[np.cumsum(is_kind, dtype=np.int32)[at]]


def _rising(values: np.ndarray, before) -> np.ndarray:
    """``(K,)`` bool: each value smaller than the one before it (``before`` for the first)."""
    back = np.empty(len(values), bool)
    if len(values):
        back[0] = values[0] < before
        np.less(values[1:], values[:-1], out=back[1:])
    return back


EVT3_KERNELS = ("numba", "numpy")
# the fast kernel when installed (numba is imported only when it first runs)
EVT3_KERNEL = "numba" if importlib.util.find_spec("numba") is not None else "numpy"
# numba's ~1 s start-up per process is repaid from about 10**8 events (~200 MB of words):
# NumPy decodes ~50 M events/s per core, numba ~140 M (docs/results/events.md); below this size the
# NumPy kernel finishes first
EVT3_NUMBA_MIN_BYTES = 1 << 27


def default_evt3_kernel(nbytes: int) -> str:
    """The kernel for ``nbytes`` of EVT 3.0 words when none is given (see the module doc)."""
    return EVT3_KERNEL if nbytes >= EVT3_NUMBA_MIN_BYTES else "numpy"


def check_evt3_kernel(kernel: str | None, nbytes: int = 0) -> str:
    """The EVT 3.0 kernel to run: ``kernel``, or :func:`default_evt3_kernel` for None."""
    kernel = default_evt3_kernel(nbytes) if kernel is None else kernel
    if kernel not in EVT3_KERNELS:
        raise ValueError(f"unknown EVT 3.0 kernel {kernel!r} (use 'numba' or 'numpy')")
    if kernel == "numba" and importlib.util.find_spec("numba") is None:
        raise ValueError("the numba EVT 3.0 kernel needs numba: pip install numba "
                         "(or pass evt3_kernel='numpy')")
    return kernel


def decode_evt3(words: np.ndarray, state: dict, time_mode: str = "spec",
                kernel: str | None = None) -> np.ndarray:
    """Decode ``(N,)`` uint16 EVT 3.0 words; ``state`` (row, time, base, wraps) carries over.

    ``time_mode="carry"`` also adds 4096 us at every decrease of TIME_LOW, as some third-party
    decoders do (it reproduces ``evt3_sample.npy``); ``"spec"`` follows the format.

    Args:
        words: ``(N,)`` uint16 words.
        state: the decoder state, ``{}`` at the start of the file; updated in place.
        time_mode: ``"spec"`` or ``"carry"``.
        kernel: ``"numba"``, ``"numpy"`` (see the module docstring) or None for
            :func:`default_evt3_kernel` of these words' bytes.

    Returns:
        ``(E,)`` :data:`EVENT_DTYPE` events in word order (a vector's bits in increasing x).
    """
    if time_mode not in ("spec", "carry"):
        raise EventFormatError(f"unknown EVT 3.0 time mode {time_mode!r} ('spec' or 'carry')")
    if check_evt3_kernel(kernel, words.nbytes) == "numba":
        from torchseq.events import _evt3_numba

        return _evt3_numba.decode(words, state, time_mode == "carry")
    return _decode_evt3_numpy(words, state, time_mode)


def _decode_evt3_numpy(words: np.ndarray, state: dict, time_mode: str) -> np.ndarray:
    """The NumPy kernel of :func:`decode_evt3`.

    Only the event words (ADDR_X, VECT_12, VECT_8) are decoded in full: each takes its row,
    time and vector base from the latest word of that kind before it (a cumulative count of
    that kind indexes its values), events are built once per word as records and repeated
    for the bits of a vector (bit positions from ``np.unpackbits``), so there is no sort.
    The vector base is carried modulo 2**16 (x is 16-bit arithmetic), as the numba kernel
    carries it.
    """
    w = np.asarray(words, np.uint16)
    typ = w >> 12
    e = np.flatnonzero(_EVENT_WORD[typ])  # event words, in order
    ew = w[e]
    # time: TIME_HIGH words with wrap counting (a decrease is a 2**24 us wrap), TIME_LOW
    is_th = typ == 0x8
    high = (w[is_th] & 0xFFF).astype(np.int64)
    loops = np.cumsum(_rising(high, state.get("high", 0))) + state.get("loops", 0)
    high_full = high + (loops << 12)
    hf = _latest(is_th, high_full, e, state.get("high_full", -1))
    is_tl = typ == 0x6
    low = (w[is_tl] & 0xFFF).astype(np.int64)
    t_e = _latest(is_tl, low, e, state.get("low", 0))
    carry_last = state.get("carry", 0)
    if time_mode == "carry":
        carries = np.cumsum(_rising(low, state.get("low", 0))) + carry_last
        carry_e = _latest(is_tl, carries, e, carry_last)
        if len(carries):
            carry_last = int(carries[-1])
        hf = np.where(hf >= 0, hf + carry_e, hf)
    t_e += hf << 12
    is_y = typ == 0x0
    rows = (w[is_y] & 0x7FF).astype(np.int16)
    row = _latest(is_y, rows, e, state.get("y", -1))
    ok = (hf >= 0) & (row >= 0)  # nothing before the first time and row
    # vectors: base = the latest VECT_BASE_X plus the 12/8 steps of the vectors since it
    i_s = np.flatnonzero((typ - np.uint16(3)) <= 2)  # VECT_BASE_X, VECT_12, VECT_8
    ws = w[i_s]
    ts = ws >> 12
    is_base = ts == 0x3
    step = _VECTOR_STEP[ts]
    done = np.cumsum(step, dtype=np.int32)
    done -= step  # steps taken before each word
    nb = np.cumsum(is_base, dtype=np.int32)
    i_base = np.flatnonzero(is_base)
    bval = np.empty(len(i_base) + 1, np.int32)  # base value minus the steps before it
    bval[0] = state.get("base", 0)
    bval[1:] = (ws[i_base] & 0x7FF) - done[i_base]
    bpol = np.empty(len(i_base) + 1, np.uint8)
    bpol[0] = state.get("pol", 0)
    bpol[1:] = (ws[i_base] >> 11) & 1
    jv = np.flatnonzero(~is_base)  # the vector words among i_s
    is_vec = ew >= 0x3000  # event words that are vectors (types 4, 5 > type 2)
    out_e = np.empty(len(e), EVENT_DTYPE)
    out_e["t"], out_e["y"] = t_e, row
    x = ew & 0x7FF
    p = (ew >> 11) & 1
    x[is_vec] = bval[nb[jv]] + done[jv]
    p[is_vec] = bpol[nb[jv]]
    out_e["x"], out_e["p"] = x, p
    if len(w):
        state.update(y=int(rows[-1]) if len(rows) else state.get("y", -1),
                     low=int(low[-1]) if len(low) else state.get("low", 0),
                     high_full=int(high_full[-1]) if len(high) else state.get("high_full", -1),
                     carry=carry_last)
        if len(ws):
            base = int(bval[nb[-1]] + done[-1] + step[-1]) & 0xFFFF
            state.update(pol=int(bpol[nb[-1]]), base=base)
        if len(high):
            state.update(high=int(high[-1]), loops=int(loops[-1]))
    if not ok.all():
        out_e, is_vec, ew, keep_v = out_e[ok], is_vec[ok], ew[ok], ok[is_vec]
        jv = jv[keep_v]
    if not is_vec.any():
        return out_e
    # every event word as a bit mask (a single ADDR_X is bit 0 of its own column), so the
    # bit offsets of all events come out in order from one unpackbits
    masks = np.ones(len(out_e), "<u2")
    masks[is_vec] = np.where(ts[jv] == 0x4, ws[jv] & 0xFFF, ws[jv] & 0xFF)
    out = np.repeat(out_e, np.bitwise_count(masks))
    out["x"] += _set_bits(masks)
    return out


_BLOCK = 1 << 16
_POSITIONS = np.tile(np.arange(16, dtype=np.int16), _BLOCK)  # 2 MB, bit positions 0..15


def _set_bits(masks: np.ndarray) -> np.ndarray:
    """Positions of the set bits of ``(E,)`` little-endian uint16 masks, mask by mask.

    Returns:
        ``(sum of popcounts,)`` int16: for each mask its set bits in increasing order.
    """
    parts = []
    for i in range(0, len(masks), _BLOCK):
        bits = np.unpackbits(masks[i : i + _BLOCK].view(np.uint8), bitorder="little")
        parts.append(_POSITIONS[: len(bits)][bits.view(bool)])
    return np.concatenate(parts) if len(parts) != 1 else parts[0]


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
             evt3_time: str = "spec", evt3_kernel: str | None = None) -> Iterator[EventStream]:
    """Stream a Prophesee EVT 3.0 / 2.0 ``.raw`` file in chunks of ``chunk_events`` words.

    Args:
        path: the ``.raw`` file.
        chunk_events: words decoded per chunk (EVT 3.0 needs about 1-2 words per event).
        sensor_size: ``(W, H)``; default from the header (``geometry``, ``format`` or the
            plugin name), else an error.
        truncated: a partial last word: ``"error"`` (default) or ``"drop"`` with a warning.
        evt3_time: ``"spec"`` (default) or ``"carry"`` (see :func:`decode_evt3`).
        evt3_kernel: ``"numba"`` or ``"numpy"``; None for :func:`default_evt3_kernel` of the
            file's size (same events either way).

    Yields:
        :class:`EventStream` chunks, time order not yet checked.
    """
    path = Path(path)
    check_truncated(truncated)
    if evt3_time not in ("spec", "carry"):
        raise EventFormatError(f"unknown EVT 3.0 time mode {evt3_time!r} ('spec' or 'carry')")
    if evt3_kernel is not None:
        evt3_kernel = check_evt3_kernel(evt3_kernel)
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
        if fmt == "evt2":
            _refuse_evt3_options(path, evt3_time, evt3_kernel)
        if fmt == "evt3":
            dtype = np.dtype("<u2")
            def decode(words, state):
                return decode_evt3(words, state, evt3_time, evt3_kernel)
        else:
            dtype, decode = np.dtype("<u4"), decode_evt2
        body = path.stat().st_size - f.tell()
        evt3_kernel = check_evt3_kernel(evt3_kernel, body)  # once per file
        state: dict = {}
        for offset, words in iter_records(f, path, dtype, body, chunk_events, truncated, "word"):
            yield Chunk(decode(words, state), size, offset)


def _refuse_evt3_options(path: Path, evt3_time: str, evt3_kernel: str | None) -> None:
    """Raise for EVT 3.0 options given for an EVT 2.0 file (they would be silently unused)."""
    given = ([f"evt3_time={evt3_time!r}"] if evt3_time != "spec" else []) + (
        [f"evt3_kernel={evt3_kernel!r}"] if evt3_kernel is not None else [])
    if given:
        one = len(given) == 1
        raise file_error(path, None, f"the header says EVT 2.0, and {' and '.join(given)} "
                         f"appl{'ies' if one else 'y'} to EVT 3.0 files only; drop "
                         f"{'it' if one else 'them'}")


def _runs(new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start index of each run (``new`` marks run starts) and, per element, its run start."""
    starts = np.flatnonzero(new)
    return starts, starts[np.cumsum(new) - 1]


def encode_evt3(events: np.ndarray) -> np.ndarray:
    """EVT 3.0 words for time-ordered events with ``0 <= t[0] < 2**24`` (see :func:`write_evt3`).

    Events sharing ``(t, y, p)`` become VECT_BASE_X + VECT_12 pairs for each 12-column block
    holding two or more of them, ADDR_X words otherwise; TIME_HIGH / TIME_LOW / ADDR_Y words
    are written when their value changes (TIME_HIGH also every 2**23 us across long gaps, so
    the 24-bit time unwraps). Vectorised: every word's position comes from a cumulative sum
    of the words each event needs.
    """
    n = len(events)
    if n == 0:
        return np.empty(0, np.uint16)
    t = events["t"].astype(np.int64)
    x, y, p = (events[f].astype(np.int64) for f in "xyp")
    new_t = np.r_[True, t[1:] != t[:-1]]
    th = t >> 12
    gap = np.r_[th[0], th[1:] - th[:-1]]  # TIME_HIGH steps between events
    extra = np.where(np.r_[False, gap[1:] > 2048], (gap - 1) // 2048, 0)  # long gaps
    new_th = np.r_[True, gap[1:] != 0]
    new_y = np.r_[True, y[1:] != y[:-1]]
    new_g = new_t | new_y | np.r_[True, p[1:] != p[:-1]]
    _, g_start = _runs(new_g)
    blk = (x - x[g_start]) // 12
    new_run = new_g | np.r_[True, (blk[1:] != blk[:-1]) | (x[1:] <= x[:-1])]
    r_starts, r_of = _runs(new_run)
    r_len = np.diff(np.r_[r_starts, n])
    vec_run = r_len > 1
    base = x[g_start] + 12 * blk  # block base column
    bits = np.add.reduceat(np.left_shift(1, x - base), r_starts)  # unique bits per run
    lead = new_run
    is_vec_lead = lead & vec_run[np.cumsum(new_run) - 1]
    is_single = lead & ~is_vec_lead
    # words each event needs: [extra TIME_HIGHs][TIME_HIGH][TIME_LOW][ADDR_Y][event words]
    need = (extra + new_th + new_t + new_y + is_single + 2 * is_vec_lead).astype(np.int64)
    end = np.cumsum(need)
    pos = end - need  # first word of each event
    words = np.empty(int(end[-1]), np.uint16)
    k = np.flatnonzero(extra)
    if len(k):  # intermediate TIME_HIGHs every 2048 periods across long gaps
        reps = extra[k]
        owner = np.repeat(k, reps)
        j = np.arange(len(owner)) - np.repeat(np.cumsum(reps) - reps, reps) + 1
        words[np.repeat(pos[k], reps) + j - 1] = 0x8000 | ((th[owner] - gap[owner] + 2048 * j)
                                                           & 0xFFF)
    pos = pos + extra
    i = np.flatnonzero(new_th)
    words[pos[i]] = 0x8000 | (th[i] & 0xFFF)
    pos = pos + new_th
    i = np.flatnonzero(new_t)
    words[pos[i]] = 0x6000 | (t[i] & 0xFFF)
    pos = pos + new_t
    i = np.flatnonzero(new_y)
    words[pos[i]] = y[i]  # ADDR_Y (type 0), master camera
    pos = pos + new_y
    i = np.flatnonzero(is_single)
    words[pos[i]] = 0x2000 | (p[i] << 11) | x[i]
    i = np.flatnonzero(is_vec_lead)
    words[pos[i]] = 0x3000 | (p[i] << 11) | base[i]
    words[pos[i] + 1] = 0x4000 | bits[np.cumsum(new_run)[i] - 1]
    return words


def write_evt3(path: str | Path, stream: EventStream) -> None:
    """Write events as a Prophesee EVT 3.0 ``.raw`` file (atomically), read by :func:`iter_raw`.

    Events sharing a timestamp are stored (and read back) ordered by ``(y, p, x)``.

    Args:
        path: output ``.raw`` file.
        stream: time-ordered events with ``0 <= t[0] < 2**24`` us (EVT 3.0 holds 24-bit
            time; later times are unwrapped by the reader) on a sensor of at most 2048x2048.
    """
    stream.validate()
    ev, (w, h) = stream.events, stream.sensor_size
    if w > 2048 or h > 2048:
        raise EventFormatError(f"EVT 3.0 holds at most 2048x2048 pixels, got {w}x{h}")
    if len(ev) and not 0 <= ev["t"][0] < 1 << 24:
        raise EventFormatError("EVT 3.0 times must start in [0, 2**24) us; shift them")
    ev = ev[np.lexsort((ev["x"], ev["p"], ev["y"], ev["t"]))]
    header = f"% evt 3.0\n% format EVT3;height={h};width={w}\n% geometry {w}x{h}\n% end\n"
    with atomic_open(path) as f:
        f.write(header.encode("ascii"))
        f.write(encode_evt3(ev).astype("<u2").tobytes())

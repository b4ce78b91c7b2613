"""EVT 3.0 decoding as one compiled pass over the words (numba), behind ``decode_evt3``.

The maths is :func:`torchseq.events.prophesee.decode_evt3`'s (that module's docstring gives
the word types); this is a private kernel of it, chosen with ``kernel="numba"``. It walks
the words once as a state machine, the way the format is meant to be read: TIME_HIGH,
TIME_LOW, ADDR_Y and VECT_BASE_X words set the state, ADDR_X / VECT_12 / VECT_8 words emit
events straight into the output fields. The state is the same eight integers the NumPy
kernel carries across chunks, so the two kernels can hand a file over mid-stream.

Imported only when the kernel is chosen (numba's import and first compilation cost about a
second; ``cache=True`` keeps the compiled code beside this file for later processes).
"""

from __future__ import annotations

import numba
import numpy as np

from torchseq.events.stream import EVENT_DTYPE

# the carried state, in this order (the NumPy kernel's dict keys and their initial values)
STATE = (("y", -1), ("low", 0), ("high_full", -1), ("carry", 0), ("pol", 0), ("base", 0),
         ("high", 0), ("loops", 0))
_POPCOUNT = np.array([bin(i).count("1") for i in range(4096)], np.int64)


@numba.njit(cache=True, nogil=True)
def _upper_bound(words, popcount):  # pragma: no cover - compiled
    """Events the words can hold at most: one per ADDR_X, the set bits of each vector."""
    n = 0
    for i in range(len(words)):
        w = words[i]
        typ = w >> 12
        if typ == 0x2:
            n += 1
        elif typ == 0x4:
            n += popcount[w & 0xFFF]
        elif typ == 0x5:
            n += popcount[w & 0xFF]
    return n


@numba.njit(cache=True, nogil=True)
def _decode(words, carry_mode, st, t_out, x_out, y_out, p_out):  # pragma: no cover - compiled
    """Decode into the output fields; ``st`` (int64, :data:`STATE` order) is updated.

    Returns the number of events written (events before the first TIME_HIGH or ADDR_Y are
    dropped, as the NumPy kernel drops them). ``x`` keeps the NumPy kernel's 16-bit
    arithmetic: a vector running past column 32767 wraps to a negative column, which the
    readers' contents check then reports.
    """
    y, low, high_full, carry, pol, base, high, loops = (
        st[0], st[1], st[2], st[3], st[4], st[5], st[6], st[7])
    n = 0
    for i in range(len(words)):
        w = np.int64(words[i])
        typ = w >> 12
        if typ == 0x2 or typ == 0x4 or typ == 0x5:
            if typ == 0x2:
                mask, first, p = np.int64(1), w & 0x7FF, (w >> 11) & 1
            else:
                mask = w & (0xFFF if typ == 0x4 else 0xFF)
                first, p = base, pol
                base += 12 if typ == 0x4 else 8
            if high_full >= 0 and y >= 0:
                t = low + ((high_full + carry) << 12)
                bit = 0
                while mask:
                    if mask & 1:
                        x = (first + bit) & 0xFFFF
                        t_out[n] = t
                        x_out[n] = x - 0x10000 if x >= 0x8000 else x
                        y_out[n] = y
                        p_out[n] = p
                        n += 1
                    mask >>= 1
                    bit += 1
        elif typ == 0x0:
            y = w & 0x7FF
        elif typ == 0x6:
            v = w & 0xFFF
            if carry_mode and v < low:
                carry += 1
            low = v
        elif typ == 0x8:
            v = w & 0xFFF
            if v < high:
                loops += 1
            high = v
            high_full = v + (loops << 12)
        elif typ == 0x3:
            base = w & 0x7FF
            pol = (w >> 11) & 1
    st[0], st[1], st[2], st[3], st[4], st[5], st[6], st[7] = (
        y, low, high_full, carry, pol, base & 0xFFFF, high, loops)
    return n


def decode(words: np.ndarray, state: dict, carry_mode: bool) -> np.ndarray:
    """``(N,)`` uint16 words -> ``(E,)`` :data:`EVENT_DTYPE` events; ``state`` updated in place.

    The output is allocated once at the words' upper bound (at most 12 events per word, so
    bounded by the input) and cut to the events decoded.
    """
    words = np.ascontiguousarray(words, np.uint16)
    st = np.array([state.get(k, v) for k, v in STATE], np.int64)
    out = np.empty(_upper_bound(words, _POPCOUNT), EVENT_DTYPE)
    n = _decode(words, carry_mode, st, out["t"], out["x"], out["y"], out["p"])
    state.update(zip((k for k, _ in STATE), st.tolist()))
    return out if n == len(out) else out[:n].copy()

"""Test helper: write DDD20-style HDF5 recordings of libcaer packets, and decode them by loop.

The layout (ddd20-utils' recorder): ``/dvs/data`` ``(N, 3)`` variable-length uint8 rows
``[host time as decimal text, 28-byte packet header, packet body]``, ``/dvs/timestamp``
``(N,)`` host times, both chunked by 128 rows and grown in blocks of 2048 rows, so the
tail rows stay empty. Headers are ``<hhiiiiii`` (type, source, size, ts offset, ts overflow,
capacity, number, valid); a polarity event is ``<Ii`` (data, timestamp).
"""

import struct

import h5py
import numpy as np

HEADER = struct.Struct("<hhiiiiii")
POLARITY = struct.Struct("<Ii")


def header(etype, size, ts_offset, overflow, capacity, number, valid, source=1) -> bytes:
    """28 header bytes."""
    return HEADER.pack(etype, source, size, ts_offset, overflow, capacity, number, valid)


def polarity_packet(t, x, y, p, valid=None, capacity=None):
    """``(header, body)`` of one polarity packet; all ``t`` must share ``t >> 31``."""
    n = len(t)
    valid = [True] * n if valid is None else list(valid)
    overflow = int(t[0]) >> 31 if n else 0
    assert all(int(v) >> 31 == overflow for v in t)
    capacity = n if capacity is None else capacity
    body = bytearray(capacity * 8)
    for i in range(n):
        data = (int(x[i]) << 17) | (int(y[i]) << 2) | (int(p[i]) << 1) | int(valid[i])
        POLARITY.pack_into(body, 8 * i, data, int(t[i]) & 0x7FFFFFFF)
    return header(1, 8, 4, overflow, capacity, n, sum(valid)), bytes(body)


def polarity_packets(events, per=1000):
    """``(header, body)`` polarity packets of ``per`` events from an event array, vectorised
    (same bit layout as :func:`polarity_packet`, which the byte tests use)."""
    out = []
    for a in range(0, len(events), per):
        ev = events[a:a + per]
        t = ev["t"].astype(np.int64)
        for over in np.unique(t >> 31):
            part = ev[(t >> 31) == over]
            data = ((part["x"].astype(np.uint32) << 17) | (part["y"].astype(np.uint32) << 2)
                    | (part["p"].astype(np.uint32) << 1) | 1)
            ts = (part["t"].astype(np.int64) & 0x7FFFFFFF).astype(np.uint32)
            body = np.stack([data, ts], 1).astype("<u4").tobytes()
            out.append((header(1, 8, 4, int(over), len(part), len(part), len(part)), body))
    return out


def frame_packet(w, h, ts=0, valid=True):
    """One APS frame event of ``w x h`` pixels at position (0, 0)."""
    size = 36 + w * h * 2
    head = struct.pack("<Iiiiiiiii", int(valid), ts, ts, ts, ts, w, h, 0, 0)
    body = head + bytes(w * h * 2)
    return header(2, size, 12, 0, 1, 1, int(valid)), body


def imu_packet(ts=0):
    """One IMU6 event (36 bytes: info, timestamp, 7 floats)."""
    body = struct.pack("<Ii7f", 1, ts, *range(7))
    return header(3, 36, 4, 0, 1, 1, 1), body


def write_ddd20(path, packets, chunked=True, attrs=None, grow=2048):
    """Write ``packets`` (``(header, body)`` pairs) as DDD20's ``/dvs/data`` rows."""
    vl = h5py.vlen_dtype(np.uint8)
    n = len(packets)
    rows = -(-max(n, 1) // grow) * grow if chunked else n
    with h5py.File(path, "w") as f:
        g = f.create_group("dvs")
        kw = {"chunks": (128, 3), "maxshape": (None, 3)} if chunked else {}
        d = g.create_dataset("data", (rows, 3), dtype=vl, **kw)
        ts = g.create_dataset("timestamp", (rows,), dtype=np.int64,
                              **({"chunks": (128,), "maxshape": (None,)} if chunked else {}))
        for i, (head, body) in enumerate(packets):
            host = 1_500_000_000_000_000 + 1000 * i
            d[i] = np.array([np.frombuffer(str(host).encode(), np.uint8),
                             np.frombuffer(head, np.uint8), np.frombuffer(body, np.uint8)],
                            dtype=object)
            ts[i] = host
        v = f.create_group("vehicle_speed")  # a vehicle signal, as DDD20 files hold
        v.create_dataset("data", data=np.zeros((4, 2)))
        v.create_dataset("timestamp", data=np.zeros(4, np.int64))
        for k, val in (attrs or {}).items():
            g.attrs[k] = val


def oracle(path):
    """``(t, x, y, p)`` lists: every valid polarity event, decoded byte by byte in Python."""
    out = ([], [], [], [])
    with h5py.File(path, "r") as f:
        for row in f["dvs/data"][()]:
            head, body = bytes(row[1]), bytes(row[2])
            if not head:
                continue
            etype, _, _, _, overflow, _, number, _ = HEADER.unpack(head)
            if etype != 1:
                continue
            for i in range(number):
                data, ts = POLARITY.unpack_from(body, 8 * i)
                if data & 1:
                    out[0].append(overflow * 2**31 + ts)
                    out[1].append((data >> 17) & 0x7FFF)
                    out[2].append((data >> 2) & 0x7FFF)
                    out[3].append((data >> 1) & 1)
    return out

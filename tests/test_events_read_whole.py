"""read_events gathers chunks into one buffer; concat_events copies rows as raw words."""

import numpy as np
import pytest

import torchseq.events.io as io
from torchseq.events import (
    EVENT_DTYPE,
    EventFormatError,
    EventStream,
    iter_events,
    make_events,
    read_events,
    write_aedat2,
    write_aedat4,
)
from torchseq.events.prophesee import write_evt3
from torchseq.events.stream import concat_events


def stream(n, seed=0, w=128, h=128):
    rng = np.random.default_rng(seed)
    return EventStream(make_events(np.sort(rng.integers(0, 10 * n, n)), rng.integers(0, w, n),
                                   rng.integers(0, h, n), rng.integers(0, 2, n)), (w, h))


def test_concat_events_equals_numpy_concatenate():
    ev = stream(1000).events
    parts = [ev[:10], ev[10:10], ev[10:500:3], ev[500:]]  # empty and strided parts too
    got = concat_events(parts)
    assert got.dtype == EVENT_DTYPE and got.flags.writeable
    assert np.array_equal(got, np.concatenate(parts))
    got[0] = got[1]  # a fresh array, not a view of a part
    assert not np.array_equal(got[0], ev[0]) or np.array_equal(ev[0], ev[1])
    assert len(concat_events([])) == 0
    with pytest.raises(EventFormatError, match="EVENT_DTYPE"):
        concat_events([np.zeros(3, [("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")])])


@pytest.mark.parametrize("suffix", [".aedat", ".aedat4", ".raw", ".npy"])
# one event per chunk is slow (a Python step per event): CI's slow pass; 37 keeps small,
# odd chunks that cut packets in the quick run
@pytest.mark.parametrize("chunk", [pytest.param(1, marks=pytest.mark.slow), 37, 700, 5000,
                                   1 << 20])
def test_read_events_equals_the_streamed_chunks(tmp_path, suffix, chunk):
    s = stream(4000, seed=len(suffix))
    path = tmp_path / f"e{suffix}"
    if suffix == ".aedat":
        write_aedat2(path, s, layout="davis")
    elif suffix == ".aedat4":
        write_aedat4(path, s, packet_events=300)
    elif suffix == ".raw":
        write_evt3(path, s)
    else:
        np.save(path, s.events)
    whole = read_events(path, chunk_events=chunk, sensor_size=s.sensor_size)
    parts = [c.events for c in iter_events(path, chunk, sensor_size=s.sensor_size)]
    assert whole.events.flags.writeable and whole.events.dtype == EVENT_DTYPE
    assert np.array_equal(whole.events, np.concatenate(parts))
    assert np.array_equal(np.sort(whole.events, order=["t", "y", "p", "x"]),
                          np.sort(s.events, order=["t", "y", "p", "x"]))


def test_read_events_grows_when_the_first_chunk_underestimates(tmp_path, monkeypatch):
    # a DAVIS file whose first 10,000 records are mostly IMU samples (skipped): the first
    # chunk holds few events per byte, so the output must grow past its first estimate
    s = stream(50_000, seed=3, w=240, h=180)
    path = tmp_path / "imu.aedat"
    write_aedat2(path, s, layout="davis")
    data = bytearray(path.read_bytes())
    head = len(data) - 8 * len(s)
    a = np.frombuffer(data, ">u4", 2 * len(s), head).reshape(-1, 2)[:, 0].copy()
    a[:10_000][np.arange(10_000) % 10 != 0] |= 1 << 31
    rec = np.frombuffer(data, ">u4", 2 * len(s), head).reshape(-1, 2).copy()
    rec[:, 0] = a
    data[head:] = rec.tobytes()
    path.write_bytes(bytes(data))
    targets = []
    real_put = io._put
    monkeypatch.setattr(io, "_put", lambda out, at, ev: targets.append((id(out), len(out)))
                        or real_put(out, at, ev))
    got = read_events(path, chunk_events=10_000).events
    keep = np.ones(len(s), bool)
    keep[:10_000] = np.arange(10_000) % 10 == 0
    assert np.array_equal(got, s.events[keep])
    buffers = dict(targets)  # id -> length of each output buffer written to
    assert len(buffers) == 2 and min(buffers.values()) < len(got)  # it grew, once


def test_read_events_falls_back_when_the_estimate_cannot_be_allocated(tmp_path, monkeypatch):
    s = stream(50_000, seed=4)
    path = tmp_path / "e.aedat"
    write_aedat2(path, s)
    refused = []
    real_empty = np.empty

    def empty(n, *args, **kw):  # the system refuses the first estimate (56,250 + 10,000 rows)
        if n > 60_000 and not refused:
            refused.append(n)
            raise MemoryError(f"cannot allocate {n} rows")
        return real_empty(n, *args, **kw)

    monkeypatch.setattr(io.np, "empty", empty)
    got = read_events(path, chunk_events=10_000).events
    monkeypatch.undo()
    assert refused and np.array_equal(got, s.events)

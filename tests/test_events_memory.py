"""Readers hold a bounded amount of memory: streaming ~ a chunk, a whole read ~ the events."""

import tracemalloc

import numpy as np
import pytest

from torchseq.events import (
    EventStream,
    iter_events,
    make_events,
    read_events,
    write_aedat2,
    write_aedat4,
)
from torchseq.events.prophesee import decode_evt3, write_evt3

N = 600_000
CHUNK = 1 << 14


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    rng = np.random.default_rng(0)
    s = EventStream(make_events(np.sort(rng.integers(0, 10**7, N)), rng.integers(0, 240, N),
                                rng.integers(0, 180, N), rng.integers(0, 2, N)), (240, 180))
    d = tmp_path_factory.mktemp("mem")
    write_aedat2(d / "e.aedat", s, layout="davis")
    write_aedat4(d / "e.aedat4", s)
    write_evt3(d / "e.raw", s)
    decode_evt3(np.zeros(0, np.uint16), {}, kernel="numba")  # numba's import is not the reader's
    return d


def options(name):
    return {"evt3_kernel": "numba"} if name.endswith(".raw") else {}


def traced_peak(fn):
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("name", ["e.aedat", "e.aedat4", "e.raw"])
def test_streaming_holds_about_a_chunk_whatever_the_file(files, name):
    n = 0

    def stream():
        nonlocal n
        for chunk in iter_events(files / name, CHUNK, **options(name)):
            n += len(chunk)

    peak = traced_peak(stream)
    assert n == N
    # the events take 16 * N = 9.6 MB; a chunk of 2**14 events 0.26 MB, its raw records and
    # temporaries a few times that
    assert peak < 16 * N / 4, peak


@pytest.mark.parametrize("name", ["e.aedat", "e.aedat4", "e.raw"])
def test_whole_read_holds_the_events_plus_about_a_chunk(files, name):
    peak = traced_peak(lambda: read_events(files / name, chunk_events=CHUNK, **options(name)))
    # one output sized from the first chunk (+1/8) and a chunk: not all chunks plus a copy
    assert peak < 1.4 * 16 * N, peak

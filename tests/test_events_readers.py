import base64
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

from torchseq.events import (
    EVENT_DTYPE,
    EventFormatError,
    EventStream,
    iter_events,
    make_events,
    read_events,
    write_aedat2,
    write_npz,
)
from torchseq.events.lz4frame import LZ4Error, decompress_frames

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "events"


def need(name):
    path = DATA / name
    if not path.exists():
        pytest.skip(f"real event data {path} is absent")
    return path


def header_len(path):
    data = path.read_bytes()
    pos = 0
    while data[pos:pos + 1] == b"#":
        pos = data.index(b"\n", pos) + 1
    return pos


def jaer_loop(path, n, davis, w, h):
    """Independent decoder: a plain loop with jAER's extractor formulas, rows from the top."""
    data = path.read_bytes()
    pos, out = header_len(path), []
    for i in range(n):
        a, t = struct.unpack_from(">Ii", data, pos + 8 * i)
        if davis:
            if a & 0x80000000 or a & 0x400:
                continue
            x, y, p = w - 1 - ((a >> 12) & 0x3FF), (a >> 22) & 0x1FF, 1 if a & 0x800 else 0
        else:
            x, y, p = w - 1 - ((a >> 1) & 0x7F), (a >> 8) & 0x7F, (1 - a) & 1
        out.append((t, x, h - 1 - y, p))
    return out


def as_tuples(ev):
    return [(int(e["t"]), int(e["x"]), int(e["y"]), int(e["p"])) for e in ev]


# ---------------------------------------------------------------- real files


def test_evt3_carry_mode_equals_reference_npy_exactly():
    ref = np.load(need("evt3_sample.npy"))
    got = read_events(need("evt3_sample.raw"), evt3_time="carry")
    assert got.sensor_size == (1280, 720)
    assert got.events.dtype == ref.dtype == EVENT_DTYPE
    assert len(got) == 219_596
    assert np.array_equal(got.events, ref)


@pytest.mark.parametrize("chunk", [777, 100_000])
def test_evt3_chunked_equals_whole(chunk):
    path = need("evt3_sample.raw")
    whole = read_events(path)
    for mode in ("spec", "carry"):
        parts = np.concatenate([c.events for c in iter_events(path, chunk, evt3_time=mode)])
        assert np.array_equal(parts, read_events(path, evt3_time=mode).events)
    assert np.array_equal(np.concatenate([c.events for c in iter_events(path, chunk)]),
                          whole.events)


def test_evt3_spec_mode_differs_from_reference_only_by_low_wrap_carries():
    ref = np.load(need("evt3_sample.npy"))
    got = read_events(need("evt3_sample.raw")).events
    for f in "xyp":
        assert np.array_equal(got[f], ref[f])
    diff = ref["t"] - got["t"]
    assert (diff % 4096 == 0).all() and (diff >= 0).all()
    assert (np.diff(got["t"]) >= 0).all()
    assert got["t"][-1] - got["t"][0] == 8801  # TIME_HIGH goes 2861..2863 only: < 3 * 4096 us


def test_aedat2_dvs128_real_file():
    path = need("alex_walking_again.aedat")
    s = read_events(path)
    assert s.sensor_size == (128, 128)
    assert len(s) == (path.stat().st_size - header_len(path)) // 8 == 19_182
    e = s.events
    assert e["x"].min() >= 0 and e["x"].max() <= 127 and e["y"].min() >= 0 and e["y"].max() <= 127
    assert (np.diff(e["t"]) >= 0).all()
    assert as_tuples(e[:300]) == jaer_loop(path, 300, False, 128, 128)


def test_aedat2_davis_real_file_skips_imu():
    path = need("IMU_translBoxes.aedat")
    s = read_events(path)
    assert s.sensor_size == (240, 180)
    n_records = (path.stat().st_size - header_len(path)) // 8
    loop = jaer_loop(path, n_records, True, 240, 180)
    assert len(s) == len(loop) == 162_771 < n_records  # 33,837 IMU records dropped
    assert as_tuples(s.events[:2000]) == loop[:2000]
    assert as_tuples(s.events[-500:]) == loop[-500:]
    assert s.events["x"].max() < 240 and s.events["y"].max() < 180


def test_aedat4_real_file_matches_aedat_package_figures():
    s = read_events(need("sample.aedat4"))
    e = s.events
    # reference figures from the independent Rust-based `aedat` 2.3.0 package on this file
    assert s.sensor_size == (320, 240)
    assert len(e) == 111_954
    assert (int(e["t"][0]), int(e["t"][-1])) == (1605537493718345, 1605537494308262)
    assert int(e["x"].astype(np.int64).sum()) == 18_342_405
    assert int(e["y"].astype(np.int64).sum()) == 15_105_898
    assert int(e["p"].sum()) == 55_023
    assert (np.diff(e["t"]) >= 0).all()


def test_npy_reader_streams_and_infers_size():
    path = need("evt3_sample.npy")
    with pytest.warns(UserWarning, match="no sensor size"):
        s = read_events(path)
    assert s.sensor_size == (1280, 720)
    chunks = list(iter_events(path, 50_000, sensor_size=(1280, 720)))
    assert len(chunks) == 5 and np.array_equal(np.concatenate([c.events for c in chunks]),
                                               s.events)


def test_wrong_sensor_size_is_an_error():
    with pytest.raises(EventFormatError, match="outside the 64x64 sensor"):
        read_events(need("alex_walking_again.aedat"), sensor_size=(64, 64))


# ---------------------------------------------------------------- round trips


def random_events(n, w, h, seed=0, t0=0):
    rng = np.random.default_rng(seed)
    t = t0 + np.sort(rng.integers(0, 5_000_000, n))
    return EventStream(make_events(t, rng.integers(0, w, n), rng.integers(0, h, n),
                                   rng.integers(0, 2, n)), (w, h))


def test_npz_round_trip(tmp_path):
    s = random_events(1000, 40, 30)
    write_npz(tmp_path / "e.npz", s)
    back = read_events(tmp_path / "e.npz")
    assert back.sensor_size == (40, 30) and np.array_equal(back.events, s.events)
    assert [p.name for p in tmp_path.iterdir()] == ["e.npz"]  # no temporary left behind


@pytest.mark.parametrize("layout,size", [("dvs128", (128, 128)), ("davis", (240, 180)),
                                         ("davis", (346, 260))])
def test_aedat2_round_trip(tmp_path, layout, size):
    s = random_events(5000, *size, seed=1)
    write_aedat2(tmp_path / "e.aedat", s, layout=layout)
    back = read_events(tmp_path / "e.aedat")
    assert back.sensor_size == size and np.array_equal(back.events, s.events)
    chunks = list(iter_events(tmp_path / "e.aedat", chunk_events=333))
    assert np.array_equal(np.concatenate([c.events for c in chunks]), s.events)


def test_aedat2_first_record_starting_with_hash_byte(tmp_path):
    # a DAVIS address whose top byte is 0x23 ('#') right after the header
    s = EventStream(make_events([5, 6], [10, 11], [180 - 1 - 140, 3], [0, 1]), (240, 180))
    write_aedat2(tmp_path / "e.aedat", s, layout="davis")
    data = (tmp_path / "e.aedat").read_bytes()
    end = data.index(b"sensor_size: 240x180\r\n") + len(b"sensor_size: 240x180\r\n")
    assert data[end:end + 1] == b"#"
    assert np.array_equal(read_events(tmp_path / "e.aedat").events, s.events)


def test_aedat2_timestamp_wrap_is_unwrapped(tmp_path):
    t = np.array([2**32 - 300, 2**32 - 10, 2**32 + 5, 2**32 + 2**31 + 9, 2 * 2**32 + 1], np.int64)
    s = EventStream(make_events(t, [1, 2, 3, 4, 5], [0, 0, 1, 1, 2], [1, 0, 1, 0, 1]), (128, 128))
    write_aedat2(tmp_path / "w.aedat", s)
    raw = np.frombuffer((tmp_path / "w.aedat").read_bytes()[-40:], ">u4").reshape(5, 2)[:, 1]
    assert (raw < 2**32).all() and raw[2] == 5  # the file holds wrapped 32-bit times
    for chunk in (1, 2, 100):
        back = np.concatenate([c.events for c in iter_events(tmp_path / "w.aedat", chunk)])
        assert np.array_equal(back["t"], t)


def test_csv_with_and_without_header(tmp_path):
    (tmp_path / "a.csv").write_text("t,x,y,p\n10,1,2,1\n20,3,4,0\n")
    (tmp_path / "b.txt").write_text("# comment\n10 1 2 1\n20 3 4 -1\n")
    (tmp_path / "c.csv").write_text("x,y,polarity,timestamp\n1,2,1,10\n3,4,0,20\n")
    for name in ("a.csv", "b.txt", "c.csv"):
        s = read_events(tmp_path / name, sensor_size=(8, 8))
        assert as_tuples(s.events) == [(10, 1, 2, 1), (20, 3, 4, 0)]
    (tmp_path / "d.csv").write_text("t,x,y\n1,2,3\n")
    with pytest.raises(EventFormatError, match="header"):
        read_events(tmp_path / "d.csv")


# ---------------------------------------------------------------- bad input


def test_truncated_aedat2(tmp_path):
    s = random_events(100, 128, 128)
    write_aedat2(tmp_path / "e.aedat", s)
    data = (tmp_path / "e.aedat").read_bytes()
    (tmp_path / "t.aedat").write_bytes(data[:-3])
    with pytest.raises(EventFormatError, match="truncated, 5 trailing"):
        read_events(tmp_path / "t.aedat")
    with pytest.warns(UserWarning, match="dropped"):
        back = read_events(tmp_path / "t.aedat", truncated="drop")
    assert np.array_equal(back.events, s.events[:-1])


def test_truncated_raw_and_aedat4(tmp_path):
    raw = need("evt3_sample.raw").read_bytes()
    (tmp_path / "t.raw").write_bytes(raw[:-1])
    with pytest.raises(EventFormatError, match="truncated"):
        read_events(tmp_path / "t.raw")
    a4 = need("sample.aedat4").read_bytes()
    (tmp_path / "t.aedat4").write_bytes(a4[:len(a4) // 2])
    with pytest.raises(EventFormatError, match="truncated"):
        read_events(tmp_path / "t.aedat4")
    with pytest.warns(UserWarning, match="dropped"):
        part = read_events(tmp_path / "t.aedat4", truncated="drop")
    full = read_events(need("sample.aedat4"))
    assert 0 < len(part) < len(full) and np.array_equal(part.events, full.events[:len(part)])


@pytest.mark.parametrize("content,match", [
    (b"", "empty file"),
    (b"#!AER-DAT3.1\r\n", "unsupported AEDAT version"),
    (b"hello world, not events", "unknown event file format"),
    (b"% Date 2020\n% something else\n\x00\x80", "no supported format"),
    (b"#!AER-DAT2.0\r\n# no chip here\r\n" + bytes(16), "names no known chip"),
    (b"#!AER-DAT4.0\r\n\x10", "truncated AEDAT4 header"),
])
def test_bad_headers(tmp_path, content, match):
    (tmp_path / "bad.aedat").write_bytes(content)
    with pytest.raises(EventFormatError, match=match):
        read_events(tmp_path / "bad.aedat")


def test_header_only_file_gives_empty_stream(tmp_path):
    write_aedat2(tmp_path / "e.aedat", EventStream(make_events([], [], [], []), (128, 128)))
    s = read_events(tmp_path / "e.aedat")
    assert len(s) == 0 and s.sensor_size == (128, 128)


def test_backwards_time_error_and_sort(tmp_path):
    s = EventStream(make_events([10, 30, 20, 40], [0, 1, 2, 3], [0, 0, 0, 0], [1, 1, 0, 0]),
                    (4, 4))
    np.savez(tmp_path / "e.npz", events=s.events, sensor_size=[4, 4])
    with pytest.raises(EventFormatError, match="backwards at event #2"):
        read_events(tmp_path / "e.npz")
    with pytest.warns(UserWarning, match="sorted"):
        back = read_events(tmp_path / "e.npz", sort=True)
    assert back.events["t"].tolist() == [10, 20, 30, 40] and back.events["x"].tolist() == [0, 2,
                                                                                         1, 3]
    write_aedat2(tmp_path / "a.aedat", EventStream(s.events[np.argsort(s.events["t"])], (4, 4)),
                 layout="davis")
    with pytest.raises(EventFormatError, match="backwards"):
        EventStream(s.events, (4, 4)).validate()


def test_event_stream_helpers():
    s = random_events(50, 10, 5)
    tensors = s.to_tensors()
    assert tensors["t"].dtype.is_floating_point is False and tensors["x"].shape == (50,)
    assert tensors["x"].data_ptr() == s.events["x"].__array_interface__["data"][0]  # a view
    assert s.duration_us == int(s.events["t"][-1] - s.events["t"][0])
    with pytest.raises(EventFormatError, match="lacks field"):
        EventStream(np.zeros(3, [("t", "i8"), ("x", "i2")]), (4, 4))
    with pytest.raises(EventFormatError, match="positive"):
        EventStream(s.events, (0, 4))
    signed = np.zeros(2, [("t", "i8"), ("x", "i2"), ("y", "i2"), ("p", "i1")])
    signed["p"] = [-1, 1]
    assert EventStream(signed, (1, 1)).events["p"].tolist() == [0, 1]


# ---------------------------------------------------------------- LZ4 fallback

# LZ4 frames made by the `lz4` 4.4.5 package (C library) from DATA / RANDOM below:
# default; with block + content checksums and content size; an uncompressed (raw) block.
FRAMES = [
    "BCJNGGhATAgAAAAAAAA8KgEAAP8BdG9yY2hzZXEgZXZlbnRzIBAA////AP/xAAECAwQFBgcICQoLDA0ODxAREhMUFR"
    "YXGBkaGxwdHh8gISIjJCUmJygpKissLS4vMDEyMzQ1Njc4OTo7PD0+P0BBQkNERUZHSElKS0xNTk9QUVJTVFVWV1hZ"
    "WltcXV5fYGFiY2RlZmdoaWprbG1ub3BxcnN0dXZ3eHl6e3x9fn+AgYKDhIWGh4iJiouMjY6PkJGSk5SVlpeYmZqbnJ"
    "2en6ChoqOkpaanqKmqq6ytrq+wsbKztLW2t7i5uru8vb6/wMHCw8TFxsfIycrLzM3Oz9DR0tPU1dbX2Nna29zd3t/g"
    "4eLj5OXm5+jp6uvs7e7v8PHy8/T19vf4+fr7/P3+/wAB///wDwEA/xRQAAAAAAAAAAAA",
    "BCJNGHxATAgAAAAAAADnKgEAAP8BdG9yY2hzZXEgZXZlbnRzIBAA////AP/xAAECAwQFBgcICQoLDA0ODxAREhMUFR"
    "YXGBkaGxwdHh8gISIjJCUmJygpKissLS4vMDEyMzQ1Njc4OTo7PD0+P0BBQkNERUZHSElKS0xNTk9QUVJTVFVWV1hZ"
    "WltcXV5fYGFiY2RlZmdoaWprbG1ub3BxcnN0dXZ3eHl6e3x9fn+AgYKDhIWGh4iJiouMjY6PkJGSk5SVlpeYmZqbnJ"
    "2en6ChoqOkpaanqKmqq6ytrq+wsbKztLW2t7i5uru8vb6/wMHCw8TFxsfIycrLzM3Oz9DR0tPU1dbX2Nna29zd3t/g"
    "4eLj5OXm5+jp6uvs7e7v8PHy8/T19vf4+fr7/P3+/wAB///wDwEA/xRQAAAAAAB+xrluAAAAAIVXZ2E=",
    "BCJNGGhAQAAAAAAAAABcQAAAgP/kInnzvQaDZqhSwbuWUfPNGOwI9qTnJNJvrNKusNryqXLNP6Av1E9IcHjeRR9fbC"
    "Rt7kUzUeTTyjrKQUxGwWgAAAAA",
]
DATA_BYTES = (b"torchseq events " * 50) + bytes(range(256)) * 4 + b"\x00" * 300
RANDOM = base64.b64decode("/+QiefO9BoNmqFLBu5ZR880Y7Aj2pOck0m+s0q6w2vKpcs0/oC/UT0hweN5FH19s"
                          "JG3uRTNR5NPKOspBTEbBaA==")


def test_pure_python_lz4_against_frames_from_the_c_library():
    frames = [base64.b64decode(f) for f in FRAMES]
    assert decompress_frames(frames[0]) == DATA_BYTES
    assert decompress_frames(frames[1]) == DATA_BYTES
    assert decompress_frames(frames[2]) == RANDOM
    assert decompress_frames(frames[0] + frames[2]) == DATA_BYTES + RANDOM  # concatenated
    with pytest.raises(LZ4Error):
        decompress_frames(frames[0][:-20])
    with pytest.raises(LZ4Error, match="not an LZ4 frame"):
        decompress_frames(b"\x00" * 12)


def test_aedat4_pure_python_path_equals_library_path(monkeypatch):
    pytest.importorskip("lz4")
    path = need("sample.aedat4")
    fast = read_events(path)
    import torchseq.events.aedat4 as a4

    monkeypatch.setattr(a4, "lz4_decompress", decompress_frames)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.array_equal(read_events(path).events, fast.events)


def test_evt2_hand_made_words(tmp_path):
    # EVT 2.0 words built by hand from the format description: TIME_HIGH holds t >> 6,
    # CD events hold t & 63 (bits 22..27), x (bits 11..21), y (bits 0..10); type 0 OFF, 1 ON
    def cd(on, t, x, y):
        return (int(on) << 28) | ((t & 63) << 22) | (x << 11) | y

    words = [cd(1, 0, 1, 1),  # before any TIME_HIGH: dropped
             (0x8 << 28) | (1000 >> 6), cd(1, 1000, 3, 2), cd(0, 1010, 15, 7),
             (0xA << 28) | 5,  # an external trigger: skipped
             (0x8 << 28) | (5000 >> 6), cd(1, 5000, 0, 0)]
    data = b"% evt 2.0\n% geometry 16x8\n% end\n" + np.array(words, "<u4").tobytes()
    (tmp_path / "e.raw").write_bytes(data)
    s = read_events(tmp_path / "e.raw")
    assert s.sensor_size == (16, 8)
    assert as_tuples(s.events) == [(1000, 3, 2, 1), (1010, 15, 7, 0), (5000, 0, 0, 1)]

import base64
import struct
import warnings
import zipfile
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
    write_aedat4,
    write_npz,
)
from torchseq.events.lz4frame import LZ4Error, decompress_frames
from torchseq.events.prophesee import write_evt3

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

    assert a4.lz4_decompress is a4._lz4_package  # lz4 installed: the C kernel is the one used
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


# ---------------------------------------------------------------- AEDAT 4 writer


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_aedat4_round_trip(tmp_path, compression):
    s = random_events(3000, 640, 480, seed=3, t0=1_600_000_000_000_000)
    write_aedat4(tmp_path / "e.aedat4", s, compression=compression, packet_events=700)
    back = read_events(tmp_path / "e.aedat4")
    assert back.sensor_size == (640, 480) and np.array_equal(back.events, s.events)
    chunks = list(iter_events(tmp_path / "e.aedat4", chunk_events=1000))
    assert [len(c) for c in chunks] == [1400, 1400, 200]  # whole packets of 700
    assert np.array_equal(np.concatenate([c.events for c in chunks]), s.events)


def test_aedat4_writer_layout_matches_the_real_file():
    # the writer's packet flatbuffer decodes like the real DV packets: same header fields
    from torchseq.events.aedat4 import _events_packet, decode_events_packet
    ev = random_events(5, 320, 240).events
    assert np.array_equal(decode_events_packet(_events_packet(ev)), ev)
    raw = _events_packet(ev)
    assert struct.unpack_from("<I", raw)[0] == len(raw) - 4 and raw[8:12] == b"EVTS"
    assert (len(raw) - 16 * 5) % 8 == 0  # the struct vector is 8-byte aligned in the buffer


# ---------------------------------------------------------------- regressions (fuzzer finds)
# each of these failed on the reader before this change with a foreign exception or garbage


def a4_bytes():
    return need("sample.aedat4").read_bytes()


def a4_info_span(data):
    start = data.index(b"<dv version")
    return start, data.index(b"</dv>") + 5


@pytest.mark.parametrize("mutate,match", [
    (lambda d: d[:18] + struct.pack("<I", 60_000) + d[22:], "IOHeader: offset"),  # root offset
    (lambda d: d[:14] + struct.pack("<i", -5) + d[18:], "truncated AEDAT4 header"),
    (lambda d: d.replace(b'"int">320<', b'"int">3x0<'), "bad sizeX"),
    (lambda d: d.replace(b'"int">320<', b'"int">9e9<'), "bad sizeX"),
])
def test_aedat4_header_damage(tmp_path, mutate, match):
    path = tmp_path / "bad.aedat4"
    path.write_bytes(mutate(a4_bytes()))
    with pytest.raises(EventFormatError, match=match) as err:
        read_events(path)
    assert str(path) in str(err.value) and "byte" in str(err.value)


def first_packet(data):
    start = 18 + struct.unpack_from("<i", data, 14)[0]
    return start, struct.unpack_from("<ii", data, start)


def test_aedat4_negative_packet_size(tmp_path):
    data = a4_bytes()
    start, (sid, size) = first_packet(data)
    path = tmp_path / "neg.aedat4"
    path.write_bytes(data[:start + 4] + struct.pack("<i", -7) + data[start + 8:])
    with pytest.raises(EventFormatError, match=f"negative size -7 \\(at byte {start}\\)"):
        read_events(path)


def test_aedat4_packet_flatbuffer_offsets_checked(tmp_path):
    s = random_events(50, 32, 32)
    write_aedat4(tmp_path / "e.aedat4", s, compression="none")
    data = bytearray((tmp_path / "e.aedat4").read_bytes())
    start, _ = first_packet(bytes(data))
    data[start + 8 + 4: start + 8 + 8] = struct.pack("<I", 0x7FFFFFF0)  # root offset
    (tmp_path / "e.aedat4").write_bytes(bytes(data))
    with pytest.raises(EventFormatError, match="events packet: offset"):
        read_events(tmp_path / "e.aedat4")


def test_aedat4_corrupt_zstd_packet(tmp_path):
    write_aedat4(tmp_path / "z.aedat4", random_events(2000, 64, 64), compression="zstd")
    data = bytearray((tmp_path / "z.aedat4").read_bytes())
    start, (_, size) = first_packet(bytes(data))
    for i in range(start + 8 + 6, start + 8 + size, 7):
        data[i] ^= 0x5A
    (tmp_path / "z.aedat4").write_bytes(bytes(data))
    with pytest.raises(EventFormatError, match="Zstd packet") as err:
        read_events(tmp_path / "z.aedat4")
    assert f"byte {start}" in str(err.value)


def test_aedat4_decompression_is_capped(tmp_path, monkeypatch):
    import torchseq.events.aedat4 as a4
    write_aedat4(tmp_path / "e.aedat4", random_events(5000, 64, 64), compression="lz4")
    monkeypatch.setattr(a4, "PACKET_LIMIT", 1000)
    monkeypatch.setattr(a4._decompress, "__defaults__", (1000,))
    with pytest.raises(EventFormatError, match="more than 1000 bytes"):
        read_events(tmp_path / "e.aedat4")


def npz_with_member(path, name, npy_bytes, compression=zipfile.ZIP_STORED):
    with zipfile.ZipFile(path, "w", compression) as z:
        z.writestr(name, npy_bytes)


def npy_bytes(header: str, body: bytes = b"", version=1) -> bytes:
    text = header.encode("latin1")
    pad = (-(len(text) + 11) % 64) if version == 1 else (-(len(text) + 13) % 64)
    text = text + b" " * pad + b"\n"
    if version == 1:
        return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + body
    return b"\x93NUMPY\x02\x00" + struct.pack("<I", len(text)) + text + body


EV_DESCR = str(EVENT_DTYPE.descr)


def test_npz_declaring_ten_billion_events_allocates_nothing_big(tmp_path):
    import tracemalloc
    path = tmp_path / "bomb.npz"
    npz_with_member(path, "events.npy", npy_bytes(
        f"{{'descr': {EV_DESCR}, 'fortran_order': False, 'shape': (10000000000,), }}", bytes(64)))
    assert path.stat().st_size < 400
    tracemalloc.start()
    with pytest.raises(EventFormatError, match="declares 10000000000 elements") as err:
        read_events(path)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 5_000_000 and str(path) in str(err.value)


def test_damaged_npz_files(tmp_path):
    s = random_events(100, 16, 16)
    write_npz(tmp_path / "ok.npz", s)
    data = (tmp_path / "ok.npz").read_bytes()
    method = bytearray(data)  # compression method 99 (unknown) in every header
    for sig, at in ((b"PK\x03\x04", 8), (b"PK\x01\x02", 10)):
        i = data.find(sig)
        while i >= 0:
            method[i + at: i + at + 2] = struct.pack("<H", 99)
            i = data.find(sig, i + 4)
    cases = {"cut.npz": data[:len(data) // 2], "method.npz": bytes(method)}
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(EventFormatError, match="not a readable .npz") as err:
            read_events(tmp_path / name)
        assert name in str(err.value)


def test_npz_malformed_sensor_size(tmp_path):
    s = random_events(20, 16, 16)
    for bad in ([1, 2, 3], [[16, 16]], [16.5, 16], [70000, 16], [0, 16]):
        np.savez(tmp_path / "e.npz", events=s.events, sensor_size=np.asarray(bad))
        with pytest.raises(EventFormatError, match="sensor_size"):
            read_events(tmp_path / "e.npz")
    with pytest.raises(EventFormatError, match="sensor_size"):
        read_events(tmp_path / "e.npz", sensor_size=(16,))


@pytest.mark.parametrize("arr,match", [
    (np.zeros((), EVENT_DTYPE), "1-D"),                                       # 0-d
    (np.zeros(3, [("t", "<i8"), ("x", "<i2")]), "fields t, x, y, p"),         # missing fields
    (np.array([(1, np.inf, 0, 1)], [("t", "<i8"), ("x", "<f8"), ("y", "<f8"), ("p", "u1")]),
     r"x\[0\] = np.float64\(inf\)"),                                          # OverflowError
    (np.array([(2**63, 1, 1, 1)], [("t", "<u8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")]),
     "not an integer in"),                                                    # t >= 2**63
    (np.array([(1e400, 1, 1, 1)], [("t", "<f8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")]),
     "not an integer in"),                                                    # t = inf
])
def test_npy_foreign_arrays(tmp_path, arr, match):
    np.save(tmp_path / "e.npy", arr)
    for read in (lambda: read_events(tmp_path / "e.npy"),
                 lambda: list(iter_events(tmp_path / "e.npy", 1, sensor_size=(8, 8)))):
        with pytest.raises(EventFormatError, match=match) as err:
            read()
        assert "e.npy" in str(err.value)


def test_corrupt_npy_header(tmp_path):
    for i, header in enumerate([f"{{'descr': {EV_DESCR[:-3]}", "{'descr': '<i8', 'fortran_",
                                "not python at all (", "{'descr': 'O', 'fortran_order': "
                                "False, 'shape': (3,), }"]):
        (tmp_path / f"h{i}.npy").write_bytes(npy_bytes(header, bytes(48)))
        with pytest.raises(EventFormatError, match="at byte 0") as err:
            read_events(tmp_path / f"h{i}.npy", sensor_size=(4, 4))
        assert f"h{i}.npy" in str(err.value)


def test_npy_declaring_more_than_the_file_holds(tmp_path):
    (tmp_path / "e.npy").write_bytes(npy_bytes(
        f"{{'descr': {EV_DESCR}, 'fortran_order': False, 'shape': (1000,), }}", bytes(160)))
    with pytest.raises(EventFormatError, match="declares 1000 elements"):
        read_events(tmp_path / "e.npy", sensor_size=(4, 4))


def test_csv_coordinates_beyond_int16_do_not_wrap(tmp_path):
    (tmp_path / "e.csv").write_text("t,x,y,p\n10,65541,2,1\n")
    with pytest.raises(EventFormatError, match="x"):
        read_events(tmp_path / "e.csv", sensor_size=(8, 8))
    with pytest.raises(EventFormatError, match="x"):
        read_events(tmp_path / "e.csv")


@pytest.mark.parametrize("t", ["inf", "1e400", "9" * 40, str(2**63), "nan", "123456.5", "1.5x"])
def test_csv_hostile_timestamps(tmp_path, t):
    (tmp_path / "e.csv").write_text(f"5,1,1,1\n{t},1,1,1\n")
    with pytest.raises(EventFormatError, match="line 2|t") as err:
        read_events(tmp_path / "e.csv", sensor_size=(4, 4))
    assert "e.csv" in str(err.value)


def test_csv_times_are_exact_integers(tmp_path):
    (tmp_path / "e.csv").write_text("9007199254740993,1,2,1\n9007199254740995,1,2,-1\n"
                                    "9007199254740996.0,0,0,0\n")
    s = read_events(tmp_path / "e.csv", sensor_size=(4, 4))
    assert s.events["t"].tolist() == [9007199254740993, 9007199254740995, 9007199254740996]
    assert s.events["p"].tolist() == [1, 0, 0]


def test_aedat2_header_sensor_beyond_int16(tmp_path):
    s = random_events(10, 240, 180)
    write_aedat2(tmp_path / "e.aedat", s, layout="davis")
    data = (tmp_path / "e.aedat").read_bytes().replace(b"sensor_size: 240x180",
                                                       b"sensor_size: 70000x180")
    (tmp_path / "e.aedat").write_bytes(data)
    with pytest.raises(EventFormatError, match="at most 32768") as err:
        read_events(tmp_path / "e.aedat")
    assert "e.aedat" in str(err.value) and "byte 0" in str(err.value)


def test_backwards_check_does_not_overflow(tmp_path):
    big = np.iinfo(np.int64)
    # a jump from near +2**63 to near -2**63 goes backwards (np.diff wraps it to +1)
    back = make_events([big.max, big.min], [0, 1], [0, 0], [1, 0])
    np.savez(tmp_path / "b.npz", events=back, sensor_size=[4, 4])
    with pytest.raises(EventFormatError, match="backwards"):
        read_events(tmp_path / "b.npz")
    with pytest.raises(EventFormatError, match="backwards"):
        EventStream(back, (4, 4)).validate()
    # ... and the forward jump from -2**63 to +2**63 - 1 is in order (np.diff wraps to -1)
    fwd = make_events([big.min, big.max], [0, 1], [0, 0], [1, 0])
    np.save(tmp_path / "f.npy", fwd)
    assert np.array_equal(read_events(tmp_path / "f.npy", sensor_size=(4, 4)).events, fwd)
    assert len(list(iter_events(tmp_path / "f.npy", 1, sensor_size=(4, 4)))) == 2
    np.save(tmp_path / "b.npy", back)
    with pytest.raises(EventFormatError, match="backwards at event #1"):
        list(iter_events(tmp_path / "b.npy", 1, sensor_size=(4, 4)))


def test_polarity_rule_is_the_same_whole_and_chunked(tmp_path):
    ev = np.zeros(3, [("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "<i2")])
    ev["t"], ev["p"] = [1, 2, 3], [-1, 1, 255]
    np.save(tmp_path / "e.npy", ev)
    for chunk in (1, 2, 100):
        with pytest.raises(EventFormatError, match=r"p\[\d\] = np.int16\(255\)"):
            read_events(tmp_path / "e.npy", sensor_size=(2, 2), chunk_events=chunk)
        with pytest.raises(EventFormatError, match=r"p\[\d\] = np.int16\(255\)"):
            list(iter_events(tmp_path / "e.npy", chunk, sensor_size=(2, 2)))
    ev["p"][2] = 0
    np.save(tmp_path / "e.npy", ev)
    for chunk in (1, 2, 100):
        got = np.concatenate([c.events["p"] for c in iter_events(tmp_path / "e.npy", chunk,
                                                                 sensor_size=(2, 2))])
        assert got.tolist() == [0, 1, 0]


def test_make_events_is_exact():
    with pytest.raises(EventFormatError, match="x"):
        make_events([1], [40000], [0], [1])
    with pytest.raises(EventFormatError, match="t"):
        make_events([2.0**63], [0], [0], [1])
    with pytest.raises(EventFormatError, match="p"):
        make_events([1], [0], [0], [2])
    ev = make_events(np.array([2**62 + 1], np.uint64), [32767], [-32768], [True])
    assert ev["t"][0] == 2**62 + 1 and ev["x"][0] == 32767 and ev["p"][0] == 1


# ---------------------------------------------------------------- EVT 3.0 writer and decoder


def evt3_loop(words, carry=False):
    """Independent EVT 3.0 decoder: a plain state machine over the words (format rules)."""
    y = high = low = None
    base, pol, loops, carries, out = 0, 0, 0, 0, []
    for w in (int(v) for v in words):
        typ, val = w >> 12, w & 0xFFF
        if typ == 0x0:
            y = val & 0x7FF
        elif typ == 0x8:
            if high is not None and val < high:
                loops += 1
            high = val
        elif typ == 0x6:
            if carry and low is not None and val < low:
                carries += 1
            low = val
        elif typ == 0x3:
            base, pol = val & 0x7FF, val >> 11
        elif typ in (0x2, 0x4, 0x5):
            ok = high is not None and y is not None
            t = ((high + (loops << 12) + carries) << 12) + (low or 0) if ok else None
            if typ == 0x2:
                if ok:
                    out.append((t, val & 0x7FF, y, val >> 11))
            else:
                n = 12 if typ == 0x4 else 8
                for b in range(n):
                    if ok and (val >> b) & 1:
                        out.append((t, base + b, y, pol))
                base += n
    return out


def test_evt3_decoder_against_a_plain_loop_on_random_words():
    from torchseq.events.prophesee import decode_evt3
    rng = np.random.default_rng(11)
    for trial in range(40):
        n = int(rng.integers(0, 1500))
        typ = rng.choice([0, 2, 3, 4, 5, 6, 8, 0xA, 0xE, 1], n,
                         p=[.15, .2, .1, .1, .05, .15, .1, .05, .05, .05])
        words = ((typ << 12) | rng.integers(0, 4096, n)).astype(np.uint16)
        for carry in (False, True):
            state, chunk = {}, int(rng.integers(1, 400))
            got = np.concatenate([decode_evt3(words[i:i + chunk], state,
                                              "carry" if carry else "spec")
                                  for i in range(0, max(n, 1), chunk)])
            assert as_tuples(got) == evt3_loop(words, carry), (trial, carry)


def test_evt3_loop_reproduces_the_reference_npy():
    # the plain loop with the carry rule gives the shared decoded reference: the oracle is sound
    raw = need("evt3_sample.raw").read_bytes()
    pos = 0
    while raw[pos:pos + 1] == b"%":
        pos = raw.index(b"\n", pos) + 1
    words = np.frombuffer(raw[pos:pos + 2 * 40_000], "<u2")
    ref = np.load(need("evt3_sample.npy"))
    got = evt3_loop(words, carry=True)
    assert got == as_tuples(ref[:len(got)]) and len(got) > 20_000


def bursts(n, w, h, seed, span_us):
    """Edge-like events: horizontal runs of 1-24 pixels at one (t, y, p), some duplicated."""
    rng = np.random.default_rng(seed)
    lens = rng.integers(1, 25, n)
    lens = lens[:np.searchsorted(np.cumsum(lens), n) + 1]
    m = len(lens)
    t0 = np.sort(rng.integers(0, span_us, m))
    owner = np.repeat(np.arange(m), lens)
    off = np.arange(len(owner)) - np.repeat(np.cumsum(lens) - lens, lens)
    x0, y0, p0 = rng.integers(0, w - 24, m), rng.integers(0, h, m), rng.integers(0, 2, m)
    ev = make_events(t0[owner], x0[owner] + off, y0[owner], p0[owner])
    ev = np.concatenate([ev, ev[rng.random(len(ev)) < 0.02]])  # duplicate events
    return EventStream(ev[np.argsort(ev["t"], kind="stable")], (w, h))


def by_time_row_pol_x(ev):
    return ev[np.lexsort((ev["x"], ev["p"], ev["y"], ev["t"]))]


def test_evt3_writer_round_trip_across_time_wraps(tmp_path):
    s = bursts(20_000, 1280, 720, seed=5, span_us=60_000_000)  # 3.6 wraps of 2**24 us
    write_evt3(tmp_path / "e.raw", s)
    ref = by_time_row_pol_x(s.events)
    back = read_events(tmp_path / "e.raw")
    assert back.sensor_size == (1280, 720) and np.array_equal(back.events, ref)
    for chunk in (3, 1000):
        parts = np.concatenate([c.events for c in iter_events(tmp_path / "e.raw", chunk)])
        assert np.array_equal(parts, ref)
    words = np.frombuffer((tmp_path / "e.raw").read_bytes()[-2 * 3000:], "<u2")
    assert {0x3, 0x4, 0x2} <= set((words >> 12).tolist())  # vectors and singles written


def test_evt3_writer_round_trip_of_the_real_recording(tmp_path):
    real = read_events(need("evt3_sample.raw"))
    write_evt3(tmp_path / "r.raw", real)
    assert np.array_equal(read_events(tmp_path / "r.raw").events, by_time_row_pol_x(real.events))


def test_hot_pixel_mask_dense_and_sparse_paths_agree_and_stay_small():
    import tracemalloc

    from torchseq.events import hot_pixel_mask
    rng = np.random.default_rng(2)
    n = 3000
    ev = make_events(np.arange(n), rng.integers(0, 20, n), rng.integers(0, 10, n),
                     rng.integers(0, 2, n))
    ev["x"][:400], ev["y"][:400] = 7, 3  # one hot pixel
    dense = hot_pixel_mask(ev, (20, 10), 5.0)  # 200 pixels: the bincount path
    assert np.array_equal(dense, (ev["x"] != 7) | (ev["y"] != 3))
    big = ev.copy()
    big["x"], big["y"] = ev["x"] * 1500, ev["y"] * 3000  # same pixels on a 32768^2 sensor
    tracemalloc.start()
    sparse = hot_pixel_mask(big, (32768, 32768), 5.0)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert np.array_equal(sparse, dense) and peak < 2_000_000  # not 8 GiB of counts


def test_options_for_another_format(tmp_path):
    s = random_events(10, 16, 16)
    write_npz(tmp_path / "e.aedat4", s)  # an .npz under an AEDAT 4 name
    with pytest.raises(EventFormatError, match=r"is npz .* \['truncated'\] do not apply"):
        read_events(tmp_path / "e.aedat4", truncated="drop")
    with pytest.raises(TypeError, match="unknown event file option"):
        read_events(tmp_path / "e.aedat4", truncatd="drop")

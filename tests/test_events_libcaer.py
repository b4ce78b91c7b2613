"""DDD20's original recordings: libcaer packets inside HDF5 (torchseq.events.libcaer).

Files are written here in the recorder's layout (tests/libcaer_writer.py, from the facts in
ddd20-utils' record.py/datasets.py and libcaer's event headers); the expected events come
from a plain-Python decoder that reads each packet byte by byte (libcaer_writer.oracle).
"""

import struct
import warnings

import numpy as np
import pytest

h5py = pytest.importorskip("h5py", reason="h5py not installed (pip install 'torchseq[hdf5]')")

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from libcaer_writer import (  # noqa: E402
    frame_packet,
    header,
    imu_packet,
    oracle,
    polarity_packet,
    polarity_packets,
    write_ddd20,
)

from torchseq.events import EventFormatError, iter_events, read_events  # noqa: E402
from torchseq.events.libcaer import FRAME_EVENT  # noqa: E402


def _recording(seed=0, n_packets=12, crossing=True):
    """Polarity packets (some events invalid, spare capacity) between frame/IMU/special
    packets; times cross 2^31 us (the overflow counter) when ``crossing``."""
    rng = np.random.default_rng(seed)
    t0 = 2**31 - 40_000 if crossing else 1000
    packets, t = [frame_packet(346, 260, ts=5)], t0
    for k in range(n_packets):
        n = int(rng.integers(0, 40))
        ts = t + np.sort(rng.integers(0, 7000, n))
        t = int(ts[-1]) + 1 if n else t + 7000
        over = ts >> 31
        if n and over[0] != over[-1]:  # one overflow value per packet: split at the crossing
            cut = int(np.argmax(over != over[0]))
            parts = [(ts[:cut], 0), (ts[cut:], cut)]
        else:
            parts = [(ts, 0)]
        for part, _ in parts:
            m = len(part)
            packets.append(polarity_packet(part, rng.integers(0, 346, m), rng.integers(0, 260, m),
                                           rng.integers(0, 2, m), rng.random(m) > 0.2,
                                           capacity=m + int(rng.integers(0, 3))))
        if k % 4 == 1:
            packets.append(imu_packet(ts=5))
        if k % 5 == 2:
            packets.append((header(0, 8, 4, 0, 1, 1, 1), struct.pack("<Ii", 1, 5)))
    return packets


def _events(path, **kw):
    s = read_events(path, **kw)
    return s, [s.events[k].tolist() for k in "txyp"]


def test_reads_every_valid_polarity_event_like_the_byte_oracle(tmp_path):
    path = tmp_path / "rec.hdf5"
    write_ddd20(path, _recording())
    s, got = _events(path)
    want = oracle(path)
    assert len(want[0]) > 100 and max(want[0]) >= 2**31  # overflow counter in use
    assert got == [list(c) for c in want]
    assert s.sensor_size == (346, 260)  # from the APS frame, no warning needed
    for chunk in (1, 7, 1000, 1 << 20):
        parts = list(iter_events(path, chunk))
        assert all(len(c) == chunk for c in parts[:-1]) and 0 < len(parts[-1]) <= chunk
        assert np.array_equal(np.concatenate([c.events for c in parts]), s.events)


def test_unchunked_dataset_and_no_padding(tmp_path):
    path = tmp_path / "flat.h5"
    write_ddd20(path, _recording(seed=3, crossing=False), chunked=False)
    assert _events(path)[1] == [list(c) for c in oracle(path)]


def test_sensor_size_from_argument_attributes_or_coordinates(tmp_path):
    packets = [p for p in _recording(seed=1) if struct.unpack_from("<h", p[0])[0] != FRAME_EVENT]
    path = tmp_path / "noframe.h5"
    write_ddd20(path, packets)
    want = oracle(path)
    with pytest.warns(UserWarning, match="346x260"):
        s = read_events(path)
    assert s.sensor_size == (max(want[1]) + 1, max(want[2]) + 1)
    assert read_events(path, sensor_size=(400, 300)).sensor_size == (400, 300)
    write_ddd20(path, packets, attrs={"width": 346, "height": 260})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_events(path).sensor_size == (346, 260)


def test_sensor_size_from_the_first_valid_frame(tmp_path):
    path = tmp_path / "frames.h5"
    pol = polarity_packet([10], [20], [30], [1])
    write_ddd20(path, [frame_packet(8, 8, valid=False), pol, frame_packet(240, 180)])
    assert read_events(path).sensor_size == (240, 180)


def test_empty_recording_and_group_option(tmp_path):
    path = tmp_path / "empty.h5"
    write_ddd20(path, [frame_packet(8, 6)])
    s = read_events(path)
    assert len(s) == 0 and s.sensor_size == (8, 6)
    write_ddd20(path, [])
    with pytest.raises(EventFormatError, match="pass sensor_size"):
        read_events(path)
    assert len(read_events(path, sensor_size=(4, 4), group="dvs")) == 0
    with pytest.raises(EventFormatError, match="do not apply"):
        read_events(path, sensor_size=(4, 4), time_unit="ms")


def _bad(path, packets, match, **kw):
    write_ddd20(path, packets)
    with pytest.raises(EventFormatError, match=match) as err:
        read_events(path, sensor_size=(346, 260), **kw)
    assert str(path) in str(err.value) and "/dvs/data row" in str(err.value)
    assert "byte" in str(err.value)
    return str(err.value)


@pytest.mark.parametrize("edits, match", [
    ({2: 4, 3: 0, 5: 6}, "polarity packet with 4-byte events"),  # eventSize (body still fits)
    ({3: 0}, "time stamp at byte 0"),                            # eventTSOffset
    ({2: 7}, "time-stamp offset 4 outside a 7-byte event"),
    ({4: -1}, "negative ts_overflow"),                           # eventTSOverflow
    ({6: 99}, "eventNumber 99 > eventCapacity"),                 # eventNumber
    ({7: 50}, "eventValid 50 > eventNumber"),                    # eventValid
    ({5: 1000}, "header declares 1000 x 8"),                     # eventCapacity vs body
    ({2: 2}, "event size below 4 bytes"),
    ({0: -3}, "negative type"),
])
def test_malformed_headers_are_clear_errors(tmp_path, edits, match):
    head, body = polarity_packet([10, 20, 30], [1, 2, 3], [1, 2, 3], [0, 1, 0])
    fields = list(struct.unpack("<hhiiiiii", head))
    for field, value in edits.items():
        fields[field] = value
    msg = _bad(tmp_path / "bad.h5", [frame_packet(4, 4), (struct.pack("<hhiiiiii", *fields),
                                                         body)], match)
    assert "row 1" in msg


def test_malformed_bodies_are_clear_errors(tmp_path):
    head, body = polarity_packet([10, 20, 30], [1, 2, 3], [1, 2, 3], [0, 1, 0])
    _bad(tmp_path / "a.h5", [(head, body[:-3])], "body has 21 bytes.*at body byte 21")
    _bad(tmp_path / "b.h5", [(head[:20], body)], "header has 20 bytes")
    neg = bytearray(body)
    struct.pack_into("<i", neg, 12, -5)  # event #1's time stamp
    _bad(tmp_path / "c.h5", [(head, bytes(neg))], r"negative time stamp -5 in event #1 .*"
         r"body byte 12")
    late = polarity_packet([5], [1], [1], [1])
    write_ddd20(tmp_path / "d.h5", [(head, body), late])
    with pytest.raises(EventFormatError, match="backwards at event #3"):
        read_events(tmp_path / "d.h5", sensor_size=(8, 8))


def test_invalid_events_and_unused_capacity_are_dropped(tmp_path):
    head, body = polarity_packet([10, 20, 30], [1, 2, 3], [4, 5, 6], [1, 0, 1],
                                 valid=[True, False, True], capacity=5)
    spare = bytearray(body)
    struct.pack_into("<Ii", spare, 24, (9 << 17) | 1, 40)  # a valid-looking slot past number
    path = tmp_path / "v.h5"
    write_ddd20(path, [(head, bytes(spare))])
    s = read_events(path, sensor_size=(16, 16))
    assert s.events["t"].tolist() == [10, 30] and s.events["x"].tolist() == [1, 3]
    assert s.events["y"].tolist() == [4, 6] and s.events["p"].tolist() == [1, 1]


def test_eval_frames_from_a_ddd20_file(tmp_path):
    """The frames eval builds from a DDD20 file equal those of an .npz of the oracle's events."""
    from torchseq.events import EventStream, load_event_frames, make_events, write_npz

    path = tmp_path / "rec.hdf5"
    write_ddd20(path, _recording(seed=5, crossing=False))
    write_npz(tmp_path / "same.npz", EventStream(make_events(*oracle(path)), (346, 260)))
    frames = load_event_frames(path, duration_ms=10)
    assert frames.shape[-2:] == (260, 346) and frames.abs().sum() > 0
    assert frames.equal(load_event_frames(tmp_path / "same.npz", duration_ms=10))


@pytest.mark.slow
def test_torchseq_eval_on_ddd20_files_matches_the_same_events_as_aedat(tmp_path, capsys):
    """eval on the real DVS128 recording, rewritten as DDD20 packets, gives the AEDAT's metrics."""
    import json

    from cli_helpers import run_inprocess
    from conftest import shared_data

    aedat = shared_data("events", "alex_walking_again.aedat")
    s = read_events(aedat)
    path = tmp_path / "rec.hdf5"
    write_ddd20(path, polarity_packets(s.events), attrs={"width": 128, "height": 128})
    assert np.array_equal(read_events(path).events, s.events)
    metrics = []
    for src in (aedat, path):
        out = tmp_path / src.suffix[1:]
        code, err = run_inprocess("eval", capsys, "--engine", "seqslam", "--reference",
                                  str(src), "--query", str(src), "--tolerance", "2",
                                  "--frame-size", "16x16", "--image-size", "16x16",
                                  "--patch-size", "4", "--out", str(out), "--no-tensorboard")
        assert code == 0, err
        metrics.append(json.loads((out / "metrics.json").read_text())["seqslam"])
    assert metrics[0]["n_queries"] == 689
    assert metrics[1]["n_queries"] == 689 and metrics[1]["recall_at_1"] == metrics[0][
        "recall_at_1"]


# --- fuzz: mutated packets give the oracle's events or an EventFormatError -------------------

@st.composite
def _mutation(draw, n_rows):
    row = draw(st.integers(0, n_rows - 1))
    col = draw(st.sampled_from([1, 2]))  # header or body
    kind = draw(st.sampled_from(["flip", "int", "cut", "insert", "empty"]))
    return row, col, kind, draw(st.integers(0, 1 << 16)), draw(st.integers(-(2**31), 2**31 - 1))


def _mutate(packets, muts):
    rows = [[bytearray(h), bytearray(b)] for h, b in packets]
    for row, col, kind, pos, val in muts:
        buf = rows[row][col - 1]
        at = pos % (len(buf) + 1)
        if kind == "flip" and buf:
            buf[at % len(buf)] ^= 1 << (val & 7)
        elif kind == "int" and len(buf) >= 4:
            at = at % (len(buf) - 3) // 4 * 4 if col == 2 else at % (len(buf) - 3)
            struct.pack_into("<i", buf, at, val)
        elif kind == "cut":
            del buf[at:]
        elif kind == "insert":
            buf[at:at] = bytes([val & 255])
        elif kind == "empty":
            del buf[:]
    return [(bytes(h), bytes(b)) for h, b in rows]


SEED = _recording(seed=7, n_packets=5)


@pytest.mark.slow
@settings(max_examples=300, deadline=None, suppress_health_check=list(HealthCheck))
@given(muts=st.lists(_mutation(len(SEED)), min_size=1, max_size=3),
       chunk=st.sampled_from([3, 1 << 20]))
def test_fuzz_mutated_packets(tmp_path_factory, muts, chunk):
    path = tmp_path_factory.mktemp("fz") / "m.h5"
    write_ddd20(path, _mutate(SEED, muts))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a damaged frame: size from the coordinates
            s = read_events(path, chunk_events=chunk)
    except EventFormatError as err:
        assert str(path) in str(err)
        with pytest.raises(EventFormatError), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            list(iter_events(path, 5))
        return
    w, h = s.sensor_size
    ev = s.events
    assert 1 <= w <= 32768 and 1 <= h <= 32768
    assert (ev["x"] >= 0).all() and (ev["x"] < w).all() and (ev["y"] >= 0).all()
    assert (ev["y"] < h).all() and np.isin(ev["p"], (0, 1)).all()
    assert (np.diff(ev["t"]) >= 0).all()
    assert [ev[k].tolist() for k in "txyp"] == [list(c) for c in oracle(path)]


def test_rows_are_bounded_by_the_stored_chunks(tmp_path):
    """A dataset declaring 10^12 rows reads only the rows its allocated chunks hold."""
    from torchseq.events.libcaer import PacketRows

    path = tmp_path / "grown.h5"
    write_ddd20(path, _recording(seed=2, n_packets=3))
    want = _events(path)[1]
    with h5py.File(path, "a") as f:
        f["dvs/data"].resize(10**12, axis=0)
    with h5py.File(path, "r") as f:
        assert PacketRows(f["dvs/data"], "x").n == 128  # one allocated chunk
    assert _events(path)[1] == want
    flat = tmp_path / "flat.h5"
    write_ddd20(flat, _recording(seed=2, n_packets=3), chunked=False)
    with h5py.File(flat, "r") as f:  # an unchunked dataset must store every row
        assert PacketRows(f["dvs/data"], "x").n == f["dvs/data"].shape[0]


def test_heap_reader_dispatch_and_gzip_fallback(tmp_path):
    """Unfiltered chunked/contiguous datasets are read from the file's bytes (checked heap);
    a compressed one through h5py; all three give the oracle's events."""
    from torchseq.events.libcaer import PacketRows

    packets = _recording(seed=4, n_packets=4)
    for name, chunked, direct in (("c.h5", True, True), ("f.h5", False, True)):
        write_ddd20(tmp_path / name, packets, chunked=chunked)
        with h5py.File(tmp_path / name, "r") as f:
            assert PacketRows(f["dvs/data"], "x").reader.direct is direct
    gz = tmp_path / "gz.h5"
    with h5py.File(tmp_path / "c.h5", "r") as src, h5py.File(gz, "w") as f:
        f.create_dataset("dvs/data", data=src["dvs/data"][()], compression="gzip",
                         chunks=(128, 3))
    with h5py.File(gz, "r") as f:
        assert PacketRows(f["dvs/data"], "x").reader.direct is False
    want = [list(c) for c in oracle(tmp_path / "c.h5")]
    for name in ("c.h5", "f.h5", "gz.h5"):
        assert _events(tmp_path / name)[1] == want


def _patch(path, offset, data):
    raw = bytearray(path.read_bytes())
    raw[offset:offset + len(data)] = data
    path.write_bytes(bytes(raw))


@pytest.mark.parametrize("damage, match", [
    ("collection size", "beyond the end of the file"),
    ("signature", "no global heap collection"),
    ("element length", "refers to heap object"),
    ("element shorter", "which holds 28 bytes"),
    ("object size", "overruns its collection"),
])
def test_damaged_heap_is_a_clear_error_not_a_hang(tmp_path, damage, match):
    """One damaged byte in a heap collection header made h5py hang (the byte fuzz found it);
    the checked reader names the row instead."""
    from torchseq.events.libcaer import PacketRows

    path = tmp_path / "h.h5"
    write_ddd20(path, [polarity_packet([1, 2], [1, 2], [1, 2], [0, 1])])
    with h5py.File(path, "r") as f:
        rows = PacketRows(f["dvs/data"], "x")
        ref = rows.reader._refs(0, 1)[0, 1]  # row 0's header
        chunk = f["dvs/data"].id.get_chunk_info_by_coord((0, 0)).byte_offset
    addr = int(ref["addr"])
    if damage == "collection size":
        _patch(path, addr + 8, struct.pack("<Q", 1 << 40))
    elif damage == "signature":
        _patch(path, addr, b"XCOL")
    elif damage.startswith("element"):  # row 0, column 1: 28 -> 29 or 27 bytes
        _patch(path, chunk + 16, struct.pack("<I", 29 if damage == "element length" else 27))
    else:  # the first object's size field
        _patch(path, addr + 16 + 8, struct.pack("<Q", 1 << 30))
    with pytest.raises(EventFormatError, match=match) as err:
        read_events(path, sensor_size=(8, 8))
    assert str(path) in str(err.value)


@settings(max_examples=200, deadline=None, suppress_health_check=list(HealthCheck))
@given(edits=st.lists(st.tuples(st.integers(0, 1 << 20), st.integers(0, 255)), min_size=1,
                      max_size=4))
@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_fuzz_damaged_bytes_of_the_hdf5_file(tmp_path_factory, edits):
    """Bytes of the whole file overwritten (metadata, chunks, heap): data or a clear error."""
    d = tmp_path_factory.mktemp("fb")
    seed = d / "seed.h5"
    write_ddd20(seed, SEED)
    raw = bytearray(seed.read_bytes())
    for pos, val in edits:
        raw[pos % len(raw)] = val
    path = d / "m.h5"
    path.write_bytes(bytes(raw))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            s = read_events(path)
    except EventFormatError as err:
        assert str(path) in str(err)
        return
    ev = s.events
    assert (ev["x"] < s.sensor_size[0]).all() and (ev["y"] < s.sensor_size[1]).all()
    assert (np.diff(ev["t"]) >= 0).all()

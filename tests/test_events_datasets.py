"""Field-dataset layouts: HDF5 (NSAVP, DSEC/DDD20 exports, events/xs), Parquet, ground truth.

The files are made here in each layout with h5py / pyarrow; the expected events are the
arrays written, converted by hand (ns -> us by integer division, seconds -> us rounded).
"""

import warnings

import numpy as np
import pytest

from torchseq.events import EventFormatError, EventStream, iter_events, make_events, read_events
from torchseq.events.positions import (
    geodetic_to_ecef,
    ground_truth_within,
    positions_at,
    window_times,
)
from torchseq.ground_truth import GroundTruthError

try:
    import h5py
except ImportError:  # the hdf5 extra is absent: its tests skip with the reason
    h5py = None
try:
    import pyarrow as pa
except ImportError:
    pa = None
needs_h5py = pytest.mark.skipif(h5py is None,
                                reason="h5py not installed (pip install 'torchseq[hdf5]')")
needs_pyarrow = pytest.mark.skipif(pa is None,
                                   reason="pyarrow not installed (pip install 'torchseq[parquet]')")


def sample(n=500, w=40, h=30, seed=0):
    rng = np.random.default_rng(seed)
    return make_events(np.sort(rng.integers(0, 200_000, n)) + 1_000_000, rng.integers(0, w, n),
                       rng.integers(0, h, n), rng.integers(0, 2, n))


def write_nsavp(path, ev, w=40, h=30):
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        g.attrs["width"], g.attrs["height"] = w, h
        g.create_dataset("timestamps", data=ev["t"].astype(np.uint64) * 1000 + 999,
                         chunks=(64,), compression="gzip")
        g["timestamps"].attrs["units"] = "nanoseconds"
        g.create_dataset("x_coordinates", data=ev["x"].astype(np.uint16), chunks=(64,))
        g.create_dataset("y_coordinates", data=ev["y"].astype(np.uint16), chunks=(64,))
        g.create_dataset("polarities", data=ev["p"].astype(np.uint8), chunks=(64,))


@needs_h5py
def test_nsavp_layout_whole_and_chunked(tmp_path):
    ev = sample()
    write_nsavp(tmp_path / "R0_FA0_dvxplorer_left.h5", ev)
    s = read_events(tmp_path / "R0_FA0_dvxplorer_left.h5")
    assert s.sensor_size == (40, 30)
    np.testing.assert_array_equal(s.events, ev)  # 999 ns dropped by integer division
    chunks = list(iter_events(tmp_path / "R0_FA0_dvxplorer_left.h5", chunk_events=7))
    assert len(chunks) == -(-len(ev) // 7)
    np.testing.assert_array_equal(np.concatenate([c.events for c in chunks]), ev)


@needs_h5py
def test_dsec_layout_offset_and_inferred_size(tmp_path):
    ev = sample(seed=1)
    with h5py.File(tmp_path / "events.h5", "w") as f:
        f.create_dataset("t_offset", data=np.int64(5_000_000))
        g = f.create_group("events")
        for k in "txyp":
            g.create_dataset(k, data=ev[k] - (1_000_000 if k == "t" else 0))
        g.create_dataset("ms_to_idx", data=np.arange(3))
    with pytest.warns(UserWarning, match="no sensor size"):
        s = read_events(tmp_path / "events.h5")
    assert s.sensor_size == (int(ev["x"].max()) + 1, int(ev["y"].max()) + 1)
    np.testing.assert_array_equal(s.events["t"], ev["t"] + 4_000_000)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_events(tmp_path / "events.h5", sensor_size=(64, 48)).sensor_size == (64, 48)


@needs_h5py
def test_float_seconds_matrix_and_compound_layouts(tmp_path):
    ev = sample(seed=2)
    with h5py.File(tmp_path / "xs.h5", "w") as f:
        g = f.create_group("events")
        g.create_dataset("ts", data=ev["t"] / 1e6)
        g.create_dataset("xs", data=ev["x"])
        g.create_dataset("ys", data=ev["y"])
        g.create_dataset("ps", data=np.where(ev["p"] > 0, 1, -1).astype(np.int8))
        f.attrs["sensor_size"] = np.array([40, 30])
    np.testing.assert_array_equal(read_events(tmp_path / "xs.h5").events, ev)
    with h5py.File(tmp_path / "m.h5", "w") as f:
        f.create_dataset("events", data=np.stack([ev[k].astype(np.int64) for k in "txyp"], 1))
    np.testing.assert_array_equal(read_events(tmp_path / "m.h5", sensor_size=(40, 30)).events,
                                  ev)
    comp = np.zeros(len(ev), [("x", "<u2"), ("y", "<u2"), ("p", "<i2"), ("t", "<i8")])
    for k in "txyp":
        comp[k] = ev[k]
    with h5py.File(tmp_path / "c.h5", "w") as f:
        f.create_dataset("CD/events", data=comp)
        f["CD"].attrs["width"], f["CD"].attrs["height"] = 40, 30
    np.testing.assert_array_equal(read_events(tmp_path / "c.h5").events, ev)
    with h5py.File(tmp_path / "named.h5", "w") as f:
        for k, name in zip("txyp", ("stamp", "col", "row", "sign")):
            f.create_dataset(name, data=ev[k])
    got = read_events(tmp_path / "named.h5", sensor_size=(40, 30),
                      columns={"t": "stamp", "x": "col", "y": "row", "p": "sign"})
    np.testing.assert_array_equal(got.events, ev)


@needs_h5py
def test_write_hdf5_round_trip(tmp_path):
    from torchseq.events.hdf5 import write_hdf5

    ev = sample(seed=3)
    write_hdf5(tmp_path / "w.h5", EventStream(ev, (40, 30)))
    s = read_events(tmp_path / "w.h5")
    assert s.sensor_size == (40, 30)
    np.testing.assert_array_equal(s.events, ev)


def bad_file(tmp_path, name, build):
    path = tmp_path / name
    with h5py.File(path, "w") as f:
        build(f)
    return path


@needs_h5py
def test_hdf5_bad_files_raise_event_format_error(tmp_path):
    ev = sample(50)

    def lengths(f):
        for k in "txyp":
            f.create_dataset(f"events/{k}", data=ev[k][: 50 if k != "x" else 49])

    def empty_declared(f):  # contiguous, never written: declares 2 million events, stores 0 bytes
        for k in "txyp":
            f.create_dataset(f"events/{k}", shape=(2_000_000,), dtype="i8")

    def inflated(f):  # compressed, one chunk written, 4 million declared
        for k in "txyp":
            d = f.create_dataset(f"events/{k}", shape=(4_000_000,), dtype="i8", chunks=(1024,),
                                 compression="gzip")
            d[:10] = 1

    def wide(f):
        for k in "txyp":
            f.create_dataset(f"events/{k}", data=ev[k].astype(np.int64) * (70_000 if k == "x"
                                                                           else 1))

    def polarity(f):
        for k in "txyp":
            f.create_dataset(f"events/{k}", data=ev[k].astype(np.int64) * (255 if k == "p"
                                                                           else 1))

    def nan_time(f):
        for k in "txyp":
            f.create_dataset(f"events/{k}", data=np.where(np.arange(50) == 3, np.nan, 1.0)
                             if k == "t" else ev[k])

    def strings(f):
        for k in "txyp":
            f.create_dataset(f"events/{k}", data=np.array([b"a"] * 50))

    def nothing(f):
        f.create_dataset("images", data=np.zeros((2, 3, 3)))

    cases = {"lengths": (lengths, "lengths differ"), "empty": (empty_declared, "declares"),
             "inflated": (inflated, "declares"), "wide": (wide, "x outside"),
             "polarity": (polarity, "polarity"), "nan": (nan_time, "finite"),
             "strings": (strings, "numbers|integers"), "nothing": (nothing, "no group")}
    for name, (build, match) in cases.items():
        path = bad_file(tmp_path, f"{name}.h5", build)
        with pytest.raises(EventFormatError, match=match):
            read_events(path, sensor_size=(40, 30))
    good = tmp_path / "good.h5"
    write_nsavp(good, sample(5000))
    data = good.read_bytes()
    for cut in (len(data) // 2, len(data) - 100, 600):
        (tmp_path / "cut.h5").write_bytes(data[:cut])
        with pytest.raises(EventFormatError):
            read_events(tmp_path / "cut.h5")
    with pytest.raises(ValueError, match="time_unit"):
        read_events(good, time_unit="hours")


@needs_pyarrow
def test_parquet_round_trip_and_brisbane_style_tables(tmp_path):
    import pyarrow.parquet as pq

    from torchseq.events.parquet import write_parquet

    ev = sample(seed=4)
    write_parquet(tmp_path / "w.parquet", EventStream(ev, (40, 30)))
    s = read_events(tmp_path / "w.parquet")
    assert s.sensor_size == (40, 30)
    np.testing.assert_array_equal(s.events, ev)
    chunks = list(iter_events(tmp_path / "w.parquet", chunk_events=33))
    np.testing.assert_array_equal(np.concatenate([c.events for c in chunks]), ev)
    # timestamps as an Arrow timestamp[ns] column, polarity as bool, int32 coordinates
    table = pa.table({"timestamp": pa.array(ev["t"].astype(np.int64) * 1000 + 5,
                                            pa.timestamp("ns")),
                      "x": ev["x"].astype(np.int32), "y": ev["y"].astype(np.int32),
                      "polarity": ev["p"].astype(bool)})
    pq.write_table(table, tmp_path / "b.parquet", row_group_size=100)
    with pytest.warns(UserWarning, match="no sensor size"):
        got = read_events(tmp_path / "b.parquet")
    np.testing.assert_array_equal(got.events, ev)
    table = pa.table({"t": ev["t"] / 1e6, "x": ev["x"], "y": ev["y"],
                      "p": np.where(ev["p"] > 0, 1, -1)})
    pq.write_table(table, tmp_path / "s.parquet")
    np.testing.assert_array_equal(read_events(tmp_path / "s.parquet", sensor_size=(40, 30))
                                  .events, ev)


@needs_pyarrow
def test_parquet_bad_files(tmp_path, monkeypatch):
    import pyarrow.parquet as pq

    from torchseq.events import parquet as pqmod

    ev = sample(200, seed=5)
    pq.write_table(pa.table({"t": ev["t"], "x": ev["x"], "y": ev["y"]}), tmp_path / "m.parquet")
    with pytest.raises(EventFormatError, match="no 'p' column"):
        read_events(tmp_path / "m.parquet", sensor_size=(40, 30))
    pq.write_table(pa.table({"t": pa.array([1, None, 3]), "x": [0, 1, 2], "y": [0, 0, 0],
                             "p": [0, 1, 0]}), tmp_path / "null.parquet")
    with pytest.raises(EventFormatError, match="missing"):
        read_events(tmp_path / "null.parquet", sensor_size=(40, 30))
    pq.write_table(pa.table({"t": ev["t"], "x": ev["x"].astype(np.int32) + 40_000, "y": ev["y"],
                             "p": ev["p"]}), tmp_path / "wide.parquet")
    with pytest.raises(EventFormatError, match="x outside"):
        read_events(tmp_path / "wide.parquet", sensor_size=(40, 30))
    ev = sample(1000, seed=5)
    pq.write_table(pa.table({"t": ev["t"], "x": ev["x"], "y": ev["y"], "p": ev["p"]}),
                   tmp_path / "ok.parquet")
    data = (tmp_path / "ok.parquet").read_bytes()
    for cut in (len(data) // 2, len(data) - 10, 8):
        (tmp_path / "cut.parquet").write_bytes(data[:cut])
        with pytest.raises(EventFormatError):
            read_events(tmp_path / "cut.parquet", sensor_size=(40, 30))
    monkeypatch.setattr(pqmod, "MAX_EXPANSION", 0)
    with pytest.raises(EventFormatError, match="declares"):
        read_events(tmp_path / "ok.parquet", sensor_size=(40, 30))


def test_positions_and_ground_truth_against_loops():
    pose_t = np.array([0.0, 1e6, 3e6, 4e6])
    pose = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 20.0], [0.0, 20.0]])
    t = window_times(500_000, 1_000_000, 5)  # centres 1.0, 2.0, 3.0, 4.0, 5.0 s
    np.testing.assert_array_equal(t, [1e6, 2e6, 3e6, 4e6, 5e6])
    got = positions_at(t, pose_t, pose)
    np.testing.assert_allclose(got[:4], [[10, 0], [10, 10], [10, 20], [0, 20]])
    assert np.isnan(got[4]).all()  # after the last pose: no position
    ref = np.random.default_rng(0).uniform(0, 30, (7, 2))
    gt = ground_truth_within(ref, got, 8.0)
    for i in range(7):
        for j in range(5):
            d = np.hypot(*(ref[i] - got[j])) if np.isfinite(got[j]).all() else np.inf
            assert gt[i, j] == (d <= 8.0)
    assert not gt[:, 4].any()
    # WGS84: equator/prime meridian at (a, 0, 0); the pole at (0, 0, b); 0.001 deg of
    # latitude at the equator is 110.574 m (published meridian arc: 110,574 m per degree)
    e = geodetic_to_ecef([0, 90, 0], [0, 0, 0], [0, 0, 0])
    np.testing.assert_allclose(e[0], [6_378_137.0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(e[1], [0, 0, 6_356_752.314], atol=1e-3)
    d = np.linalg.norm(geodetic_to_ecef(0.001, 0) - geodetic_to_ecef(0.0, 0))
    assert abs(d - 110.574) < 0.01
    with pytest.raises(GroundTruthError):
        positions_at(t, pose_t[::-1], pose)
    with pytest.raises(GroundTruthError):
        ground_truth_within(ref, got[:, :1], 1.0)


@needs_h5py
def test_nsavp_poses_to_event_frame_ground_truth(tmp_path):
    from torchseq.events import load_event_frames
    from torchseq.events.frames import window_origin
    from torchseq.events.hdf5 import read_hdf5_positions

    ev = sample(3000, seed=6)
    write_nsavp(tmp_path / "dvs.h5", ev)
    with h5py.File(tmp_path / "applanix.h5", "w") as f:
        g = f.create_group("pose_base_link")
        g.create_dataset("timestamps", data=np.arange(0, 2_000_000, 100_000, dtype=np.uint64)
                         * 1000)
        g["timestamps"].attrs["units"] = "nanoseconds"
        g.create_dataset("positions", data=np.c_[np.arange(20) * 1.5, np.zeros((20, 2))])
        g.create_dataset("quaternions", data=np.zeros((20, 4)))
    pose_t, pose = read_hdf5_positions(tmp_path / "applanix.h5")
    np.testing.assert_array_equal(pose_t, np.arange(0, 2_000_000, 100_000))
    frames = load_event_frames(tmp_path / "dvs.h5", window_ms=20.0, anchor=1_000_000)
    origin = window_origin(ev["t"], 1_000_000)
    centres = window_times(origin, 20_000, len(frames))
    pos = positions_at(centres, pose_t, pose)
    np.testing.assert_allclose(pos[:, 0], centres * 1.5e-5)  # 1.5 m per 0.1 s
    gt = ground_truth_within(pos, pos, 0.31)
    assert gt.sum(0).tolist()[1:-1] == [3] * (len(frames) - 2)  # itself and one each side


@needs_h5py
@needs_pyarrow
def test_load_traverse_reads_field_layouts(tmp_path):
    from torchseq import EventFrameOptions, load_traverse
    from torchseq.events import accumulate
    from torchseq.events.hdf5 import write_hdf5
    from torchseq.events.parquet import write_parquet

    ev = sample(2000, seed=7)
    s = EventStream(ev, (40, 30))
    write_hdf5(tmp_path / "e.hdf5", s)
    write_parquet(tmp_path / "e.parquet", s)
    want = accumulate(s, window_us=10_000, mode="count").clamp(0, 255)
    for name in ("e.hdf5", "e.parquet"):
        got = load_traverse(tmp_path / name, EventFrameOptions(window_ms=10.0), progress=False)
        assert torch_equal(got, want)


def torch_equal(a, b):
    return a.shape == b.shape and bool((a == b).all())


@needs_h5py
@needs_pyarrow
@pytest.mark.parametrize("suffix", [".h5", ".parquet"])
def test_mutated_files_give_valid_events_or_event_format_error(tmp_path, suffix):
    """Truncations, byte flips, insertions and hostile 8-byte values in real-layout files."""
    from torchseq.events.hdf5 import write_hdf5
    from torchseq.events.parquet import write_parquet
    from torchseq.events.stream import validate_events

    rng = np.random.default_rng(11)
    good = tmp_path / f"good{suffix}"
    (write_hdf5 if suffix == ".h5" else write_parquet)(good, EventStream(sample(300), (40, 30)))
    data = good.read_bytes()
    for i in range(80):
        m = bytearray(data)
        kind = i % 4
        if kind == 0:
            m = m[:rng.integers(0, len(m))]
        elif kind == 1:
            for _ in range(rng.integers(1, 8)):
                m[rng.integers(0, len(m))] = rng.integers(0, 256)
        elif kind == 2:
            at = rng.integers(0, len(m))
            m[at:at] = rng.integers(0, 256, rng.integers(1, 16)).astype(np.uint8).tobytes()
        else:
            at = rng.integers(0, len(m) - 8)
            m[at:at + 8] = np.array([rng.integers(-2**62, 2**62)], "<i8").tobytes()
        path = tmp_path / f"m{i}{suffix}"
        path.write_bytes(bytes(m))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                s = read_events(path)
        except EventFormatError:
            continue
        validate_events(s.events, s.sensor_size)  # data that holds the invariants

"""The one float-time rule (torchseq.events.times), through every reader that meets float times.

Expected microseconds come from a plain per-element loop over Python floats (seconds times
10**6, rounded half to even as NumPy does), written here independently of the library.
"""

import warnings

import numpy as np
import pytest

from torchseq.events import EventFormatError, accumulate, iter_events, make_events, read_events
from torchseq.events.times import FLOAT_SECONDS_BELOW, float_time_unit, float_times_to_us

try:
    import h5py
except ImportError:
    h5py = None
try:
    import pyarrow as pa
    import pyarrow.parquet as pq
except ImportError:
    pa = None
needs_h5py = pytest.mark.skipif(h5py is None, reason="h5py not installed (torchseq[hdf5])")
needs_pyarrow = pytest.mark.skipif(pa is None, reason="pyarrow not installed (torchseq[parquet])")

FLOAT_DTYPE = [("t", "<f8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")]


def loop_us(seconds):
    return np.array([round(float(s) * 1_000_000) for s in seconds], np.int64)


def events_with(t):
    n = len(t)
    rng = np.random.default_rng(n)
    arr = np.zeros(n, FLOAT_DTYPE)
    arr["t"], arr["x"], arr["y"], arr["p"] = t, rng.integers(0, 8, n), rng.integers(0, 4, n), \
        rng.integers(0, 2, n)
    return arr


def seconds(n=300, start=0.0):
    return start + np.sort(np.random.default_rng(1).integers(0, 2_000_000, n)) / 1e6 + 1.25e-4


def want_events(arr, t_us):
    return make_events(t_us, arr["x"], arr["y"], arr["p"])


def read_quietly_counting(read):
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        out = read()
    return out, [str(w.message) for w in got if "float timestamps" in str(w.message)]


def test_rule_table():
    s = seconds()
    with pytest.warns(UserWarning, match="read as seconds"):
        assert float_time_unit(s) == "s"
    with pytest.warns(UserWarning, match="read as seconds"):
        np.testing.assert_array_equal(float_times_to_us(s), loop_us(s))
    whole = np.array([0.0, 5.0, 99_999.0])
    with pytest.warns(UserWarning, match="could be whole seconds"):
        assert float_time_unit(whole) == "us"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # whole numbers too large for seconds: no doubt, no noise
        assert float_time_unit(np.array([1e5, 2e6])) == "us"
        np.testing.assert_array_equal(float_times_to_us(np.array([1e5, 2e6])), [100_000, 2e6])
        # a declared unit is scaled, never guessed
        np.testing.assert_array_equal(float_times_to_us(np.array([1.5, 2.0]), unit="ms"),
                                      [1500, 2000])
    for bad, match in ((np.array([FLOAT_SECONDS_BELOW + 0.5]), "too large to be seconds"),
                       (np.array([1.6e9 + 0.25]), "time_unit='s'"),
                       (np.array([0.5, np.nan]), "NaN"),
                       (np.array([2.0 ** 63]), "beyond int64")):
        with pytest.raises(EventFormatError, match=match):
            float_times_to_us(bad)
    with pytest.raises(EventFormatError, match="beyond int64"):
        float_times_to_us(np.array([1e13]), unit="s")


def test_arrays_npy_and_npz_follow_the_rule(tmp_path):
    arr = events_with(seconds())
    want = want_events(arr, loop_us(arr["t"]))
    with pytest.warns(UserWarning, match="read as seconds"):
        frames = accumulate(arr, (8, 4), window_us=100_000, mode="count")
    assert frames.shape[0] == (want["t"][-1] - want["t"][0]) // 100_000 + 1
    np.save(tmp_path / "e.npy", arr)
    np.savez(tmp_path / "s.npz", events=arr, sensor_size=np.array([8, 4]))
    np.savez(tmp_path / "c.npz", **{k: arr[k] for k in "txyp"}, sensor_size=np.array([8, 4]))
    for name in ("e.npy", "s.npz", "c.npz"):
        got, msgs = read_quietly_counting(
            lambda name=name: read_events(tmp_path / name, sensor_size=(8, 4)))
        np.testing.assert_array_equal(got.events, want, err_msg=name)
        assert len(msgs) == 1 and "read as seconds" in msgs[0], (name, msgs)
    chunks, msgs = read_quietly_counting(
        lambda: list(iter_events(tmp_path / "e.npy", chunk_events=7, sensor_size=(8, 4))))
    np.testing.assert_array_equal(np.concatenate([c.events for c in chunks]), want)
    assert len(msgs) == 1, msgs  # decided once per file, not once per chunk
    # fractional times too large to be seconds: refused in every path
    odd = events_with(seconds() + 2e6)
    np.save(tmp_path / "odd.npy", odd)
    np.savez(tmp_path / "odd.npz", **{k: odd[k] for k in "txyp"}, sensor_size=np.array([8, 4]))
    for name in ("odd.npy", "odd.npz"):
        with pytest.raises(EventFormatError, match="too large to be seconds"):
            read_events(tmp_path / name, sensor_size=(8, 4))


def test_chunks_decide_once(tmp_path):
    # first chunk of whole numbers (read as microseconds), then fractions: refused, not mixed
    t = np.concatenate([np.arange(7, dtype=np.float64) + 200_000, 200_010.5 + np.arange(7)])
    np.save(tmp_path / "mixed.npy", events_with(t))
    with pytest.raises(EventFormatError, match="then have fractions"):
        list(iter_events(tmp_path / "mixed.npy", chunk_events=7, sensor_size=(8, 4)))
    # seconds decided on the first chunk carry on past FLOAT_SECONDS_BELOW (one recording)
    t = FLOAT_SECONDS_BELOW - 0.9375 + np.arange(14) * 0.125  # chunk 2 passes 1e5 s
    np.save(tmp_path / "cross.npy", events_with(t))
    with pytest.warns(UserWarning, match="read as seconds"):
        chunks = list(iter_events(tmp_path / "cross.npy", chunk_events=7, sensor_size=(8, 4)))
    np.testing.assert_array_equal(np.concatenate([c.events["t"] for c in chunks]), loop_us(t))


@needs_h5py
@pytest.mark.parametrize("chunk", [7, 1 << 20])
def test_hdf5_float_times(tmp_path, chunk):
    arr = events_with(seconds())
    want = want_events(arr, loop_us(arr["t"]))

    def write(name, t, units=None):
        with h5py.File(tmp_path / name, "w") as f:
            g = f.create_group("events")
            g.create_dataset("ts", data=t)
            if units:
                g["ts"].attrs["units"] = units
            for k in "xyp":
                g.create_dataset(k + "s", data=arr[k])
            g.attrs["width"], g.attrs["height"] = 8, 4
        return tmp_path / name

    def read(path, **kw):
        return np.concatenate([c.events for c in iter_events(path, chunk_events=chunk, **kw)])

    got, msgs = read_quietly_counting(lambda: read(write("s.h5", arr["t"])))
    np.testing.assert_array_equal(got, want)
    assert len(msgs) == 1 and "read as seconds" in msgs[0], msgs
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # declared: no guess, no warning
        np.testing.assert_array_equal(read(write("u.h5", arr["t"], "seconds")), want)
        np.testing.assert_array_equal(read(tmp_path / "s.h5", time_unit="s"), want)
    # whole-number floats are microseconds, as in .npy (they were seconds here before)
    whole = np.round(arr["t"] * 1e6) + 1e6
    np.testing.assert_array_equal(read(write("w.h5", whole))["t"], whole.astype(np.int64))
    # epoch seconds with fractions: refused unless declared
    epoch = arr["t"] + 1.6e9
    with pytest.raises(EventFormatError, match="too large to be seconds"):
        read(write("e.h5", epoch))
    np.testing.assert_array_equal(read(tmp_path / "e.h5", time_unit="s")["t"], loop_us(epoch))


@needs_pyarrow
@pytest.mark.parametrize("chunk", [7, 1 << 20])
def test_parquet_float_times(tmp_path, chunk):
    arr = events_with(seconds())
    want = want_events(arr, loop_us(arr["t"]))

    def write(name, t):
        table = pa.table({"t": t, "x": arr["x"], "y": arr["y"], "p": arr["p"]})
        pq.write_table(table.replace_schema_metadata({"sensor_size": "8,4"}), tmp_path / name)
        return tmp_path / name

    def read(path, **kw):
        return np.concatenate([c.events for c in iter_events(path, chunk_events=chunk, **kw)])

    got, msgs = read_quietly_counting(lambda: read(write("s.parquet", arr["t"])))
    np.testing.assert_array_equal(got, want)
    assert len(msgs) == 1 and "read as seconds" in msgs[0], msgs
    whole = np.round(arr["t"] * 1e6) + 1e6
    np.testing.assert_array_equal(read(write("w.parquet", whole))["t"], whole.astype(np.int64))
    with pytest.raises(EventFormatError, match="too large to be seconds"):
        read(write("e.parquet", arr["t"] + 1.6e9))
    np.testing.assert_array_equal(read(tmp_path / "e.parquet", time_unit="s")["t"],
                                  loop_us(arr["t"] + 1.6e9))


def test_npy_messages_name_the_file_once(tmp_path):
    np.save(tmp_path / "e.npy", events_with(seconds()))
    with pytest.warns(UserWarning, match=r"e\.npy: float timestamps with fractions"):
        read_events(tmp_path / "e.npy", sensor_size=(8, 4))
    np.save(tmp_path / "odd.npy", events_with(seconds() + 2e6))
    with pytest.raises(EventFormatError) as err:
        read_events(tmp_path / "odd.npy", sensor_size=(8, 4))
    assert str(err.value).count("odd.npy") == 1 and "too large to be seconds" in str(err.value)
    odd = events_with(seconds() + 2e6)
    np.savez(tmp_path / "c.npz", **{k: odd[k] for k in "txyp"}, sensor_size=np.array([8, 4]))
    with pytest.raises(EventFormatError) as err:
        read_events(tmp_path / "c.npz")
    assert str(err.value).count("c.npz") == 1 and "t.npy: " in str(err.value)
    with pytest.warns(UserWarning, match=r"c\.npz: float timestamps with fractions"):
        np.savez(tmp_path / "c.npz", **{k: events_with(seconds())[k] for k in "txyp"},
                 sensor_size=np.array([8, 4]))
        read_events(tmp_path / "c.npz")

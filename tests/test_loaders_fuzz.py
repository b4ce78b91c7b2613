"""Property-based tests: mutated real files give data or the library's error naming the file.

Hypothesis flips, overwrites and truncates bytes of real inputs (a corridor JPEG, frame and
event arrays, event CSVs, ground-truth CSVs and matrices, a VPR-Bench object array) and
checks that ``load_traverse`` / ``load_ground_truth`` either return well-formed data or raise
``TraverseError`` / ``GroundTruthError`` whose message names the file: never a foreign
exception, never NaN frames, never a huge allocation (each example runs under a memory cap).
"""

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchseq.ground_truth import GroundTruthError, load_ground_truth
from torchseq.sources import EventFrameOptions, TraverseError, load_traverse

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
FUZZ = settings(max_examples=40, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])

mutations = st.tuples(
    st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255)), max_size=12),
    st.one_of(st.none(), st.floats(0, 1)),  # truncate to this fraction
)


def mutate(data: bytes, mutation) -> bytes:
    edits, cut = mutation
    b = bytearray(data)
    for where, value in edits:
        b[int(where * len(b))] = value
    if cut is not None:
        b = b[:int(cut * len(b))]
    return bytes(b)


MEMORY_CAP_EXTRA = 3 << 30  # bytes above what the process uses (conftest memory_cap)
pytestmark = pytest.mark.usefixtures("memory_cap")  # conftest: address space capped


def real_jpeg() -> bytes:
    path = DATA / "corridor" / "ref" / "0000000.jpg"
    if path.is_file():
        return path.read_bytes()
    rng = np.random.default_rng(0)
    return cv2.imencode(".jpg", rng.integers(0, 255, (60, 80, 3), dtype=np.uint8))[1].tobytes()


def encoded(tmp_path, name, writer) -> bytes:
    path = tmp_path / name
    writer(path)
    return path.read_bytes()


@pytest.fixture(scope="module")
def originals(tmp_path_factory):
    d = tmp_path_factory.mktemp("orig")
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (4, 6, 8)).astype(np.uint8)
    t = np.sort(rng.integers(0, 50_000, 300)).astype(np.int64)
    ev = np.zeros(300, dtype=[("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "i1")])
    ev["t"], ev["x"], ev["y"], ev["p"] = t, rng.integers(0, 16, 300), \
        rng.integers(0, 16, 300), rng.integers(0, 2, 300)
    gt = np.eye(5, dtype=np.uint8)
    vpr = np.empty(5, dtype=object)
    vpr[:] = [[i] for i in range(5)]
    csv_gt = "query,references\n" + "".join(f"{i},{i} {max(i - 1, 0)}\n" for i in range(5))
    csv_ev = "t,x,y,p\n" + "".join(f"{a},{b},{c},{e}\n" for a, b, c, e in zip(
        ev["t"][:60], ev["x"][:60], ev["y"][:60], ev["p"][:60]))
    return {
        "jpg": real_jpeg(),
        "frames.npy": encoded(d, "f.npy", lambda p: np.save(p, frames)),
        "frames.npz": encoded(d, "f.npz", lambda p: np.savez(p, frames=frames)),
        "events.npy": encoded(d, "e.npy", lambda p: np.save(p, ev)),
        "events.npz": encoded(d, "e.npz", lambda p: np.savez(
            p, events=ev, sensor_size=np.array([16, 16]))),
        "events.csv": csv_ev.encode(),
        "gt.npy": encoded(d, "g.npy", lambda p: np.save(p, gt)),
        "vpr.npy": encoded(d, "v.npy", lambda p: np.save(p, vpr, allow_pickle=True)),
        "gt.csv": csv_gt.encode(),
    }


def check_traverse(path: Path, name_in_message: str, **kw):
    try:
        x = load_traverse(path, progress=False, **kw)
    except TraverseError as err:
        assert name_in_message in str(err), str(err)
        return
    assert isinstance(x, torch.Tensor) and x.dim() == 3 and x.shape[0] >= 1
    assert x.dtype == torch.float32 and bool(torch.isfinite(x).all())


@FUZZ
@given(mutation=mutations)
def test_mutated_image_in_a_folder(originals, tmp_path, mutation):
    folder = tmp_path / "imgs"
    folder.mkdir(exist_ok=True)
    (folder / "a.jpg").write_bytes(originals["jpg"])
    (folder / "b.jpg").write_bytes(mutate(originals["jpg"], mutation))
    check_traverse(folder, "b.jpg")
    x = None
    try:
        x = load_traverse(folder, progress=False)
    except TraverseError:
        return
    assert float(x.min()) >= 0 and float(x.max()) <= 255


@FUZZ
@given(kind=st.sampled_from(["frames.npy", "frames.npz", "events.npy", "events.npz",
                             "events.csv"]), mutation=mutations)
def test_mutated_arrays_and_event_files(originals, tmp_path, kind, mutation):
    path = tmp_path / f"m_{kind}"
    path.write_bytes(mutate(originals[kind], mutation))
    check_traverse(path, path.name, events=EventFrameOptions(window_ms=5.0))


@FUZZ
@given(kind=st.sampled_from(["gt.npy", "vpr.npy", "gt.csv"]), mutation=mutations)
def test_mutated_ground_truth(originals, tmp_path, kind, mutation):
    path = tmp_path / f"m_{kind}"
    path.write_bytes(mutate(originals[kind], mutation))
    try:
        gt = load_ground_truth(path, 5, 5)
    except GroundTruthError as err:
        assert path.name in str(err), str(err)
        return
    assert gt.dtype == bool and gt.shape == (5, 5)


@FUZZ
@given(shape=st.lists(st.integers(0, 2 ** 62), min_size=0, max_size=4),
       descr=st.sampled_from(["<f4", "|u1", "<i8", "<f8"]))
def test_headers_declaring_any_shape(tmp_path, shape, descr):
    path = tmp_path / "h.npy"
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": descr, "fortran_order": False, "shape": tuple(shape)})
        f.write(bytes(256))
    check_traverse(path, "h.npy")
    try:
        load_ground_truth(path, 4, 4)
    except GroundTruthError as err:
        assert "h.npy" in str(err)


@FUZZ
@given(times=st.lists(st.integers(0, 2**42), min_size=1, max_size=6),
       window_ms=st.sampled_from([0.05, 1.0, 10.0, 1000.0]),
       suffix=st.sampled_from([".npz", ".aedat"]))
def test_event_times_of_any_span(tmp_path, times, window_ms, suffix):
    """Issue 23 item 1: frames follow the events present; a span too sparse to hold is refused
    by name (never a MemoryError from a dense allocation sized by the time span)."""
    from torchseq.events import EventStream, make_events, write_aedat2

    t = np.sort(np.array(times, dtype=np.int64))
    n = len(t)
    ev = make_events(t, np.arange(n) % 128, np.arange(n) % 128, np.arange(n) % 2)
    path = tmp_path / f"span{suffix}"
    if suffix == ".npz":
        np.savez(path, events=ev, sensor_size=np.array([128, 128]))
    else:
        t = t % 2**32  # AEDAT 2.0 stores time modulo 2**32 (the reader unwraps)
        if (t[1:] < t[:-1]).any():
            return
        write_aedat2(path, EventStream(make_events(t, ev["x"], ev["y"], ev["p"]), (128, 128)))
    opts = EventFrameOptions(window_ms=window_ms)
    try:
        x = load_traverse(path, events=opts, progress=False, size=(16, 16))
    except TraverseError as err:
        assert path.name in str(err), str(err)
        assert not isinstance(err.__cause__, MemoryError), str(err)
        return
    window = max(1, round(window_ms * 1000))
    assert x.shape == ((int(t[-1]) - int(t[0])) // window + 1, 16, 16)
    assert float(x.sum()) > 0 and bool(torch.isfinite(x).all())


@FUZZ
@given(dtype=st.sampled_from(["|u1", "|i1", "<u2", "<i4", "<i8", "<u8", "<f2", "<f4", "<f8"]),
       raw=st.binary(min_size=24 * 8, max_size=24 * 8), suffix=st.sampled_from([".npy", ".npz"]))
def test_frame_arrays_of_any_values(tmp_path, dtype, raw, suffix):
    """Issue 23 item 2: frame arrays of any values load as 0..255 grey levels unchanged or
    are refused by name."""
    frames = np.frombuffer(raw, dtype=dtype)[:24].reshape(2, 3, 4)
    path = tmp_path / f"values{suffix}"
    if suffix == ".npz":
        np.savez(path, frames=frames)
    else:
        np.save(path, frames)
    try:
        x = load_traverse(path, progress=False)
    except TraverseError as err:
        assert path.name in str(err), str(err)
        return
    assert float(x.min()) >= 0 and float(x.max()) <= 255
    np.testing.assert_array_equal(x.numpy(), frames.astype(np.float32))

import cv2
import numpy as np
import pytest
import torch
from conftest import shared_data

from torchseq.ground_truth import (
    GroundTruthError,
    alignment_ground_truth,
    load_ground_truth,
)
from torchseq.sources import TraverseError, load_traverse, natural_key


def write_images(folder, frames, names=None):
    folder.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / (names[i] if names else f"{i}.png")), f)


def test_image_folder_natural_order_and_grey(tmp_path):
    frames = [np.full((8, 12, 3), v, np.uint8) for v in (10, 20, 30)]
    frames[1][..., 2] = 200  # OpenCV is BGR: channel 2 is red
    write_images(tmp_path / "t", frames, ["img2.png", "img10.png", "img1.png"])
    x = load_traverse(tmp_path / "t", progress=False)
    assert x.shape == (3, 8, 12) and x.dtype == torch.float32
    # natural order: img1 (30), img2 (10), img10 (red 200, green/blue 20)
    assert x[0, 0, 0] == 30 and x[1, 0, 0] == 10
    assert abs(float(x[2, 0, 0]) - (0.299 * 200 + 0.587 * 20 + 0.114 * 20)) < 1.0
    assert sorted(["a10", "a2", "a1"], key=natural_key) == ["a1", "a2", "a10"]


def test_image_folder_errors(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(TraverseError, match="no images"):
        load_traverse(tmp_path / "empty", progress=False)
    write_images(tmp_path / "mixed", [np.zeros((8, 8), np.uint8), np.zeros((9, 8), np.uint8)])
    with pytest.raises(TraverseError, match="mixed image sizes"):
        load_traverse(tmp_path / "mixed", progress=False)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "0.png").write_bytes(b"not a png")
    with pytest.raises(TraverseError, match="cannot read image"):
        load_traverse(tmp_path / "bad", progress=False)
    with pytest.raises(TraverseError, match="no such file"):
        load_traverse(tmp_path / "missing", progress=False)


def test_arrays_and_array_files(tmp_path):
    a = np.random.default_rng(0).integers(0, 255, (4, 6, 7)).astype(np.uint8)
    assert torch.equal(load_traverse(a), torch.from_numpy(a).float())
    np.save(tmp_path / "f.npy", a)
    assert torch.equal(load_traverse(tmp_path / "f.npy"), torch.from_numpy(a).float())
    np.savez(tmp_path / "f.npz", frames=a)
    assert torch.equal(load_traverse(tmp_path / "f.npz"), torch.from_numpy(a).float())
    with pytest.raises(TraverseError, match="NaN"):
        load_traverse(np.full((2, 3, 3), np.nan))
    with pytest.raises(TraverseError, match="must be"):
        load_traverse(np.zeros((3, 3)))
    with pytest.raises(TraverseError, match="no frames"):
        load_traverse(np.zeros((0, 3, 3)))


def test_video_round_trip(tmp_path):
    path = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (32, 24))
    if not writer.isOpened():
        pytest.skip("OpenCV build cannot write MJPG video here")
    for v in (30, 120, 220):
        writer.write(np.full((24, 32, 3), v, np.uint8))
    writer.release()
    x = load_traverse(path, progress=False)
    assert x.shape == (3, 24, 32)
    assert [round(float(f.mean()) / 10) for f in x] == [3, 12, 22]


def test_corridor_loads():
    x = load_traverse(shared_data("corridor", "ref"), progress=False)
    assert x.shape == (111, 120, 160)


def test_alignment_ground_truth():
    gt = alignment_ground_truth(11, 21, 1.0)
    assert gt.shape == (11, 21)
    assert gt[:, 0].nonzero()[0].tolist() == [0, 1]
    assert gt[:, 10].nonzero()[0].tolist() == [4, 5, 6]
    assert gt[:, 20].nonzero()[0].tolist() == [9, 10]


def test_ground_truth_files(tmp_path):
    csv = tmp_path / "gt.csv"
    csv.write_text("query,references\n0,0 1\n1,1\n2,\n")
    gt = load_ground_truth(csv, 3, 3)
    assert gt.tolist() == [[True, False, False], [True, True, False], [False, False, False]]
    with pytest.raises(GroundTruthError, match="covers 3 queries"):
        load_ground_truth(csv, 3, 4)
    with pytest.raises(GroundTruthError, match="outside"):
        load_ground_truth(csv, 1, 3)
    np.save(tmp_path / "gt.npy", np.eye(3, dtype=np.int64))
    assert load_ground_truth(tmp_path / "gt.npy", 3, 3).sum() == 3
    with pytest.raises(GroundTruthError, match=r"\(3, 3\)"):
        load_ground_truth(tmp_path / "gt.npy", 3, 4)
    (tmp_path / "bad.csv").write_text("a,b\n")
    with pytest.raises(GroundTruthError, match="header"):
        load_ground_truth(tmp_path / "bad.csv", 3, 3)


def test_real_ground_truth_files():
    gt = load_ground_truth(shared_data("corridor", "ground_truth.csv"), 111, 111)
    assert gt[:, 0].nonzero()[0].tolist() == [0, 1, 2]  # the file's first row
    assert gt[:, 50].nonzero()[0].tolist() == [48, 49, 50, 51, 52]
    lens = shared_data("lens-davis128", "example-reference_example-query_GT.npy")
    assert np.array_equal(load_ground_truth(lens, 100, 100), np.eye(100, dtype=bool))


# ---------------------------------------------------------------- ground truth, robustness


def test_vpr_bench_per_query_ground_truth_without_pickle(tmp_path):
    # VPR-Bench stores admissible references per query as an object array (a pickle)
    rows = np.empty((3, 2), dtype=object)
    rows[:, 0] = [0, 1, 2]
    rows[0, 1], rows[1, 1], rows[2, 1] = [0, 1], np.array([2]), 3
    np.save(tmp_path / "gt_rows.npy", rows, allow_pickle=True)
    gt = load_ground_truth(tmp_path / "gt_rows.npy", 4, 3)
    expect = np.zeros((4, 3), bool)
    expect[[0, 1], 0] = expect[2, 1] = expect[3, 2] = True
    assert np.array_equal(gt, expect)
    flat = np.empty(3, dtype=object)
    flat[:] = [[0, 1], [2], [3]]
    np.save(tmp_path / "gt_flat.npy", flat, allow_pickle=True)
    assert np.array_equal(load_ground_truth(tmp_path / "gt_flat.npy", 4, 3), expect)
    with pytest.raises(GroundTruthError, match="reference 9 outside"):
        flat[2] = [9]
        np.save(tmp_path / "bad.npy", flat, allow_pickle=True)
        load_ground_truth(tmp_path / "bad.npy", 4, 3)


class Boom:
    """A pickled payload that would run code if unpickled naively."""

    def __reduce__(self):
        return (open, ("/tmp/torchseq-pwned", "w"))


def test_object_arrays_never_run_a_pickle(tmp_path):
    import os

    a = np.empty(2, dtype=object)
    a[:] = [Boom(), [1]]
    np.save(tmp_path / "evil.npy", a, allow_pickle=True)
    with pytest.raises(GroundTruthError, match="refusing to load"):
        load_ground_truth(tmp_path / "evil.npy", 4, 2)
    assert not os.path.exists("/tmp/torchseq-pwned")


def test_ground_truth_files_of_the_wrong_kind(tmp_path):
    np.savez(tmp_path / "z.npz", a=np.eye(3))
    (tmp_path / "z.npz").rename(tmp_path / "zip.npy")
    with pytest.raises(GroundTruthError, match="zip archive"):
        load_ground_truth(tmp_path / "zip.npy", 3, 3)
    np.save(tmp_path / "s.npy", np.zeros((3, 3), dtype=[("a", "<i4")]))
    with pytest.raises(GroundTruthError, match="not numeric"):
        load_ground_truth(tmp_path / "s.npy", 3, 3)
    np.save(tmp_path / "c.npy", np.full((3, 3), "x"))
    with pytest.raises(GroundTruthError, match="not numeric"):
        load_ground_truth(tmp_path / "c.npy", 3, 3)
    (tmp_path / "bytes.csv").write_bytes(b"query,references\n0,\xff\xfe 1\n")
    with pytest.raises(GroundTruthError, match="UTF-8"):
        load_ground_truth(tmp_path / "bytes.csv", 3, 1)
    (tmp_path / "nul.csv").write_bytes(b"query,references\n0,\x00 1\n")
    with pytest.raises(GroundTruthError, match="nul.csv"):
        load_ground_truth(tmp_path / "nul.csv", 3, 1)
    with open(tmp_path / "huge.npy", "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "|u1", "fortran_order": False, "shape": (3, 10 ** 14)})
    with pytest.raises(GroundTruthError, match="declares"):
        load_ground_truth(tmp_path / "huge.npy", 3, 10 ** 14 // 10 ** 10)


def test_alignment_offset_and_widening():
    gt = alignment_ground_truth(11, 6, 0, offset=5)  # the query starts at reference 5
    assert [int(np.nonzero(gt[:, j])[0][0]) for j in range(6)] == [5, 6, 7, 8, 9, 10]
    with pytest.raises(GroundTruthError, match="offset"):
        alignment_ground_truth(11, 6, 0, offset=11)
    with pytest.raises(GroundTruthError, match="tolerance"):
        alignment_ground_truth(11, 6, float("nan"))
    from torchseq.ground_truth import widen_ground_truth

    rng = np.random.default_rng(0)
    base = rng.random((30, 7)) < 0.05
    for tol in (0, 1, 2.5, 40):
        wide = widen_ground_truth(base, tol)
        r = int(np.floor(tol))
        loop = np.zeros_like(base)  # the plain definition
        for i in range(30):
            for j in range(7):
                loop[i, j] = base[max(0, i - r):i + r + 1, j].any()
        assert np.array_equal(wide, loop)


def test_ground_truth_file_widened(tmp_path):
    (tmp_path / "gt.csv").write_text("query,references\n0,5\n1,\n")
    gt = load_ground_truth(tmp_path / "gt.csv", 10, 2, widen=2)
    assert np.nonzero(gt[:, 0])[0].tolist() == [3, 4, 5, 6, 7] and not gt[:, 1].any()


def test_damaged_and_unusual_images(tmp_path):
    folder = tmp_path / "t"
    write_images(folder, [np.zeros((8, 8), np.uint8)] * 2)
    good = (folder / "0.png").read_bytes()
    (folder / "1.png").write_bytes(good[:40] + bytes(200) + good[240:])  # damaged
    with pytest.raises(TraverseError, match="1.png"):
        load_traverse(folder, progress=False)
    # 16-bit images are scaled to 0..255, not taken as values up to 65535
    wide = tmp_path / "w"
    write_images(wide, [np.full((4, 4), 65535, np.uint16), np.full((4, 4), 257, np.uint16)])
    x = load_traverse(wide, progress=False)
    assert float(x[0, 0, 0]) == 255.0 and float(x[1, 0, 0]) == 1.0
    # float images must hold finite grey levels
    flt = tmp_path / "f"
    flt.mkdir()
    cv2.imwrite(str(flt / "0.tiff"), np.full((4, 4), np.nan, np.float32))
    with pytest.raises(TraverseError, match="NaN"):
        load_traverse(flt, progress=False)
    cv2.imwrite(str(flt / "0.tiff"), np.full((4, 4), 1000.0, np.float32))
    with pytest.raises(TraverseError, match="outside 0..255"):
        load_traverse(flt, progress=False)


def test_array_files_that_lie_or_hold_the_wrong_thing(tmp_path):
    with open(tmp_path / "huge.npy", "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "<f4", "fortran_order": False, "shape": (10 ** 12, 64, 64)})
        f.write(bytes(100))
    with pytest.raises(TraverseError, match="declares"):
        load_traverse(tmp_path / "huge.npy")
    np.savez(tmp_path / "s.npz", frames=np.zeros((3, 4, 4), dtype=[("a", "<f4")]))
    with pytest.raises(TraverseError, match="numeric"):
        load_traverse(tmp_path / "s.npz")
    (tmp_path / "bad.npz").write_bytes(b"PK\x03\x04" + bytes(100))
    with pytest.raises(TraverseError, match="bad.npz"):
        load_traverse(tmp_path / "bad.npz")
    np.save(tmp_path / "empty.npy", np.zeros((3, 0, 4), np.uint8))
    with pytest.raises(TraverseError, match="empty frames"):
        load_traverse(tmp_path / "empty.npy")
    obj = np.empty((2, 2, 2), dtype=object)
    np.save(tmp_path / "obj.npy", obj, allow_pickle=True)
    with pytest.raises(TraverseError, match="pickle"):
        load_traverse(tmp_path / "obj.npy")


# ---------------------------------------------------------------- streaming, selection


def write_video(path, frames):
    h, w = frames[0].shape
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h))
    for f in frames:
        writer.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    writer.release()


def test_streaming_sizes_equal_resizing_the_whole_traverse(tmp_path):
    from torchseq.preprocess import resize
    from torchseq.sources import load_traverse_sizes

    rng = np.random.default_rng(1)
    frames = [rng.integers(0, 255, (45, 70), dtype=np.uint8) for _ in range(7)]
    write_images(tmp_path / "f", frames)
    full = load_traverse(tmp_path / "f", progress=False)
    got, info = load_traverse_sizes(tmp_path / "f", {"a": (32, 64), "b": (24, 32), "c": None},
                                    progress=False, thumbnail=20)
    assert torch.equal(got["a"], resize(full, (32, 64)))  # bit for bit
    assert torch.equal(got["b"], resize(full, (24, 32)))
    assert torch.equal(got["c"], full)
    assert got["thumbnail"].dtype == torch.uint8 and tuple(got["thumbnail"].shape) == (7, 13, 20)
    assert info == {"n_frames": 7, "frame_size": [45, 70], "indices": list(range(7)),
                    "n_total": 7, "events": False}


@pytest.mark.parametrize("kind", ["folder", "video", "array"])
def test_frame_selection_keeps_the_same_frames_everywhere(tmp_path, kind):
    from torchseq.sources import FrameSelection, load_traverse_sizes

    frames = [np.full((16, 24), 10 * i, np.uint8) for i in range(12)]
    if kind == "folder":
        write_images(tmp_path / "f", frames)
        source = tmp_path / "f"
    elif kind == "video":
        write_video(tmp_path / "v.avi", frames)
        source = tmp_path / "v.avi"
    else:
        source = np.stack(frames)
    select = FrameSelection(start=2, stop=11, step=3, max_frames=2)
    got, info = load_traverse_sizes(source, {"x": None}, progress=False, select=select)
    # kept: 2, 5 (8 would be the third, but max_frames=2)
    assert info["indices"] == [2, 5] and info["n_total"] == 12
    assert [round(float(f.mean()) / 10) for f in got["x"]] == [2, 5]
    with pytest.raises(TraverseError, match="stop"):
        load_traverse(source, select=FrameSelection(start=5, stop=5), progress=False)


def test_tonic_sensor_size_and_event_mode(tmp_path):
    from torchseq.sources import EventFrameOptions

    assert EventFrameOptions(sensor_size=(34, 34, 2)).sensor_size == (34, 34)  # tonic's order
    with pytest.raises(TraverseError, match="sensor_size"):
        EventFrameOptions(sensor_size=(34,))
    ev = np.zeros(4, dtype=[("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "i1")])
    ev["t"], ev["x"], ev["y"], ev["p"] = [0, 1, 2, 3], [1, 1, 1, 2], [0, 0, 0, 0], [1, 1, 0, 1]
    np.save(tmp_path / "e.npy", ev)
    count = load_traverse(tmp_path / "e.npy", EventFrameOptions(
        window_ms=1.0, sensor_size=(4, 2, 2)), progress=False)
    signed = load_traverse(tmp_path / "e.npy", EventFrameOptions(
        window_ms=1.0, sensor_size=(4, 2, 2), mode="signed"), progress=False)
    assert count.shape == (1, 2, 4)  # (H, W) from tonic's (W, H, P)
    assert float(count[0, 0, 1]) == 3 and float(signed[0, 0, 1]) == 1  # 2 ON - 1 OFF


def test_evt3_time_rule_reaches_the_reader():
    from torchseq.sources import EventFrameOptions

    raw = next(iter(sorted(shared_data("events").glob("*.raw"))), None)
    if raw is None:
        pytest.skip("no EVT 3 .raw recording in ../shared/data/events")
    from torchseq.events import load_event_frames

    for rule in ("spec", "carry"):
        got = load_traverse(raw, EventFrameOptions(window_ms=50.0, evt3_time=rule),
                            progress=False)
        assert torch.equal(got, load_event_frames(raw, window_ms=50.0, evt3_time=rule))
    aedat = shared_data("events", "alex_walking_again.aedat")
    with pytest.raises(TraverseError, match=".raw files only"):
        load_traverse(aedat, EventFrameOptions(evt3_time="carry"), progress=False)


def test_window_anchor_reaches_the_accumulator_or_is_refused():
    import inspect

    from torchseq.cli.errors import UsageError
    from torchseq.cli.event_options import parse_anchor
    from torchseq.events import load_event_frames
    from torchseq.sources import EventFrameOptions

    assert parse_anchor("first") == "first" and parse_anchor("1500000") == 1_500_000
    with pytest.raises(UsageError, match="window-anchor"):
        parse_anchor("-3")
    aedat = shared_data("events", "alex_walking_again.aedat")
    opts = EventFrameOptions(window_ms=10.0, anchor="zero")
    if "anchor" in inspect.signature(load_event_frames).parameters:
        assert torch.equal(load_traverse(aedat, opts, progress=False),
                           load_event_frames(aedat, window_ms=10.0, anchor="zero"))
    else:  # an accumulator without anchoring: said, not ignored
        with pytest.raises(TraverseError, match="window anchoring"):
            load_traverse(aedat, opts, progress=False)


def test_tonic_float_seconds_are_converted_never_read_as_microseconds(tmp_path):
    # tonic-style structured events with float seconds: converted (with a warning) to the same
    # frames as the int64 microseconds; never truncated to t = 0 us as a cast would
    from torchseq.events import EventFormatError, accumulate
    from torchseq.sources import EventFrameOptions

    rng = np.random.default_rng(4)
    n = 500
    us = np.sort(rng.integers(0, 50_000, n))
    tonic = np.zeros(n, dtype=[("x", "<i2"), ("y", "<i2"), ("t", "<f8"), ("p", "i1")])
    tonic["t"], tonic["x"], tonic["y"] = us / 1e6, rng.integers(0, 8, n), rng.integers(0, 4, n)
    tonic["p"] = rng.integers(0, 2, n)
    exact = tonic.astype([("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "i1")])
    exact["t"] = us
    want = accumulate(exact, (8, 4), window_us=10_000, mode="count")
    assert want.shape[0] == 5
    with pytest.warns(UserWarning, match="read as seconds"):
        got = accumulate(tonic, (8, 4), window_us=10_000, mode="count")
    assert torch.equal(got, want)
    np.save(tmp_path / "tonic.npy", tonic)
    opts = EventFrameOptions(window_ms=10.0, sensor_size=(8, 4, 2))
    with pytest.warns(UserWarning, match="read as seconds"):
        frames = load_traverse(tmp_path / "tonic.npy", opts, progress=False)
    assert torch.equal(frames, want)
    # whole-number floats are microseconds (a float copy of int times): no conversion
    whole = tonic.copy()
    whole["t"] = us.astype(np.float64)
    assert torch.equal(accumulate(whole, (8, 4), window_us=10_000, mode="count"), want)
    # fractional times too large to be seconds: refused with the library's error
    odd = tonic.copy()
    odd["t"] = us + 0.5 + 1e6
    with pytest.raises(EventFormatError, match="too large to be seconds"):
        accumulate(odd, (8, 4), window_us=10_000)
    np.save(tmp_path / "odd.npy", odd)
    with pytest.raises(TraverseError, match="odd.npy.*too large to be seconds"):
        load_traverse(tmp_path / "odd.npy", opts, progress=False)


def _mixed_folder(folder, n=40, seed=0):
    """Colour, grey and 16-bit PNGs and grey JPEGs, natural names, random content."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        kind = i % 4
        if kind == 0:
            img, ext = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8), "png"
        elif kind == 1:
            img, ext = rng.integers(0, 256, (24, 32), dtype=np.uint8), "png"
        elif kind == 2:
            img, ext = rng.integers(0, 65536, (24, 32), dtype=np.uint16), "png"
        else:
            img, ext = rng.integers(0, 256, (24, 32), dtype=np.uint8), "jpg"
        cv2.imwrite(str(folder / f"f{i}.{ext}"), img)
    return folder


def _plain_decode(folder, n):
    """The reference: one cv2.imread per file, in natural order, by the documented rules."""
    out = []
    for i in range(n):
        path = next(folder.glob(f"f{i}.*"))
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        out.append(img.astype(np.float32) / (np.float32(257) if img.dtype == np.uint16 else 1))
    return np.stack(out)


@pytest.mark.parametrize("workers", [1, 2, 5])
def test_parallel_decode_gives_the_same_frames_bit_for_bit(tmp_path, workers, monkeypatch):
    import threading

    import torchseq.sources as sources

    folder = _mixed_folder(tmp_path / "t")
    want = _plain_decode(folder, 40)
    threads = set()
    decode = sources._decode

    def spy(path):
        threads.add(threading.current_thread().name)
        return decode(path)

    monkeypatch.setattr(sources, "_decode", spy)
    got = sources.load_image_folder(folder, progress=False, workers=workers)
    assert got.dtype == torch.float32 and np.array_equal(got.numpy(), want)
    # the workers really decode (in pool threads; the first file sizes the tasks, here)
    pool = {t for t in threads if t.startswith("torchseq-decode")}
    assert threads - pool == {threading.current_thread().name}
    assert (len(pool) > 0) == (workers > 1) and len(pool) <= workers
    select = sources.FrameSelection(start=3, step=7, max_frames=4)
    x = load_traverse(folder, progress=False, select=select)
    assert np.array_equal(x.numpy(), want[[3, 10, 17, 24]])


def test_parallel_decode_reads_ahead_a_bounded_number_of_frames(tmp_path, monkeypatch):
    import time

    import torchseq.sources as sources

    folder = _mixed_folder(tmp_path / "t", n=60)
    calls = []
    decode = sources._decode
    monkeypatch.setattr(sources, "_decode", lambda p: calls.append(p) or decode(p))
    monkeypatch.setattr(sources, "DECODE_CHUNK", 2)
    frames = sources.iter_image_folder(folder, progress=False, workers=3)
    next(frames)
    next(frames)
    time.sleep(0.3)  # the threads decode whatever they are allowed to
    assert len(calls) <= 1 + (2 * 3 + 1) * 2  # the first, then 2 x workers tasks + 1 ahead
    frames.close()
    # tasks hold at most DECODE_CHUNK_BYTES of frames: big frames go one file a task
    monkeypatch.setattr(sources, "DECODE_CHUNK", 16)
    monkeypatch.setattr(sources, "DECODE_CHUNK_BYTES", 24 * 32 * 4)
    calls.clear()
    frames = sources.iter_image_folder(folder, progress=False, workers=3)
    next(frames)
    next(frames)
    time.sleep(0.3)
    assert len(calls) <= 1 + 2 * 3 + 1
    frames.close()


def test_parallel_decode_names_a_damaged_file_in_its_turn(tmp_path):
    import torchseq.sources as sources

    folder = _mixed_folder(tmp_path / "t", n=30)
    (folder / "f21.png").unlink()
    (folder / "f21.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))  # damaged
    frames = sources.iter_image_folder(folder, progress=False, workers=4)
    got = [next(frames) for _ in range(21)]  # the frames before it arrive
    assert len(got) == 21
    with pytest.raises(TraverseError, match="f21.png"):
        next(frames)
    with pytest.raises(TraverseError, match="decode workers"):
        sources.load_image_folder(folder, progress=False, workers=0)

import numpy as np
import pytest
import torch
from events_oracle import loop_frames, loop_pool

from torchseq import EventFrameOptions, load_traverse
from torchseq.events import (
    EventFormatError,
    EventStream,
    accumulate,
    hot_pixel_mask,
    load_event_frames,
    make_events,
    refractory_mask,
    write_aedat2,
    write_npz,
)
from torchseq.events import frames as frames_module

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device"))]
DTYPES = [torch.float32, torch.float64]


def sample(n=400, w=12, h=8, seed=0, span=100_000):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, span, n))
    return make_events(t, rng.integers(0, w, n), rng.integers(0, h, n), rng.integers(0, 2, n))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("mode", ["signed", "two_channel", "binary", "count"])
@pytest.mark.parametrize("by", ["window", "count"])
def test_accumulate_matches_loop(device, dtype, mode, by):
    ev = sample()
    kw = {"window_us": 7_000} if by == "window" else {"window_us": None, "event_count": 37}
    got = accumulate(EventStream(ev, (12, 8)), mode=mode, device=device, dtype=dtype, **kw)
    ref = loop_frames(ev, 12, 8, kw["window_us"], kw.get("event_count"), mode)
    assert got.dtype == dtype and got.device.type == device
    assert tuple(got.shape) == ref.shape
    np.testing.assert_array_equal(got.cpu().numpy(), ref)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_downsample_is_block_mean(device, dtype):
    ev = sample(2000, 16, 12, seed=3)
    for mode in ("signed", "two_channel"):
        got = accumulate(ev, (16, 12), window_us=20_000, mode=mode, downsample=(3, 4),
                         device=device, dtype=dtype)
        ref = loop_pool(loop_frames(ev, 16, 12, 20_000, None, mode), 3, 4)
        tol = 1e-6 if dtype == torch.float32 else 1e-12
        np.testing.assert_allclose(got.cpu().numpy(), ref, atol=tol)


def test_empty_windows_are_zero_frames_and_no_events_is_an_error():
    ev = make_events([0, 5, 35_000], [0, 1, 2], [0, 0, 1], [1, 0, 1])
    f = accumulate(ev, (3, 2), window_us=10_000, mode="count")
    assert f.shape == (4, 2, 3)
    assert f[1].sum() == 0 and f[2].sum() == 0 and f[0].sum() == 2 and f[3, 1, 2] == 1
    with pytest.raises(EventFormatError, match="no events"):
        accumulate(make_events([], [], [], []), (3, 2))
    with pytest.raises(ValueError, match="mode"):
        accumulate(ev, (3, 2), mode="sum")
    with pytest.raises(ValueError, match="outside|sensor"):
        accumulate(ev, (2, 2))
    with pytest.raises(ValueError, match="downsample"):
        accumulate(ev, (3, 2), downsample=(4, 4))


def test_hot_pixel_filter_against_loop():
    ev = sample(500, 6, 6, seed=5)
    hot = make_events(np.arange(300) * 300, np.full(300, 2), np.full(300, 3), np.ones(300))
    allev = np.concatenate([ev, hot])
    allev = allev[np.argsort(allev["t"], kind="stable")]
    keep = hot_pixel_mask(allev, (6, 6), factor=5.0)
    counts = {}
    for e in allev:
        counts[(e["x"], e["y"])] = counts.get((e["x"], e["y"]), 0) + 1
    med = np.median(list(counts.values()))
    ref = [counts[(e["x"], e["y"])] <= 5.0 * med for e in allev]
    assert keep.tolist() == ref and not keep[(allev["x"] == 2) & (allev["y"] == 3)].any()
    f = accumulate(allev, (6, 6), window_us=None, event_count=10_000, mode="count", hot_pixel=5.0)
    assert f[0, 3, 2] == 0 and f.sum() == keep.sum()


def test_refractory_filter_against_loop():
    rng = np.random.default_rng(7)
    n = 3000
    ev = make_events(np.sort(rng.integers(0, 200_000, n)), rng.integers(0, 4, n),
                     rng.integers(0, 3, n), rng.integers(0, 2, n))
    for period in (0, 100, 500, 2_000):
        last, ref = {}, []
        for e in ev:
            key = (int(e["x"]), int(e["y"]))
            ok = key not in last or int(e["t"]) - last[key] >= period
            if ok:
                last[key] = int(e["t"])
            ref.append(ok)
        assert refractory_mask(ev, (4, 3), period).tolist() == ref


def test_load_event_frames_and_load_traverse(tmp_path):
    ev = sample(3000, 128, 128, seed=2, span=95_000)
    s = EventStream(ev, (128, 128))
    write_aedat2(tmp_path / "e.aedat", s)
    write_npz(tmp_path / "e.npz", s)
    f = load_event_frames(tmp_path / "e.aedat", window_ms=10.0, frame_size=(16, 16))
    ref = loop_pool(np.clip(loop_frames(ev, 128, 128, 10_000, None, "count"), 0, 255), 16, 16)
    assert f.dtype == torch.float32 and f.shape == (10, 16, 16)
    np.testing.assert_allclose(f.numpy(), ref, atol=1e-6)
    g = load_traverse(tmp_path / "e.npz", EventFrameOptions(window_ms=10.0, frame_size=(16, 16)),
                      progress=False)
    np.testing.assert_allclose(g.numpy(), f.numpy())
    h = load_event_frames(tmp_path / "e.npz", event_count=1000)
    assert h.shape == (3, 128, 128) and float(h.sum()) == 3000
    signed = load_event_frames(tmp_path / "e.npz", window_ms=10.0, mode="signed")
    assert (signed >= 0).all()
    np.testing.assert_array_equal(signed.numpy(), np.abs(loop_frames(ev, 128, 128, 10_000)))


def torch_kernel(monkeypatch):
    """Make the CPU build its frames with the torch kernel (the one CUDA runs)."""
    monkeypatch.setattr(frames_module, "_kernel_for",
                        lambda device: ("torch", frames_module._bins_torch))


@pytest.mark.parametrize("kernel", ["numpy", "torch"])
@pytest.mark.parametrize("anchor", ["first", "zero", 30_000, -5_000])
@pytest.mark.parametrize("mode", ["signed", "two_channel", "count"])
def test_anchor_against_loop(monkeypatch, kernel, anchor, mode):
    ev = sample(500, 12, 8, seed=4, span=100_000)
    ev["t"] += 12_345  # first event well after sensor time zero
    if kernel == "torch":
        torch_kernel(monkeypatch)
    origin = {"first": int(ev["t"].min()), "zero": 0}.get(anchor, anchor)
    got = accumulate(EventStream(ev, (12, 8)), window_us=7_000, mode=mode, anchor=anchor)
    ref = loop_frames(ev, 12, 8, 7_000, None, mode, origin=origin)
    assert tuple(got.shape) == ref.shape
    np.testing.assert_array_equal(got.numpy(), ref)
    shuffled = ev[np.random.default_rng(3).permutation(len(ev))]  # unordered: masks, division
    np.testing.assert_array_equal(accumulate(shuffled, (12, 8), window_us=7_000, mode=mode,
                                             anchor=anchor).numpy(), ref)
    if anchor == "zero":  # frame k covers [k * window, (k + 1) * window) in sensor time
        assert got.shape[0] == int(ev["t"].max()) // 7_000 + 1
        assert got[:12_345 // 7_000].abs().sum() == 0
    counted = accumulate(ev, (12, 8), window_us=None, event_count=37, mode=mode, anchor=anchor)
    ref = loop_frames(ev, 12, 8, None, 37, mode, origin=origin)
    np.testing.assert_array_equal(counted.numpy(), ref)


@pytest.mark.parametrize("kernel", ["numpy", "torch"])
def test_kernels_agree_on_unsorted_pooled_and_filtered_input(monkeypatch, kernel):
    ev = sample(3000, 16, 12, seed=9, span=90_000)
    shuffled = ev[np.random.default_rng(1).permutation(len(ev))]  # the division path
    if kernel == "torch":
        torch_kernel(monkeypatch)
    for mode in ("signed", "two_channel", "count", "binary"):
        ref = loop_frames(ev, 16, 12, 10_000, None, mode)
        got = accumulate(shuffled, (16, 12), window_us=10_000, mode=mode)
        np.testing.assert_array_equal(got.numpy(), ref)
        for size in ((3, 4), (4, 4), (5, 7)):  # divisible: pooled bins; else adaptive pool
            pooled = accumulate(ev, (16, 12), window_us=10_000, mode=mode, downsample=size)
            want = torch.nn.functional.adaptive_avg_pool2d(
                torch.from_numpy(ref), size).numpy()
            np.testing.assert_allclose(pooled.numpy(), want, atol=1e-5)
    keep = hot_pixel_mask(ev, (16, 12), 1.2) & refractory_mask(ev, (16, 12), 3_000)
    got = accumulate(ev, (16, 12), window_us=10_000, mode="count", hot_pixel=1.2,
                     refractory_us=3_000, anchor="zero")
    np.testing.assert_array_equal(got.numpy(),
                                  loop_frames(ev[keep], 16, 12, 10_000, None, "count", 0))


def test_kernel_selection():
    assert frames_module._kernel_for(torch.device("cpu"))[0] == "numpy"
    assert frames_module._kernel_for(torch.device("cuda"))[0] == "torch"
    if torch.cuda.is_available():
        ev = sample()
        got = accumulate(ev, (12, 8), device="cuda")
        np.testing.assert_array_equal(got.cpu().numpy(), accumulate(ev, (12, 8)).numpy())


def test_anchor_errors_and_bounds(monkeypatch):
    ev = sample(50, 12, 8, span=10_000)
    ev["t"] += 1_000
    for bad in ("last", 1.5, True, None):
        with pytest.raises(ValueError, match="anchor"):
            accumulate(ev, (12, 8), anchor=bad)
    with pytest.raises(EventFormatError, match="no events"):
        accumulate(ev, (12, 8), anchor=10**9)  # every event before the anchor
    with pytest.raises(ValueError, match="t_start"):
        accumulate(ev, (12, 8), t_start=5_000)
    np.testing.assert_array_equal(accumulate(ev, (12, 8), t_start=0).numpy(),
                                  accumulate(ev, (12, 8), anchor="zero").numpy())
    with pytest.raises(ValueError, match="not both"):
        accumulate(ev, (12, 8), t_start=0, anchor=0)
    with pytest.raises(ValueError, match="elements"):  # a far anchor: ~10**12 empty windows
        accumulate(ev, (12, 8), window_us=1, anchor=-10**12)
    monkeypatch.setattr(frames_module, "MAX_FRAME_ELEMENTS", 9 * 96)
    with pytest.raises(ValueError, match="elements"):
        accumulate(ev, (12, 8), window_us=1_000)
    bad_p = ev.copy()
    bad_p["p"][3] = 255
    with pytest.raises(ValueError, match="polarity"):
        accumulate(bad_p, (12, 8))
    neg = ev.copy()
    neg["x"][0] = -1
    with pytest.raises(ValueError, match="outside"):
        accumulate(neg, (12, 8))


def test_load_event_frames_anchor(tmp_path):
    ev = sample(3000, 32, 32, seed=6, span=45_000)
    ev["t"] += 20_000
    write_npz(tmp_path / "e.npz", EventStream(ev, (32, 32)))
    first = load_event_frames(tmp_path / "e.npz", window_ms=10.0)
    zero = load_event_frames(tmp_path / "e.npz", window_ms=10.0, anchor="zero")
    given = load_event_frames(tmp_path / "e.npz", window_ms=10.0, anchor=40_000)
    assert zero.shape[0] == int(ev["t"].max()) // 10_000 + 1 and zero[:2].sum() == 0
    np.testing.assert_array_equal(zero.numpy(), np.clip(loop_frames(
        ev, 32, 32, 10_000, None, "count", 0), 0, 255))
    np.testing.assert_array_equal(given.numpy(), np.clip(loop_frames(
        ev, 32, 32, 10_000, None, "count", 40_000), 0, 255))
    assert float(first.sum()) == 3000 and float(given.sum()) == (ev["t"] >= 40_000).sum()


def test_load_event_frames_every_mode_against_loop(tmp_path):
    # count, signed, binary and two-channel traverse frames from one file, each against the
    # plain loop; two-channel frames are OFF | ON side by side (H, 2W), each half pooled
    ev = sample(2000, 16, 8, seed=11, span=45_000)
    write_npz(tmp_path / "e.npz", EventStream(ev, (16, 8)))
    count = np.clip(loop_frames(ev, 16, 8, 10_000, None, "count"), 0, 255)
    expect = {
        "count": count,
        "signed": np.clip(np.abs(loop_frames(ev, 16, 8, 10_000, None, "signed")), 0, 255),
        "binary": 255 * loop_frames(ev, 16, 8, 10_000, None, "binary"),
    }
    two = np.clip(loop_frames(ev, 16, 8, 10_000, None, "two_channel"), 0, 255)
    expect["two_channel"] = np.concatenate([two[:, 0], two[:, 1]], axis=-1)
    for mode, ref in expect.items():
        got = load_event_frames(tmp_path / "e.npz", window_ms=10.0, mode=mode)
        np.testing.assert_array_equal(got.numpy(), ref, err_msg=mode)
    pooled = load_event_frames(tmp_path / "e.npz", window_ms=10.0, mode="two_channel",
                               frame_size=(4, 4))
    assert pooled.shape == (5, 4, 8)
    np.testing.assert_allclose(pooled.numpy(), np.concatenate(
        [loop_pool(two[:, 0], 4, 4), loop_pool(two[:, 1], 4, 4)], axis=-1), atol=1e-5)
    # the halves sum to the count frames: nothing lost, nothing doubled
    np.testing.assert_array_equal(expect["two_channel"][..., :16] +
                                  expect["two_channel"][..., 16:], count)
    with pytest.raises(ValueError, match="mode"):
        load_event_frames(tmp_path / "e.npz", mode="polarity")


def test_load_event_frames_time_crop_against_loop(tmp_path):
    ev = sample(3000, 16, 8, seed=12, span=90_000)
    ev["t"] += 7_000
    write_npz(tmp_path / "e.npz", EventStream(ev, (16, 8)))
    t = ev["t"].astype(np.int64)

    def ref(begin, end):
        kept = ev[(t >= begin) & (t < end)]
        return np.clip(loop_frames(kept, 16, 8, 10_000, None, "count", begin), 0, 255)

    # first event as anchor: skip 15 ms, keep 40 ms -> windows start at t0 + 15 ms
    t0 = int(t.min())
    got = load_event_frames(tmp_path / "e.npz", window_ms=10.0, start_ms=15, duration_ms=40)
    np.testing.assert_array_equal(got.numpy(), ref(t0 + 15_000, t0 + 55_000))
    assert got.shape[0] == 4
    # sensor-time anchor: the crop counts from sensor time 0, windows stay on that grid
    got = load_event_frames(tmp_path / "e.npz", window_ms=10.0, anchor="zero", start_ms=30,
                            duration_ms=20)
    np.testing.assert_array_equal(got.numpy(), ref(30_000, 50_000))
    got = load_event_frames(tmp_path / "e.npz", window_ms=10.0, anchor=20_000, start_ms=5)
    np.testing.assert_array_equal(got.numpy(), ref(25_000, 10**9))
    # event-count windows inside the crop
    got = load_event_frames(tmp_path / "e.npz", event_count=100, start_ms=15, duration_ms=40)
    assert float(got.sum()) == ((t >= t0 + 15_000) & (t < t0 + 55_000)).sum()
    with pytest.raises(EventFormatError, match=r"no events in the time crop.*spans 7\d+\.\.9\d+"):
        load_event_frames(tmp_path / "e.npz", start_ms=500)
    with pytest.raises(ValueError, match="duration_ms"):
        load_event_frames(tmp_path / "e.npz", duration_ms=float("nan"))


def test_load_event_frames_pixel_filters(tmp_path):
    ev = sample(600, 6, 6, seed=13, span=50_000)
    hot = make_events(np.arange(400) * 120, np.full(400, 2), np.full(400, 3), np.ones(400))
    allev = np.concatenate([ev, hot])
    allev = allev[np.argsort(allev["t"], kind="stable")]
    write_npz(tmp_path / "e.npz", EventStream(allev, (6, 6)))
    keep = hot_pixel_mask(allev, (6, 6), 5.0) & refractory_mask(allev, (6, 6), 300)
    got = load_event_frames(tmp_path / "e.npz", event_count=10_000, hot_pixel=5.0,
                            refractory_us=300)
    np.testing.assert_array_equal(got.numpy(), np.clip(
        loop_frames(allev[keep], 6, 6, None, 10_000, "count"), 0, 255))
    assert got[0, 3, 2] == 0 and 0 < float(got.sum()) < 600


def test_tonic_sensor_size_with_polarity_count(tmp_path):
    # tonic's sensor_size=(W, H, P): P, the polarity count, is not a size
    ev = sample(300, 12, 8, seed=14)
    want = accumulate(ev, (12, 8), window_us=20_000, mode="count")
    assert torch.equal(accumulate(ev, (12, 8, 2), window_us=20_000, mode="count"), want)
    write_npz(tmp_path / "e.npz", EventStream(ev, (12, 8)))
    got = load_event_frames(tmp_path / "e.npz", window_ms=20.0, sensor_size=(12, 8, 2))
    assert torch.equal(got, want.clamp(0, 255))
    with pytest.raises(ValueError, match="sensor_size"):
        accumulate(ev, (12, 8, 5), window_us=20_000)


def test_huge_declared_sensor_is_bounded():
    # a header declaring the largest sensor an int16 coordinate allows, with three events:
    # a full frame would be 2**30 float32 (4 GiB); accumulate refuses before allocating it
    side = 1 << 15
    ev = make_events([0, 5, 9], [0, 4095, side - 1], [0, 2047, side - 1], [1, 0, 1])
    stream = EventStream(ev, (side, side))
    for mode in ("signed", "two_channel"):
        with pytest.raises(ValueError, match="MAX_FRAME_PIXELS"):
            accumulate(stream, mode=mode)
    with pytest.raises(ValueError, match="MAX_FRAME_PIXELS"):  # no divisor: full-size buffer
        accumulate(stream, downsample=(3, 3))
    # a dividing downsample bins straight into pooled pixels: small buffer, exact blocks
    got = accumulate(stream, downsample=(16, 16), mode="two_channel")
    want = np.zeros((1, 2, 16, 16))
    block = (side // 16) ** 2
    want[0, 1, 0, 0] = 1 / block
    want[0, 0, 0, 1] = 1 / block  # x = 4095 lies in block column 1 (2048-wide blocks)
    want[0, 1, 15, 15] = 1 / block
    np.testing.assert_array_equal(got.numpy(), want)


def test_frame_pixel_budget_boundary(monkeypatch):
    ev = sample(200, 12, 8, seed=3)
    full = accumulate(ev, (12, 8), mode="two_channel")
    monkeypatch.setattr(frames_module, "MAX_FRAME_PIXELS", 2 * 8 * 12)  # exactly one frame
    np.testing.assert_array_equal(accumulate(ev, (12, 8), mode="two_channel").numpy(),
                                  full.numpy())
    np.testing.assert_array_equal(
        accumulate(ev, (12, 8), mode="two_channel").numpy(),
        loop_frames(ev, 12, 8, window_us=10_000, mode="two_channel"))
    monkeypatch.setattr(frames_module, "MAX_FRAME_PIXELS", 2 * 8 * 12 - 1)
    with pytest.raises(ValueError, match="2x8x12"):
        accumulate(ev, (12, 8), mode="two_channel")
    monkeypatch.setattr(frames_module, "MAX_FRAME_PIXELS", 4 * 6)  # pooled frame fits
    np.testing.assert_allclose(accumulate(ev, (12, 8), mode="signed", downsample=(4, 6)).numpy(),
                               loop_pool(loop_frames(ev, 12, 8, window_us=10_000), 4, 6),
                               rtol=0, atol=1e-6)


def test_a_far_time_anchor_warns_about_its_empty_leading_windows():
    import warnings

    ev = sample(50, 12, 8, span=10_000)
    ev["t"] += 10_000_000  # the recording starts 10 s after sensor time zero
    with pytest.warns(UserWarning, match=r"1,000 of the 1,00[12] windows \(10.0 s\) .* empty"):
        f = accumulate(ev, (12, 8), window_us=10_000, anchor="zero")
    assert f.shape[0] in (1001, 1002) and f[:1000].abs().sum() == 0 and f[1000:].abs().sum() > 0
    with pytest.warns(UserWarning, match="100 of the 10[12] windows"):  # the bound itself
        accumulate(ev, (12, 8), window_us=10_000, anchor=10_000_000 - 100 * 10_000)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning: the first event, or few empty windows
        accumulate(ev, (12, 8), window_us=10_000)
        accumulate(ev, (12, 8), window_us=10_000, anchor=10_000_000 - 99 * 10_000)
        accumulate(ev, (12, 8), event_count=10, anchor="zero")

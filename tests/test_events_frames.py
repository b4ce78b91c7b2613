import numpy as np
import pytest
import torch

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

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device"))]
DTYPES = [torch.float32, torch.float64]


def loop_frames(ev, w, h, window_us=None, event_count=None, mode="signed"):
    """Plain-Python reference: one event at a time into a list of frames."""
    t0 = int(ev["t"].min())
    chans = 2 if mode == "two_channel" else 1
    frames = {}
    for i, e in enumerate(ev):
        k = i // event_count if event_count else (int(e["t"]) - t0) // window_us
        f = frames.setdefault(k, np.zeros((chans, h, w)))
        c = int(e["p"]) if chans == 2 else 0
        if mode == "signed":
            f[c, e["y"], e["x"]] += 1 if e["p"] else -1
        elif mode == "binary":
            f[c, e["y"], e["x"]] = 1
        else:
            f[c, e["y"], e["x"]] += 1
    n = max(frames) + 1
    out = np.stack([frames.get(k, np.zeros((chans, h, w))) for k in range(n)])
    return out if chans == 2 else out[:, 0]


def loop_pool(frames, out_h, out_w):
    """Block mean for integer factors, written as loops."""
    h, w = frames.shape[-2:]
    fh, fw = h // out_h, w // out_w
    out = np.zeros(frames.shape[:-2] + (out_h, out_w))
    for i in range(out_h):
        for j in range(out_w):
            block = frames[..., i * fh:(i + 1) * fh, j * fw:(j + 1) * fw]
            out[..., i, j] = block.mean(axis=(-2, -1))
    return out


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

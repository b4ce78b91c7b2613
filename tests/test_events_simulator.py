import math

import numpy as np
import pytest
import torch

from torchseq.events.simulator import frames_to_events


def loop_simulator(frames, times, c, eps=1.0):
    """Scalar reference: walk each pixel through each interval, one crossing at a time."""
    n, h, w = frames.shape
    out = []
    for y in range(h):
        for x in range(w):
            ref = math.log(frames[0, y, x] + eps)
            for k in range(n - 1):
                a, b = math.log(frames[k, y, x] + eps), math.log(frames[k + 1, y, x] + eps)
                while b - ref >= c - 1e-12 or ref - b >= c - 1e-12:
                    up = b > ref
                    ref = ref + c if up else ref - c
                    t = times[k] + (ref - a) / (b - a) * (times[k + 1] - times[k])
                    out.append((round(t), x, y, int(up)))
    return sorted(out)


def as_sorted(stream):
    e = stream.events
    return sorted(zip(e["t"].tolist(), e["x"].tolist(), e["y"].tolist(), e["p"].tolist()))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_moving_edge_gives_on_events_at_the_edge(dtype):
    n, h, w = 8, 3, 10
    frames = torch.full((n, h, w), 50.0, dtype=dtype)
    for k in range(n):
        frames[k, :, : k + 1] = 200.0  # a bright region sweeping right, 1 px per frame
    s = frames_to_events(frames, fps=1000.0, contrast_threshold=0.2)
    e = s.events
    jumps = math.floor((math.log(201) - math.log(51)) / 0.2)  # 6 crossings per pixel
    assert s.sensor_size == (w, h)
    assert len(e) == (n - 1) * h * jumps and (e["p"] == 1).all()
    interval = e["t"] // 1000  # frame interval of each event
    assert np.array_equal(e["x"], interval + 1)  # column k+1 brightens between frames k, k+1
    for j in range(1, jumps + 1):  # exact crossing times inside the interval
        frac = 0.2 * j / (math.log(201) - math.log(51))
        t = 1000 * frac
        assert ((e["t"] % 1000) == round(t)).sum() == (n - 1) * h
    off = frames_to_events(frames.flip(-1), fps=1000.0)  # mirror: still brightening -> ON
    assert (off.events["p"] == 1).all()
    dark = frames_to_events(frames.flip(0), fps=1000.0)  # time reversed: darkening -> OFF
    assert (dark.events["p"] == 0).all() and len(dark) == len(e)


def test_matches_scalar_reference_with_multiple_crossings():
    rng = np.random.default_rng(0)
    frames = rng.uniform(0, 255, (6, 4, 5))
    times = np.array([0, 1000, 2500, 2600, 5000, 9000], dtype=np.float64)
    s = frames_to_events(frames, timestamps_us=times, contrast_threshold=0.15)
    assert as_sorted(s) == loop_simulator(frames, times, 0.15)
    assert (np.diff(s.events["t"]) >= 0).all()


def test_speed_factor_scales_time_and_seeded_noise():
    rng = np.random.default_rng(1)
    frames = rng.uniform(10, 245, (5, 6, 6))
    a = frames_to_events(frames, fps=100.0)
    b = frames_to_events(frames, fps=100.0, speed=0.5)
    assert len(a) == len(b) and np.array_equal(a.events["x"], b.events["x"])
    assert np.abs(b.events["t"] - 2 * a.events["t"]).max() <= 1  # rounding to whole us
    n1 = frames_to_events(frames, fps=100.0, threshold_noise=0.05, seed=3)
    n2 = frames_to_events(frames, fps=100.0, threshold_noise=0.05, seed=3)
    n3 = frames_to_events(frames, fps=100.0, threshold_noise=0.05, seed=4)
    assert np.array_equal(n1.events, n2.events) and not np.array_equal(n1.events, n3.events)
    r = frames_to_events(frames, fps=100.0, refractory_us=5_000)
    assert 0 < len(r) < len(a)
    for x, y in {(int(e["x"]), int(e["y"])) for e in r.events}:
        t = r.events["t"][(r.events["x"] == x) & (r.events["y"] == y)]
        assert (np.diff(t) >= 5_000).all()
    bg = frames_to_events(np.full((3, 10, 10), 100.0), fps=10.0, noise_rate_hz=50.0, seed=0)
    assert 850 < len(bg) < 1150  # 100 pixels x 50 Hz x 0.2 s = 1000 expected (Poisson)


def test_bad_input():
    with pytest.raises(ValueError, match="T >= 2"):
        frames_to_events(np.zeros((1, 4, 4)), fps=10)
    with pytest.raises(ValueError, match="timestamps"):
        frames_to_events(np.zeros((3, 4, 4)))
    with pytest.raises(ValueError, match="increase"):
        frames_to_events(np.zeros((3, 4, 4)), timestamps_us=[0, 5, 5])
    with pytest.raises(ValueError, match="non-negative"):
        frames_to_events(np.full((3, 4, 4), np.nan), fps=10)

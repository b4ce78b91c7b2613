import numpy as np
import pytest

from torchseq.events.runs import EventRun, ground_truth
from torchseq.events.stream import EventStream


def run(speed, units_per_s):
    return EventRun(EventStream(np.zeros(0, [("t", "<i8"), ("x", "<i2"), ("y", "<i2"),
                                            ("p", "u1")]), (4, 4)), speed, units_per_s)


@pytest.mark.parametrize("units_per_s,window_us", [(10.0, 100_000), (3.3, 303_030),
                                                   (7.0, 142_857)])
def test_windows_a_whole_tolerance_apart_are_kept(units_per_s, window_us):
    """Windows one place apart: window i sits at about i + 0.5 places; every pair of windows
    at most 2 indices apart is within +-2 places, whatever the rounding of the products."""
    n = 400
    r = run(1.0, units_per_s)
    pos = r.window_positions(n, window_us)
    step = window_us * 1e-6 * units_per_s  # route units per window
    got = ground_truth(pos, pos, 2 * step)
    want = np.array([[abs(i - j) <= 2 for j in range(n)] for i in range(n)])
    assert np.array_equal(got, want)


def test_pairs_past_the_tolerance_stay_out():
    got = ground_truth(np.array([0.0, 1.0, 2.0]), np.array([0.0]), 1.0)
    assert got[:, 0].tolist() == [True, True, False]
    got = ground_truth(np.array([1e6, 1e6 + 2.001]), np.array([1e6]), 2.0)
    assert got[:, 0].tolist() == [True, False]

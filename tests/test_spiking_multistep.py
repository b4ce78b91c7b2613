"""experiments/spiking_multistep.py: its k-WTA by inhibition keeps the k largest sums.

The design study (docs/results/nir.md, "Several time steps per frame: a design study")
replaces the rate model's k-WTA with IF units and one inhibitory counter stepped over T steps
per frame; its agreement figures hold only if that network keeps exactly the top k where the
schedule resolves the k-th place. Checked against a plain top-k on random sums spaced wider
than one step of the schedule (no ties), and that a coarse schedule reports its ties (more
than k winners) rather than hiding them.
"""

import numpy as np
import pytest
import torch
from conftest import load_script


@pytest.fixture(scope="module")
def ms():
    return load_script("experiments/spiking_multistep.py")


def spaced_sums(frames=12, units=40, seed=0):
    # each frame a permutation of 0..units-1 plus noise < 0.3 (neighbours >= 0.4 apart),
    # shifted by up to 10 per frame (the k-th sum moves from frame to frame, as on a route)
    g = torch.Generator().manual_seed(seed)
    perm = torch.stack([torch.randperm(units, generator=g) for _ in range(frames)])
    shift = 10.0 * torch.rand(frames, 1, generator=g, dtype=torch.float64)
    return perm.double() + shift + 0.3 * torch.rand(frames, units, generator=g,
                                                    dtype=torch.float64)


def plain_topk(h, k):
    out = torch.zeros_like(h)
    for i in range(h.shape[0]):  # a plain loop: the k largest of each row
        order = sorted(range(h.shape[1]), key=lambda j: -float(h[i, j]))
        for j in order[:k]:
            out[i, j] = 1.0
    return out


@pytest.mark.parametrize("k", [1, 7, 20])
def test_inhibition_kwta_is_topk_without_ties(ms, k):
    h = spaced_sums()
    lo, hi = ms.ring_bounds(h, k)
    steps = int((hi - lo) / 0.4) + 2  # one schedule step is finer than any gap
    got = ms.inhibition_kwta(h, k, steps, lo, hi, "ramp")
    assert torch.equal(got, plain_topk(h, k))


def test_coarse_schedule_reports_ties(ms):
    h = spaced_sums()
    lo, hi = ms.ring_bounds(h, 7)
    got = ms.inhibition_kwta(h, 7, 3, lo, hi, "ramp")  # 3 steps: several cross together
    assert (got.sum(1) > 7).any()  # ties at the k-th place keep every unit that crossed
    # whatever won is a top set: no loser above a winner
    win_min = torch.where(got > 0, h, torch.full_like(h, float("inf"))).min(1).values
    lose_max = torch.where(got > 0, torch.full_like(h, -float("inf")), h).max(1).values
    assert (win_min > lose_max).all()


@pytest.fixture(scope="module")
def route():
    from test_spiking import tiny

    model, demo, sp = tiny()
    xr = model.encode(demo.reference).double()
    xq = model.encode(demo.query).double()
    rate = model.run(demo.query).matches.reference.numpy()
    return model, sp, xr, xq, rate


def test_own_pipeline_all_exact_is_the_rate_model(ms, route):
    # the study's stage switches hold only if its all-exact path is the rate model
    model, sp, xr, xq, rate = route
    r = ms.simulate(model, xr, xq, sp.calibration["theta2"], ms.RATE)
    assert (r["reference"] == rate).all()
    assert (r["fired"] == model.config.k).all()


def test_division_by_timing_tends_to_the_mad_division(ms, route):
    # a long window: the counts are max(c, 0) / MAD to about 1e-6, the evidence is the float
    # MAD division's and so are the decisions (a window that ignores the frame's MAD, or
    # counts that are not rectified, part from them)
    model, sp, xr, xq, _rate = route
    th = sp.calibration["theta2"]
    mad = ms.simulate(model, xr, xq, th, "kwta:mad:evidence:exact")
    div = ms.simulate(model, xr, xq, th, "kwta:div1000000:evidence:exact")
    top = float(np.abs(mad["evidence"]).max())
    np.testing.assert_allclose(div["evidence"], mad["evidence"], rtol=0, atol=1e-4 * top)
    assert (mad["reference"] == div["reference"]).all()
    assert div["window"][2] >= 1000000 // 2

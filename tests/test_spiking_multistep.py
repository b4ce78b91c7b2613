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


def test_own_pipeline_all_exact_is_the_rate_model(ms, tiny_runs):
    # the study's stage switches hold only if its all-exact path is the rate model
    model, sp, xr, xq, rate, _ = tiny_runs
    r = ms.simulate(model, xr, xq, sp.calibration["theta2"], ms.RATE)
    assert (r["reference"] == rate).all()
    assert (r["fired"] == model.config.k).all()


def test_division_by_timing_tends_to_the_mad_division(ms, tiny_runs):
    # a long window: the counts are max(c, 0) / MAD to about 1e-6, the evidence is the float
    # MAD division's and so are the decisions (a window that ignores the frame's MAD, or
    # counts that are not rectified, part from them)
    model, sp, xr, xq, _rate, _ = tiny_runs
    th = sp.calibration["theta2"]
    mad = ms.simulate(model, xr, xq, th, "kwta:mad:evidence:exact")
    div = ms.simulate(model, xr, xq, th, "kwta:div1000000:evidence:exact")
    top = float(np.abs(mad["evidence"]).max())
    np.testing.assert_allclose(div["evidence"], mad["evidence"], rtol=0, atol=1e-4 * top)
    assert (mad["reference"] == div["reference"]).all()
    assert div["window"][2] >= 1000000 // 2


def test_rungs_square_by_parts(ms):
    # the rungs' sum is the chord interpolant of x^2 through the knots (numpy's interp on
    # the knots as an independent reference), exact at each knot, and linear past the last
    knots, weights = ms.square_rungs(top=3.0, first=0.1, ratio=2.0)
    assert knots.tolist() == pytest.approx([0.0, 0.1, 0.2, 0.4, 0.8, 1.6])
    ext = np.append(knots.numpy(), 3.2)  # the knot past the top closes the last chord
    x = torch.linspace(-3.2, 3.2, 2001, dtype=torch.float64)
    got = ms.rung_squares(x, knots, weights).numpy()
    want = np.interp(np.abs(x.numpy()), ext, ext ** 2)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ms.rung_squares(knots, knots, weights).numpy(),
                               knots.numpy() ** 2, rtol=0, atol=1e-12)
    assert float(ms.rung_squares(torch.tensor([6.4], dtype=torch.float64), knots,
                                 weights)) == pytest.approx(3.2 ** 2 + (1.6 + 3.2) * 3.2)
    with pytest.raises(ValueError, match="0 < first"):
        ms.square_rungs(top=1.0, first=0.0)


def centred_frames(frames=30, units=24, seed=0):
    # two cohorts (14 + 10 units), each frame its own spread, centred within each cohort
    gen = torch.Generator().manual_seed(seed)
    c = torch.randn(frames, units, generator=gen, dtype=torch.float64)
    c = c * (0.5 + torch.rand(frames, 1, generator=gen, dtype=torch.float64))
    g = torch.zeros(units, 2, dtype=torch.float64)
    g[:14, 0] = 1.0
    g[14:, 1] = 1.0
    return c - ((c @ g) / g.sum(0)) @ g.T, g


@pytest.mark.parametrize("steps", [16, 64, 128])
def test_square_window_closed_form_is_the_stepped_network(ms, steps):
    # the closed form (analog integrator) against the network stepped with 0/1 spikes: the
    # integer spikes close the window at most one step later, and with the same window the
    # + units' counts are the same
    c, g = centred_frames()
    rate = 1.0 / float(c.abs().max())
    knots, weights = ms.square_rungs(float(c.abs().max()), 0.25 * float(c.std()), 2.0)
    q = (ms.rung_squares(c, knots, weights) @ g) / g.sum(0)
    theta = steps ** 2 * rate * q.median(0).values / 2.0
    count, win = ms.square_window(c, g, rate, knots, weights, theta)
    count_s, win_s = ms.square_window_steps(c, g, rate, knots, weights, theta, 64 * steps)
    assert (win_s > 0).all()
    assert float(win.median()) == pytest.approx(steps, rel=0.15)
    assert ((win_s - win >= 0) & (win_s - win <= 1)).all()
    same = ((win_s == win).double() @ g.T) > 0
    assert torch.equal(count_s[same], count[same])
    assert (count_s - count).abs().max() <= 1
    # the window is one over each frame's cohort std: sqrt(2 theta / (rate var)) to 10%
    var = ((c ** 2) @ g) / g.sum(0)
    np.testing.assert_allclose(win, (2.0 * theta / (rate * var)).sqrt(), rtol=0.1 + 1 / steps)


def test_square_division_tends_to_the_std_division(ms, tiny_runs):
    # fine rungs and a long window: the evidence is the rate model's division by each frame's
    # cohort std (rectified) to 1e-3 and so are the decisions; a window from the MAD, or a
    # single integrator (a window of one over the variance), parts from it
    model, sp, xr, xq, rate, _ = tiny_runs
    th = sp.calibration["theta2"]
    exact = ms.simulate(model, xr, xq, th, "kwta:frame:evidence:exact")
    sq = ms.simulate(model, xr, xq, th, "kwta:sq100000k0.01r1.05:evidence:exact")
    assert exact["evidence"] is not None
    top = float(np.abs(exact["evidence"]).max())
    np.testing.assert_allclose(sq["evidence"], exact["evidence"], rtol=0, atol=2e-3 * top)
    assert (sq["reference"] == rate).all()


def test_every_variant_reports_the_same_fields(ms, tiny_runs):
    # main tabulates every field of every variant: the split's one-step path must carry them
    model, sp, xr, xq, _rate, _ = tiny_runs
    th = sp.calibration["theta2"]
    keys = {v: set(ms.simulate(model, xr, xq, th, v)) for v in
            [ms.SPIKING, ms.RATE, "kwta:sq64:evidence:exact", "kwta:div64:evidence:exact"]}
    assert len({frozenset(k) for k in keys.values()}) == 1, keys

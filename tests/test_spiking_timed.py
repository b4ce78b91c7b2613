"""The timed spiking model (torchseq.neural.spiking_timed): each phase against a plain loop.

Phase A (k-WTA by inhibition), phase B (division by the cohort std by timing) and phase C
(the ring by rate, both kernels) are checked against scalar per-unit loops written here from
the module's docstring; the converted model against the rate model on the demo (quick) and
on the corridor and LENS over seeds 0-7 (slow: the agreement goal of 0.95).
"""

import math

import numpy as np
import pytest
import torch
from conftest import shared_data

from torchseq.demo import make_demo
from torchseq.export.hardware_budget import check
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.neural import spiking_timed as st
from torchseq.neural.spiking import SpikingError
from torchseq.neural.spiking_timed import TimedConfig, TimedSpikingSeqSLAM

SMALL = TimedConfig(l2_steps=64, norm_steps=64, ring_steps=1024)


@pytest.fixture(scope="module")
def demo():
    d = make_demo()
    model = NeuralSeqSLAM(NeuralConfig(seed=0))
    model.fit(d.reference, log=False)
    return d, model


@pytest.fixture(scope="module")
def net(demo):
    d, model = demo
    return TimedSpikingSeqSLAM.convert(model, d.reference, SMALL)


# ---------------------------------------------------------------- phase A
def plain_kwta(first, k, steps):
    """IF units one by one: fire once (self-inhibition), a counter stops the layer."""
    f, m = first.shape
    out = np.zeros((f, m))
    for i in range(f):
        v = [0.0] * m
        fired = [False] * m
        count, stopped = 0, False
        for t in range(1, steps + 1):
            if stopped:
                break
            spikes = 0
            for j in range(m):
                if fired[j]:
                    continue
                v[j] += (float(first[i, j]) if t == 1 else 0.0) + 1.0 / steps
                if v[j] > 1.0:
                    fired[j], out[i, j] = True, 1.0
                    spikes += 1
            count += spikes
            stopped = count > k - 0.5  # inhibits from the next step
    return torch.from_numpy(out)


@pytest.mark.parametrize("k,steps", [(1, 16), (5, 8), (5, 64), (12, 3)])
def test_kwta_by_inhibition_is_the_plain_loop(k, steps):
    g = torch.Generator().manual_seed(k * 100 + steps)
    first = torch.rand(4, 30, generator=g, dtype=torch.float64) * 1.2 - 0.1
    got, counter = st.kwta_by_inhibition(first, k, steps)
    assert torch.equal(got, plain_kwta(first, k, steps))
    assert torch.equal(counter, (got.sum(1) >= k).double())  # the counter fires once
    # a top set: no loser above a winner
    win_min = torch.where(got > 0, first, torch.full_like(first, math.inf)).min(1).values
    lose_max = torch.where(got > 0, torch.full_like(first, -math.inf), first).max(1).values
    assert (win_min > lose_max).all()


# ---------------------------------------------------------------- phase B
def plain_divide(c, cohorts, rate, knots, weights, theta, steps):
    f, n = c.shape
    r, nc = len(knots), cohorts.shape[1]
    size = cohorts.sum(0)
    plus = np.zeros((f, n))
    windows = np.zeros((f, nc))
    for i in range(f):
        v = np.zeros((2, n, r))
        acc, wv = np.zeros(nc), np.zeros(nc)
        for t in range(1, steps + 1):
            closed = windows[i] > 0
            spikes_to = np.zeros(nc)
            for s, sign in enumerate((1.0, -1.0)):
                for j in range(n):
                    for q in range(r):
                        v[s, j, q] += rate * (sign * float(c[i, j]) - float(knots[q]))
                        v[s, j, q] += 0.5 if t == 1 else 0.0
                        if v[s, j, q] > 1.0:
                            v[s, j, q] -= 1.0
                            for cc in range(nc):
                                if cohorts[j, cc]:
                                    spikes_to[cc] += float(weights[q]) / float(size[cc])
                                    if s == 0 and q == 0 and not closed[cc]:
                                        plus[i, j] += 1.0
            acc += spikes_to
            wv += acc
            for cc in range(nc):
                if windows[i, cc] == 0 and wv[cc] > float(theta[cc]):
                    windows[i, cc] = t
    return torch.from_numpy(plus), torch.from_numpy(windows)


@pytest.mark.parametrize("kernel", st.NORM_KERNELS)
def test_divide_by_timing_is_the_plain_loop(kernel):
    g = torch.Generator().manual_seed(3)
    c = torch.randn(3, 6, generator=g, dtype=torch.float64)
    cohorts = torch.tensor([[1, 0], [1, 0], [1, 0], [0, 1], [0, 1], [0, 1]], dtype=torch.float64)
    knots, weights = st.square_rungs(float(c.abs().max()), 0.3, 2.0)
    rate = 1.0 / float(c.abs().max())
    theta = torch.tensor([20.0, 35.0], dtype=torch.float64)
    plus, windows, _ = st.divide_by_timing(c, cohorts, rate, knots, weights, theta, 200, kernel)
    ref_plus, ref_windows = plain_divide(c, cohorts, rate, knots, weights, theta, 200)
    assert (windows > 0).all()  # the check is not vacuous: every window closed
    assert torch.equal(windows, ref_windows) and torch.equal(plus, ref_plus)
    # a phase shorter than a window clips it (reported as 0) and stops its counts there
    short = int(windows.min()) - 1
    p2, w2, _ = st.divide_by_timing(c, cohorts, rate, knots, weights, theta, short, kernel)
    assert (w2 == 0).all()
    assert torch.equal(p2, plain_divide(c, cohorts, rate, knots, weights, theta, short)[0])


def test_division_kernels_agree_spike_for_spike():
    g = torch.Generator().manual_seed(11)
    c = torch.randn(9, 60, generator=g, dtype=torch.float64)
    c[4] = 0.0  # a blank frame: no window closes
    cohorts = torch.zeros(60, 3, dtype=torch.float64)
    cohorts[torch.arange(60), torch.arange(60) % 3] = 1.0
    knots, weights = st.square_rungs(float(c.abs().max()), 0.25, 2.0)
    theta = torch.tensor([100.0, 150.0, 200.0], dtype=torch.float64)
    rate = 1.0 / float(c.abs().max())
    for steps in (400, 25):  # windows closing at different steps per frame; all clipped
        a = st.divide_by_timing(c, cohorts, rate, knots, weights, theta, steps, "torch")
        b = st.divide_by_timing(c, cohorts, rate, knots, weights, theta, steps, "numba")
        assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert len(set(a[1][a[1] > 0].tolist())) > 3 and (a[1][4] == 0).all()
    with pytest.raises(SpikingError, match="division kernel"):
        st.divide_by_timing(c, cohorts, rate, knots, weights, theta, 10, "fast")
    with pytest.raises(SpikingError, match="one cohort per unit"):
        st.divide_by_timing(c, torch.ones(60, 3, dtype=torch.float64), rate, knots, weights,
                            theta, 10, "numba")


def test_divide_by_timing_divides_by_the_spread():
    # the + counts measure c / std: the same frame at twice the spread counts about the same
    g = torch.Generator().manual_seed(5)
    c = torch.randn(4, 40, generator=g, dtype=torch.float64)
    c = c - c.mean(1, keepdim=True)
    cohorts = torch.ones(40, 1, dtype=torch.float64)
    knots, weights = st.square_rungs(8.0, 0.25, 2.0)
    rate = 1.0 / 8.0
    theta = torch.tensor([2000.0], dtype=torch.float64)
    p1, w1, _ = st.divide_by_timing(c, cohorts, rate, knots, weights, theta, 10_000)
    p2, w2, _ = st.divide_by_timing(2.0 * c, cohorts, rate, knots, weights, theta, 10_000)
    assert (w2 < w1).all()  # a wider spread closes the window sooner
    assert p1.max() >= 20  # counts large enough for the comparison to mean something
    assert (p1 - p2).abs().max() <= 0.1 * p1.max()


def test_square_rungs_interpolate_the_square():
    knots, weights = st.square_rungs(10.0, 0.5, 2.0)
    assert knots.tolist() == [0.0, 0.5, 1.0, 2.0, 4.0, 8.0]
    x = knots
    assert torch.allclose(st.rung_squares(x, knots, weights), x ** 2)  # exact at the knots
    mid = torch.linspace(0.0, 8.0, 97, dtype=torch.float64)
    assert (st.rung_squares(mid, knots, weights) >= mid ** 2 - 1e-12).all()  # chords above
    assert torch.equal(st.rung_squares(-mid, knots, weights), st.rung_squares(mid, knots, weights))


# ---------------------------------------------------------------- phase C
def plain_ring(drive, steps):
    out = np.zeros(drive.shape)
    for idx in np.ndindex(drive.shape):
        v, n = 0.0, 0
        for _ in range(steps):
            v += float(drive[idx])
            if v > 1.0:
                v -= 1.0
                n += 1
        out[idx] = n
    return torch.from_numpy(out)


def test_ring_kernels_are_the_plain_loop_spike_for_spike():
    steps = 64
    exact = torch.tensor([[0.0, -0.5, 1.0, 2.5, 1 / 64, 3 / 64, 0.5, 1 - 2.0 ** -32]],
                         dtype=torch.float64)  # integer crossings, saturation, silence
    g = torch.Generator().manual_seed(0)
    noise = st.ring_drive(torch.rand(3, 50, generator=g, dtype=torch.float64) * 1.3 - 0.1)
    for drive in (st.ring_drive(exact), noise):
        ref = plain_ring(drive, steps)
        assert torch.equal(st.ring_by_rate(drive, steps, "stepped"), ref)
        assert torch.equal(st.ring_by_rate(drive, steps, "closed"), ref)
    with pytest.raises(SpikingError, match="ring kernel"):
        st.ring_by_rate(noise, steps, "fast")


def test_ring_drive_is_on_its_grid_and_clamped():
    d = st.ring_drive(torch.tensor([1e9, -1e9, 0.1, math.pi], dtype=torch.float64))
    assert d[0] == st.DRIVE_MAX and d[1] == -st.DRIVE_MAX
    assert torch.equal(d / st.DRIVE_GRID, torch.round(d / st.DRIVE_GRID))


@pytest.mark.parametrize("ring,norm", [("closed", "numba"), ("stepped", "torch")])
def test_the_chosen_kernels_run(demo, ring, norm, monkeypatch):
    d, model = demo
    ran = []
    for name in ("_ring_closed", "_ring_stepped", "_divide_torch", "_divide_numba"):
        real = getattr(st, name)
        monkeypatch.setattr(st, name, lambda *a, _r=real, _n=name: ran.append(_n) or _r(*a))
    cfg = TimedConfig(l2_steps=16, norm_steps=16, ring_steps=64, ring_kernel=ring,
                      norm_kernel=norm)
    net = TimedSpikingSeqSLAM.convert(model, d.reference[:40], cfg)
    assert net.ring_kernel == ring and net.norm_kernel == norm
    ran.clear()
    net.run(d.query[:3])
    assert ran == [f"_divide_{norm}"] + [f"_ring_{ring}"] * 3
    assert TimedConfig().norm_kernel == "numba" and TimedConfig().ring_kernel == "closed"


# ---------------------------------------------------------------- the model
def test_agrees_with_the_rate_model_on_the_demo(demo, net):
    d, model = demo
    rate = model.run(d.query).matches.reference
    out = net.run(d.query)
    assert out["reference"].shape == rate.shape
    assert (out["reference"] == rate).double().mean() >= 0.95  # 1.000 measured
    assert out["steps_per_frame"] == 64 + 6 * 64 + 1024
    k = model.config.k
    assert (out["winners"] >= k).all() and (out["winners"] <= k + 5).all()
    assert (out["windows"] > 0).all()  # no window clipped on the demo
    assert net.calibration["reference_clipped"] == 0
    assert set(out["spikes"]) == {"l2", "norm", "ring"}
    assert torch.equal(out["spikes"]["ring"], out["counts"].sum(1))


def test_run_is_forward_frame_by_frame(demo, net):
    d, _ = demo
    x = net.encode(d.query[:20])
    out = net.run(x, encoded=True)
    state = None
    for t in range(20):
        step, state = net(x[t:t + 1], state)
        assert torch.equal(step.counts, out["counts"][t:t + 1])
        assert int(step.reference) == int(out["reference"][t])
    # two streams at once: each is its own run
    both, _ = net(torch.stack([x[0], x[5]]))
    assert torch.equal(both.counts[1], net(x[5:6])[0].counts[0])


def test_weights_on_the_chip_grid(demo):
    d, model = demo
    net8 = TimedSpikingSeqSLAM.convert(model, d.reference, TimedConfig(
        l2_steps=64, norm_steps=64, ring_steps=1024, weight_bits=8))
    for name in ("w1", "w3", "shift"):
        w = getattr(net8, name)
        for row in w[w.abs().sum(1) > 0][:50]:
            scale = 2.0 ** torch.ceil(torch.log2(row.abs().max() / 127))
            q = row / scale
            assert torch.equal(q, torch.round(q)) and q.abs().max() <= 127, name
    rate = model.run(d.query).matches.reference
    assert (net8.run(d.query)["reference"] == rate).double().mean() >= 0.95
    b = net8.budget()
    fits = check(b)
    assert fits["loihi2"]["fits"], fits["loihi2"]
    assert not fits["xylo_audio2"]["fits"]
    float_reasons = check(TimedSpikingSeqSLAM.convert(model, d.reference, SMALL).budget())
    assert any("TimedConfig(weight_bits=8)" in r for r in float_reasons["loihi2"]["exceeds"])
    assert any("timed model has no event input" in r for r in fits["speck"]["exceeds"])


def test_budget_counts(net):
    b = net.budget()
    m, d = net.w1.shape
    n, c, r = net.n_units, net.cohorts.shape[1], net.knots.numel()
    assert b["populations"]["rate"] == 2 * n * r
    assert b["neurons"] == m + 1 + n + 2 * n * r + 2 * c + 3 * n
    assert b["effective_synapses"] == sum(b["effective_synapses_by_pair"].values())
    assert b["effective_synapses_by_pair"]["l2->l3"] == int((net.w3 != 0).sum())
    assert b["inputs"] == d + 2 and b["outputs"] == n
    assert b["max_fan_in"] >= m  # the L3 integrators read every L2 unit (dense centred l3)


@pytest.mark.parametrize("kw,match", [
    ({"l2_steps": 0}, "l2_steps"), ({"ring_steps": 1.5}, "ring_steps"),
    ({"norm_max_steps": 10}, "norm_max_steps"), ({"ratio": 1.0}, "ratio"),
    ({"first": 0.0}, "first"), ({"widen": -1.0}, "widen"), ({"weight_bits": 1}, "weight_bits"),
    ({"ring_kernel": "numba"}, "ring_kernel"), ({"norm_kernel": "closed"}, "norm_kernel"),
    ({"chunk": True}, "chunk")])
def test_bad_config(demo, kw, match):
    d, model = demo
    with pytest.raises(SpikingError, match=match):
        TimedSpikingSeqSLAM.convert(model, d.reference, TimedConfig(**kw))


def test_bad_input(demo, net):
    d, _ = demo
    with pytest.raises(SpikingError, match="has not learnt"):
        TimedSpikingSeqSLAM.convert(NeuralSeqSLAM(NeuralConfig(seed=0)), d.reference)
    with pytest.raises(SpikingError, match="R >= 2"):
        TimedSpikingSeqSLAM.convert(demo[1], d.reference[:1])
    with pytest.raises(SpikingError, match="encoded frames"):
        net(torch.zeros(2, 5))
    x = net.encode(d.query[:2])
    with pytest.raises(SpikingError, match="NaN"):
        net(torch.where(torch.arange(x.shape[1]) == 3, math.nan, x))
    with pytest.raises(SpikingError, match="state must be"):
        net(x, torch.zeros(3, net.n_units, dtype=torch.float64))
    with pytest.raises(SpikingError, match="at least one frame"):
        net.run(x[:0], encoded=True)
    with pytest.raises(SpikingError, match="cannot be encoded"):
        net.run(d.query[0])


# ---------------------------------------------------------------- real data
def real_pair(name):
    from torchseq.sources import load_traverse

    if name == "corridor":
        root = shared_data("corridor")
        return load_traverse(root / "ref", progress=False), \
            load_traverse(root / "query", progress=False)
    root = shared_data("lens-davis128")
    return load_traverse(root / "example-reference", progress=False), \
        load_traverse(root / "example-query", progress=False)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["corridor", "lens"])
def test_agreement_goal_over_eight_seeds(name):
    # issue 26's goal: >= 0.95 of the rate model's decisions on every seed 0-7, calibrated on
    # the reference only. Measured worst (float / 8-bit weights): corridor 0.991 / 0.964,
    # LENS 0.970 / 0.970; the one-step model 0.685 / 0.790 (docs/results/nir.md)
    ref, qry = real_pair(name)
    torch.set_num_threads(1)
    worst = {None: 1.0, 8: 1.0}
    for seed in range(8):
        model = NeuralSeqSLAM(NeuralConfig(seed=seed))
        model.fit(ref, log=False)
        rate = model.run(qry).matches.reference
        for bits in worst:
            out = TimedSpikingSeqSLAM.convert(model, ref, TimedConfig(weight_bits=bits)).run(qry)
            worst[bits] = min(worst[bits], float((out["reference"] == rate).double().mean()))
    assert min(worst.values()) >= 0.95, worst


def test_synaptic_ops_count_spikes_and_graded_steps(demo, net):
    d, _ = demo
    x = net.encode(d.query[:4])
    step, _ = net(x)
    z2 = net.winners(x)
    n, m = net.n_units, net.w1.shape[0]
    fan = [int((net.w3[:, i] != 0).sum()) + 2 for i in range(m)]
    for b in range(4):  # phase A: the input once, each winner's fan-out, the counter's M
        winners = [i for i in range(m) if z2[b, i] > 0]
        want = int((net.w1 != 0).sum()) + sum(fan[i] for i in winners) + m * (len(winners) >= net.k)
        assert int(step.ops["a"][b]) == want
    t = net.config.ring_steps
    assert torch.equal(step.ops["c"], t * (n + float((net.shift != 0).sum())) + step.counts.sum(1))
    assert (step.ops["b"] > step.spikes["norm"]).all()

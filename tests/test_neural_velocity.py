"""The adaptive-velocity ring (``ring_velocity="adaptive"``, torchseq/neural/velocity.py).

References: today's ring step (``ring_step``) for speed 1, a plain NumPy loop written here
(matrix powers of the shift, ``np.polyfit`` for the slope) for the whole adaptive step, and
the demo's own speed for the estimator.
"""

import math

import numpy as np
import pytest
import torch

from torchseq.demo import make_demo
from torchseq.layers import RingParams, RingState, ring_step
from torchseq.layers.ring import band_diagonals
from torchseq.layers.ring_velocity import ring_step_velocity
from torchseq.metrics import evaluate
from torchseq.neural import NeuralConfig, NeuralError, NeuralSeqSLAM
from torchseq.neural.velocity import VelocityState, VelocityTracker

SMALL = dict(hidden=512, n_output=60)


ROUTE = dict(n_reference=60, speed=0.7, seed=3)  # the conftest ``route`` fixture's demo


_MODELS = {}


def fitted(route, **kw):
    key = tuple(sorted(kw.items()))
    if key not in _MODELS:
        model = NeuralSeqSLAM(NeuralConfig(**{**SMALL, **kw}))
        model.fit(route.reference, log=False)
        _MODELS[key] = model
    return _MODELS[key]


# ---------------------------------------------------------------- speed 1 is today's ring
def test_speed_one_is_ring_step_bit_for_bit():
    g = torch.Generator().manual_seed(0)
    n = 30
    shift = torch.rand(n, n, generator=g) * (torch.rand(n, n, generator=g) < 0.2)
    banded = torch.tril(torch.triu(torch.rand(n, n, generator=g), -2))  # lags 0..2
    a, e = torch.rand(4, n, generator=g), torch.rand(4, n, generator=g)
    params = RingParams(0.97, 0.03)
    ones = torch.ones(4, dtype=torch.float64)
    want, _ = ring_step(e, RingState(a), shift, params)
    assert torch.equal(ring_step_velocity(e, a, shift, params, ones), want)
    diag = band_diagonals(banded, 2)
    want, _ = ring_step(e, RingState(a), banded, params, diag)
    assert torch.equal(ring_step_velocity(e, a, banded, params, ones, diag), want)
    # other speeds move by the mixed powers: 0 keeps the activity, 2 is two shifts
    s2 = shift @ shift
    got = ring_step_velocity(e, a, shift, params, torch.tensor([0.0, 2.0, 0.5, 1.25]))
    mixes = [a[0], a[1] @ s2.T, 0.5 * a[2] + 0.5 * a[2] @ shift.T,
             0.75 * a[3] @ shift.T + 0.25 * a[3] @ s2.T]
    want = 0.97 * torch.stack(mixes) + 0.03 * e
    torch.testing.assert_close(got, want, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("fast", [False, True])
def test_pinned_adaptive_model_steps_like_the_fixed_model(route, fast):
    fixed = fitted(route)
    pinned = fitted(route, ring_velocity="adaptive", velocity_min=1.0, velocity_max=1.0)
    if fast:  # the inference modules' step, else the layers'
        fixed, pinned = fixed.inference(), pinned.inference()
    s_fixed = s_pinned = None
    for t in range(30):
        frames = torch.stack([route.query[t], route.reference[t]])  # two streams
        out_f, s_fixed = fixed.step(frames, s_fixed)
        out_p, s_pinned = pinned.step(frames, s_pinned)
        assert torch.equal(out_p.activity, out_f.activity)
        assert torch.equal(out_p.reference, out_f.reference)
        assert torch.equal(s_pinned.velocity, torch.ones(2, dtype=torch.float64))


# ---------------------------------------------------------------- a plain-loop reference
def reference_loop(evidence: np.ndarray, shift: np.ndarray, decay: float, gain: float,
                   centre: np.ndarray, cfg: NeuralConfig):
    """The adaptive step of docs/guide/neural.md written out frame by frame, one stream."""
    a, v, seen = np.zeros(shift.shape[0]), 1.0, []
    refs, speeds = [], []
    for e in evidence:
        n = math.floor(v)
        f = v - n
        moved = np.linalg.matrix_power(shift, n) @ a
        a = decay * ((1 - f) * moved + f * (shift @ moved)) + gain * e
        seen.append(float(centre[int(np.argmax(a))]))
        refs.append(int(seen[-1]))
        if len(seen) >= cfg.velocity_window:
            p = np.array(seen[-cfg.velocity_window:])
            t = np.arange(len(p), dtype=np.float64)
            slope, icpt = np.polyfit(t, p, 1)
            ok = np.abs(p - (slope * t + icpt)).max() <= cfg.velocity_tolerance
            v = v + cfg.velocity_rate * ((slope if ok else 1.0) - v)
            v = min(max(v, cfg.velocity_min), cfg.velocity_max)
        speeds.append(v)
    return np.array(refs), np.array(speeds)


@pytest.mark.parametrize("kw", [dict(velocity_window=8), dict(velocity_window=5,
                                                               velocity_rate=1.0,
                                                               velocity_tolerance=1.0)])
def test_step_and_run_follow_a_plain_loop(route, kw):
    model = fitted(route, ring_velocity="adaptive", ring_spread=1, ring_stay=0.0, **kw)
    cfg, q = model.config, route.query
    with torch.no_grad():
        ev = torch.cat([model.evidence(model.code(model.encode(q[t:t + 1])))
                        for t in range(len(q))])
    want_refs, want_v = reference_loop(ev.double().numpy(), model.ring.shift.double().numpy(),
                                       *model.ring.params, model.unit_centre.numpy(), cfg)
    assert np.ptp(want_v) > 0.1  # the loop really changed speed on this route
    state, refs, speeds = None, [], []
    for t in range(len(q)):
        out, state = model.step(q[t:t + 1], state)
        refs.append(int(out.reference))
        speeds.append(float(state.velocity))
    assert refs == want_refs.tolist()
    np.testing.assert_allclose(speeds, want_v, atol=1e-9)
    assert model.run(q).matches.reference.tolist() == refs  # run: the inference module


def test_run_scans_with_the_velocity_loop_and_equals_the_modules_step(route):
    model = fitted(route, ring_velocity="adaptive")
    module = model.inference()
    assert module.kernels["scan"] == "velocity_loop"
    assert model.inference("portable").kernels["scan"] == "velocity_loop"
    assert fitted(route).inference().kernels["scan"] == "numpy"
    with pytest.raises(NeuralError, match="velocity_loop"):
        model.inference({"scan": "numpy"})
    with pytest.raises(NeuralError, match="velocity_loop"):
        fitted(route).inference({"scan": "velocity_loop"})
    res = model.run(route.query)
    state, refs = None, []
    for t in range(len(route.query)):
        out, state = module.step(route.query[t:t + 1], state)
        refs.append(int(out.reference))
        torch.testing.assert_close(out.activity[0], res.activity[t], atol=1e-5, rtol=1e-5)
    assert refs == res.matches.reference.tolist()


def test_adaptive_state_is_checked(route):
    model = fitted(route, ring_velocity="adaptive")
    frame = route.query[:1]
    _, state = model.step(frame)
    assert isinstance(state, VelocityState)
    with pytest.raises(NeuralError, match="VelocityState"):
        model.step(frame, RingState(state.activity))
    with pytest.raises(NeuralError, match="do not fit"):
        model.step(route.query[:2], state)


# ---------------------------------------------------------------- the estimator
@pytest.mark.parametrize("speed", [0.7, 1.4])
def test_the_estimate_converges_to_the_demo_speed(speed):
    d = make_demo(n_reference=120, size=(48, 64), speed=speed, seed=1)
    model = NeuralSeqSLAM(NeuralConfig.adaptive_velocity(hidden=1024))
    model.fit(d.reference, log=False)
    state, speeds = None, []
    for t in range(len(d.query)):
        _, state = model.step(d.query[t:t + 1], state)
        speeds.append(float(state.velocity))
    late = np.array(speeds[len(speeds) // 2:])
    assert abs(np.median(late) - speed) < 0.05, np.round(late, 2)


def test_a_relocalisation_jump_is_bounded_and_recovers():
    cfg = NeuralConfig(ring_velocity="adaptive")
    tracker = VelocityTracker(cfg.velocity_window, cfg.velocity_min, cfg.velocity_max,
                              cfg.velocity_tolerance, cfg.velocity_rate)
    state = tracker.initial(torch.zeros(1, 4))
    speeds = []
    for t in range(160):  # 0.7x, then a jump of 60 frames forward at t = 80
        pos = 0.7 * t + (60 if t >= 80 else 0)
        state = tracker.update(state, torch.tensor([round(pos)]), state.activity)
        speeds.append(float(state.velocity))
    speeds = np.array(speeds)
    assert abs(speeds[75:80] - 0.7).max() < 0.05  # converged before the jump
    jump = speeds[80:80 + cfg.velocity_window]
    assert jump.min() >= 0.65 and jump.max() <= 1.0  # untrusted: back towards 1, not 4
    assert abs(speeds[-20:] - 0.7).max() < 0.05  # recovered


@pytest.mark.filterwarnings("ignore:a route of 60 frames on 20 output units")
@pytest.mark.filterwarnings("ignore:ring_velocity=.adaptive. on 3.0 frames per unit")
def test_tolerance_scales_with_the_frames_per_unit(route):
    one = VelocityTracker.from_model(fitted(route, ring_velocity="adaptive"))
    assert one.tolerance == 3.0  # 60 frames on 60 units
    coarse = fitted(route, ring_velocity="adaptive", n_output=20)  # 3 frames per unit
    assert VelocityTracker.from_model(coarse).tolerance == 9.0


# ---------------------------------------------------------------- the spiking form refuses it
def test_spiking_form_refuses_the_adaptive_model(route):
    """(The float ONNX graph holds it: tests/test_export_onnx_velocity.py; the integer
    format version 3: tests/test_export_int_velocity.py.)"""
    from torchseq.neural.spiking import SpikingError, SpikingSeqSLAM

    model = fitted(route, ring_velocity="adaptive")
    with pytest.raises(SpikingError, match="ring_velocity='adaptive'"):  # NIR is built from it
        SpikingSeqSLAM.convert(model, route.reference)


# ---------------------------------------------------------------- config and checkpoint
@pytest.mark.parametrize("field, value, match", [
    ("ring_velocity", "auto", "ring_velocity must be one of 'fixed', 'adaptive'"),
    ("velocity_window", 2, "velocity_window must be in 3..4096"),
    ("velocity_window", 8.0, "velocity_window must be an integer"),
    ("velocity_min", 1.5, "velocity_min must be a finite number in \\[0, 1\\]"),
    ("velocity_max", 0.9, "velocity_max must be a finite number in \\[1, 8\\]"),
    ("velocity_max", math.inf, "velocity_max must be a finite number"),
    ("velocity_tolerance", -1.0, "velocity_tolerance must be a finite number"),
    ("velocity_rate", 0.0, "velocity_rate must be a finite number in \\(0, 1\\]"),
])
def test_bad_velocity_fields_are_refused(field, value, match):
    with pytest.raises(NeuralError, match=match):
        NeuralConfig(**{field: value}).validate()


def test_checkpoint_round_trips_the_adaptive_settings(route, tmp_path):
    model = fitted(route, ring_velocity="adaptive", velocity_window=9, velocity_rate=0.5)
    model.save(tmp_path / "m.pt")
    back = NeuralSeqSLAM.load(tmp_path / "m.pt")
    assert back.config == model.config
    assert back.run(route.query).matches.reference.tolist() == \
        model.run(route.query).matches.reference.tolist()
    old = {k: v for k, v in model.config.to_dict().items() if not k.startswith(("ring_vel",
                                                                                "velocity_"))}
    assert NeuralConfig.from_dict(old).ring_velocity == "fixed"  # older files: the fixed ring


# ---------------------------------------------------------------- what it buys
@pytest.mark.slow
def test_demo_severe_recall_with_the_adaptive_ring():
    """demo-severe (strong lighting change at 0.8x speed): the fixed ring 0.84, adaptive 1.0."""
    d = make_demo(gain=0.45, gamma=2.4, gradient=0.45, noise=20.0)
    model = NeuralSeqSLAM(NeuralConfig.adaptive_velocity())
    model.fit(d.reference, log=False)
    assert evaluate(model.run(d.query).matches, d.ground_truth)["recall_at_1"] >= 0.95


@pytest.mark.filterwarnings("ignore:a route of 12 frames on 6 output units")
def test_fit_warns_when_the_adaptive_ring_gets_units_of_several_frames():
    """Measured worse than the fixed ring there (docs/results/neural.md, Long routes): said
    loudly."""
    import warnings as _w

    frames = torch.rand(12, 24, 32) * 255
    small = dict(hidden=256, k_fraction=0.1)
    with pytest.warns(UserWarning, match="ring_velocity='adaptive' on 2.0 frames per unit"):
        NeuralSeqSLAM(NeuralConfig.adaptive_velocity(n_output=6, **small)).fit(frames)
    with _w.catch_warnings():
        _w.filterwarnings("ignore", message="a route of", category=UserWarning)
        _w.filterwarnings("error", message="ring_velocity='adaptive'", category=UserWarning)
        NeuralSeqSLAM(NeuralConfig.adaptive_velocity(n_output=12, **small)).fit(frames)
        NeuralSeqSLAM(NeuralConfig.adaptive_velocity(n_output=8, **small)).fit(frames)  # 1.5

import fractions

import numpy as np
import pytest
import torch
from conftest import DEVICES, coarse_units_expected

from torchseq.neural import NeuralConfig, NeuralError, NeuralResult, NeuralSeqSLAM, NeuralStep
from torchseq.neural.model import seqslam_bytes

SMALL = dict(hidden=1024, n_output=555)


ROUTE = dict(n_reference=80, seed=3)  # the conftest ``route`` fixture's demo


@pytest.fixture(scope="module")
def fitted(route):
    model = NeuralSeqSLAM(NeuralConfig(**SMALL))
    log = model.fit(route.reference)
    return model, log


def test_fit_log_and_buffers(fitted, route):
    model, log = fitted
    r = route.reference.shape[0]
    assert model.n_units == r and log.winners.tolist() == list(range(r))
    assert log.evidence.shape == (r, r)
    assert torch.equal(log.evidence.argmax(1), log.winners)  # each frame excites its own unit
    assert torch.equal(model.unit_to_reference[:, 0], torch.arange(r))
    assert torch.equal(model.unit_to_reference[:, 1], torch.arange(1, r + 1))
    sd = model.state_dict()
    for name in ("l1.weight", "l1.mask", "l3.weight", "l3.mask", "ring.shift", "cohorts",
                 "unit_to_reference", "unit_centre"):
        assert name in sd
    # Hebbian weights live inside the mask only
    assert (sd["l3.weight"][sd["l3.mask"] == 0] == 0).all()


def test_exact_replay_is_recognised_exactly(fitted, route):
    model, _ = fitted
    res = model.run(route.reference)
    assert isinstance(res, NeuralResult) and res.activity.shape == (80, 80)
    assert not res.matches.lower_is_better
    assert torch.equal(res.matches.reference, torch.arange(80))
    assert (res.matches.score > 0).all()


def test_step_equals_run_and_batches_are_independent(fitted, route):
    model, _ = fitted
    q = route.query[:30]
    res = model.run(q)
    state, refs, acts = None, [], []
    for t in range(30):
        # stream 0 sees the query, stream 1 the reference backwards: independent streams
        frames = torch.stack([q[t], route.reference[79 - t]])
        out, state = model.step(frames, state)
        assert isinstance(out, NeuralStep) and out.activity.shape == (2, 80)
        refs.append(out.reference)
        acts.append(out.activity[0])
    torch.testing.assert_close(torch.stack(acts), res.activity, atol=1e-5, rtol=1e-5)
    assert torch.equal(torch.stack(refs)[:, 0], res.matches.reference)


def stretched(frames, speed):
    idx = np.floor(np.arange(0, frames.shape[0] - 1e-9, speed)).astype(np.int64)
    return frames[torch.from_numpy(idx)], idx


@pytest.mark.parametrize("speed,floor", [(0.5, 0.95), (0.7, 0.95), (1.4, 0.95), (2.0, 0.9)])
def test_time_stretched_replay(fitted, route, speed, floor):
    model, _ = fitted
    query, idx = stretched(route.reference, speed)
    ref = model.run(query).matches.reference.numpy()
    hit = np.abs(ref - idx) <= 2
    assert hit.mean() >= floor, (speed, hit.mean())


def test_demo_query_recall(fitted, route):
    model, _ = fitted
    ref = model.run(route.query).matches.reference.numpy()
    ok = route.ground_truth[ref, np.arange(len(ref))]
    assert ok.mean() >= 0.9  # measured 0.929 (small model: 1024 L2 units, 20% L2 -> L3 mask)


def test_more_frames_than_units(route):
    # the ring's own readout (the unit search, the default here, is tests/test_unit_search.py)
    model = NeuralSeqSLAM(NeuralConfig(hidden=1024, n_output=30, unit_search="off"))
    with pytest.warns(UserWarning, match=r"80 frames on 30 output units .*: 2\.7 frames per"):
        model.fit(route.reference)  # said: places are units of 80 / 30 frames
    assert model.n_units == 30
    spans = model.unit_to_reference
    assert int(spans[0, 0]) == 0 and int(spans[-1, 1]) == 80
    assert torch.equal(spans[1:, 0], spans[:-1, 1])
    res = model.run(route.reference)
    unit = res.activity.argmax(1)
    t = torch.arange(80)
    inside = (spans[unit, 0] <= t) & (t < spans[unit, 1])
    assert inside.float().mean() >= 0.95
    assert torch.equal(res.matches.reference, model.unit_centre[unit])


def test_checkpoint_round_trip(fitted, route, tmp_path):
    model, _ = fitted
    path = tmp_path / "m.pt"
    model.save(path, extra={"route": "demo", "n": 80})
    assert not list(tmp_path.glob("*.tmp"))
    back = NeuralSeqSLAM.load(path)
    assert back.extra == {"route": "demo", "n": 80}
    assert back.config == model.config
    for (k, a), (k2, b) in zip(model.state_dict().items(), back.state_dict().items()):
        assert k == k2 and torch.equal(a, b)
    a, b = model.run(route.query), back.run(route.query)
    assert torch.equal(a.activity, b.activity)
    assert torch.equal(a.matches.reference, b.matches.reference)


def test_checkpoint_errors(fitted, tmp_path):
    model, _ = fitted
    with pytest.raises(NeuralError, match="no such"):
        NeuralSeqSLAM.load(tmp_path / "missing.pt")
    path = tmp_path / "m.pt"
    model.save(path)
    data = path.read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(NeuralError, match="not a readable"):
        NeuralSeqSLAM.load(tmp_path / "cut.pt")
    blob = torch.load(path, weights_only=True)
    blob["state_dict"]["l1.mask"] = blob["state_dict"]["l1.mask"][:, :5]
    torch.save(blob, tmp_path / "bad_shape.pt")
    with pytest.raises(NeuralError, match="does not fit"):
        NeuralSeqSLAM.load(tmp_path / "bad_shape.pt")
    del blob["state_dict"]["ring.shift"]
    torch.save(blob, tmp_path / "missing.pt")
    with pytest.raises(NeuralError, match="does not fit"):
        NeuralSeqSLAM.load(tmp_path / "missing.pt")
    torch.save({"format": "torchseq.neural/99"}, tmp_path / "v99.pt")
    with pytest.raises(NeuralError, match="format"):
        NeuralSeqSLAM.load(tmp_path / "v99.pt")
    with pytest.raises(NeuralError, match="not learnt"):
        NeuralSeqSLAM(NeuralConfig(**SMALL)).save(tmp_path / "x.pt")


def test_fit_again_replaces_the_route(route):
    model = NeuralSeqSLAM(NeuralConfig(hidden=512))
    model.fit(route.reference[:30], log=False)
    model.run(route.query[:5])  # folds the weights
    model.fit(route.reference[:50], log=False)
    assert model.n_units == 50 and model.unit_to_reference.shape == (50, 2)
    assert torch.equal(model.run(route.reference[:50]).matches.reference, torch.arange(50))


def test_deterministic_under_seed(route):
    ref = route.reference[:30]
    a = NeuralSeqSLAM(NeuralConfig(hidden=512, seed=7))
    b = NeuralSeqSLAM(NeuralConfig(hidden=512, seed=7))
    c = NeuralSeqSLAM(NeuralConfig(hidden=512, seed=8))
    for m in (a, b, c):
        m.fit(ref, log=False)
    for k, v in a.state_dict().items():
        assert torch.equal(v, b.state_dict()[k])
    assert not torch.equal(a.l1.mask, c.l1.mask)
    assert torch.equal(a.run(route.query[:20]).activity, b.run(route.query[:20]).activity)


@pytest.mark.parametrize("device", DEVICES)
def test_device_and_colour_input(route, device):
    model = NeuralSeqSLAM(NeuralConfig(hidden=512), device=device)
    model.fit(route.reference[:20], log=False)
    rgb = route.reference[:20, :, :, None].expand(-1, -1, -1, 3)
    out = model.run(rgb)
    assert torch.equal(out.matches.reference, torch.arange(20))


def test_errors(fitted, route):
    model, _ = fitted
    fresh = NeuralSeqSLAM(NeuralConfig(hidden=256))
    with pytest.raises(NeuralError, match="fit"):
        fresh.step(route.query[:1])
    with pytest.raises(NeuralError, match="fit"):
        fresh.run(route.query)
    with pytest.raises(NeuralError, match="T >= 2"):
        fresh.fit(route.reference[:1])
    with pytest.raises(NeuralError, match="T >= 2"):
        fresh.fit(route.reference[:0])
    with pytest.raises(NeuralError, match=r"\(T, H, W\)"):
        fresh.fit(route.reference[0])
    with pytest.raises(NeuralError, match="empty"):
        model.run(route.query[:0])
    with pytest.raises(NeuralError, match=r"\(B, H, W\)"):
        model.step(route.query[0])
    bad = route.query[:3].clone()
    bad[1, 5, 5] = float("nan")
    with pytest.raises(NeuralError, match="NaN"):
        model.run(bad)
    with pytest.raises(NeuralError, match="NaN"):
        fresh.fit(torch.cat([route.reference[:4], bad]))
    _, state = model.step(route.query[:2])
    with pytest.raises(NeuralError, match="state"):
        model.step(route.query[:3], state)


def test_config_validation_and_dict():
    cfg = NeuralConfig()
    assert cfg.n_input == 768 and cfg.k == 307 and cfg.n_output == 4096 and cfg.density == 0.2
    t1 = NeuralConfig.table1()
    assert t1.n_output == 555 and t1.k == 154 and t1.density_out == 0.2
    assert t1.hidden == 3072 and t1.density == 0.2
    assert NeuralConfig.table1(seed=3).seed == 3
    assert NeuralConfig.from_dict(cfg.to_dict()) == cfg
    for bad in (dict(input_size=(25, 32)), dict(patch_mode="x"), dict(density=0.0),
                dict(k_fraction=1.5), dict(ring_decay=1.0), dict(n_cohorts=0),
                dict(hebbian="x"), dict(hidden=0), dict(ring_spread=0)):
        with pytest.raises(NeuralError):
            NeuralConfig(**bad).validate()
    with pytest.raises(NeuralError, match="unknown"):
        NeuralConfig.from_dict({"bogus": 1})


def test_model_bytes(fitted):
    model, _ = fitted
    dense = model.model_bytes()
    sparse = model.model_bytes(masked_only=True)
    expect = sum(t.numel() * t.element_size() for t in model.state_dict().values())
    assert dense == expect and sparse < dense
    assert seqslam_bytes(80) == 80 * 2048 * 4
    cmp = model.memory_comparison()
    assert cmp == {"n_reference": 80, "n_units": 80, "neural_bytes": dense,
                   "neural_masked_bytes": sparse, "seqslam_bytes": 80 * 2048 * 4}
    # masked store: each weight row keeps exactly its mask's fan-in values
    l1 = model.l1.out_features * model.l1.fan_in * 4
    assert sparse == dense - model.l1.mask.numel() * 8 - model.l3.mask.numel() * 8 + l1 + \
        model.l3.out_features * model.l3.fan_in * 4


def test_wrapped_ring_run_equals_steps(route):
    model = NeuralSeqSLAM(NeuralConfig(hidden=512, ring_wrap=True))
    model.fit(route.reference[:30], log=False)
    assert model.ring.shift[0, 29] > 0  # the loop closes: last place leads to the first
    query = torch.cat([route.reference[20:30], route.reference[:10]])
    res = model.run(query)
    state, acts = None, []
    for t in range(len(query)):
        out, state = model.step(query[t:t + 1], state)
        acts.append(out.activity[0])
    torch.testing.assert_close(torch.stack(acts), res.activity, atol=1e-5, rtol=1e-5)
    expect = torch.cat([torch.arange(20, 30), torch.arange(10)])
    assert (res.matches.reference == expect).float().mean() >= 0.9


def test_bfloat16_l1_is_close_and_opt_in(fitted, route):
    model, _ = fitted
    exact = model.run(route.query)
    again = model.run(route.query)
    approx = model.run(route.query, l1_dtype=torch.bfloat16)
    assert torch.equal(exact.activity, again.activity)  # the exact path is not affected
    same = (approx.matches.reference == exact.matches.reference).float().mean()
    assert same >= 0.95
    assert not torch.equal(approx.activity, exact.activity)


def test_progress_callback_starts_at_zero_and_ends_at_the_total(route):
    # a bar must start its clock before the work (else a one-batch fit shows millions of
    # frames/s), then count up to the total in batches
    model = NeuralSeqSLAM(NeuralConfig(hidden=256, n_output=20, chunk=16))
    calls = []
    with coarse_units_expected():  # a small model: units of several frames
        model.fit(route.reference[:40], progress=lambda done, total: calls.append((done, total)))
    assert calls == [(0, 40), (16, 40), (32, 40), (40, 40)]
    calls.clear()
    model.run(route.query[:20], progress=lambda done, total: calls.append((done, total)))
    assert calls[0] == (0, 20) and calls[-1] == (20, 20)
    assert all(a[0] < b[0] for a, b in zip(calls, calls[1:]))


def test_the_engine_times_nothing():
    # timing belongs to the scripts (issue 10, section 4): results carry no wall times
    import dataclasses

    from torchseq.neural import NeuralFitLog

    assert [f.name for f in dataclasses.fields(NeuralResult)] == [
        "matches", "activity", "stage", "scores", "ranked", "ranked_score"]
    assert [f.name for f in dataclasses.fields(NeuralFitLog)] == [
        "winners", "evidence", "unit_to_reference", "self_check"]
    import torchseq.neural.model as model_module

    assert not hasattr(model_module, "time")


def test_unreadable_checkpoint_errors_are_one_plain_line(tmp_path):
    # torch's safe-loader text is multi-line with terminal escapes and advises
    # weights_only=False; the library's error names the cause in one plain line instead
    (tmp_path / "config.json").write_text('{"hidden": 512}')
    torch.save({"format": "x", "bad": fractions.Fraction(1, 2)}, tmp_path / "pickled.pt")
    expect = {"config.json": "no intact torch.save archive",
              "pickled.pt": "safe loader .* refuses: Unsupported global: GLOBAL "
                            "fractions.Fraction"}
    for name, why in expect.items():
        with pytest.raises(NeuralError, match=f"not a readable torchseq checkpoint .*{why}") as e:
            NeuralSeqSLAM.load(tmp_path / name)
        text = str(e.value)
        assert "\n" not in text and "\x1b" not in text and "weights_only` set to `False" not in text

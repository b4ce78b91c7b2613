"""Novelty recruitment (``NeuralConfig.recruit="novelty"``): a new unit where the L2 codes
stop matching the current unit, checked against a plain-loop reference written here."""

import warnings
from fractions import Fraction

import numpy as np
import pytest
import torch

from torchseq.demo import make_demo
from torchseq.export.int_model import choose_pool, device_frames, integer_model
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.neural import NeuralConfig, NeuralError, NeuralSeqSLAM
from torchseq.neural.learning import (
    learn_readout,
    novelty_starts,
    recruit_by_novelty,
    recruit_units,
)


# ---------------------------------------------------------------- plain-loop reference
def loop_starts(codes: list[list[float]], k: int, threshold: float) -> list[int]:
    """The rule on dense 0/1 codes with plain loops, in exact rationals: frame t starts a
    new unit when (code_t . mean code of the current unit's frames) / k < threshold."""
    starts, total, held = [0], [int(v) for v in codes[0]], 1  # the unit's code sum, frames
    for t in range(1, len(codes)):
        dot = sum(int(a) * b for a, b in zip(codes[t], total))
        if Fraction(dot, k * held) < Fraction(threshold):  # code_t . (total / held) / k
            starts.append(t)
            total, held = [0] * len(total), 0
        total = [a + int(b) for a, b in zip(total, codes[t])]
        held += 1
    return starts


def loop_recruit(codes: list[list[float]], k: int, n_units: int) -> list[int]:
    """Bisection on [0, 2] for the largest threshold with at most n_units stretches, then
    the longest stretch halved (earliest first) until there are n_units."""
    lo, hi = 0.0, 2.0
    best = loop_starts(codes, k, lo)
    for _ in range(60):
        if len(best) == n_units:
            break
        mid = (lo + hi) / 2
        if mid in (lo, hi):
            break
        got = loop_starts(codes, k, mid)
        if len(got) <= n_units:
            lo, best = mid, got
        else:
            hi = mid
    bounds = best + [len(codes)]
    while len(bounds) - 1 < n_units:
        lengths = [b - a for a, b in zip(bounds, bounds[1:])]
        i = lengths.index(max(lengths))
        a, b = bounds[i], bounds[i + 1]
        mid = a + (b - a) // 2
        cut = None
        for t in range(a + 1, b):  # fewest winners shared with t - 1, then nearest mid
            key = (sum(x * y for x, y in zip(codes[t], codes[t - 1])), abs(t - mid))
            if cut is None or key < cut[0]:
                cut = (key, t)
        bounds.insert(i + 1, cut[1])
    return bounds[:-1]


def drifting_winners(rng, n_frames: int, hidden: int, k: int, moves) -> np.ndarray:
    """(T, k) winner indices of a code that drifts: each frame replaces ``moves[t]`` winners."""
    cur = rng.choice(hidden, k, replace=False)
    out = []
    for t in range(n_frames):
        m = int(moves[t % len(moves)])
        if m:
            free = np.setdiff1d(np.arange(hidden), cur)
            cur = cur.copy()
            cur[rng.choice(k, m, replace=False)] = rng.choice(free, m, replace=False)
        out.append(np.sort(cur))
    return np.array(out)


def dense(winners: np.ndarray, hidden: int) -> list[list[float]]:
    codes = np.zeros((len(winners), hidden))
    np.put_along_axis(codes, winners, 1.0, axis=1)
    return codes.tolist()


# ---------------------------------------------------------------- the segmentation
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_segmentation_equals_the_plain_loop(seed):
    rng = np.random.default_rng(seed)
    hidden, k = 40, 8
    w = drifting_winners(rng, 70, hidden, k, moves=rng.integers(0, 4, 13))
    codes = dense(w, hidden)
    for threshold in (0.0, 0.3, 0.55, 0.7, 0.8, 0.9, 1.0, 1.5):
        assert novelty_starts(w, threshold).tolist() == loop_starts(codes, k, threshold)
    assert novelty_starts(w, 0.0).tolist() == [0]
    assert novelty_starts(w, 1.5).tolist() == list(range(70))
    for n in (1, 2, 5, 11, 23, 40, 69, 70):
        unit, spans = recruit_by_novelty(torch.from_numpy(w), n)
        starts = loop_recruit(codes, k, n)
        assert spans[:, 0].tolist() == starts
        # exact count, contiguous cover of the route, unit_of_frame agrees with the spans
        assert spans.shape == (n, 2) and int(spans[0, 0]) == 0 and int(spans[-1, 1]) == 70
        assert torch.equal(spans[1:, 0], spans[:-1, 1]) and bool((spans[:, 1] > spans[:, 0]).all())
        assert torch.equal(unit, torch.repeat_interleave(torch.arange(n),
                                                         spans[:, 1] - spans[:, 0]))


def test_one_frame_per_unit_is_the_uniform_recruitment():
    w = drifting_winners(np.random.default_rng(3), 30, 50, 5, moves=[1, 2])
    for a, b in zip(recruit_by_novelty(w, 30), recruit_units(30, 30)):
        assert torch.equal(a, b)


def test_stretches_of_identical_codes_become_the_units():
    rng = np.random.default_rng(4)
    lengths = [5, 1, 9, 3, 2, 7, 4]
    w = np.concatenate([np.repeat(np.sort(rng.choice(60, 6, replace=False))[None], n, 0)
                        for n in lengths])  # a new random code per stretch
    first = np.concatenate([[0], np.cumsum(lengths)[:-1]]).tolist()
    _, spans = recruit_by_novelty(w, len(lengths))
    assert spans[:, 0].tolist() == first
    # fewer units: whole stretches merge; every boundary is still a stretch change
    _, spans = recruit_by_novelty(w, 4)
    assert set(spans[:, 0].tolist()) <= set(first)
    # one code for the whole route: no threshold separates it and no frame differs from
    # the previous, so the longest stretch is halved until there are enough
    same = np.repeat(w[:1], 12, 0)
    assert recruit_by_novelty(same, 4)[1][:, 0].tolist() == [0, 3, 6, 9]


def test_bad_winners_and_counts_are_refused():
    w = np.zeros((5, 2), np.int64) + [0, 1]
    twice = np.zeros((5, 2), np.int64) + [1, 1]
    for bad, n in ((w, 0), (w, 6), (w.astype(float), 2), (w[:, :0], 2), (w - 3, 2), (twice, 2)):
        with pytest.raises(ValueError):
            recruit_by_novelty(bad, n)
    # sparse labels are compacted, not used to size the sums
    big = np.array([[2**40, 2**41], [2**40, 2**41], [5, 6]], np.int64)
    assert novelty_starts(big, 0.5).tolist() == [0, 2]


# ---------------------------------------------------------------- the model
def blocky_route(lengths, seed=5, size=(24, 32)) -> torch.Tensor:
    """Frames in stretches of identical random images (a new image per stretch)."""
    g = torch.Generator().manual_seed(seed)
    return torch.cat([(torch.rand(1, *size, generator=g) * 255).expand(n, -1, -1)
                      for n in lengths])


def test_fit_puts_unit_boundaries_at_the_scenery_changes():
    lengths = [6, 2, 11, 3, 8, 1, 5]
    ref = blocky_route(lengths)
    # the ring's decisions (unit_search="off"; the search decides alike for both rules here)
    cfg = NeuralConfig(unit_search="off", hidden=512, n_output=len(lengths), recruit="novelty")
    model = NeuralSeqSLAM(cfg)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # several frames per unit
        log = model.fit(ref)
    first = np.concatenate([[0], np.cumsum(lengths)[:-1]]).tolist()
    assert model.unit_to_reference[:, 0].tolist() == first
    assert torch.equal(log.unit_to_reference, model.unit_to_reference)
    spans = model.unit_to_reference
    assert torch.equal(model.unit_centre, (spans[:, 0] + spans[:, 1] - 1) // 2)
    # each unit's weights are learnt over its own frames: the kept winner indices give the
    # same weights as codes computed afresh (the uniform path's stream)
    codes = [(0, len(ref), model.code(model.encode(ref)))]
    want = learn_readout(codes, log.winners, spans, model.l3.mask, cfg.hebbian,
                         cfg.eps, cfg.l3_levels)
    assert torch.equal(model.l3.weight, want)
    # and the shift matrix from that winner sequence: long units stay longer
    assert model.ring.shift[2, 2] > model.ring.shift[1, 1]
    # the reference played back is placed in the right stretch of scenery more often than
    # by units that straddle two stretches (the misses: the ring lags at each change)
    uniform = NeuralSeqSLAM(NeuralConfig(unit_search="off", hidden=512, n_output=len(lengths)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        uniform.fit(ref, log=False)
    assert uniform.unit_to_reference[:, 0].tolist() == recruit_units(36, 7)[1][:, 0].tolist()
    scene = torch.repeat_interleave(torch.arange(len(lengths)), torch.tensor(lengths))
    right = [float((scene[m.run(ref).matches.reference] == scene).float().mean())
             for m in (model, uniform)]
    assert right[0] >= 0.8 and right[0] > right[1]  # measured 0.83 against 0.78


def test_routes_within_n_output_give_the_uniform_model_exactly():
    ref = make_demo(n_reference=30, size=(24, 32), step=4.0).reference
    a = NeuralSeqSLAM(NeuralConfig(unit_search="off", hidden=256, n_output=30))
    b = NeuralSeqSLAM(NeuralConfig(unit_search="off", hidden=256, n_output=40, recruit="novelty"))
    a.fit(ref, log=False)
    with pytest.warns(UserWarning, match="recruit='novelty' has no effect on a route of 30 "
                      "frames with n_output=40"):
        b.fit(ref, log=False)
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    assert NeuralConfig().recruit == "uniform"


def test_recruit_is_validated_and_travels_in_checkpoints(tmp_path):
    with pytest.raises(NeuralError, match="recruit must be one of 'uniform', 'novelty'"):
        NeuralConfig(unit_search="off", recruit="surprise").validate()
    with pytest.raises(NeuralError, match="recruit must be one of"):
        NeuralConfig(unit_search="off", recruit=True).validate()
    d = NeuralConfig().to_dict()
    del d["recruit"]  # a checkpoint written before the field existed
    assert NeuralConfig.from_dict(d).recruit == "uniform"
    ref = blocky_route([4, 2, 6, 3])
    model = NeuralSeqSLAM(NeuralConfig(
        unit_search="off", hidden=256, n_output=4, recruit="novelty"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(ref, log=False)
    model.save(tmp_path / "m.pt")
    back = NeuralSeqSLAM.load(tmp_path / "m.pt")
    assert back.config.recruit == "novelty"
    assert back.unit_to_reference[:, 0].tolist() == [0, 4, 6, 12]
    assert torch.equal(back.run(ref).matches.reference, model.run(ref).matches.reference)


# ---------------------------------------------------------------- exports, unequal spans
def test_integer_export_follows_unequal_spans():
    d = make_demo(n_reference=60, size=(48, 64), seed=1)
    model = NeuralSeqSLAM(NeuralConfig(
        unit_search="off", hidden=512, n_output=20, readout="interpolate",
                                       recruit="novelty"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(d.reference, log=False)
    lengths = (model.unit_to_reference[:, 1] - model.unit_to_reference[:, 0]).unique()
    assert lengths.numel() >= 3  # the units really are unequal
    pool = choose_pool(tuple(d.query.shape[1:]), model.config.input_size)
    im = integer_model(model, pool)
    assert np.array_equal(im.arrays["unit_to_ref"], model.unit_to_reference.numpy())
    frames = device_frames(d.query, model.config.input_size, pool)
    ref_int = IntegerRuntime(im).run(frames)[0]
    ref_float = model.run(torch.from_numpy(frames).float()).matches.reference.numpy()
    assert np.mean(ref_int == ref_float) >= 0.95


def test_spiking_form_follows_unequal_spans():
    from torchseq.neural.spiking import SpikingSeqSLAM

    d = make_demo(n_reference=100, size=(48, 64))
    model = NeuralSeqSLAM(NeuralConfig(
        unit_search="off", hidden=1024, n_output=50, recruit="novelty"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(d.reference, log=False)
    lengths = model.unit_to_reference[:, 1] - model.unit_to_reference[:, 0]
    assert int(lengths.max()) >= 3  # unequal units (the mean is 2)
    sp = SpikingSeqSLAM.convert(model, d.reference)
    rate = model.run(d.query).matches.reference.numpy()
    spk = sp.run(d.query)["reference"].numpy()
    assert np.mean(rate == spk) >= 0.94  # measured 0.96; tests/test_spiking.py: 0.94 as well

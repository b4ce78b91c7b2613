"""Each rule of Neural SeqSLAM against a plain loop written here from docs/guide/neural.md
("Step maths").

The loops use Python floats and lists only, so they share no code with the library.
"""

import itertools
import math

import pytest
import torch
from conftest import coarse_units_expected

from torchseq.demo import make_demo
from torchseq.layers import cohort_normalise
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.neural.learning import cohort_membership, hebbian_weights, recruit_units
from torchseq.neural.readout import decide


def cohort_loop(evidence, cohort_of_unit, eps):
    """z-score each row within each cohort: population std, eps added to the std."""
    out = []
    for row in evidence.tolist():
        z = [0.0] * len(row)
        for c in set(cohort_of_unit):
            units = [u for u, cu in enumerate(cohort_of_unit) if cu == c]
            mean = sum(row[u] for u in units) / len(units)
            std = math.sqrt(sum((row[u] - mean) ** 2 for u in units) / len(units))
            for u in units:
                z[u] = (row[u] - mean) / (std + eps)
        out.append(z)
    return torch.tensor(out, dtype=torch.float64)


def one_hot(cohort_of_unit):
    return torch.nn.functional.one_hot(torch.tensor(cohort_of_unit)).to(torch.float64)


@pytest.mark.parametrize("cohort_of_unit", [
    [0] * 7,  # one cohort
    [0, 0, 0, 1, 1, 1, 1, 2, 2, 2],  # several, uneven
    [0, 1, 0, 2, 1, 2, 2, 0, 1, 1, 0],  # units of a cohort need not be adjacent
    [0, 0, 1, 2, 2, 2],  # a cohort of one unit
])
@pytest.mark.parametrize("eps", [1e-6, 0.5])
@pytest.mark.parametrize("kernel", ["torch", "numpy"])
def test_cohort_normalise_equals_loop(cohort_of_unit, eps, kernel):
    g = torch.Generator().manual_seed(len(cohort_of_unit))
    e = torch.randn(5, len(cohort_of_unit), generator=g, dtype=torch.float64) * 3 + 1
    want = cohort_loop(e, cohort_of_unit, eps)
    got = cohort_normalise(e, one_hot(cohort_of_unit), eps, kernel=kernel)
    torch.testing.assert_close(got, want, atol=1e-12, rtol=1e-12)
    rect = cohort_normalise(e, one_hot(cohort_of_unit), eps, rectify=True, kernel=kernel)
    torch.testing.assert_close(rect, want.clamp_min(0.0), atol=1e-12, rtol=1e-12)


def zscore_loop(frame, patch):
    """Patch z-scores of one (H, W) frame: sample std, a flat block gives 0."""
    rows = frame.tolist()
    out = [[0.0] * len(rows[0]) for _ in rows]
    for r0 in range(0, len(rows), patch):
        for c0 in range(0, len(rows[0]), patch):
            px = [rows[r][c] for r in range(r0, r0 + patch) for c in range(c0, c0 + patch)]
            mean = sum(px) / len(px)
            std = math.sqrt(sum((p - mean) ** 2 for p in px) / (len(px) - 1))
            for r in range(r0, r0 + patch):
                for c in range(c0, c0 + patch):
                    out[r][c] = 0.0 if std == 0 else (rows[r][c] - mean) / std
    return torch.tensor(out, dtype=torch.float64)


@pytest.mark.parametrize("patch", [2, 4])
def test_patch_zscore_equals_loop_and_its_kernels_agree_bit_for_bit(patch):
    from torchseq.preprocess import patch_normalise, zscore_pixel_major

    g = torch.Generator().manual_seed(patch)
    frames = torch.rand(3, 8, 12, generator=g) * 255
    frames[1, :patch, :patch] = 7.0  # a flat block
    z = patch_normalise(frames, patch, "zscore")
    for t in range(3):
        torch.testing.assert_close(z[t].double(), zscore_loop(frames[t], patch),
                                   atol=1e-5, rtol=1e-5)
    assert torch.equal(z[1, :patch, :patch], torch.zeros(patch, patch))
    a = zscore_pixel_major(frames, patch, "torch")
    b = zscore_pixel_major(frames, patch, "numpy")
    assert torch.equal(a, b)  # the same element-wise operations in the same order


def test_cohort_normalise_flat_cohorts_give_zero_and_eps_bounds_the_scale():
    cohorts = [0, 0, 0, 1, 1, 1]
    e = torch.tensor([[2.0, 2.0, 2.0, 1.0, 5.0, 3.0],  # cohort 0 flat
                      [4.0, 4.0, 4.0, 7.0, 7.0, 7.0]], dtype=torch.float64)  # both flat
    got = cohort_normalise(e, one_hot(cohorts), 1e-6)
    assert torch.equal(got[0, :3], torch.zeros(3, dtype=torch.float64))
    assert torch.equal(got[1], torch.zeros(6, dtype=torch.float64))
    torch.testing.assert_close(got, cohort_loop(e, cohorts, 1e-6), atol=1e-12, rtol=1e-12)
    # a tiny spread: eps, not the std, sets the scale
    tiny = torch.tensor([[0.0, 1e-9, 2e-9]], dtype=torch.float64)
    z = cohort_normalise(tiny, one_hot([0, 0, 0]), 1e-3)
    torch.testing.assert_close(z, cohort_loop(tiny, [0, 0, 0], 1e-3), atol=1e-15, rtol=1e-9)
    assert float(z.abs().max()) < 2e-6


@pytest.mark.parametrize("n_units,n_cohorts", [(10, 1), (10, 3), (11, 4), (7, 7), (5, 9),
                                               (555, 8)])
def test_cohort_layout_is_contiguous_near_equal_blocks(n_units, n_cohorts):
    m = cohort_membership(n_units, n_cohorts)
    c = min(n_cohorts, n_units)
    assert m.shape == (n_units, c) and torch.equal(m.sum(1), torch.ones(n_units))
    which = m.argmax(1).tolist()
    for u in range(n_units):  # unit u in cohort floor(u * C / N)
        assert which[u] == u * c // n_units
    assert which == sorted(which)  # contiguous blocks, in order
    sizes = [which.count(k) for k in range(c)]
    assert min(sizes) >= 1 and max(sizes) - min(sizes) <= 1


@pytest.mark.parametrize("n_frames,n_units", [(1, 1), (10, 10), (10, 3), (17, 5), (555, 200)])
def test_recruitment_equals_loop(n_frames, n_units):
    unit, spans = recruit_units(n_frames, n_units)
    want = [t * n_units // n_frames for t in range(n_frames)]
    assert unit.tolist() == want
    for u in range(n_units):
        frames = [t for t in range(n_frames) if want[t] == u]
        assert frames == list(range(frames[0], frames[-1] + 1))  # one contiguous stretch
        assert spans[u].tolist() == [frames[0], frames[-1] + 1]
    lengths = (spans[:, 1] - spans[:, 0]).tolist()
    assert max(lengths) - min(lengths) <= 1


def hebbian_loop(codes, unit_of_frame, mask, rule, eps):
    """Weights of each unit: its frames' mean code (minus the route's, centred), masked,
    divided by the row's sum of absolute values plus eps."""
    n_units, hidden = len(mask), len(mask[0])
    route_mean = [sum(c[j] for c in codes) / len(codes) for j in range(hidden)]
    rows = []
    for u in range(n_units):
        mine = [c for c, w in zip(codes, unit_of_frame) if w == u]
        row = []
        for j in range(hidden):
            v = sum(c[j] for c in mine) / len(mine)
            if rule == "centred":
                v -= route_mean[j]
            row.append(v * mask[u][j])
        norm = sum(abs(v) for v in row) + eps
        rows.append([v / norm for v in row])
    return torch.tensor(rows, dtype=torch.float64)


@pytest.mark.parametrize("rule", ["mean", "centred"])
def test_hebbian_rules_equal_loop(rule):
    g = torch.Generator().manual_seed(4)
    codes = (torch.rand(13, 20, generator=g) < 0.3).to(torch.float64)
    unit, spans = recruit_units(13, 4)
    mask = (torch.rand(4, 20, generator=g) < 0.5).to(torch.float64)
    sums = torch.zeros(4, 20, dtype=torch.float64).index_add_(0, unit, codes)
    counts = (spans[:, 1] - spans[:, 0]).to(torch.float64)
    got = hebbian_weights(sums, counts, codes.mean(0), mask, rule, 1e-6)
    want = hebbian_loop(codes.tolist(), unit.tolist(), mask.tolist(), rule, 1e-6)
    torch.testing.assert_close(got, want, atol=1e-12, rtol=1e-12)
    other = hebbian_loop(codes.tolist(), unit.tolist(), mask.tolist(),
                         "mean" if rule == "centred" else "centred", 1e-6)
    assert not torch.allclose(got, other, atol=1e-3)  # the two rules really differ here


@pytest.mark.parametrize("hebbian", [None, "mean"])  # None: the default config
def test_fit_learns_the_configured_hebbian_rule(hebbian):
    demo = make_demo(n_reference=30, size=(48, 64), seed=1)
    cfg = NeuralConfig(hidden=256, n_output=12, **({} if hebbian is None else
                                                   {"hebbian": hebbian}))
    rule = hebbian or "centred"
    assert cfg.hebbian == rule  # the documented default is the centred rule
    model = NeuralSeqSLAM(cfg)
    with coarse_units_expected():  # a small model: units of several frames
        model.fit(demo.reference, log=False)
    with torch.no_grad():
        codes = model.l2(model.l1(model.encode(demo.reference)))  # the eager layers
    unit = [t * 12 // 30 for t in range(30)]
    w = hebbian_loop(codes.double().tolist(), unit, model.l3.mask.tolist(), rule, cfg.eps)
    # the rows are then rounded to l3_levels steps of max|row| / l3_levels: the learnt weight
    # is the grid point nearest the loop's (float32 vs float64 may pick either at a half)
    step = w.abs().amax(1, keepdim=True) / cfg.l3_levels
    err = (model.l3.weight.double() - w).abs()
    assert bool((err <= step * (0.5 + 1e-4)).all())
    assert float(err.max()) > 1e-6  # (and the rounding did happen)


def test_decide_equals_loop():
    g = torch.Generator().manual_seed(5)
    act = torch.rand(50, 40, generator=g)
    act[3] = 1.0  # all tied: first index wins
    act[4, 10] = act[4, 30] = 2.0  # a tie between two far units: the first one
    centre = torch.arange(40) * 3
    for (window, n), kernel in itertools.product(
            ((5, 40), (2, 40), (30, 40), (39, 40), (0, 40), (5, 6)), ("torch", "numpy")):
        a = act[:, :n] if kernel == "torch" or window != 2 else act[:1, :n]  # (B = 1 too)
        ref, conf = decide(a, centre[:n], window, kernel)
        for b in range(a.shape[0]):
            row = a[b].tolist()
            u = max(range(n), key=lambda i: (row[i], -i))
            rivals = [row[v] for v in range(n) if abs(v - u) > window]
            second = max(rivals) if rivals else min(row)
            assert int(ref[b]) == int(centre[u])
            assert float(conf[b]) == pytest.approx(row[u] - second, abs=1e-7)

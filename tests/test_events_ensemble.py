"""Temporal-window ensembles: one-pass member frames against a per-window loop; matching."""

import numpy as np
import pytest
import torch
from events_oracle import add_event

from torchseq.events import EventStream, accumulate, make_events
from torchseq.events.ensemble import accumulate_ensemble, ensemble_base, match_ensemble
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig


def sample(n=1200, w=10, h=6, seed=0, span=200_000, t0=3_000):
    rng = np.random.default_rng(seed)
    return make_events(np.sort(rng.integers(0, span, n)) + t0, rng.integers(0, w, n),
                       rng.integers(0, h, n), rng.integers(0, 2, n))


def loop_member(ev, w, h, origin, step, L, n_frames, mode):
    """Frame k: events with origin <= t and |t - centre_k| within [-L/2, L/2), one at a time."""
    out = np.zeros((n_frames, h, w))
    for k in range(n_frames):
        lo = origin + k * step + (step - L) / 2
        for e in ev:
            t = int(e["t"])
            if t >= origin and lo <= t < lo + L:
                add_event(out[k], e, mode)
    return out


@pytest.mark.parametrize("mode", ["count", "signed", "binary"])
@pytest.mark.parametrize("anchor", ["first", "zero", 40_000])
def test_members_match_loop(mode, anchor):
    ev = sample()
    windows = (10_000, 6_000, 20_000, 34_000)
    got = accumulate_ensemble(EventStream(ev, (10, 6)), windows, step_us=10_000, mode=mode,
                              anchor=anchor, dtype=torch.float64)
    origin = {"first": int(ev["t"][0]), "zero": 0}.get(anchor, anchor)
    n = (int(ev["t"].max()) - origin) // 10_000 + 1
    assert got.shape == (4, n, 6, 10)
    for i, L in enumerate(windows):
        np.testing.assert_array_equal(got[i].numpy(),
                                      loop_member(ev, 10, 6, origin, 10_000, L, n, mode))
    single = accumulate(ev, (10, 6), window_us=10_000, mode=mode, anchor=anchor,
                        dtype=torch.float64)
    np.testing.assert_array_equal(got[0].numpy(), single.numpy())


def test_downsampled_members_and_base():
    ev = sample(3000, 16, 12, seed=1)
    for mode in ("count", "binary"):
        got = accumulate_ensemble(ev, (10_000, 30_000), sensor_size=(16, 12), mode=mode,
                                  downsample=(4, 4))
        full = accumulate_ensemble(ev, (10_000, 30_000), sensor_size=(16, 12), mode=mode)
        want = torch.nn.functional.adaptive_avg_pool2d(full.flatten(0, 1), (4, 4))
        np.testing.assert_allclose(got.flatten(0, 1).numpy(), want.numpy(), atol=1e-5)
    assert ensemble_base(10_000, (10_000, 20_000, 40_000)) == 5_000
    assert ensemble_base(10_000, (6_000,)) == 2_000
    with pytest.raises(ValueError, match="even"):
        ensemble_base(10_000, (10_001,))
    with pytest.raises(ValueError):
        ensemble_base(10_000, ())


@pytest.mark.parametrize("edges", [False, True])
def test_match_ensemble_single_member_is_seqslam_and_members_combine(edges):
    rng = np.random.default_rng(2)
    ref = torch.from_numpy(rng.uniform(0, 255, (40, 16, 16)).astype(np.float32))
    idx = np.clip(np.round(np.arange(50) * 0.8).astype(int), 0, 39)
    qry = ref[idx] + torch.from_numpy(rng.normal(0, 20, (50, 16, 16)).astype(np.float32))
    cfg = SeqSLAMConfig(image_size=(16, 16), patch_size=4, ds=10, speed_ratio=0.8,
                        edges=edges)
    one = match_ensemble([ref], [qry], cfg)
    plain = SeqSLAM(cfg).match(ref, qry)
    assert torch.equal(one.matches.reference, plain.matches.reference)
    torch.testing.assert_close(one.matches.score, plain.matches.score, equal_nan=True)
    torch.testing.assert_close(one.ranked, plain.ranked)
    # the edge queries (first and last ds/2) are matched exactly when the config asks
    assert bool((one.matches.reference[:5] >= 0).all()) == edges
    torch.testing.assert_close(one.enhanced, plain.enhanced)
    other = ref.flip(-1)  # a second member that sees the place differently
    two = match_ensemble([ref, other], [qry, qry[..., :].flip(-1)], cfg)
    e1 = SeqSLAM(cfg).match(other, qry.flip(-1)).enhanced
    torch.testing.assert_close(two.enhanced, (plain.enhanced + e1) / 2)
    with pytest.raises(ValueError, match="same number"):
        match_ensemble([ref], [qry, qry], cfg)

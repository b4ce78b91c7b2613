"""Fit's self-check (issue 20): the share of the reference, disturbed, that wins its own unit.

The figure's relation to real recall is measured on nordland-b by
``experiments/neural_long_route.py selfcheck`` (docs/results/neural-long-routes.md); these
tests pin its definition against a plain loop and the warning's behaviour.
"""

import json
import warnings

import numpy as np
import pytest
import torch

from torchseq.demo import make_demo
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.neural.selfcheck import (
    SELF_CHECK_FLOOR,
    SELF_CHECK_NOISE,
    disturbed,
    self_recall,
)


def loop_self_recall(units, spans, tol):
    """Independent oracle: frame t is right when its unit's stretch, widened by tol, holds t."""
    right = 0
    for t, u in enumerate(units):
        first, end = spans[u]
        if first - tol <= t < end + tol:
            right += 1
    return right / len(units)


@pytest.mark.parametrize("tol", [0, 2, 5])
def test_self_recall_matches_a_plain_loop(tol):
    rng = np.random.default_rng(1)
    starts = np.sort(rng.choice(np.arange(1, 90), 9, replace=False))
    bounds = np.concatenate([[0], starts, [90]])
    spans = np.stack([bounds[:-1], bounds[1:]], 1)
    units = rng.integers(0, 10, 90)
    got = self_recall(torch.from_numpy(units), torch.from_numpy(spans), tol)
    assert got == pytest.approx(loop_self_recall(units.tolist(), spans.tolist(), tol))


def test_self_recall_one_frame_units_is_within_tolerance():
    spans = torch.stack([torch.arange(10), torch.arange(1, 11)], 1)
    units = torch.tensor([0, 1, 4, 3, 4, 9, 6, 7, 8, 0])  # off by 0,0,2,0,0,4,0,0,0,9
    assert self_recall(units, spans, 2) == pytest.approx(0.8)


def test_self_recall_refuses_empty():
    with pytest.raises(ValueError, match="non-empty"):
        self_recall(torch.zeros(0, dtype=torch.int64), torch.zeros(1, 2, dtype=torch.int64))


def test_disturbed_adds_seeded_noise_of_the_stated_size():
    x = torch.zeros(400, 768)
    a = disturbed(x, torch.Generator().manual_seed(3))
    b = disturbed(x, torch.Generator().manual_seed(3))
    assert torch.equal(a, b)
    assert float(a.std()) == pytest.approx(SELF_CHECK_NOISE, rel=0.02)


def test_fit_reports_the_figure_it_computes():
    d = make_demo(n_reference=60)
    model = NeuralSeqSLAM(NeuralConfig(hidden=512))
    log = model.fit(d.reference, log=False)
    assert log.self_check == model.self_check
    # recompute by hand: the disturbed reference's L3 winners, same generator seed
    gen = torch.Generator().manual_seed(model.config.seed)
    with torch.no_grad():
        units = model.l3(model.code(disturbed(model.encode(d.reference), gen))).argmax(1)
    assert log.self_check == pytest.approx(self_recall(units, model.unit_to_reference))
    assert model.fit(d.reference, log=False, check=False).self_check is None


def test_fit_is_quiet_on_a_route_it_separates():
    d = make_demo(n_reference=60)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        log = NeuralSeqSLAM(NeuralConfig(hidden=512)).fit(d.reference, log=False)
    assert log.self_check >= SELF_CHECK_FLOOR


def test_fit_warns_once_with_the_figure_when_units_do_not_separate():
    # 240 unrelated noise frames on 12 units: each unit averages 20 views that share nothing
    frames = torch.from_numpy(np.random.default_rng(0).uniform(0, 255, (240, 24, 32))
                              .astype(np.float32))
    model = NeuralSeqSLAM(NeuralConfig(hidden=512, n_output=12))
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        log = model.fit(frames, log=False)
    said = [str(w.message) for w in got if "self-check" in str(w.message)]
    assert log.self_check < SELF_CHECK_FLOOR
    assert len(said) == 1
    assert f"only {log.self_check:.2f} of the reference frames" in said[0]
    assert "raise n_output" in said[0] and "docs/results/neural-long-routes.md" in said[0]
    assert len(said[0]) <= 240  # one short line; the figures behind the link


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_train_and_eval_record_the_figure(tmp_path, capsys):
    from cli_helpers import run_inprocess

    out = tmp_path / "t"
    code, err = run_inprocess("train", capsys, "--demo-frames", "40", "--neural-hidden", "256",
                              "--no-tensorboard", "--out", str(out))
    assert code == 0, err
    saved = json.loads((out / "train.json").read_text())
    assert 0.0 <= saved["self_check"] <= 1.0
    assert saved["seqslam_template_bytes"] == 40 * 32 * 64  # one uint8 64x32 frame a place
    ev = tmp_path / "e"
    code, err = run_inprocess("eval", capsys, "--engine", "neural", "--demo-frames", "40",
                              "--neural-hidden", "256", "--out", str(ev))
    assert code == 0, err
    m = json.loads((ev / "metrics.json").read_text())
    assert m["neural"]["self_check"] == pytest.approx(saved["self_check"])
    assert m["neural"]["seqslam_template_bytes"] == 40 * 32 * 64
    code, err = run_inprocess("eval", capsys, "--engine", "neural", "--demo-frames", "40",
                              "--checkpoint", str(out / "model.pt"), "--out", str(tmp_path / "c"))
    assert code == 0, err
    m = json.loads((tmp_path / "c" / "metrics.json").read_text())
    assert m["neural"]["self_check"] == pytest.approx(saved["self_check"])

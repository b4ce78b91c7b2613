"""Temporal-window ensembles on the command line: ``--window-ms 5,10,20``.

The eval run's matches are checked against the library's one-pass ensemble
(``accumulate_ensemble`` + ``match_ensemble``) on the same simulated runs, and a member's
frames against a plain loop over the events.
"""

import csv
import dataclasses
import json

import numpy as np
import pytest
import torch

import torchseq.cli.eval as cli_eval
import torchseq.cli.train as cli_train
from torchseq.cli.errors import UsageError
from torchseq.cli.eval_settings import config_dict
from torchseq.cli.event_options import event_frame_options, window_members
from torchseq.cli.runs import config_text, run_main
from torchseq.demo import make_world, render
from torchseq.events import load_event_frames
from torchseq.events.ensemble import accumulate_ensemble, match_ensemble
from torchseq.events.runs import simulate_run
from torchseq.preprocess import resize
from torchseq.seqslam import SeqSLAMConfig

WINDOWS = (5.0, 10.0, 20.0)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A reference run (80 windows of 10 ms) and a query run at 66% of its speed."""
    folder = tmp_path_factory.mktemp("runs")
    world = make_world(900, 32, 3)
    positions = np.arange(0.0, 801.0, 2.0)
    views = render(world, positions, 48)  # (401, 32, 48)
    paths = {}
    for name, speed, seed in (("ref", 1.0, 1), ("query", 0.66, 2)):
        run = simulate_run(views, positions, speed, 1000.0, seed=seed, threshold_noise=0.03)
        np.savez(folder / f"{name}.npz", t=run.stream.events["t"], x=run.stream.events["x"],
                 y=run.stream.events["y"], p=run.stream.events["p"])
        paths[name] = (folder / f"{name}.npz", run)
    return paths


def test_window_members_parses_lists_and_refuses_bad_ones():
    assert window_members(10.0) == (10.0, None)
    assert window_members((20.0, 5.0, 10.0)) == (10.0, (20.0, 5.0, 10.0))
    assert window_members([5.0, 10.0, 20.0, 40.0]) == (10.0, (5.0, 10.0, 20.0, 40.0))
    for bad, message in (((10.0, 10.001), "even number"), ((5.0, 5.0), "twice"),
                         ((5.0, -1.0), "must be in"), ((), "at least one")):
        with pytest.raises(UsageError, match=message):
            window_members(bad)
    args = cli_eval.build_parser().parse_args(["--window-ms", "5,10,20"])
    assert args.window_ms == WINDOWS
    assert cli_eval.build_parser().parse_args(["--window-ms", "7"]).window_ms == 7.0


def loop_member(events, w, h, step_us, length_us, n):
    """Frame k: events with t in [c_k - L/2, c_k + L/2), c_k = (k + 0.5) step (anchor 0)."""
    out = np.zeros((n, h, w))
    for k in range(n):
        lo = k * step_us + (step_us - length_us) / 2
        sel = (events["t"] >= lo) & (events["t"] < lo + length_us)
        np.add.at(out[k], (events["y"][sel], events["x"][sel]), 1)
    return out


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_a_member_is_the_centred_window_and_the_step_member_is_the_plain_frames(runs):
    path, run = runs["ref"]
    plain = load_event_frames(path, window_ms=10, anchor="zero", sensor_size=(48, 32))
    same = load_event_frames(path, window_ms=10, anchor="zero", sensor_size=(48, 32),
                             centred_ms=10)
    torch.testing.assert_close(same, plain)
    wide = load_event_frames(path, window_ms=10, anchor="zero", sensor_size=(48, 32),
                             centred_ms=20)
    want = loop_member(run.stream.events, 48, 32, 10_000, 20_000, len(wide)).clip(0, 255)
    np.testing.assert_array_equal(wide.numpy(), want)
    with pytest.raises(ValueError, match="event_count"):
        load_event_frames(path, event_count=100, centred_ms=20)


def eval_run(tmp_path, runs, *extra):
    out = tmp_path / "out"
    code = cli_eval.main([
        "--reference", str(runs["ref"][0]), "--query", str(runs["query"][0]),
        "--engine", "seqslam", "--preset", "events", "--speed-ratio", "0.66", "--ds", "20",
        "--window-anchor", "zero", "--sensor-size", "48x32", "--tolerance", "2",
        "--no-progress", "--no-tensorboard", "--out", str(out), *extra])
    assert code == 0
    with open(out / "matches.csv") as f:
        rows = list(csv.DictReader(f))
    ref = torch.tensor([int(r["reference"]) if r["reference"] else -1 for r in rows])
    return ref, json.loads((out / "metrics.json").read_text())


@pytest.mark.slow
def test_eval_ensemble_equals_the_library_ensemble(tmp_path, runs):
    got, summary = eval_run(tmp_path, runs, "--window-ms", "5,10,20", "--edges")
    assert summary["inputs"]["window_ensemble_ms"] == list(WINDOWS)
    cfg = SeqSLAMConfig.events(speed_ratio=0.66, ds=20, edges=True)
    members = []
    for name in ("ref", "query"):
        m = accumulate_ensemble(runs[name][1].stream, [int(w * 1000) for w in WINDOWS],
                                step_us=10_000, anchor="zero")
        members.append([resize(x.clamp(0, 255), cfg.image_size) for x in m])
    want = match_ensemble(members[0], members[1], cfg)
    assert torch.equal(got, want.matches.reference)
    single, _ = eval_run(tmp_path, runs, "--edges", "--overwrite")
    assert not torch.equal(single, got)  # the members changed the matches: the ensemble ran


def test_ensemble_refusals(tmp_path, runs, capsys):
    base = ["--reference", str(runs["ref"][0]), "--query", str(runs["query"][0]),
            "--engine", "seqslam", "--no-progress", "--no-tensorboard"]
    for extra, message in (
            (["--window-ms", "5,10,20", "--event-count", "500"], "needs time windows"),
            (["--window-ms", "10,10.001"], "even number")):
        code = run_main(cli_eval.main, "eval.py", base + ["--out", str(tmp_path / "o")] + extra)
        err = capsys.readouterr().err
        assert code == 2 and message in err, err
    with pytest.raises(SystemExit) as exit_:  # argparse's own one-line error
        cli_eval.build_parser().parse_args(["--window-ms", "5,nan"])
    assert exit_.value.code == 2 and "must be a finite number" in capsys.readouterr().err
    code = run_main(cli_train.main, "train.py", [
        "--reference", str(runs["ref"][0]), "--window-ms", "5,10,20", "--no-progress",
        "--no-tensorboard", "--out", str(tmp_path / "t")])
    err = capsys.readouterr().err
    assert code == 2 and "is for eval's SeqSLAM" in err, err


def test_the_event_preset_resolves_to_the_measured_settings(tmp_path):
    """docs/results/event-preset.md: the seed's setting, edges, ds = 100 reference windows."""
    want = SeqSLAMConfig(image_size=(16, 16), patch_size=8, ds=152, speed_ratio=0.66,
                         speed_tolerance=0.2, match_at="trajectory", edges=True)
    assert SeqSLAMConfig.events(0.66) == want
    assert SeqSLAMConfig.events(0.25).ds == 400 and SeqSLAMConfig.events().ds == 100
    assert SeqSLAMConfig.events(1.5).ds == 67 and SeqSLAMConfig.events(0.25, ds=20).ds == 20
    s = cli_eval.parse_args(["--preset", "events", "--speed-ratio", "0.66",
                             "--engine", "seqslam"])[0]
    assert s.seqslam == want
    opts = event_frame_options(s.run)
    assert opts.window_ms == 10.0 and opts.members_ms is None  # one window, no ensemble
    # a typed flag wins over the preset even at its dataclass default, and a replay keeps it
    off = cli_eval.parse_args(["--preset", "events", "--speed-ratio", "0.66", "--no-edges",
                               "--engine", "seqslam"])[0]
    assert off.seqslam == dataclasses.replace(want, edges=False)
    path = tmp_path / "config.json"
    path.write_text(config_text(config_dict(off)))
    assert cli_eval.parse_args(["--config", str(path)])[0].seqslam == off.seqslam

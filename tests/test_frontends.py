"""End-to-end runs of eval.py and train.py as a user runs them (subprocess, small demo)."""

import csv
import importlib.util
import json
import subprocess
import sys

import numpy as np
import pytest
from cli_helpers import ROOT, load_script, run_inprocess
from conftest import shared_data


def run(script, *args, check=True):
    proc = subprocess.run([sys.executable, str(ROOT / script), *args, "--no-progress"],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"{script} failed ({proc.returncode}):\n{proc.stderr}")
    return proc


@pytest.mark.slow
def test_eval_seqslam_on_demo_writes_every_output(tmp_path):
    out = tmp_path / "out"
    run("eval.py", "--engine", "seqslam", "--demo-frames", "80", "--out", str(out))
    metrics = json.loads((out / "metrics.json").read_text())
    s = metrics["seqslam"]
    assert s["n_queries"] == 99  # floor(79 / 0.8) + 1 query frames
    assert s["n_matched"] == 89  # ds/2 = 5 queries at either end cannot be matched
    assert s["recall_at_1"] >= 0.85  # measured 89/99: every matched query is correct
    assert 0 < s["auc"] <= 1 and s["parameters"]["ds"] == 10
    rows = list(csv.DictReader(open(out / "matches.csv")))
    assert len(rows) == 99 and {r["engine"] for r in rows} == {"seqslam"}
    assert rows[0]["reference"] == ""  # the first ds/2 queries get no match
    assert int(rows[50]["reference"]) in range(80)
    for png in ("seqslam_difference_matrix", "seqslam_matched_pairs", "pr_curve"):
        assert (out / f"{png}.png").stat().st_size > 1000
    assert any((out / "tensorboard").iterdir())
    assert json.loads((out / "config.json").read_text())["engine"] == "seqslam"


@pytest.mark.slow
def test_eval_on_corridor_with_csv_ground_truth(tmp_path):
    data = shared_data("corridor")
    run("eval.py", "--engine", "seqslam", "--reference", str(data / "ref"), "--query",
        str(data / "query"), "--ground-truth", str(data / "ground_truth.csv"),
        "--out", str(tmp_path), "--no-tensorboard")
    m = json.loads((tmp_path / "metrics.json").read_text())["seqslam"]
    # measured 0.378 with OpenSeqSLAM's defaults on this fisheye corridor (tolerance +-2 frames)
    assert m["n_queries"] == 111 and m["recall_at_1"] > 0.3


@pytest.mark.parametrize("args, message", [
    (["--reference", "/nonexistent/ref", "--query", "/nonexistent/q"], "no such file"),
    (["--reference", "x"], "give both --reference and --query"),
    (["--engine", "bogus"], "--engine must be one of"),
    (["--demo-frames", "30", "--ds", "1000", "--engine", "seqslam"],
     "--ds 1000 is longer than the query (37 frames)"),
])
def test_eval_bad_input_is_one_line(tmp_path, capsys, args, message):
    code, err = run_inprocess("eval", capsys, *args, "--out", str(tmp_path))
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("eval.py: error: ") and message in lines[0]


def test_eval_ground_truth_that_does_not_fit(tmp_path, capsys):
    bad = tmp_path / "gt.npy"
    np.save(bad, np.eye(5, dtype=np.int64))
    frames = tmp_path / "frames.npy"
    np.save(frames, np.random.default_rng(0).integers(0, 255, (30, 32, 64)).astype(np.uint8))
    code, err = run_inprocess("eval", capsys, "--engine", "seqslam", "--reference", str(frames),
                              "--query", str(frames), "--ground-truth", str(bad),
                              "--out", str(tmp_path / "out"))
    assert code == 2 and "(30, 30)" in err


def test_eval_help_explains_every_flag(capsys):
    with pytest.raises(SystemExit) as exit_info:
        load_script("eval").main(["--help-all"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    for flag in ("--reference", "--query", "--ground-truth", "--tolerance", "--engine", "--ds",
                 "--vmin", "--vmax", "--speed-ratio", "--metric", "--out", "--window-ms",
                 "--event-count", "--frame-size", "--checkpoint", "--evt3-kernel"):
        assert flag in out


@pytest.mark.slow
def test_train_then_eval_neural_checkpoint(tmp_path):
    import torch

    from torchseq.neural import NeuralSeqSLAM

    trained = run("train.py", "--demo-frames", "60", "--neural-hidden", "512",
                  "--neural-n-output", "60", "--out", str(tmp_path / "train"), "--export")
    # --export says what it validated on, the device input, and the verdict (main: silent)
    assert "export: validated on the checkpoint's own reference: demo" in trained.stdout
    assert "export: device input: uint8 96x128" in trained.stdout
    assert trained.stdout.strip().endswith("export: PASS")
    validation = json.loads((tmp_path / "train" / "export" / "validation.json").read_text())
    assert validation["passed"] and validation["integer_agreement"] >= 0.99
    assert validation["recall_at_1"]["integer_onnx"] >= 0.95  # validated on the demo query
    ckpt = tmp_path / "train" / "model.pt"
    saved = torch.load(ckpt, weights_only=True)
    assert saved["config"]["hidden"] == 512  # the checkpoint carries its config
    assert NeuralSeqSLAM.load(ckpt).n_units == 60
    for png in ("reference_activity", "ring_shift_matrix"):
        assert (tmp_path / "train" / f"{png}.png").stat().st_size > 1000
    assert any((tmp_path / "train" / "tensorboard").iterdir())
    out = tmp_path / "eval"
    run("eval.py", "--engine", "both", "--checkpoint", str(ckpt), "--demo-frames", "60",
        "--out", str(out))
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["neural"]["recall_at_1"] >= 0.95
    assert metrics["neural"]["parameters"]["hidden"] == 512
    assert {r["engine"] for r in csv.DictReader(open(out / "matches.csv"))} == \
        {"seqslam", "neural"}
    assert (out / "neural_activity.png").exists()


def test_train_bad_input_is_one_line(tmp_path, capsys):
    code, err = run_inprocess("train", capsys, "--reference", str(tmp_path / "nothing"),
                              "--out", str(tmp_path))
    assert code == 2 and err.startswith("train.py: error: ")
    assert len(err.strip().splitlines()) == 1
    code, err = run_inprocess("train", capsys, "--neural-hidden", "-3", "--out", str(tmp_path))
    assert code == 2 and "hidden" in err


def test_train_takes_evals_neural_flag_names_and_no_others(capsys):
    """The pre-release names (--hidden, ...) are refused; the --neural-* ones are eval's."""
    import dataclasses

    import torchseq.cli.eval as cli_eval
    import torchseq.cli.train as cli_train
    from torchseq.neural import NeuralConfig
    for old in (["--hidden", "64"], ["--n-output", "9"], ["--eps", "0.1"], ["--chunk", "8"],
                ["--no-rectify"], ["--seed", "3"]):
        with pytest.raises(SystemExit):
            cli_train.parse_args(old)
        assert f"unrecognized arguments: {' '.join(old)}" in capsys.readouterr().err
    dests = {"neural_" + f.name for f in dataclasses.fields(NeuralConfig)}

    def neural_flags(parser):
        return sorted(s for a in parser._actions if a.dest in dests for s in a.option_strings)
    flags = neural_flags(cli_train.build_parser())
    assert flags == neural_flags(cli_eval.build_parser()) and "--no-neural-rectify" in flags


def test_eval_takes_event_files(tmp_path, capsys):
    # a real DVS128 recording against itself: 10 ms windows pooled to 16x16
    aedat = shared_data("events", "alex_walking_again.aedat")
    code, err = run_inprocess("eval", capsys, "--engine", "seqslam", "--reference", str(aedat),
                              "--query", str(aedat), "--tolerance", "2", "--frame-size",
                              "16x16", "--image-size", "16x16", "--patch-size", "4",
                              "--out", str(tmp_path), "--no-tensorboard")
    assert code == 0, err
    m = json.loads((tmp_path / "metrics.json").read_text())["seqslam"]
    assert m["n_queries"] == 689  # 6.89 s of events in 10 ms windows
    assert m["recall_at_1"] > 0.95  # measured 0.985: a replay of the same recording


def test_run_folders_overwrite_and_config_replay(tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    base = ["--engine", "seqslam", "--demo-frames", "40", "--ds", "6", "--no-tensorboard"]
    # in-process (the real script as a subprocess: test_cli_contract and the slow
    # test_eval_seqslam_on_demo_writes_every_output)
    assert run_inprocess("eval", capsys, *base, "--out", str(out))[0] == 0
    first = json.loads((out / "metrics.json").read_text())["seqslam"]
    (out / "stale.png").write_bytes(b"x")
    code, err = run_inprocess("eval", capsys, *base, "--out", str(out))
    assert code == 2 and "already holds files" in err
    assert run_inprocess("eval", capsys, *base, "--out", str(out), "--overwrite")[0] == 0
    assert not (out / "stale.png").exists()  # the old run's files do not mix with the new
    # replay: same settings from config.json, new folder, same numbers
    replay = tmp_path / "replay"
    assert run_inprocess("eval", capsys, "--config", str(out / "config.json"),
                         "--out", str(replay))[0] == 0
    saved = json.loads((out / "config.json").read_text())
    assert saved["seqslam"]["ds"] == 6 and saved["demo_frames"] == 40
    assert json.loads((replay / "config.json").read_text())["seqslam"] == saved["seqslam"]
    assert json.loads((replay / "metrics.json").read_text())["seqslam"]["recall_at_1"] == \
        first["recall_at_1"]
    # no --out: a fresh timestamped folder under runs/ of the working directory
    monkeypatch.chdir(tmp_path)
    assert run_inprocess("eval", capsys, *base)[0] == 0
    assert run_inprocess("eval", capsys, *base)[0] == 0
    made = list((tmp_path / "runs").glob("eval-*/metrics.json"))
    assert len(made) == 2


def test_sweep_writes_one_row_per_setting(tmp_path, capsys):
    out = tmp_path / "sweep"
    assert run_inprocess("eval", capsys, "--engine", "seqslam", "--demo-frames", "40",
                         "--sweep", "ds=4,6,8", "--no-tensorboard", "--out", str(out))[0] == 0
    rows = list(csv.DictReader(open(out / "sweep.csv")))
    assert [r["setting"] for r in rows] == ["--ds 4", "--ds 6", "--ds 8"]
    assert all(r["engine"] == "seqslam" and 0 <= float(r["recall_at_1"]) <= 1 for r in rows)
    # each row is the run that flag gives on its own
    single = tmp_path / "single"
    assert run_inprocess("eval", capsys, "--engine", "seqslam", "--demo-frames", "40", "--ds",
                         "6", "--no-tensorboard", "--out", str(single))[0] == 0
    m = json.loads((single / "metrics.json").read_text())["seqslam"]
    assert float(rows[1]["recall_at_1"]) == pytest.approx(m["recall_at_1"])
    assert float(rows[1]["operating_recall"]) == pytest.approx(m["operating_point"]["recall"])
    # the sweep replays from its config.json
    assert run_inprocess("eval", capsys, "--config", str(out / "config.json"),
                         "--out", str(tmp_path / "again"))[0] == 0
    again = list(csv.DictReader(open(tmp_path / "again" / "sweep.csv")))
    assert [{k: v for k, v in r.items() if k != "seconds"} for r in again] == \
        [{k: v for k, v in r.items() if k != "seconds"} for r in rows]


def test_neural_flags_place_resolution_and_recall_at_k(tmp_path, capsys):
    out = tmp_path / "n"
    code, err = run_inprocess("eval", capsys, "--engine", "neural", "--demo-frames", "60",
                              "--neural-hidden", "256", "--neural-n-output", "20",
                              "--neural-patch-size", "8", "--no-tensorboard", "--out", str(out))
    assert code == 0, err
    assert "3.0 frames per unit, so the ring alone blurs the route; the unit search decides" in err
    m = json.loads((out / "metrics.json").read_text())
    n = m["neural"]
    assert n["parameters"]["hidden"] == 256 and n["parameters"]["patch_size"] == 8
    assert n["frames_per_unit"] == 3.0 and m["warnings"]
    assert n["recall_at_1"] <= n["recall_at_5"] <= n["recall_at_10"] <= 1
    op = n["operating_point"]
    assert op["precision_target"] == 0.99 and (op["precision"] is None or op["precision"] >= 0.99)


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_checkpoint_on_another_reference_is_said_plainly(tmp_path, capsys):
    ckpt_dir = tmp_path / "train"
    assert run_inprocess("train", capsys, "--demo-frames", "40", "--neural-hidden", "256",
                         "--neural-n-output", "40", "--no-tensorboard",
                         "--out", str(ckpt_dir))[0] == 0
    ckpt = str(ckpt_dir / "model.pt")
    code, err = run_inprocess("eval", capsys, "--engine", "neural", "--checkpoint", ckpt,
                              "--demo-frames", "40", "--no-tensorboard", "--out",
                              str(tmp_path / "same"))
    assert code == 0 and "warning" not in err
    code, err = run_inprocess("eval", capsys, "--engine", "neural", "--checkpoint", ckpt,
                              "--demo-frames", "50", "--no-tensorboard", "--out",
                              str(tmp_path / "other"))
    assert code == 0, err
    assert "does not match this reference" in err
    assert "it learnt 40 reference frames, this reference has 50" in err
    warnings = json.loads((tmp_path / "other" / "metrics.json").read_text())["warnings"]
    assert any("does not match" in w for w in warnings)


def test_help_is_plain_text_with_one_default_each(capsys):
    for script in ("train", "eval"):
        with pytest.raises(SystemExit):
            load_script(script).main(["--help-all"])
        out = capsys.readouterr().out
        assert "``" not in out and ":class:" not in out
        entries = out.split("\n  -")
        assert all(e.count("(default") <= 1 for e in entries), [
            e for e in entries if e.count("(default") > 1]
    assert "--neural-patch-size" in out and "--neural-seed" in out and "--patch-size" in out


def test_size_flags_take_n_for_n_by_n():
    from torchseq.cli.errors import UsageError
    from torchseq.cli.flags import parse_size

    assert parse_size("16") == (16, 16) and parse_size("12x16") == (12, 16)
    with pytest.raises(UsageError):
        parse_size("16x")


def test_selection_slices_the_ground_truth_file(tmp_path):
    import cv2

    import torchseq.cli.eval as cli_eval
    from torchseq.cli.inputs import load_data

    rng = np.random.default_rng(0)
    for name in ("ref", "query"):
        (tmp_path / name).mkdir()
        for i in range(20):
            cv2.imwrite(str(tmp_path / name / f"{i}.png"),
                        rng.integers(0, 255, (32, 64), dtype=np.uint8))
    rows = ["query,references"] + [f"{q},{q} {min(q + 1, 19)}" for q in range(20)]
    (tmp_path / "gt.csv").write_text("\n".join(rows) + "\n")
    s, _, _, _ = cli_eval.parse_args([
        "--reference", str(tmp_path / "ref"), "--query", str(tmp_path / "query"),
        "--ground-truth", str(tmp_path / "gt.csv"), "--start", "3", "--frame-step", "4",
        "--engine", "seqslam", "--no-progress"])
    notes = []
    ref, query, gt, source = load_data(s.run, {"32x64": (32, 64)}, notes)
    assert ref.info["indices"] == [3, 7, 11, 15, 19] and len(query) == 5
    full = np.zeros((20, 20), bool)
    for q in range(20):
        full[[q, min(q + 1, 19)], q] = True
    assert np.array_equal(gt, full[np.ix_([3, 7, 11, 15, 19], [3, 7, 11, 15, 19])])
    assert source["selection"]["frame_step"] == 4 and not notes


def test_event_flags_reach_the_reader_and_small_frames_warn(tmp_path, capsys):
    aedat = shared_data("events", "alex_walking_again.aedat")
    code, err = run_inprocess("eval", capsys, "--engine", "seqslam", "--reference", str(aedat),
                              "--query", str(aedat), "--tolerance", "2", "--frame-size", "16",
                              "--event-mode", "signed", "--max-frames", "120",
                              "--out", str(tmp_path / "o"), "--no-tensorboard")
    assert code == 0, err
    # 16x16 event frames under the default 32x64 SeqSLAM size: said, not silently upsampled
    assert "frames are 16x16, smaller than the 32x64" in err
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert m["inputs"]["reference_frame_size"] == [16, 16] and m["seqslam"]["n_queries"] == 120
    cfg = json.loads((tmp_path / "o" / "config.json").read_text())
    assert cfg["event_mode"] == "signed" and cfg["max_frames"] == 120


def test_a_recording_too_short_for_the_windows_says_what_fits(tmp_path, capsys):
    aedat = shared_data("events", "alex_walking_again.aedat")
    code, err = run_inprocess("eval", capsys, "--engine", "seqslam", "--reference", str(aedat),
                              "--query", str(aedat), "--window-ms", "2000", "--frame-size",
                              "16", "--image-size", "16", "--patch-size", "4",
                              "--out", str(tmp_path / "o"))
    assert code == 2
    # 6.89 s of events fill 4 windows of 2 s; windows of 600 ms give 12 >= ds = 10 frames
    assert "fills 4 windows of 2000 ms (more than 6000 ms of events); --window-ms 600 " \
        "or less gives at least 10 frames" in err


def test_event_crop_mode_and_filters_reach_the_traverse(tmp_path, capsys, monkeypatch):
    # a tiny synthetic recording: 300 ms on a 16x16 sensor, starting at sensor time 1 s
    from torchseq.events import EventStream, make_events, write_npz

    rng = np.random.default_rng(3)
    n = 6000
    t = np.sort(rng.integers(1_000_000, 1_300_000, n))
    write_npz(tmp_path / "e.npz", EventStream(make_events(
        t, rng.integers(0, 16, n), rng.integers(0, 16, n), rng.integers(0, 2, n)), (16, 16)))
    import torchseq.events.traverse as traverse

    seen = []
    real = traverse.load_event_windows  # what load_traverse calls (empty windows kept sparse)

    def spy(path, **kwargs):
        seen.append(kwargs)
        return real(path, **kwargs)

    monkeypatch.setattr(traverse, "load_event_windows", spy)
    out = tmp_path / "o"
    code, err = run_inprocess(
        "eval", capsys, "--engine", "seqslam", "--reference", str(tmp_path / "e.npz"),
        "--query", str(tmp_path / "e.npz"), "--tolerance", "1", "--window-anchor", "zero",
        "--t-start", "1050", "--duration", "200", "--event-mode", "two-channel",
        "--hot-pixel", "20", "--refractory-us", "100", "--image-size", "16x32",
        "--patch-size", "4", "--out", str(out), "--no-tensorboard")
    assert code == 0, err
    assert seen and all(k["mode"] == "two_channel" and k["anchor"] == "zero" and
                        k["start_ms"] == 1050 and k["duration_ms"] == 200 and
                        k["hot_pixel"] == 20 and k["refractory_us"] == 100 for k in seen)
    m = json.loads((out / "metrics.json").read_text())
    # 200 ms of 10 ms windows from sensor time 1.05 s; OFF | ON side by side: 16x32 frames
    assert m["seqslam"]["n_queries"] == 20
    assert m["inputs"]["reference_frame_size"] == [16, 32] and not m["warnings"]
    cfg = json.loads((out / "config.json").read_text())
    assert (cfg["t_start"], cfg["duration"], cfg["event_mode"]) == (1050, 200, "two-channel")
    # a crop past the recording's end says what the recording spans
    code, err = run_inprocess("eval", capsys, "--engine", "seqslam", "--reference",
                              str(tmp_path / "e.npz"), "--query", str(tmp_path / "e.npz"),
                              "--t-start", "5000", "--out", str(tmp_path / "late"))
    assert code == 2 and "no events in the time crop" in err and "spans 1000" in err


@pytest.mark.parametrize("args, message", [
    (["--event-mode", "polarity"], "--event-mode must be one of count, signed, two-channel"),
    (["--duration", "0"], "--duration must be in"),
    (["--t-start", "-5"], "--t-start must be in"),
    (["--hot-pixel", "0"], "--hot-pixel must be"),
    (["--refractory-us", "-1"], "--refractory-us must be"),
    (["--event-count", "500", "--window-ms", "5"], "--window-ms 5 has no effect with --event"),
])
@pytest.mark.parametrize("script", ["eval", "train"])
def test_event_flags_are_checked_before_any_work(tmp_path, capsys, args, message, script):
    code, err = run_inprocess(script, capsys, *args, "--out", str(tmp_path / "o"))
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()  # refused before the run folder was made


def readme_commands(word):
    """The ``torchseq eval`` commands of the README and the evaluate guide (where its longer
    examples live) that mention ``word``, as argv lists."""
    import shlex

    text = "\n".join((ROOT / name).read_text(encoding="utf-8") for name in (
        "README.md", "docs/guide/evaluate.md")).replace("\\\n", " ")
    return [shlex.split(line.split("torchseq eval", 1)[1]) for line in text.splitlines()
            if line.startswith("torchseq eval") and word in line]


def test_readme_event_examples_never_resize_event_frames():
    # each README event example reads its event frames at the size they are made: no silent
    # upsampling of 16x16 frames to the default 32x64 (nor squeezing of two-channel frames)
    from torchseq.cli.eval import parse_args
    from torchseq.cli.flags import parse_size

    examples = readme_commands(".aedat")
    assert len(examples) >= 2 and any("two-channel" in argv for argv in examples)
    for argv in examples:
        s = parse_args(argv)[0]
        h, w = parse_size(s.run.frame_size)
        frame = (h, 2 * w) if s.run.event_mode.replace("-", "_") == "two_channel" else (h, w)
        assert tuple(s.seqslam.image_size) == frame, argv
        if s.run.engine in ("neural", "both"):
            assert tuple(s.neural.input_size) == frame, argv


@pytest.mark.parametrize("script", ["eval", "train"])
def test_event_flags_without_event_files_are_refused(tmp_path, capsys, script):
    # --window-ms & co. used to be ignored silently for the demo, image folders and arrays
    np.save(tmp_path / "frames.npy", np.zeros((12, 8, 8), np.uint8))
    inputs = [[], ["--reference", str(tmp_path / "frames.npy")]]
    if script == "eval":
        inputs[1] += ["--query", str(tmp_path / "frames.npy")]
    for i, given in enumerate(inputs):
        for flags, named in ((["--window-ms", "5"], "--window-ms applies"),
                             (["--event-mode", "signed", "--hot-pixel", "3"],
                              "--event-mode, --hot-pixel apply"),
                             # given at their default values, the user still meant them
                             (["--window-ms", "10", "--event-mode=count"],
                              "--window-ms, --event-mode apply")):
            out = tmp_path / f"o{i}"
            code, err = run_inprocess(script, capsys, *given, *flags, "--out", str(out))
            assert code == 2 and named in err and "no input is one" in err, err
            assert len(err.strip().splitlines()) == 1 and not out.exists()


def test_event_flags_count_for_event_files_only():
    from torchseq.cli.errors import UsageError
    from torchseq.cli.eval import parse_args
    from torchseq.cli.event_options import check_event_flags_apply

    s = parse_args(["--window-ms", "5", "--frame-size", "16"])[0]
    with pytest.raises(UsageError, match="--window-ms, --frame-size apply"):
        check_event_flags_apply(s.run, {"--reference": None, "--query": None})
    aedat = shared_data("events", "alex_walking_again.aedat")
    check_event_flags_apply(s.run, {"--reference": str(aedat), "--query": None})  # one is
    check_event_flags_apply(parse_args([])[0].run, {"--reference": None})  # defaults: fine


def test_events_preset_sizes_two_channel_images_to_the_frames():
    from torchseq.cli.eval import parse_args

    def size(*argv):
        return tuple(parse_args(list(argv))[0].seqslam.image_size)

    assert size("--preset", "events") == (16, 16)
    assert size("--preset", "events", "--event-mode", "two-channel") == (16, 32)  # OFF | ON
    assert size("--preset", "events", "--event-mode", "two_channel") == (16, 32)
    assert size("--preset", "events", "--event-mode", "two-channel",
                "--image-size", "16x16") == (16, 16)  # an explicit size is kept (and warned)
    assert size("--preset", "openseqslam", "--event-mode", "two-channel") == (32, 64)


def test_two_channel_frames_squeezed_by_the_image_size_warn(tmp_path, capsys):
    from torchseq.events import EventStream, make_events, write_npz

    rng = np.random.default_rng(4)
    n = 4000
    t = np.sort(rng.integers(0, 200_000, n))
    write_npz(tmp_path / "e.npz", EventStream(make_events(
        t, rng.integers(0, 16, n), rng.integers(0, 16, n), rng.integers(0, 2, n)), (16, 16)))
    common = ["--engine", "seqslam", "--reference", str(tmp_path / "e.npz"), "--query",
              str(tmp_path / "e.npz"), "--tolerance", "1", "--event-mode", "two-channel",
              "--patch-size", "4", "--no-tensorboard"]
    code, err = run_inprocess("eval", capsys, *common, "--image-size", "16x16",
                              "--out", str(tmp_path / "sq"))
    assert code == 0, err
    assert "two-channel event frames are 16x32" in err and "halves change shape" in err
    m = json.loads((tmp_path / "sq" / "metrics.json").read_text())
    assert any("halves change shape" in w for w in m["warnings"])
    code, err = run_inprocess("eval", capsys, *common, "--image-size", "8x16",
                              "--out", str(tmp_path / "ok"))
    assert code == 0 and "halves change shape" not in err, err  # same shape: no warning


def test_time_unit_flag_reads_epoch_seconds_csv(tmp_path, capsys):
    # a CSV of Unix-epoch seconds: refused without a unit, read with --time-unit s
    rng = np.random.default_rng(0)
    n = 4000
    t = 1_700_000_000.0 + np.sort(rng.random(n)) * 2.0
    rows = "".join(f"{a:.6f},{b},{c},{d}\n" for a, b, c, d in zip(
        t, rng.integers(0, 16, n), rng.integers(0, 16, n), rng.integers(0, 2, n)))
    path = tmp_path / "e.csv"
    path.write_text("t,x,y,p\n" + rows)
    common = ["--engine", "seqslam", "--reference", str(path), "--query", str(path),
              "--window-ms", "100", "--ds", "4", "--image-size", "16x16", "--patch-size", "4",
              "--no-tensorboard"]
    code, err = run_inprocess("eval", capsys, *common, "--out", str(tmp_path / "a"))
    assert code == 2 and "--time-unit s" in err
    code, err = run_inprocess("eval", capsys, *common, "--time-unit", "s",
                              "--out", str(tmp_path / "b"))
    assert code == 0, err
    m = json.loads((tmp_path / "b" / "metrics.json").read_text())["seqslam"]
    assert m["n_queries"] == 20  # 2 s of events in 100 ms windows
    aedat = shared_data("events", "alex_walking_again.aedat")
    code, err = run_inprocess("eval", capsys, "--reference", str(aedat), "--query", str(aedat),
                              "--time-unit", "s", "--out", str(tmp_path / "c"))
    assert code == 2 and "time_unit" in err and "do not apply" in err
    code, err = run_inprocess("eval", capsys, "--time-unit", "h")
    assert code == 2 and "--time-unit must be s, ms, us or ns" in err


def test_evt3_kernel_flag_reaches_the_decoder(tmp_path, capsys, monkeypatch):
    import torchseq.events.prophesee as prophesee

    raw = shared_data("events", "evt3_sample.raw")
    kernels = []
    real = prophesee.decode_evt3

    def spy(words, state, time_mode="spec", kernel=None):
        kernels.append(kernel)
        return real(words, state, time_mode, kernel)

    monkeypatch.setattr(prophesee, "decode_evt3", spy)
    # auto picks the fast kernel for any size here, so an explicit numpy is told apart
    monkeypatch.setattr(prophesee, "EVT3_NUMBA_MIN_BYTES", 0)
    common = ["--engine", "seqslam", "--reference", str(raw), "--query", str(raw),
              "--window-ms", "0.5", "--frame-size", "16", "--image-size", "16", "--ds", "4",
              "--patch-size", "4", "--tolerance", "1", "--no-tensorboard"]
    counts = {}
    choices = ["auto", "numpy"] + (["numba"] if importlib.util.find_spec("numba") else [])
    for kernel in choices:
        kernels.clear()
        out = tmp_path / kernel
        code, err = run_inprocess("eval", capsys, *common, "--evt3-kernel", kernel,
                                  "--out", str(out))
        assert code == 0, err
        assert kernels and set(kernels) == {prophesee.EVT3_KERNEL if kernel == "auto"
                                            else kernel}
        counts[kernel] = json.loads((out / "metrics.json").read_text())["seqslam"]
        assert json.loads((out / "config.json").read_text())["evt3_kernel"] == kernel
    assert all(c["n_queries"] == counts["auto"]["n_queries"] and
               c["recall_at_1"] == counts["auto"]["recall_at_1"] for c in counts.values())
    code, err = run_inprocess("eval", capsys, *common, "--evt3-kernel", "fast")
    assert code == 2 and "--evt3-kernel must be auto, numpy or numba, got 'fast'" in err
    aedat = shared_data("events", "alex_walking_again.aedat")
    code, err = run_inprocess("eval", capsys, "--reference", str(aedat), "--query", str(aedat),
                              "--evt3-kernel", "numpy", "--out", str(tmp_path / "a"))
    assert code == 2 and "EVT 3 kernel applies to .raw files only" in err
    code, err = run_inprocess("train", capsys, "--evt3-kernel", "numpy",
                              "--out", str(tmp_path / "t"))
    assert code == 2 and "--evt3-kernel applies to event files only" in err


def test_evt3_kernel_numba_without_numba_is_refused(monkeypatch):
    from torchseq.cli.errors import UsageError
    from torchseq.cli.eval import parse_args
    from torchseq.cli.event_options import event_frame_options

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "numba" else real(name, *a))
    with pytest.raises(UsageError, match="--evt3-kernel numba needs numba"):
        event_frame_options(parse_args(["--evt3-kernel", "numba"])[0].run)


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_checkpoint_of_other_event_settings_or_selection_is_said(tmp_path, capsys):
    # same recording, same frame count and size: only the frames' making differs
    aedat = str(shared_data("events", "alex_walking_again.aedat"))
    events = ["--frame-size", "16", "--max-frames", "60"]
    assert run_inprocess("train", capsys, "--reference", aedat, *events, "--neural-hidden", "128",
                         "--neural-n-output", "60", "--no-tensorboard",
                         "--out", str(tmp_path / "t"))[0] == 0
    common = ["--engine", "neural", "--checkpoint", str(tmp_path / "t" / "model.pt"),
              "--reference", aedat, "--query", aedat, "--tolerance", "2", "--no-tensorboard"]
    code, err = run_inprocess("eval", capsys, *common, *events, "--evt3-kernel", "auto",
                              "--out", str(tmp_path / "same"))
    assert code == 0 and "does not match" not in err, err
    code, err = run_inprocess("eval", capsys, *common, *events, "--event-mode", "signed",
                              "--out", str(tmp_path / "mode"))
    assert code == 0 and "does not match this reference (its event frame settings differ " \
        "(mode 'count' -> 'signed'))" in err, err
    m = json.loads((tmp_path / "mode" / "metrics.json").read_text())
    assert any("mode 'count' -> 'signed'" in w for w in m["warnings"])
    code, err = run_inprocess("eval", capsys, *common, *events, "--start", "50",
                              "--out", str(tmp_path / "start"))
    assert code == 0 and "its frame selection differs (start 0 -> 50)" in err, err


@pytest.mark.slow
def test_place_resolution_warning_follows_the_readout(tmp_path, capsys):
    # the interpolating readout reads places within a unit: 3 frames per unit are fine there
    # (the ring decides: with the unit search on, the warning is the search's, issue 33)
    common = ["--engine", "neural", "--demo-frames", "60", "--neural-hidden", "128",
              "--neural-readout", "interpolate", "--neural-unit-search", "off",
              "--no-tensorboard"]
    code, err = run_inprocess("eval", capsys, *common, "--neural-n-output", "20",
                              "--out", str(tmp_path / "fine"))
    assert code == 0 and "frames per unit" not in err, err
    code, err = run_inprocess("eval", capsys, *common, "--neural-n-output", "6",
                              "--out", str(tmp_path / "coarse"))
    assert code == 0 and "10.0 frames per unit: past 8 any readout fails; raise " \
        "--neural-n-output" in err, err


@pytest.mark.slow
def test_train_export_reads_an_event_query_as_its_reference(tmp_path, capsys, monkeypatch):
    # the export read an --export-query event file with default settings (10 ms windows at
    # the full 128x128) although the model learnt 20 ms windows pooled to 16x16
    import torchseq.cli.export as export_cli
    import torchseq.export.checkpoint as checkpoint

    seen = {}

    def spy(ckpt, out, query=None, **kwargs):
        seen["query"] = query
        return True

    monkeypatch.setattr(checkpoint, "export_checkpoint", spy)
    monkeypatch.setattr(export_cli, "summary_lines", lambda out: [])
    aedat = str(shared_data("events", "alex_walking_again.aedat"))
    code, err = run_inprocess("train", capsys, "--reference", aedat, "--frame-size", "16",
                              "--window-ms", "20", "--event-mode", "signed", "--max-frames",
                              "60", "--neural-hidden", "64", "--neural-n-output", "60",
                              "--no-tensorboard", "--export", "--export-query", aedat,
                              "--out", str(tmp_path / "t"))
    assert code == 0, err
    from torchseq.sources import EventFrameOptions, load_traverse

    made = load_traverse(aedat, events=EventFrameOptions(window_ms=20, frame_size=(16, 16),
                                                         mode="signed"), progress=False)
    assert tuple(seen["query"].shape) == (345, 16, 16)  # 6.89 s of 20 ms windows, whole file
    assert np.array_equal(np.asarray(seen["query"]), np.asarray(made))


@pytest.mark.slow
def test_events_preset_on_a_real_two_channel_recording_keeps_the_halves(tmp_path, capsys):
    aedat = str(shared_data("events", "alex_walking_again.aedat"))
    out = tmp_path / "o"
    code, err = run_inprocess("eval", capsys, "--engine", "seqslam", "--preset", "events",
                              "--event-mode", "two-channel", "--frame-size", "16",
                              "--reference", aedat, "--query", aedat, "--tolerance", "2",
                              "--no-tensorboard", "--out", str(out))
    assert code == 0, err
    m = json.loads((out / "metrics.json").read_text())
    # OFF | ON halves of 16x16 each: the preset's images are 16x32, nothing resized
    assert m["inputs"]["reference_frame_size"] == [16, 32]
    assert m["seqslam"]["parameters"]["image_size"] == [16, 32]
    assert m["seqslam"]["parameters"]["ds"] == 100 and m["warnings"] == []
    assert m["seqslam"]["recall_at_1"] > 0.8  # measured 0.855 (replay, 100-frame sequences)

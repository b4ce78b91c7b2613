"""The library's warnings in a command-line run: one readable line each, counted, in the json.

They used to print as raw ``UserWarning`` lines (file, line number, source line) and were
missing from the run's ``metrics.json``, so a run's record did not say that its inputs had
been guessed at or its results coarsened.
"""

import json
import warnings

import pytest
from cli_helpers import run_inprocess
from conftest import shared_data


def test_reader_warning_is_one_counted_line_and_in_metrics(tmp_path, capsys):
    # the real decoded EVT 3 sample stores no sensor size: the reader warns for each traverse
    npy = shared_data("events", "evt3_sample.npy")
    out = tmp_path / "o"
    code, err = run_inprocess("eval", capsys, "--engine", "seqslam", "--reference", str(npy),
                              "--query", str(npy), "--window-ms", "1", "--frame-size", "16",
                              "--image-size", "16", "--ds", "4", "--patch-size", "4",
                              "--tolerance", "1", "--no-tensorboard", "--out", str(out))
    assert code == 0, err
    said = "no sensor size stored; using 1280x720 from the largest coordinates"
    lines = err.strip().splitlines()
    assert "UserWarning" not in err and "warnings.warn" not in err
    assert [line for line in lines if "no sensor size" in line] == [
        f"eval.py: warning: {npy}: {said} (--sensor-size WxH sets it)",
        f"eval.py: warning: 2 times in all: "
        f"{(f'{npy}: {said} (--sensor-size WxH sets it)')[:77]}..."]
    m = json.loads((out / "metrics.json").read_text())
    assert m["warnings"] == [f"{npy}: {said} (--sensor-size WxH sets it) (2 times)"]


def test_fit_warning_is_in_train_json(tmp_path, capsys):
    # 40 reference frames on 4 output units: fit warns that places are 10 frames wide
    out = tmp_path / "t"
    code, err = run_inprocess("train", capsys, "--demo-frames", "40", "--neural-hidden", "64",
                              "--neural-n-output", "4", "--no-tensorboard", "--out", str(out))
    assert code == 0, err
    assert "train.py: warning: a route of 40 frames on 4 output units" in err
    assert "UserWarning" not in err
    saved = json.loads((out / "train.json").read_text())
    # and fit's self-check (issue 20): units of 10 frames do not separate the reference
    assert len(saved["warnings"]) == 2 and "10.0 frames per unit" in saved["warnings"][0]
    assert saved["warnings"][1].startswith("self-check: only")
    assert saved["reference"]["n_frames"] == 40 and saved["n_units"] == 4
    assert saved["model_bytes"] > 0 and saved["fit_seconds"] > 0


def test_sweep_json_counts_a_warning_of_every_point(tmp_path, capsys):
    out = tmp_path / "s"
    code, err = run_inprocess("eval", capsys, "--engine", "neural", "--demo-frames", "40",
                              "--neural-hidden", "64", "--neural-n-output", "4",
                              "--sweep", "neural_density=0.5,0.6", "--no-tensorboard",
                              "--out", str(out))
    assert code == 0, err
    # one cause, one warning: the run's (naming --neural-n-output), not also fit's
    assert err.count("warning: neural: a route of 40 frames on 4 output units") == 1
    assert "output units (n_output)" not in err
    notes = json.loads((out / "sweep.json").read_text())["warnings"]
    assert any(n.startswith("neural: a route of 40 frames") and n.endswith("(2 times)")
               for n in notes)


def test_log_counts_repeats_and_leaves_developer_warnings_alone(capsys, monkeypatch):
    from torchseq.cli.run_warnings import WarningLog

    log = WarningLog("prog")
    monkeypatch.setattr(warnings, "showwarning", lambda *a, **k: passed.append(a[0]))
    passed = []
    with log.capture():
        for _ in range(3):
            warnings.warn("same\n  thing")
        warnings.warn("number", RuntimeWarning)
        warnings.warn("old api", DeprecationWarning)
        log.add("the front end's own")
    err = capsys.readouterr().err.splitlines()
    assert err == ["prog: warning: same thing", "prog: warning: RuntimeWarning: number",
                   "prog: warning: the front end's own",
                   "prog: warning: 3 times in all: same thing"]
    assert log.entries() == ["same thing (3 times)", "RuntimeWarning: number",
                             "the front end's own"]
    assert [str(m) for m in passed] == ["old api"]  # Python's own handling (here: the spy)


def test_user_warning_filters_are_kept(monkeypatch):
    from torchseq.cli.run_warnings import WarningLog

    monkeypatch.setattr("sys.warnoptions", ["error"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # as python -W error sets it up
        with pytest.raises(UserWarning, match="fatal here"), WarningLog("prog").capture():
            warnings.warn("fatal here")


def test_truncated_recording_hint_and_warning_name_the_flag(tmp_path, capsys):
    # the real AEDAT 4 sample cut inside a packet: the reader's hint names --truncated, and
    # the repair's warning lands in metrics.json
    cut = tmp_path / "cut.aedat4"
    cut.write_bytes(shared_data("events", "sample.aedat4").read_bytes()[:150_000])
    common = ["--engine", "seqslam", "--reference", str(cut), "--query", str(cut),
              "--tolerance", "2", "--ds", "4", "--no-tensorboard"]
    code, err = run_inprocess("eval", capsys, *common, "--out", str(tmp_path / "a"))
    assert code == 2 and "cut short; pass --truncated drop to ignore it" in err, err
    code, err = run_inprocess("eval", capsys, *common, "--truncated", "drop",
                              "--out", str(tmp_path / "b"))
    assert code == 0, err
    m = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert m["warnings"] == [f"{cut}: truncated, the packet at byte 146309 is cut short, "
                             f"dropped (2 times)"]

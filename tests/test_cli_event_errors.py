"""Event-file errors of the command lines say why: a start past the end of a recording names
the recording's time span and the requested start."""

import numpy as np
import pytest
from conftest import shared_data

import torchseq.cli.eval as cli_eval
from torchseq.cli.runs import run_main
from torchseq.events import EventFormatError, accumulate

SPAN = "the recording spans 11718656..11727457 us (8.801 ms)"  # evt3_sample.raw's events


def eval_error(tmp_path, capsys, *args):
    raw = shared_data("events", "evt3_sample.raw")
    code = run_main(cli_eval.main, "eval.py", [
        "--engine", "seqslam", "--reference", str(raw), "--query", str(raw), "--no-progress",
        "--no-tensorboard", "--out", str(tmp_path / "o"), *args])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    return err[0]


def test_window_anchor_past_the_end_names_the_span_and_the_anchor(tmp_path, capsys):
    err = eval_error(tmp_path, capsys, "--window-anchor", "11800000")
    assert "the windows start at 11800000 us (the anchor), after the last event" in err
    assert SPAN in err


def test_t_start_past_the_end_names_the_span_and_the_start(tmp_path, capsys):
    err = eval_error(tmp_path, capsys, "--t-start", "100")
    assert "no events in the time crop [11818656, end) us" in err
    assert "it starts 100 ms after the window origin, 11718656 us" in err and SPAN in err
    err = eval_error(tmp_path, capsys, "--window-anchor", "zero", "--t-start", "20000")
    assert "[20000000, end) us (it starts 20000 ms after the window origin, 0 us)" in err
    assert SPAN in err


@pytest.mark.parametrize("order", [[0, 1, 2], [2, 0, 1]])
def test_accumulate_names_the_span_in_or_out_of_time_order(order):
    t = np.array([1000, 2500, 4000])[order]
    events = np.zeros(3, dtype=[("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
    events["t"] = t
    with pytest.raises(EventFormatError,
                       match=r"start at 9000 us .*spans 1000\.\.4000 us \(3 ms\)"):
        accumulate(events, window_us=100, anchor=9000, sensor_size=(4, 4))


def evt2_file(path):
    """A small EVT 2.0 .raw built by hand from the format description (the project has no
    EVT 2.0 writer): TIME_HIGH words (type 8, t >> 6) and CD events (type 1 ON / 0 OFF,
    t & 63 in bits 22..27, x in 11..21, y in 0..10), one event per ms for 40 ms."""
    words = []
    for t in range(0, 40_000, 1000):
        words += [(0x8 << 28) | (t >> 6), (int(t % 2000 == 0) << 28) | ((t & 63) << 22)
                  | ((t // 1000 % 16) << 11) | (t // 1000 % 8)]
    path.write_bytes(b"% evt 2.0\n% geometry 16x8\n% end\n" + np.array(words, "<u4").tobytes())
    return path


def test_evt3_options_on_an_evt2_file_are_refused(tmp_path, capsys):
    from torchseq.events import read_events

    raw = evt2_file(tmp_path / "e2.raw")
    assert len(read_events(raw)) == 40  # the file itself reads
    with pytest.raises(EventFormatError, match=r"e2\.raw: the header says EVT 2\.0, and "
                       r"evt3_kernel='numpy' applies to EVT 3\.0 files only; drop it"):
        read_events(raw, evt3_kernel="numpy")
    with pytest.raises(EventFormatError, match=r"evt3_time='carry' and evt3_kernel='numpy' "
                       r"apply to EVT 3\.0 files only; drop them"):
        read_events(raw, evt3_time="carry", evt3_kernel="numpy")
    common = ["--engine", "seqslam", "--reference", str(raw), "--query", str(raw),
              "--window-ms", "2", "--image-size", "8x16", "--ds", "4", "--patch-size", "0",
              "--no-progress", "--no-tensorboard"]
    code = run_main(cli_eval.main, "eval.py", [*common, "--evt3-kernel", "numpy",
                                                "--out", str(tmp_path / "a")])
    err = capsys.readouterr().err
    assert code == 2 and "the header says EVT 2.0, and --evt3-kernel numpy applies to EVT " \
        "3.0 files only; drop it" in err, err
    code = run_main(cli_eval.main, "eval.py", [*common, "--evt3-time", "carry",
                                                "--out", str(tmp_path / "b")])
    err = capsys.readouterr().err
    assert code == 2 and "--evt3-time carry applies to EVT 3.0 files only" in err, err
    # auto (the default) is the readers' own choice: fine on any .raw
    code = run_main(cli_eval.main, "eval.py", [*common, "--evt3-kernel", "auto",
                                                "--out", str(tmp_path / "c")])
    assert code == 0, capsys.readouterr().err

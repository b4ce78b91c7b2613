"""One warning per cause, and no progress bars in redirected logs (issue 23, item 13)."""

import io

import pytest
from conftest import shared_data

import torchseq.cli.eval as cli_eval
from torchseq.cli.runs import run_main


def run(tmp_path, capsys, *args, out="o"):
    code = run_main(cli_eval.main, "eval.py", [*args, "--no-tensorboard",
                                               "--out", str(tmp_path / out)])
    return code, capsys.readouterr().err


@pytest.mark.slow
def test_coarse_units_are_warned_once(tmp_path, capsys):
    code, err = run(tmp_path, capsys, "--engine", "neural", "--demo-frames", "60",
                    "--neural-hidden", "256", "--neural-n-output", "20", "--no-progress")
    assert code == 0
    lines = [line for line in err.splitlines() if "output units" in line]
    assert len(lines) == 1 and "3.0 frames per unit" in lines[0], err


@pytest.mark.slow
def test_small_event_frames_of_both_traverses_are_one_warning(tmp_path, capsys):
    aedat = str(shared_data("events", "alex_walking_again.aedat"))
    code, err = run(tmp_path, capsys, "--engine", "neural", "--reference", aedat, "--query",
                    aedat, "--frame-size", "16", "--max-frames", "150",
                    "--no-progress")
    assert code == 0, err
    lines = [line for line in err.splitlines() if "smaller than" in line]
    assert len(lines) == 1 and lines[0].endswith(
        "warning: reference and query frames are 16x16, smaller than the 24x32 an engine "
        "reads: they are upsampled (set --image-size or --neural-input-size to the frame "
        "size)"), err


def test_no_progress_bars_in_a_redirected_log(tmp_path, capsys):
    corridor = shared_data("corridor")
    code, err = run(tmp_path, capsys, "--engine", "seqslam", "--reference",
                    str(corridor / "ref"), "--query", str(corridor / "query"))
    assert code == 0 and "\r" not in err and "reading" not in err, err
    assert not cli_eval.progress_wanted([], io.StringIO())
    assert cli_eval.progress_wanted(["--progress"], io.StringIO())

    class Tty(io.StringIO):
        def isatty(self):
            return True

    assert cli_eval.progress_wanted([], Tty())

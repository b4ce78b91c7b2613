"""API consistency of the front-end modules: imports that behave, plots that leave no trace."""

import os
import subprocess
import sys

import numpy as np
import pytest


def test_import_preprocess_gives_the_module():
    import torchseq
    import torchseq.preprocess as pre

    assert pre.__name__ == "torchseq.preprocess" and callable(pre.resize)
    assert torchseq.preprocess is pre and not callable(pre)


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_importing_plots_keeps_the_users_backend():
    code = ("import matplotlib; import torchseq.cli.plots as p; import matplotlib.pyplot as plt; "
            "f = p.plot_matrix([[0, 1], [1, 0]], 't'); "
            "print(matplotlib.get_backend(), len(plt.get_fignums()))")
    env = {**os.environ, "MPLBACKEND": "svg"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["svg", "0"]  # main switched everyone to Agg


def test_event_frames_in_matched_pairs_are_scaled():
    from torchseq.cli.plots import _grey_range

    rng = np.random.default_rng(0)
    events = rng.poisson(0.8, (6, 16, 16)).astype(np.float32)  # a few counts per pixel
    events[:, 3, 3] = 255  # a hot pixel
    camera = rng.uniform(0, 255, (6, 16, 16)).astype(np.float32)
    lo, hi = _grey_range(events[0]).values()  # a reference (event) frame
    assert lo == 0 and hi <= 5  # stretched to its counts, not to the hot pixel
    qlo, qhi = _grey_range(camera[0]).values()  # a camera frame keeps 0..255
    assert (qlo, qhi) == (0, 255)

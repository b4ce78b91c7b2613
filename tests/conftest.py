import contextlib
import os
import warnings
from pathlib import Path

import pytest
import torch
from hypothesis import settings

# Property tests draw the same cases on every run (CI must not flip on a new draw); set
# HYPOTHESIS_PROFILE=explore to draw fresh cases while hunting for bugs.
settings.register_profile("torchseq", derandomize=True, database=None, deadline=None)
settings.register_profile("explore", derandomize=False, database=None, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "torchseq"))

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="CUDA is not available on this machine"))]


def shared_data(*parts: str) -> Path:
    """Path under ../shared/data, skipping the test with a clear reason when it is absent."""
    path = DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data not found at {path} (the ../shared/data folder is absent)")
    return path


COARSE_UNITS = r"a route of \d+ frames on \d+ output units"  # NeuralSeqSLAM.fit's warning


@contextlib.contextmanager
def coarse_units_expected():
    """Block whose fit is known to give units of several frames (small test models).

    Only fit's coarse-units warning is filtered, only inside the block: other warnings, and
    this one anywhere else, still reach pytest's summary.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=COARSE_UNITS, category=UserWarning)
        yield

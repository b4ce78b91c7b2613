import contextlib
import dataclasses
import os
import warnings
from pathlib import Path

import numpy as np
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


@pytest.fixture(scope="module")
def memory_cap(request):
    """Cap the address space at what the process uses now plus ``MEMORY_CAP_EXTRA`` bytes of
    the module (2 GiB by default), so a huge allocation fails loudly instead of swapping."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    used = int(open("/proc/self/statm").read().split()[0]) * resource.getpagesize()
    cap = used + getattr(request.module, "MEMORY_CAP_EXTRA", 2 << 30)
    if hard != resource.RLIM_INFINITY:
        cap = min(cap, hard)
    resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    yield
    resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def shared_data(*parts: str) -> Path:
    """Path under ../shared/data, skipping the test with a clear reason when it is absent."""
    path = DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data not found at {path} (the ../shared/data folder is absent)")
    return path


def load_script(relative: str):
    """A script of the repository (``"experiments/x.py"``) imported as a module by its path."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / relative
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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


@pytest.fixture(scope="module")
def route(request):
    """The test module's synthetic route: ``make_demo(size=(48, 64), **ROUTE)``.

    ``ROUTE`` is a dict of the module (its length, seed, speed), so each module keeps its data.
    """
    from torchseq.demo import make_demo

    return make_demo(**{"size": (48, 64), **request.module.ROUTE})


@pytest.fixture(scope="module")
def tiny_runs():
    """The tiny spiking model's runs (``spiking_helpers.tiny``): ``(model, spiking, xr, xq,
    rate, spiking_run)``, with ``xr``/``xq`` the float64 encoded reference and query and
    ``rate`` the rate model's decisions."""
    from spiking_helpers import tiny

    model, demo, sp = tiny()  # levels=6
    xr, xq = (model.encode(x).double() for x in (demo.reference, demo.query))
    return model, sp, xr, xq, model.run(demo.query).matches.reference.numpy(), sp.run(demo.query)


@dataclasses.dataclass(frozen=True)
class Corridor:
    """The real corridor pair (../shared/data/corridor), loaded once per session.

    Attributes:
        root: the folder (``ref/``, ``query/``, ``ground_truth.csv``), for command-line tests.
        ref: ``(111, 120, 160)`` float32 grey reference frames, as ``load_traverse`` gives them.
        query: ``(111, 120, 160)`` float32 grey query frames.
        ground_truth: ``(111, 111)`` bool, read-only: query q matches references q-2 ... q+2.

    Shared by every test of the session: never modify ``ref`` or ``query`` in place (clone
    first). The fixture checks at the end of the session that they are unchanged.
    """

    root: Path
    ref: torch.Tensor
    query: torch.Tensor
    ground_truth: np.ndarray


@pytest.fixture(scope="session")
def corridor():
    """The corridor pair, decoded once per session; skips with a reason when it is absent."""
    from torchseq.ground_truth import load_ground_truth
    from torchseq.sources import load_traverse

    root = shared_data("corridor")
    ref = load_traverse(root / "ref", progress=False)
    query = load_traverse(root / "query", progress=False)
    gt = load_ground_truth(root / "ground_truth.csv", len(ref), len(query))
    gt.setflags(write=False)
    data = Corridor(root, ref, query, gt)
    pristine = (ref.clone(), query.clone())
    yield data
    assert torch.equal(ref, pristine[0]) and torch.equal(query, pristine[1]), \
        "a test modified the shared corridor frames in place (clone them first)"


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true",
                     help="also run the tests marked slow (CI runs them as a second pass)")


def pytest_collection_modifyitems(config, items):
    """The default run leaves out tests marked slow.

    ``--runslow``, any ``-m``, or a test named by its node id (``file.py::test``) brings them in.

    ``python -m pytest -q`` is the quick run (target: 3 minutes on a quiet 2-core machine); CI runs
    ``python -m pytest -q -m slow`` (``.ci/run``), so every test still runs there.
    """
    if config.getoption("--runslow") or config.getoption("markexpr"):
        return
    if any("::" in arg for arg in config.args):  # tests named one by one run as asked
        return
    slow = [item for item in items if item.get_closest_marker("slow") is not None]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [item for item in items if item.get_closest_marker("slow") is None]

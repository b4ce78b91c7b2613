"""Which kernel ran: the integer stages' ``kernel=`` choice, the runtimes' kernels, the int8 GEMMs.

Every stage function of :mod:`torchseq.export.int_functional` runs its torch definition for
``kernel="torch"`` and its NumPy kernel (:mod:`torchseq.export.int_kernels`) for
``kernel="numpy"``, never the other; the two agree bit for bit stage by stage; the runtimes
run only the kernel chosen at construction, and :class:`StreamRuntime` says (and is checked
on) whether its int8 GEMMs ran.
"""

from functools import lru_cache

import numpy as np
import pytest
import torch
from conftest import coarse_units_expected

import torchseq.export.int_functional as F
import torchseq.export.int_kernels as K
from torchseq.demo import make_demo
from torchseq.export import IntegerInputError
from torchseq.export.int_model import choose_pool, device_frames, integer_model
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.export.int_stream import StreamRuntime
from torchseq.neural import NeuralConfig, NeuralSeqSLAM

# stage -> (its torch body in int_functional, its NumPy kernel in int_kernels)
STAGES = {
    "input_stage": ("_input_stage_torch", "input_stage"),
    "l1_sums": ("_l1_sums_torch", "l1_sums"),
    "kwta_code": ("_kwta_code_torch", "kwta_code"),
    "l3_sums": ("_l3_sums_torch", "l3_sums"),
    "rescale": ("_rescale_torch", "rescale"),
    "cohort_gain": ("_cohort_gain_torch", "cohort_gain"),
    "ring_step": ("_ring_step_torch", "ring_step"),
    "velocity_ring": ("_velocity_ring_torch", "velocity_ring"),
    "velocity_update": ("_velocity_update_torch", "velocity_update"),
    "decide": ("_decide_torch", "decide"),
}
FIXED = set(STAGES) - {"velocity_ring", "velocity_update"}
ADAPTIVE = set(STAGES) - {"ring_step"}


@lru_cache(maxsize=None)
def model(adaptive: bool = False):
    demo = make_demo(n_reference=16, size=(16, 16), seed=5)
    torch.manual_seed(0)
    cfg = dict(input_size=(8, 8), hidden=64, n_output=10, n_cohorts=2)
    # the ring alone: the integer format has no form of the unit search (refused by name)
    config = (NeuralConfig.adaptive_velocity(**cfg) if adaptive
              else NeuralConfig(**cfg, unit_search="off"))
    net = NeuralSeqSLAM(config)
    with coarse_units_expected():
        net.fit(demo.reference, log=False)
    pool = choose_pool((16, 16), (8, 8))
    return integer_model(net, pool), device_frames(demo.query, (8, 8), pool)


@pytest.fixture
def ran(monkeypatch):
    """Spies on every stage's two kernels: the list of ``(stage, kernel)`` calls."""
    calls = []
    for stage, (torch_name, numpy_name) in STAGES.items():
        for mod, name, kind in ((F, torch_name, "torch"), (K, numpy_name, "numpy")):
            real = getattr(mod, name)

            def spy(*a, _real=real, _tag=(stage, kind), **kw):
                calls.append(_tag)
                return _real(*a, **kw)

            monkeypatch.setattr(mod, name, spy)
    return calls


@pytest.mark.parametrize("adaptive", [False, True])
@pytest.mark.parametrize("kernel", ["numpy", "torch"])
def test_runtime_runs_every_stage_with_its_kernel_only(ran, kernel, adaptive):
    im, frames = model(adaptive)
    rt = IntegerRuntime(im, kernel=kernel)
    out, state = rt.step(frames[:3])
    rt.step(frames[3:6], state)
    assert rt.kernel == kernel
    assert {k for _, k in ran} == {kernel}, ran
    assert {s for s, _ in ran} == (ADAPTIVE if adaptive else FIXED)


def stage_args(im, frames, adaptive):
    """The arguments of every stage on real intermediate values of ``im``, as NumPy arrays."""
    p, a, st = im.params, im.arrays, im.velocity
    rng = np.random.default_rng(7)
    n = p["n_units"]
    cohort = a["cohort"].astype(np.int64)
    size = np.bincount(cohort, minlength=p["n_cohorts"]).astype(np.int64)
    x = K.input_stage(frames, p).astype(np.int64)
    hid = K.l1_sums(x, a["l1.cols"], a["l1.values"]).astype(np.int64)
    code = K.kwta_code(hid, p["k"]).astype(np.int64)
    e = K.l3_sums(code, K.dense_t(a["l3.cols"], a["l3.values"], p["hidden"]))
    big_e = K.rescale(e, a["l3.row_scale"], p["e_shift"])
    state = rng.integers(-2**20, 2**20, (frames.shape[0], n)).astype(np.int32)
    g = rng.integers(-2**18, 2**18, (frames.shape[0], n))
    args = {
        "input_stage": (frames, p),
        "l1_sums": (x, a["l1.cols"].astype(np.int64), a["l1.values"].astype(np.int64)),
        "kwta_code": (hid, p["k"]),
        "l3_sums": (code, a["l3.cols"].astype(np.int64), a["l3.values"].astype(np.int64)),
        "rescale": (e, a["l3.row_scale"].astype(np.int64), p["e_shift"]),
        "cohort_gain": (big_e, cohort, size, im.cohort),
        "ring_step": (state, g, a["ring.cols"].astype(np.int64),
                      a["ring.values"].astype(np.int64), p["ring_frac"]),
        "decide": (state, a["unit_centre"].astype(np.int64), a["unit_to_ref"].astype(np.int64),
                   p["window"], p["readout"]),
    }
    if adaptive:
        b = frames.shape[0]
        speed = rng.integers(st.v_min, st.v_max + 1, b)
        pos = np.sort(rng.integers(0, 16, (b, st.window)), 1)
        args["velocity_ring"] = (state, g, speed, a["ring.cols"].astype(np.int64),
                                 a["ring.shift"].astype(np.int64), p["ring_frac"], st)
        args["velocity_update"] = (speed, pos, rng.integers(0, st.window + 1, b),
                                   rng.integers(0, 16, b), st)
    return args


@pytest.mark.parametrize("adaptive", [False, True])
def test_each_stage_runs_the_chosen_kernel_and_both_agree(ran, adaptive):
    im, frames = model(adaptive)
    for stage, args in stage_args(im, frames, adaptive).items():
        out = {}
        for kernel in ("numpy", "torch"):
            ran.clear()
            torch_args = [torch.from_numpy(np.array(v)) if isinstance(v, np.ndarray) else v
                          for v in args]
            got = getattr(F, stage)(*(args if kernel == "numpy" else torch_args), kernel=kernel)
            assert ran == [(stage, kernel)], (stage, kernel, ran)
            out[kernel] = [np.asarray(v) for v in (got if isinstance(got, tuple) else (got,))]
        for n, t in zip(out["numpy"], out["torch"]):
            assert np.array_equal(n.astype(np.int64), t.astype(np.int64)), stage


def test_a_stage_returns_the_kind_it_was_given():
    im, frames = model()
    for kernel in ("numpy", "torch"):
        assert isinstance(F.input_stage(frames, im.params, kernel=kernel), np.ndarray)
        got = F.input_stage(torch.from_numpy(frames), im.params, kernel=kernel)
        assert isinstance(got, torch.Tensor)
    with pytest.raises(IntegerInputError, match="kernel must be one of"):
        F.input_stage(frames, im.params, kernel="fast")


def test_stream_runtime_reports_and_runs_its_int8_gemms(ran, monkeypatch):
    im, frames = model()
    stream = StreamRuntime(im, chunk=5)
    gemm = []
    for name in ("int8_l1_sums", "int8_l3_sums"):
        real = getattr(K, name)
        monkeypatch.setattr(K, name, lambda *a, _r=real, _n=name: gemm.append(_n) or _r(*a))
    got = stream.run(frames)
    want = IntegerRuntime(im).run(frames)
    for g, w in zip(got, want):
        assert g.dtype == w.dtype and np.array_equal(g, w)
    # the int8 L3 GEMM is exact for any code of these weights: a CPU with oneDNN builds it
    assert (stream.l3_int8 is not None) == hasattr(torch.ops.onednn, "qlinear_pointwise")
    assert stream.kernels["l3"] == ({"int8"} if stream.l3_int8 is not None else {"numpy"})
    assert ("int8_l3_sums" in gemm) == (stream.l3_int8 is not None)
    assert stream.kernels["l1"] <= {"int8", "numpy"} and stream.kernels["l1"]
    assert ("int8_l1_sums" in gemm) == (stream.l1_int8 is not None)
    assert {k for _, k in ran} == {"numpy"}  # everything else: the NumPy kernels

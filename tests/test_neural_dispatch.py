"""Which kernel ran, per stage, device, dtype and mode (in the manner of kornia's
``test_selection_dispatch``): the private kernels are wrapped so that each call is recorded.

On an x86-64 CPU the int8 GEMM must be there: its absence fails here, it is not skipped.
"""

import contextlib
from unittest import mock

import numpy as np
import pytest
import torch
from conftest import DEVICES

from torchseq.layers import kernels as K
from torchseq.layers import ring as R
from torchseq.neural import NeuralConfig, NeuralError, NeuralSeqSLAM, readout
from torchseq.neural import _step_numba as S
from torchseq.neural import inference as I

ROUTE = dict(n_reference=40, seed=8)  # the conftest ``route`` fixture's demo


@pytest.fixture(scope="module")
def grid_model(route):
    """The default config (integer grids) at a small size."""
    model = NeuralSeqSLAM(NeuralConfig(hidden=512, n_output=40))
    model.fit(route.reference, log=False)
    return model


@contextlib.contextmanager
def recording(module):
    """Yield a list of the kernels that ran, in order, as ``stage:kernel`` strings."""
    ran = []

    def wrap(target, name, label):
        original = getattr(target, name)

        def spy(*args, **kwargs):
            ran.append(label(*args, **kwargs) if callable(label) else label)
            return original(*args, **kwargs)
        return mock.patch.object(target, name, side_effect=spy)

    original_call = K.Int8Linear.__call__

    def int8_call(self, x):
        ran.append("l1:int8_gemm" if self is module.l1_int8 else "l3:int8_gemm")
        return original_call(self, x)

    def scan_label(d, *args):
        return "scan:numpy" if isinstance(d, np.ndarray) else "scan:torch"

    patches = [
        mock.patch.object(K.Int8Linear, "__call__", int8_call),
        wrap(K, "kwta_partition", "kwta:partition"),
        wrap(K, "kwta_partition_indices", "kwta:partition"),
        wrap(K, "cohort_normalise_numpy", "cohorts:numpy"),
        wrap(K, "topk_indices", "kwta:topk"),
        wrap(K, "sum_rows", "l3:embedding_bag"),
        wrap(R, "_ring_step_banded", "ring:banded"),
        wrap(R, "_scan_blocks", scan_label),
        wrap(readout, "_decide_numpy", "decide:numpy"),
        wrap(I, "zscore_pixel_major", lambda f, p, kernel="torch": f"input:{kernel}"),
        wrap(S, "step", "step:numba"),  # read by a module on its first compiled step
    ]
    with contextlib.ExitStack() as stack:
        for p in patches:
            stack.enter_context(p)
        yield ran


def test_int8_kernels_exist_on_x86(grid_model):
    """The default model sits on its integer grids: on x86 the int8 GEMM must be chosen."""
    kernels = grid_model.inference().kernels
    if I.int8_expected():
        # AVX-512: int8 at every batch; AVX2 alone: float32 below SMALL_BATCH (it is faster)
        want = "int8_gemm" if I.int8_l1_at_batch_1() else "int8_gemm_or_float32_gemm"
        assert kernels["l1"] == want, "oneDNN's int8 GEMM is missing or inexact here"
        assert kernels["l3"] == "int8_gemm_or_embedding_bag"
    else:
        assert kernels["l1"] == "float32_gemm"


def test_compiled_step_is_the_auto_choice(grid_model):
    """numba is in the test and fast extras: without it (or off the model's grids) this fails."""
    assert I.numba_available(), "numba is missing: the compiled online step cannot run"
    assert grid_model.inference().kernels["step"] == "stages_or_numba"


@pytest.mark.parametrize("batch", [1, 3, 16, 40])
def test_auto_cpu_step_dispatch(grid_model, route, batch):
    inf = grid_model.inference()
    frames = route.query[:batch]
    with recording(inf) as ran:
        with torch.inference_mode():
            inf(frames)
    if batch < I.SMALL_BATCH:  # one compiled pass, no stage kernel
        assert ran == ["step:numba"]
        return
    l1 = inf.kernels["l1"]
    int8 = l1 == "int8_gemm" or (l1 == "int8_gemm_or_float32_gemm" and batch >= I.SMALL_BATCH)
    l3 = ("l3:int8_gemm" if inf.kernels["l3"] != "embedding_bag" and batch >= I.SMALL_BATCH
          else "l3:embedding_bag")
    want = ["input:numpy", "l1:int8_gemm" if int8 else None, "kwta:partition", l3,
            "cohorts:numpy", "ring:banded", "decide:numpy"]
    assert ran == [w for w in want if w]


def test_the_or_kernel_picks_by_batch_and_decides_as_either(grid_model, route):
    """``int8_gemm_or_float32_gemm``: float32 below SMALL_BATCH, int8 from there on."""
    if grid_model.inference().l1_int8 is None:
        pytest.skip("no oneDNN int8 GEMM on this machine")
    either = grid_model.inference({"l1": "int8_gemm_or_float32_gemm"})  # asked: the stages
    for batch, want in ((1, False), (I.SMALL_BATCH - 1, False), (I.SMALL_BATCH, True)):
        with recording(either) as ran, torch.inference_mode():
            either(route.query[:batch])
        assert ("l1:int8_gemm" in ran) == want, batch
    with torch.inference_mode():
        for name in ("int8_gemm", "float32_gemm"):
            one = grid_model.inference({"l1": name})
            assert torch.equal(one.run(route.query).matches.reference,
                               either.run(route.query).matches.reference)


def test_auto_cpu_run_dispatch(grid_model, route):
    inf = grid_model.inference()
    with recording(inf) as ran:
        got = inf.run(route.query)
    int8 = inf.kernels["l1"].startswith("int8_gemm")  # run's chunks are past SMALL_BATCH
    assert ran[0] == "input:numpy" and ran[-2:] == ["scan:numpy", "decide:numpy"]
    assert ("l1:int8_gemm" in ran) == int8
    assert "ring:banded" not in ran  # the sequence form, not the step
    want = grid_model.run(route.query)  # the model's run: a new module with the auto kernels
    assert torch.equal(got.matches.reference, want.matches.reference)
    assert torch.equal(got.activity, want.activity)


def test_portable_kernels_are_plain_torch(grid_model, route):
    inf = grid_model.inference("portable")
    assert inf.kernels == I.PORTABLE
    with recording(inf) as ran:
        inf(route.query[:3])
        inf.scan(torch.rand(20, grid_model.n_units))
    assert ran == ["input:torch", "scan:torch"]  # no NumPy, no int8, no embedding-bag


def test_float_model_falls_back_to_float_kernels(route):
    model = NeuralSeqSLAM(NeuralConfig(hidden=512, n_output=40, l1_levels=0, l3_levels=0))
    model.fit(route.reference, log=False)
    inf = model.inference()
    assert inf.kernels["l1"] == "float32_gemm" and inf.kernels["l3"] == "embedding_bag"
    assert inf.kernels["step"] == "stages"  # the compiled step needs the integer grids
    with recording(inf) as ran:
        inf(route.query[:20])
        inf(route.query[:1])
    assert ran[6:] == ran[:6]  # batch 1 too: the stages
    del ran[6:]
    assert ran == ["input:numpy", "kwta:partition", "l3:embedding_bag", "cohorts:numpy",
                   "ring:banded", "decide:numpy"]


def test_explicit_kernels_and_wrapped_ring(grid_model, route):
    inf = grid_model.inference({"kwta": "topk", "l3": "embedding_bag", "ring": "dense",
                                "decide": "torch", "input": "torch", "cohorts": "torch"})
    with recording(inf) as ran:
        inf(route.query[:2])
    assert ran[0] == "input:torch" and ran[-2:] == ["kwta:topk", "l3:embedding_bag"]
    wrapped = NeuralSeqSLAM(NeuralConfig(hidden=512, n_output=20, ring_wrap=True))
    wrapped.fit(route.reference[:20], log=False)
    assert wrapped.inference().kernels["ring"] == "dense"
    with pytest.raises(NeuralError, match="banded"):
        wrapped.inference({"ring": "banded"})


def test_kernels_do_not_follow_grad_mode_or_history(grid_model, route):
    inf = grid_model.inference()
    logs = []
    for ctx in (torch.enable_grad, torch.no_grad, torch.inference_mode):
        with recording(inf) as ran, ctx():
            inf.step(route.query[:2])
        logs.append(ran)
    assert logs[0] == logs[1] == logs[2] and logs[0]
    grid_model.run(route.query[:5])
    for ctx in (torch.enable_grad, torch.inference_mode):
        with recording(inf) as ran, ctx():
            grid_model.step(route.query[:2])
        assert ran == []  # the model's step is the layers whatever ran before: no kernel


def test_bad_kernel_requests(grid_model):
    for bad in ("fast", {"l9": "x"}, {"l1": "cuda_gemm"}, {"l3": "int8_gemm", "kwta": "topk"}):
        with pytest.raises(NeuralError):
            grid_model.inference(bad)


@pytest.mark.parametrize("device", DEVICES)
def test_device_dispatch(route, device):
    model = NeuralSeqSLAM(NeuralConfig(hidden=512, n_output=40), device=device)
    model.fit(route.reference, log=False)
    inf = model.inference()
    if device == "cpu":
        assert inf.kernels["input"] == "numpy" and inf.kernels["scan"] == "numpy"
        return
    assert inf.kernels == {"input": "torch", "l1": "float32_gemm", "kwta": "topk",
                           "l3": "embedding_bag", "cohorts": "torch", "ring": "banded",
                           "scan": "torch", "decide": "torch", "step": "stages"}
    with recording(inf) as ran:
        out, _ = inf(route.query[:3])
    assert ran == ["input:torch", "kwta:topk", "l3:embedding_bag", "ring:banded"]
    assert out.activity.device.type == "cuda"
    with pytest.raises(NeuralError, match="CPU"):
        model.inference({"kwta": "partition"})

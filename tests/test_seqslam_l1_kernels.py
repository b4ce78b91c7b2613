"""The compiled uint8 L1 kernel ("sad", ``seqslam/_l1_numba.py``): exact against a plain loop
and bit for bit against the thermometer kernel, the rule that chooses it, and numba's import
left to the runs that pay for it."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import shared_data
from seqslam_oracle import oracle_difference

from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
from torchseq.seqslam import difference as difference_module
from torchseq.seqslam.difference import (
    SAD_MIN_WORK,
    difference_with_kernel,
    l1_kernel,
    thermometer_levels,
)

ROOT = Path(__file__).resolve().parents[1]


EXTREMES = {"uint8": (0, 255), "0_255": (0, 255), "openseqslam": (0, 135),
            "signed": (-300, -45)}


def _values(kind: str, shape, g: torch.Generator) -> torch.Tensor:
    """Integer-valued float32 descriptors of one kind."""
    if kind == "uint8":  # the whole byte range: too many levels for the thermometer
        x = torch.randint(0, 256, shape, generator=g)
    elif kind == "0_255":  # two values a byte apart: a gap the thermometer cannot weigh
        x = torch.randint(0, 2, shape, generator=g) * 255
    elif kind == "openseqslam":  # 0 for flat blocks beside 119..135
        x = torch.randint(119, 136, shape, generator=g)
        x[torch.rand(shape, generator=g) < 0.1] = 0
    else:  # "signed": negative integers, offset by the minimum into uint8
        x = torch.randint(-300, -44, shape, generator=g)
    return x.float()


def _pair(kind: str, n_ref: int, n_query: int, dim: int, seed: int = 0):
    """Reference and query of one kind, the kind's lowest and highest values both present."""
    g = torch.Generator().manual_seed(seed)
    ref, query = _values(kind, (n_ref, dim), g), _values(kind, (n_query, dim), g)
    ref[0, 0], query[-1, -1] = EXTREMES[kind]
    return ref, query


@pytest.fixture(autouse=True)
def _one_intra_op_thread():
    """Many small torch ops here: on a busy 2-core host their OpenMP regions spin (seconds)."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


SHAPES = [(1, 1, 1), (1, 9, 33), (3, 1, 31), (37, 29, 2049), (130, 70, 64)]


@pytest.mark.parametrize("kind", ["uint8", "0_255", "openseqslam", "signed"])
@pytest.mark.parametrize("shape", SHAPES)
def test_sad_is_the_plain_loop_and_the_thermometer_bit_for_bit(kind, shape):
    dim = shape[2]
    ref, query = _pair(kind, *shape, seed=sum(shape))
    want = torch.cdist(ref.double()[None], query.double()[None], p=1)[0].numpy()  # exact
    if ref.shape[0] * query.shape[0] <= 100:  # and the plain loop, one pair at a time
        np.testing.assert_array_equal(want, oracle_difference(ref.numpy(), query.numpy()))
    # one row per block (max_chunk_elements = D) and the whole query at once; 1 and 2 workers
    for budget, threads in ((dim, 1), (dim, 2), (2**26, 1), (2**26, 2)):
        got, kernel = difference_with_kernel(ref, query, max_chunk_elements=budget,
                                             threads=threads, kernel="sad")
        assert kernel == "sad" and got.dtype == torch.float32 and got.shape == want.shape
        np.testing.assert_array_equal(got.double().numpy(), want)
    if thermometer_levels(ref, query) is not None:
        therm, kernel = difference_with_kernel(ref, query, kernel="thermometer")
        assert kernel == "thermometer" and torch.equal(got, therm)


@pytest.mark.parametrize("budget_rows, n_query", [(1, 9), (3, 9), (3, 2), (64, 9)])
def test_sad_blocks_stay_within_the_budget(monkeypatch, budget_rows, n_query):
    """Every uint8 block handed to the compiled loop holds at most max_chunk_elements."""
    from torchseq.seqslam import _l1_numba

    seen = []
    real = _l1_numba.sad
    monkeypatch.setattr(_l1_numba, "sad", lambda a, b, *rest: seen.append((a.size, b.size))
                        or real(a, b, *rest))
    ref, query = _pair("openseqslam", 10, n_query, 48)
    budget = budget_rows * 48
    got, kernel = difference_with_kernel(ref, query, max_chunk_elements=budget, kernel="sad")
    assert kernel == "sad" and seen and max(max(s) for s in seen) <= budget
    np.testing.assert_array_equal(got.double().numpy(), oracle_difference(ref, query))


def test_sad_keeps_float64():
    ref, query = (x.double() for x in _pair("uint8", 20, 7, 100))
    got, kernel = difference_with_kernel(ref, query, kernel="sad")
    assert kernel == "sad" and got.dtype == torch.float64
    np.testing.assert_array_equal(got.numpy(), oracle_difference(ref.numpy(), query.numpy()))


def test_forced_kernels_refuse_data_they_cannot_take():
    x = _pair("openseqslam", 10, 10, 64)[0]
    with pytest.raises(ValueError, match="'sad' L1 kernel"):
        difference_with_kernel(x + 0.5, x, kernel="sad")  # not integer-valued
    with pytest.raises(ValueError, match="'sad' L1 kernel"):
        difference_with_kernel(x * 2, x, kernel="sad")  # 0..270: not a byte
    with pytest.raises(ValueError, match="'thermometer' L1 kernel"):
        difference_with_kernel(_pair("uint8", 10, 1, 64)[0], x, kernel="thermometer")
    with pytest.raises(ValueError, match="kernel must be"):
        difference_with_kernel(x, x, kernel="gemm")
    with pytest.raises(ValueError, match="kernel must be"):
        difference_with_kernel(x, x, metric="l2", kernel="sad")
    const = torch.full((4, 64), 127.0)
    assert difference_with_kernel(const, const, kernel="sad")[1] == "constant"


@pytest.mark.parametrize("product", ["float32", "int8"])
def test_l1_kernel_rule(monkeypatch, product):
    """"sad" from R Q D = SAD_MIN_WORK on CPU, where the alternative is the float32 thermometer
    product or cdist; the thermometer where its int8 GEMM runs (AVX-512), below the size, for
    data outside a byte and without numba."""
    monkeypatch.setattr(difference_module, "thermometer_product", lambda device: product)
    assert SAD_MIN_WORK == 2**31
    ref, query = _pair("openseqslam", 1024, 1024, 2048)  # R Q D = 2**31 exactly
    levels = thermometer_levels(ref, query)
    big = "sad" if product == "float32" else "thermometer"
    assert l1_kernel(ref, query, levels) == big
    assert l1_kernel(ref, query[:1023], levels) == "thermometer"  # one query fewer
    wide = (ref % 4) * 100  # 0, 100, 200, 300: few levels, a span above a byte
    assert thermometer_levels(wide, wide) is not None
    assert l1_kernel(wide, wide, thermometer_levels(wide, wide)) == "thermometer"
    many, many_q = _pair("uint8", 1024, 1024, 2048)  # no thermometer levels: else cdist
    assert thermometer_levels(many, many_q) is None
    assert l1_kernel(many, many_q, None) == "sad"
    assert l1_kernel(many + 0.5, many_q, None) == "cdist"
    monkeypatch.setattr(difference_module, "sad_available", lambda: False)
    assert l1_kernel(ref, query, levels) == "thermometer"
    assert l1_kernel(many, many_q, None) == "cdist"


def test_the_int8_rule_switches_where_the_saving_pays_numbas_start_up(monkeypatch):
    """Against the int8 thermometer product (AVX-512) "sad" from R Q D (k - 6) >= 6e10:
    1,712 places at nordland-b's 16 thresholds, 3,828 at the demo's 8, never at 6 or fewer."""
    monkeypatch.setattr(difference_module, "thermometer_product", lambda device: "int8")
    assert (difference_module.SAD_INT8_TIE_LEVELS, difference_module.SAD_INT8_MIN_SAVING) == \
        (6, 6 * 10**10)
    for k, n in ((16, 1712), (8, 3828)):
        levels = (119 + torch.arange(k, dtype=torch.float64), None)
        x = torch.full((1, 2048), 119.0)
        assert l1_kernel(x.expand(n, -1), x.expand(n, -1), levels) == "sad"
        assert l1_kernel(x.expand(n - 1, -1), x.expand(n - 1, -1), levels) == "thermometer"
    levels = (119 + torch.arange(6, dtype=torch.float64), None)
    x = torch.full((1, 2048), 119.0).expand(10**5, -1)
    assert l1_kernel(x, x, levels) == "thermometer"


@pytest.mark.parametrize("product, kernel, saving", [
    ("float32", "sad", None), ("int8", "thermometer", None), ("int8", "sad", 40 * 30 * 64)])
def test_the_chosen_kernel_is_the_one_that_ran(monkeypatch, product, kernel, saving):
    ran = []
    for name in ("_l1_sad", "_l1_thermometer"):
        real = getattr(difference_module, name)
        monkeypatch.setattr(difference_module, name,
                            lambda *a, real=real, name=name: ran.append(name) or real(*a))
    monkeypatch.setattr(difference_module, "thermometer_product", lambda device: product)
    monkeypatch.setattr(difference_module, "SAD_MIN_WORK", 40 * 30 * 64)
    if saving is not None:  # the int8 rule's size made this run's: R Q D (k - 6)
        ref, query = _pair("openseqslam", 40, 30, 64)
        k = thermometer_levels(ref, query)[0].numel()
        monkeypatch.setattr(difference_module, "SAD_INT8_MIN_SAVING", saving * (k - 6))
    ref, query = _pair("openseqslam", 40, 30, 64)
    d, got = difference_with_kernel(ref, query)
    assert got == kernel and ran == [f"_l1_{kernel}"]
    np.testing.assert_array_equal(d.double().numpy(), oracle_difference(ref, query))
    assert difference_with_kernel(ref, query[:29])[1] == "thermometer"  # below the size


@pytest.mark.slow  # a fresh interpreter importing torch and numba: 5-10 s on a busy 2-core host
def test_a_small_run_never_imports_numba_and_sad_does(tmp_path):
    """numba (seconds to import and load) only where the size rule picks "sad"."""
    code = """
import json, sys, torch
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
from torchseq.seqslam import difference
difference.thermometer_product = lambda device: "float32"  # the rule of a CPU without AVX-512
g = torch.Generator().manual_seed(0)
x = (119 + torch.randint(0, 17, (300, 2048), generator=g)).float()
small = SeqSLAM(SeqSLAMConfig.openseqslam()).match_descriptors(x, x[:200])
seen = {"small": small.kernels["difference"], "numba_small": "numba" in sys.modules}
seen["forced"] = difference.difference_with_kernel(x, x[:3], kernel="sad")[1]
seen["numba_forced"] = "numba" in sys.modules
print(json.dumps(seen))
"""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got == {"small": "thermometer", "numba_small": False, "forced": "sad",
                   "numba_forced": True}


def _match_both(monkeypatch, ref, query, config):
    """The engine's results with the size rule choosing "sad" and then the thermometer."""
    monkeypatch.setattr(difference_module, "thermometer_product", lambda device: "float32")
    out = {}
    for kernel, min_work in (("sad", 0), ("thermometer", 2**62)):
        monkeypatch.setattr(difference_module, "SAD_MIN_WORK", min_work)
        out[kernel] = SeqSLAM(config).match(ref, query)
        assert out[kernel].kernels["difference"] == kernel
    return out["sad"], out["thermometer"]


@pytest.mark.parametrize("keep_matrices", [True, False])
def test_sad_and_thermometer_give_the_same_matches_on_the_corridor(monkeypatch, corridor,
                                                                   keep_matrices):
    from torchseq.metrics import evaluate

    cfg = SeqSLAMConfig.openseqslam(keep_matrices=keep_matrices, max_chunk_elements=2**16)
    sad, therm = _match_both(monkeypatch, corridor.ref, corridor.query, cfg)
    if keep_matrices:
        assert torch.equal(sad.difference, therm.difference)
        assert float(sad.difference.std()) > 0  # real distances, not a blank matrix
    assert torch.equal(sad.matches.reference, therm.matches.reference)
    torch.testing.assert_close(sad.matches.score, therm.matches.score, rtol=0, atol=0,
                               equal_nan=True)  # the unmatched ends are NaN in both
    assert torch.equal(sad.ranked, therm.ranked)
    recall = evaluate(sad.matches, corridor.ground_truth)["recall_at_1"]
    assert recall == evaluate(therm.matches, corridor.ground_truth)["recall_at_1"]
    assert recall > 0.3  # the corridor is matched (0.38: the ends stay unmatched), not noise


@pytest.mark.slow  # 1,788 x 1,788 places through the thermometer's float32 product
def test_sad_and_thermometer_give_the_same_matches_on_nordland(monkeypatch):
    from torchseq.metrics import evaluate
    from torchseq.sources import load_traverse

    root = shared_data("nordland-b")
    ref = load_traverse(root / "summer", progress=False)
    query = load_traverse(root / "winter", progress=False)
    i = np.arange(len(query))
    gt = np.abs(i[None, :] - i[:len(ref), None]) <= 2
    sad, therm = _match_both(monkeypatch, ref, query, SeqSLAMConfig.openseqslam(threads=1))
    assert torch.equal(sad.difference, therm.difference)
    assert torch.equal(sad.matches.reference, therm.matches.reference)
    assert torch.equal(sad.ranked, therm.ranked)
    recall = evaluate(sad.matches, gt)["recall_at_1"]
    assert recall == evaluate(therm.matches, gt)["recall_at_1"] and recall > 0.2


@pytest.mark.slow  # decodes nordland-b's 2 x 1,788 frames
def test_this_cpu_picks_sad_for_the_whole_of_nordland(monkeypatch):
    # no rule patched: the rule of this machine's CPU kind (float32 product: from 2**31; int8:
    # from R Q D (k - 6) >= 6e10, k = 16 here) picks "sad" for 1,788 places, and it ran
    from torchseq.sources import load_traverse

    pytest.importorskip("numba")
    root = shared_data("nordland-b")
    s = SeqSLAM(SeqSLAMConfig(threads=1))
    ref = s.descriptors(load_traverse(root / "summer", progress=False))
    query = s.descriptors(load_traverse(root / "winter", progress=False))
    assert thermometer_levels(ref, query)[0].numel() == 16
    ran = []
    real = difference_module._l1_sad
    monkeypatch.setattr(difference_module, "_l1_sad", lambda *a: ran.append(1) or real(*a))
    assert difference_with_kernel(ref, query)[1] == "sad" and ran == [1]
    assert l1_kernel(ref[:1000], query[:1000], thermometer_levels(ref, query)) == (
        "sad" if difference_module.thermometer_product("cpu") == "float32" else "thermometer")

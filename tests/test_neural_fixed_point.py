import math

import pytest
import torch
from conftest import coarse_units_expected

from torchseq.layers import kwta
from torchseq.layers.kernels import Int8Linear, kwta_partition
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.neural.config import NeuralError
from torchseq.neural.inference import int8_expected
from torchseq.preprocess import block_order, quantise_input, zscore_blocks
from torchseq.quantise import factor_power_of_two, factor_rows, integer_weights, round_rows


def test_quantise_input_grid_and_identity():
    x = torch.tensor([0.0, 0.01, 0.016, -0.02, 1.0 / 64, 3.75])
    q = quantise_input(x, 32)
    assert torch.equal(q * 32, torch.round(q * 32))  # on the 1/32 grid
    assert torch.equal(q, torch.tensor([0.0, 0.0, 1 / 32, -1 / 32, 0.0, 120 / 32]))  # 0.5 -> even
    assert quantise_input(x, 0) is x


def test_integer_weights_round_trip():
    g = torch.Generator().manual_seed(0)
    bound = math.sqrt(3 / 154)
    w = (torch.rand(50, 80, generator=g) * 2 - 1) * bound
    iw = integer_weights(w, bound, 64)
    n, step = factor_power_of_two(iw, 64)
    assert math.log2(step) == round(math.log2(step))
    assert n.dtype == torch.int8 and int(n.abs().max()) <= 64
    assert torch.equal(n.float() * step, iw)
    assert torch.equal(n.float(), torch.round(w / bound * 64))  # w rescaled to +-64, rounded
    assert factor_power_of_two(w, 64) is None  # float weights are not on a grid
    assert factor_power_of_two(iw * 3, 64) is None  # 3 * 2**e is not a power of two


def test_round_rows_round_trip():
    g = torch.Generator().manual_seed(1)
    w = torch.randn(20, 300, generator=g) * (torch.rand(20, 300, generator=g) < 0.2)
    w[3] = 0.0  # an all-zero row stays zero
    r = round_rows(w, 127)
    assert torch.equal(r[3], torch.zeros(300))
    n, scale = factor_rows(r, 127)
    assert n.dtype == torch.int8 and int(n.abs().max()) == 127
    torch.testing.assert_close(n.float() * scale[:, None], r, rtol=1e-6, atol=0.0)
    step = w.abs().amax(1, keepdim=True) / 127
    assert ((r - w).abs() <= step / 2 + 1e-7).all()  # nearest grid point
    assert factor_rows(w, 127) is None


def test_int8_linear_is_exact():
    g = torch.Generator().manual_seed(2)
    n = torch.randint(-64, 65, (96, 200), generator=g, dtype=torch.int8)
    n[0] = 64
    n[1] = -64  # extreme rows
    scale = torch.full((96,), 2.0**-8)
    lin = Int8Linear.create(n, scale, 1 / 32, 128)
    if lin is None:
        assert not int8_expected(), "oneDNN's int8 GEMM is missing or inexact on this x86 CPU"
        pytest.skip("no oneDNN int8 GEMM on this (non-x86) machine")
    x = torch.randint(0, 256, (33, 200), generator=g, dtype=torch.uint8)
    x[0] = 255
    x[1] = 0
    want = ((x.double() - 128) @ n.double().T) * (2.0**-8 / 32)  # exact integers, float64
    assert torch.equal(lin(x), want.float())


@pytest.mark.parametrize("ties", [False, True])
def test_kwta_code_equals_kwta(ties):
    g = torch.Generator().manual_seed(3)
    h = torch.randn(40, 500, generator=g)
    if ties:
        h = torch.randint(-6, 7, (40, 500), generator=g).float()  # many ties at the threshold
        h[5] = 0.0  # every entry tied
    code = kwta_partition(h, 37)
    assert code.dtype == torch.bool
    assert torch.equal(code.float(), kwta(h, 37, binary=True))
    assert torch.equal(kwta(h, 37, binary=True, kernel="partition"), kwta(h, 37, binary=True))
    assert torch.equal(kwta(h, 37, kernel="partition"), kwta(h, 37))


@pytest.fixture(scope="module")
def model():
    from torchseq.demo import make_demo

    demo = make_demo(n_reference=80, speed=0.8)
    m = NeuralSeqSLAM(NeuralConfig(hidden=1024, n_output=60))
    with coarse_units_expected():  # a small model: units of several frames
        m.fit(demo.reference, log=False)
    return m, demo


def test_default_model_sits_on_its_integer_grids(model):
    m, _ = model
    assert factor_power_of_two(m.l1.folded_weight(), 64) is not None
    assert factor_rows(m.l3.folded_weight(), 127) is not None
    x = m.encode(torch.rand(3, 24, 32) * 255)
    assert torch.equal(x * 32, torch.round(x * 32)) and float((x * 32).abs().max()) <= 120


def test_int8_path_equals_float_path(model):
    m, demo = model
    fast = m.inference({"l1": "int8_gemm"}) if m.inference().l1_int8 is not None else None
    if fast is None:
        assert not int8_expected(), "the int8 kernels are missing on this x86 CPU"
        pytest.skip("no oneDNN int8 GEMM on this (non-x86) machine")
    slow = m.inference({"l1": "float32_gemm", "l3": "embedding_bag"})
    x = m.encode(demo.query)[:, block_order(24, 32, 4)]  # block-major, as the modules take it
    xq = (x * 32 + 128).to(torch.uint8)
    with torch.no_grad():
        assert torch.equal(fast.l1_int8(xq), x @ slow.w1_t)  # exact L1
        torch.testing.assert_close(fast.evidence(demo.query), slow.evidence(demo.query),
                                   rtol=1e-5, atol=1e-5)
        one = fast.evidence(demo.query[:1])  # below SMALL_BATCH: the embedding-bag L3
        torch.testing.assert_close(one, slow.evidence(demo.query[:1]), rtol=1e-5, atol=1e-5)
    a, b = m.run(demo.query), m.run(demo.query)
    assert torch.equal(a.activity, b.activity)
    c = slow.run(demo.query)
    assert torch.equal(a.matches.reference, c.matches.reference)
    torch.testing.assert_close(a.activity, c.activity, rtol=1e-4, atol=1e-5)


def test_float_model_falls_back():
    m = NeuralSeqSLAM(NeuralConfig(hidden=256, n_output=10, input_steps=0, l1_levels=0,
                                   l3_levels=0))
    with coarse_units_expected():  # a small model: units of several frames
        m.fit(torch.rand(20, 24, 32) * 255, log=False)
    assert m.inference().kernels["l1"] == "float32_gemm"
    assert m.inference().kernels["l3"] == "embedding_bag"
    for ask in ({"l1": "int8_gemm"}, {"l3": "int8_gemm"}):
        with pytest.raises(NeuralError, match="int8"):
            m.inference(ask)
    assert m.run(torch.rand(5, 24, 32) * 255).matches.reference.shape == (5,)


def test_config_grid_fields():
    old = NeuralConfig().to_dict()
    for key in ("input_steps", "l1_levels", "l3_levels"):
        del old[key]
    cfg = NeuralConfig.from_dict(old)  # a checkpoint written before the grids existed
    assert (cfg.input_steps, cfg.l1_levels, cfg.l3_levels) == (0, 0, 0)
    for bad in (dict(input_steps=-1), dict(l1_levels=65), dict(l3_levels=128)):
        with pytest.raises(NeuralError):
            NeuralConfig(**bad).validate()


def test_zscore_blocks_equal_patch_normalise():
    from torchseq.preprocess import patch_normalise

    g = torch.Generator().manual_seed(4)
    frames = torch.rand(6, 24, 32, generator=g) * 255
    frames[1] = 9.0  # flat
    frames[2, :4, :4] = 3.0  # one flat block
    z = zscore_blocks(frames, 4)  # (6, 48, 16)
    order = block_order(24, 32, 4)
    want = patch_normalise(frames, 4, "zscore").reshape(6, -1)[:, order].reshape(6, 48, 16)
    assert torch.equal(z, want)  # patch_normalise's z-scores are this z-score
    assert torch.equal(z[1], torch.zeros(48, 16)) and torch.equal(z[2, 0], torch.zeros(16))
    loop = [int(r) * 32 + int(c) for br in range(6) for bc in range(8)
            for r in range(4 * br, 4 * br + 4) for c in range(4 * bc, 4 * bc + 4)]
    assert order.tolist() == loop

import pytest
import torch
from conftest import DEVICES

from torchseq.layers import MaskedLinear, make_mask, masked_linear
from torchseq.layers.functional import mask_fan_in

DTYPES = [torch.float32, torch.float64]


@pytest.mark.parametrize("out_f,in_f,density", [(7, 13, 0.2), (3072, 768, 0.2), (5, 4, 1.0),
                                                 (4, 10, 0.01)])
def test_mask_exact_per_row(out_f, in_f, density):
    mask = make_mask(out_f, in_f, density, torch.Generator().manual_seed(1))
    per_row = max(1, round(density * in_f))
    assert mask.shape == (out_f, in_f)
    assert set(mask.unique().tolist()) <= {0.0, 1.0}
    assert (mask.sum(1) == per_row).all()
    assert int(mask.sum()) == out_f * per_row == out_f * mask_fan_in(in_f, density)


def test_mask_seeded_and_random():
    a = MaskedLinear(50, 20, 0.3, seed=3)
    b = MaskedLinear(50, 20, 0.3, seed=3)
    c = MaskedLinear(50, 20, 0.3, seed=4)
    assert torch.equal(a.mask, b.mask) and torch.equal(a.weight, b.weight)
    assert not torch.equal(a.mask, c.mask)
    w = a.weight.detach().clone()
    with torch.no_grad():
        a.weight.zero_()
    a.reset_parameters()
    assert torch.equal(a.weight, w)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bias", [False, True])
def test_module_equals_function_and_reference(device, dtype, bias):
    layer = MaskedLinear(12, 9, 0.25, bias=bias, seed=0, device=device, dtype=dtype)
    x = torch.randn(4, 3, 12, device=device, dtype=dtype)
    y = layer(x)
    assert y.shape == (4, 3, 9) and y.dtype == dtype
    assert torch.equal(y, masked_linear(x, layer.weight, layer.mask, layer.bias))
    # independent loop reference: sum only over connected inputs
    ref = torch.zeros(4, 3, 9, device=device, dtype=dtype)
    for o in range(9):
        for i in range(12):
            if layer.mask[o, i] == 1:
                ref[..., o] += x[..., i] * layer.weight[o, i]
        if bias:
            ref[..., o] += layer.bias[o]
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(y, ref, atol=tol, rtol=tol)
    torch.testing.assert_close(layer.folded_weight(), layer.weight * layer.mask)


def test_gradients_stay_in_mask_and_sgd_learns():
    torch.manual_seed(0)
    layer = MaskedLinear(20, 5, 0.3, bias=True, seed=1, dtype=torch.float64)
    target = MaskedLinear(20, 5, 0.3, bias=True, seed=1, dtype=torch.float64)
    with torch.no_grad():
        target.weight.mul_(-2.0)
    x = torch.randn(64, 20, dtype=torch.float64)
    y = target(x).detach()
    outside = layer.weight.detach()[layer.mask == 0].clone()
    opt = torch.optim.SGD(layer.parameters(), lr=0.05)
    losses = []
    for _ in range(20):
        opt.zero_grad()
        loss = ((layer(x) - y) ** 2).mean()
        loss.backward()
        assert (layer.weight.grad[layer.mask == 0] == 0).all()
        assert layer.weight.grad[layer.mask == 1].abs().sum() > 0
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]
    assert torch.equal(layer.weight.detach()[layer.mask == 0], outside)
    assert not layer.mask.requires_grad and "mask" in dict(layer.named_buffers())


def test_gradcheck():
    layer = MaskedLinear(6, 4, 0.5, bias=True, seed=2, dtype=torch.float64)
    x = torch.randn(3, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda x, w, b: masked_linear(x, w, layer.mask, b), (x, layer.weight, layer.bias))


def test_errors():
    with pytest.raises(ValueError, match="density"):
        MaskedLinear(4, 4, 0.0)
    with pytest.raises(ValueError, match="density"):
        make_mask(4, 4, 1.5)
    with pytest.raises(ValueError, match="positive"):
        make_mask(0, 4, 0.5)

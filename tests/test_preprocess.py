import math

import numpy as np
import pytest
import torch

from torchseq.preprocess import BT601, patch_normalise, preprocess, resize, to_grey


def loop_patch_normalise(img: np.ndarray, patch: int) -> np.ndarray:
    """OpenSeqSLAM's rule written as plain loops over blocks and pixels (float64)."""
    out = np.zeros_like(img, dtype=np.float64)
    for by in range(0, img.shape[0], patch):
        for bx in range(0, img.shape[1], patch):
            block = [float(img[y, x]) for y in range(by, by + patch) for x in range(bx, bx + patch)]
            mean = sum(block) / len(block)
            std = (sum((v - mean) ** 2 for v in block) / (len(block) - 1)) ** 0.5
            for y in range(by, by + patch):
                for x in range(bx, bx + patch):
                    z = 0.0 if std == 0 else (img[y, x] - mean) / std
                    r = math.copysign(math.floor(abs(z) + 0.5), z)  # MATLAB round
                    out[y, x] = min(255.0, max(0.0, 127.0 + r))
    return out


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_patch_normalise_matches_loop_reference(dtype):
    rng = np.random.default_rng(0)
    imgs = rng.integers(0, 256, (3, 16, 24)).astype(np.float64)
    imgs[1, :8, :8] = 42.0  # a flat block: std 0 maps to 127
    got = patch_normalise(torch.tensor(imgs, dtype=dtype), 8).double().numpy()
    for t in range(3):
        np.testing.assert_array_equal(got[t], loop_patch_normalise(imgs[t], 8))
    assert got[1, :8, :8].min() == got[1, :8, :8].max() == 127.0


def test_patch_normalise_zscore_has_unit_sample_std():
    x = torch.rand(2, 16, 16, dtype=torch.float64) * 255
    z = patch_normalise(x, 8, mode="zscore").reshape(2, 2, 8, 2, 8)
    assert torch.allclose(z.mean(dim=(2, 4)), torch.zeros(2, 2, 2, dtype=torch.float64), atol=1e-9)
    assert torch.allclose(z.std(dim=(2, 4)), torch.ones(2, 2, 2, dtype=torch.float64))


def test_patch_normalise_errors():
    with pytest.raises(ValueError, match="multiple of the patch"):
        patch_normalise(torch.zeros(1, 10, 16), 8)
    with pytest.raises(ValueError, match="mode"):
        patch_normalise(torch.zeros(1, 8, 8), 8, mode="bogus")
    with pytest.raises(ValueError, match="shape"):
        patch_normalise(torch.zeros(8, 8), 8)


def test_to_grey_uses_bt601_weights():
    rgb = torch.tensor([[[[255.0, 0.0, 0.0], [0.0, 255.0, 0.0], [0.0, 0.0, 255.0]]]])
    grey = to_grey(rgb)
    assert grey.shape == (1, 1, 3)
    expected = torch.tensor([BT601[0], BT601[1], BT601[2]]) * 255
    assert torch.allclose(grey[0, 0], expected, atol=1e-4)
    with pytest.raises(ValueError):
        to_grey(torch.zeros(2, 3))


def test_resize_no_op_and_area_mean():
    x = torch.rand(2, 32, 64)
    assert resize(x, (32, 64)) is x
    small = resize(x, (16, 32))
    assert torch.allclose(small, x.reshape(2, 16, 2, 32, 2).mean(dim=(2, 4)), atol=1e-6)
    assert resize(x, (40, 80)).shape == (2, 40, 80)
    with pytest.raises(ValueError):
        resize(x, (0, 4))


def test_preprocess_shapes_and_nan_error():
    frames = torch.rand(5, 48, 64, 3) * 255
    d = preprocess(frames, (32, 64), 8)
    assert d.shape == (5, 2048)
    assert d.min() >= 0 and d.max() <= 255
    frames[2, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        preprocess(frames, (32, 64), 8)
    with pytest.raises(ValueError, match="empty"):
        preprocess(torch.zeros(0, 32, 64), (32, 64))


def test_patch_normalise_rounds_halves_away_from_zero():
    # MATLAB's round (OpenSeqSLAM) takes halves away from zero; torch.round would give 0, 2, ...
    from torchseq.preprocess import round_half_away

    x = torch.tensor([-2.5, -1.5, -0.5, 0.5, 1.5, 2.5, 0.49])
    assert round_half_away(x).tolist() == [-3.0, -2.0, -1.0, 1.0, 2.0, 3.0, 0.0]

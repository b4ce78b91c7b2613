"""Frame array files hold grey levels in 0..255, as the loader promises (issue 23, item 2).

``.npy``/``.npz`` frames holding -5, -128, 1e38 or 1.8e19 came back unchanged; they are now
refused with the file, the values found and the remedy.
"""

import numpy as np
import pytest
import torch

from torchseq.sources import TraverseError, load_traverse

BAD = [(np.int8, -5), (np.int8, -128), (np.float32, 1e38), (np.uint64, 1.8e19),
       (np.float64, 255.5), (np.uint16, 65535), (np.float32, -1e-3)]


def save(path, frames):
    if path.suffix == ".npz":
        np.savez(path, frames=frames)
    else:
        np.save(path, frames)


@pytest.mark.parametrize("suffix", [".npy", ".npz"])
@pytest.mark.parametrize("dtype,value", BAD)
def test_values_outside_0_255_are_refused(tmp_path, suffix, dtype, value):
    frames = np.full((3, 4, 5), 7, dtype=dtype)
    frames[1, 2, 3] = dtype(value)
    path = tmp_path / f"bad{suffix}"
    save(path, frames)
    with pytest.raises(TraverseError) as err:
        load_traverse(path, progress=False)
    text = str(err.value)
    assert str(path) in text and "grey levels in 0..255" in text, text
    assert f"{float(np.float32(frames.min())):.6g}..{float(np.float32(frames.max())):.6g}" in text
    assert "x * 255 for floats in [0, 1]" in text


@pytest.mark.parametrize("suffix", [".npy", ".npz"])
@pytest.mark.parametrize("frames", [
    np.arange(0, 256, dtype=np.uint8).reshape(4, 8, 8),
    np.linspace(0, 255, 96, dtype=np.float64).reshape(2, 6, 8),
    np.linspace(0, 1, 96, dtype=np.float32).reshape(2, 6, 8),  # dim, but grey levels
    np.full((2, 3, 3, 3), 255, dtype=np.int64),  # RGB
])
def test_grey_levels_in_range_load_unchanged(tmp_path, suffix, frames):
    path = tmp_path / f"ok{suffix}"
    save(path, frames)
    x = load_traverse(path, progress=False)
    ref = frames.astype(np.float32)
    if ref.ndim == 4:  # equal channels: grey is the same level
        ref = ref[..., 0]
    assert x.dtype == torch.float32
    np.testing.assert_allclose(x.numpy(), ref, rtol=1e-6)

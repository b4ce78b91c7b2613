"""Frame preprocessing shared by both engines: grey, resize, patch normalisation.

All functions are time-first: frames are ``(T, H, W)`` float tensors with grey levels in
0..255. Colour frames ``(T, H, W, 3)`` are RGB.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from torchseq._checks import check_finite, check_not_empty, check_shape

# ITU-R BT.601 luma weights, as MATLAB's rgb2gray and OpenCV's RGB2GRAY use them.
BT601 = (0.299, 0.587, 0.114)
# The exact weights of MATLAB's and Octave's rgb2gray (the first row of the inverse of the
# NTSC YIQ matrix), which OpenSeqSLAM applies to uint8 frames.
MATLAB_RGB2GRAY = (0.298936021293775, 0.587043074451121, 0.114020904255103)


def to_grey(frames: torch.Tensor) -> torch.Tensor:
    """Convert frames to float grey levels.

    Args:
        frames: ``(T, H, W)`` grey or ``(T, H, W, 3)`` RGB, any real dtype.

    Returns:
        ``(T, H, W)`` float32 (float64 stays float64).
    """
    if frames.dim() == 4 and frames.shape[-1] == 3:
        w = torch.tensor(BT601, dtype=torch.float64, device=frames.device)
        grey = (frames.to(torch.float64) * w).sum(-1)
    elif frames.dim() == 3:
        grey = frames
    else:
        raise ValueError(f"frames must be (T, H, W) or (T, H, W, 3), got {tuple(frames.shape)}")
    dtype = torch.float64 if frames.dtype == torch.float64 else torch.float32
    return grey.to(dtype)


def resize(frames: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Resize frames to ``size = (H, W)``: area averaging when shrinking, bilinear otherwise.

    A no-op when the frames already have that size.

    Args:
        frames: ``(T, H, W)`` float.
        size: ``(height, width)`` of the output.

    Returns:
        ``(T, size[0], size[1])``.
    """
    check_shape(frames, ("T", "H", "W"), "frames")
    h, w = int(size[0]), int(size[1])
    if h <= 0 or w <= 0:
        raise ValueError(f"size must be positive, got {size}")
    if tuple(frames.shape[1:]) == (h, w):
        return frames
    x = frames.unsqueeze(1)
    if h <= frames.shape[1] and w <= frames.shape[2]:
        x = F.adaptive_avg_pool2d(x, (h, w))
    else:
        x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
    return x.squeeze(1)


def round_half_away(x: torch.Tensor) -> torch.Tensor:
    """Round halves away from zero, as MATLAB's ``round`` does (``torch.round`` rounds to even)."""
    return torch.sign(x) * torch.floor(x.abs() + 0.5)


def patch_normalise(frames: torch.Tensor, patch: int = 8, mode: str = "seqslam") -> torch.Tensor:
    """Normalise each non-overlapping ``patch x patch`` block to zero mean and unit std.

    ``mode="seqslam"`` reproduces OpenSeqSLAM: each pixel becomes
    ``127 + round((p - mean) / std)`` with the block's sample std, clamped to 0..255, rounding
    halves away from zero like MATLAB.
    ``mode="zscore"`` returns the float z-scores ``(p - mean) / std``. A flat block (std 0)
    maps to 127 (or 0 in z-score mode) instead of NaN. The z-scores are
    :func:`zscore_pixel_major`'s (the one z-score of torchseq), laid back out as images. Uses
    only ops that export to ONNX.

    Args:
        frames: ``(T, H, W)`` float, ``H`` and ``W`` multiples of ``patch``.
        patch: block side in pixels.
        mode: ``"seqslam"`` or ``"zscore"``.

    Returns:
        ``(T, H, W)`` float, same dtype as the input.
    """
    check_shape(frames, ("T", "H", "W"), "frames")
    t, h, w = frames.shape
    if patch < 2 or h % patch or w % patch:
        raise ValueError(f"frame size {h}x{w} is not a multiple of the patch side {patch} "
                         "(at least 2)")
    if mode not in ("seqslam", "zscore"):
        raise ValueError(f"mode must be 'seqslam' or 'zscore', got {mode!r}")
    z = zscore_pixel_major(frames, patch)  # (p * p, T, blocks)
    z = z.reshape(patch, patch, t, h // patch, w // patch).permute(2, 3, 0, 4, 1)
    z = z.reshape(t, h, w)
    if mode == "seqslam":
        z = (127.0 + round_half_away(z)).clamp(0.0, 255.0)
    return z


def block_order(height: int, width: int, patch: int) -> torch.Tensor:
    """``(H * W,)`` pixel index (row-major) of each position in block-major order.

    Block-major: blocks row by row, and within a block its pixels row by row.
    """
    idx = torch.arange(height * width).reshape(height // patch, patch, width // patch, patch)
    return idx.permute(0, 2, 1, 3).reshape(-1)


def zscore_blocks(frames: torch.Tensor, patch: int, kernel: str = "torch") -> torch.Tensor:
    """Sample z-scores of non-overlapping ``patch x patch`` blocks, in block-major order.

    :func:`zscore_pixel_major` (the definition) as ``(T, blocks, p * p)``.

    Args:
        frames: ``(T, H, W)`` float, ``H`` and ``W`` multiples of ``patch``.
        patch: block side.
        kernel: see :func:`zscore_pixel_major`.

    Returns:
        ``(T, (H / p) * (W / p), p * p)`` (a permuted view).
    """
    return zscore_pixel_major(frames, patch, kernel).permute(1, 2, 0)


def zscore_pixel_major(frames: torch.Tensor, patch: int, kernel: str = "torch") -> torch.Tensor:
    """The patch z-score: ``(p - mean) / std`` of each ``patch x patch`` block, pixel-major.

    ``mean`` and the sample ``std`` (``n - 1``) of the block's ``n = p * p`` pixels; a flat
    block gives 0. Sums run over the block's pixels first to last (:func:`in_order_sum`),
    so every kernel and the ONNX graph round alike. Laid out ``(p * p, T, blocks)``: each
    pixel position of a block is one contiguous row over all frames and blocks, so the sums
    are whole-row additions (several times faster on the CPU than reductions over the
    strided block axes of an image).

    Kernels: ``"torch"`` (any device, differentiable, exportable) and ``"numpy"`` (CPU, no
    gradients: the same element-wise operations in the same order, the square root still
    torch's, so the same bits, with a fraction of the per-call overhead on small batches).

    Args:
        frames: ``(T, H, W)`` float, ``H`` and ``W`` multiples of ``patch``.
        patch: block side.
        kernel: ``"torch"`` or ``"numpy"``.

    Returns:
        ``(p * p, T, (H / p) * (W / p))``.
    """
    t, h, w = frames.shape
    n = patch * patch
    if kernel == "numpy":
        if frames.device.type != "cpu" or frames.requires_grad:
            raise ValueError("the numpy z-score kernel needs a CPU tensor without gradients")
        pixels = (frames.numpy().reshape(t, h // patch, patch, w // patch, patch)
                  .transpose(2, 4, 0, 1, 3).reshape(n, t, -1))
        # np.add.reduce over the first axis of a C-contiguous array adds row after row, first
        # to last: in_order_sum's order (the bit-for-bit test against "torch" checks it)
        dev = pixels - np.add.reduce(pixels, axis=0) / n
        # torch's sqrt, not NumPy's: the two differ in the last bit for some float32 inputs
        std = torch.from_numpy(np.add.reduce(dev * dev, axis=0) / (n - 1)).sqrt_().numpy()
        return torch.from_numpy(dev / np.where(std > 0, std, std.dtype.type(1)))
    if kernel != "torch":
        raise ValueError(f"kernel must be 'torch' or 'numpy', got {kernel!r}")
    pixels = (frames.reshape(t, h // patch, patch, w // patch, patch)
              .permute(2, 4, 0, 1, 3).reshape(n, t, -1))
    dev = pixels - in_order_sum(pixels) / n
    std = (in_order_sum(dev * dev) / (n - 1)).sqrt()
    return dev / torch.where(std > 0, std, torch.ones_like(std))  # a flat block: 0 / 1


def in_order_sum(x):
    """Sum over the first axis, first to last: ``(n, ...) -> (...)`` (tensor or NumPy array).

    Element-wise additions in a fixed order round the same way in PyTorch, NumPy and any
    ONNX runtime (a reduction kernel may add in another order), so the exported graph
    computes bit for bit the model's z-scores.
    """
    s = x[0]
    for i in range(1, x.shape[0]):
        s = s + x[i]
    return s


def quantise_input(x: torch.Tensor, steps: int) -> torch.Tensor:
    """Round ``x`` to multiples of ``1 / steps`` (half to even, like ONNX ``Round``).

    Args:
        x: any float tensor.
        steps: grid steps per unit; ``0`` returns ``x`` unchanged.
    """
    if not steps:
        return x
    return torch.round(x * steps) / steps


def preprocess(
    frames: torch.Tensor, size: tuple[int, int], patch: int = 8, mode: str = "seqslam"
) -> torch.Tensor:
    """Grey, resize and patch-normalise a traverse, then flatten to descriptors.

    Args:
        frames: ``(T, H, W)`` or ``(T, H, W, 3)``.
        size: ``(height, width)`` to resize to, e.g. ``(32, 64)`` for OpenSeqSLAM.
        patch: patch normalisation side (0 disables it).
        mode: see :func:`patch_normalise`.

    Returns:
        ``(T, size[0] * size[1])`` float descriptors.
    """
    check_not_empty(frames, "frames")
    grey = to_grey(frames)
    check_finite(grey, "frames")
    small = resize(grey, size)
    if patch:
        small = patch_normalise(small, patch, mode)
    return small.reshape(small.shape[0], -1)


def _to_uint8_values(x: torch.Tensor) -> torch.Tensor:
    """What storing ``x`` in a MATLAB uint8 array keeps.

    Halves rounded away from zero, saturated to 0..255, NaN -> 0.
    """
    return round_half_away(x).nan_to_num(0.0).clamp(0.0, 255.0)


def grey_openseqslam(frames: torch.Tensor) -> torch.Tensor:
    """OpenSeqSLAM's grey levels: ``rgb2gray`` on uint8 frames, i.e. integers 0..255.

    RGB frames get MATLAB's ``rgb2gray`` weights (:data:`MATLAB_RGB2GRAY`) in float64, then
    uint8 storage (round halves away, saturate); grey frames are stored in uint8 the same way
    (``imread`` gives uint8).

    Args:
        frames: ``(T, H, W)`` grey or ``(T, H, W, 3)`` RGB, levels 0..255, any real dtype.

    Returns:
        ``(T, H, W)`` float64 holding integers 0..255.
    """
    if frames.dim() == 4 and frames.shape[-1] == 3:
        w = torch.tensor(MATLAB_RGB2GRAY, dtype=torch.float64, device=frames.device)
        grey = (frames.to(torch.float64) * w).sum(-1)
    elif frames.dim() == 3:
        grey = frames.to(torch.float64)
    else:
        raise ValueError(f"frames must be (T, H, W) or (T, H, W, 3), got {tuple(frames.shape)}")
    return _to_uint8_values(grey)


def patch_normalise_openseqslam(frames: torch.Tensor, patch: int = 8) -> torch.Tensor:
    """OpenSeqSLAM's ``patchNormalize`` on uint8 images, value for value.

    Each ``patch x patch`` block becomes ``127 + round((p - mean) / std)`` (sample std,
    float64) stored in uint8: rounded halves away from zero, saturated to 0..255, and a flat
    block (std 0, so z = 0/0 = NaN) becomes **0** (torchseq's own rule,
    :func:`patch_normalise`, writes 127 there).

    Args:
        frames: ``(T, H, W)`` integer grey levels (see :func:`grey_openseqslam`), ``H`` and
            ``W`` multiples of ``patch``.
        patch: block side in pixels.

    Returns:
        ``(T, H, W)`` float64 holding integers 0..255.
    """
    check_shape(frames, ("T", "H", "W"), "frames")
    t, h, w = frames.shape
    if patch < 2 or h % patch or w % patch:
        raise ValueError(f"frame size {h}x{w} is not a multiple of the patch side {patch} "
                         "(>= 2)")
    n = patch * patch
    x = frames.to(torch.float64).reshape(t, h // patch, patch, w // patch, patch)
    x = x.permute(0, 1, 3, 2, 4).reshape(t, h // patch, w // patch, n)
    mean = x.sum(-1, keepdim=True) / n
    dev = x - mean
    std = ((dev * dev).sum(-1, keepdim=True) / (n - 1)).sqrt()
    z = torch.where(std > 0, dev / torch.where(std > 0, std, 1.0), math.nan)
    out = _to_uint8_values(127.0 + round_half_away(z))  # NaN -> 0, as MATLAB's uint8 store
    out = out.reshape(t, h // patch, w // patch, patch, patch).permute(0, 1, 3, 2, 4)
    return out.reshape(t, h, w)


def preprocess_openseqslam(frames: torch.Tensor, size: tuple[int, int],
                           patch: int = 8) -> torch.Tensor:
    """OpenSeqSLAM's preprocessing: integer grey, resize, uint8 patch normalisation.

    Frames that already have ``size`` are not resized (OpenSeqSLAM's demo reads 64x32
    images with ``DO_RESIZE = 0``); others are area-averaged and stored as uint8 (OpenSeqSLAM
    resizes with MATLAB's ``imresize(..., 'lanczos3')``, whose kernel this does not
    reproduce).

    Args:
        frames: ``(T, H, W)`` or ``(T, H, W, 3)`` with levels 0..255.
        size: ``(height, width)``, e.g. ``(32, 64)``.
        patch: patch normalisation side (0 disables it).

    Returns:
        ``(T, size[0] * size[1])`` float32 descriptors holding integers 0..255 (float64 input
        gives float64).
    """
    check_not_empty(frames, "frames")
    frames = torch.as_tensor(frames)
    if frames.is_floating_point():
        check_finite(frames, "frames")
    grey = grey_openseqslam(frames)
    small = resize(grey, size)
    if tuple(small.shape[1:]) != tuple(grey.shape[1:]):
        small = _to_uint8_values(small)
    if patch:
        small = patch_normalise_openseqslam(small, patch)
    dtype = torch.float64 if frames.dtype == torch.float64 else torch.float32
    return small.reshape(small.shape[0], -1).to(dtype)

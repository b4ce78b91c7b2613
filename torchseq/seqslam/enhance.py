"""Local contrast enhancement of a difference matrix (OpenSeqSLAM's ``enhanceContrast``)."""

from __future__ import annotations

import torch

from torchseq._checks import check_finite, check_not_empty, check_shape

# On CPU, blocks of about this many elements stay in the L2 cache (measured: about 2x faster at
# 20000 x 20000 than 64M-element blocks, which spend their time in page faults).
CPU_BLOCK_ELEMENTS = 2**18


def _enhance_rows(d_t: torch.Tensor, half: int) -> torch.Tensor:
    """Z-score each entry of ``d_t (C, R)`` against its window along the last axis.

    The window of entry ``i`` is ``max(0, i - half) .. min(R - 1, i + half)``; both passes
    (mean, then sample variance about it) are sums of ``2 * half + 1`` shifted slices of a
    zero-padded copy, with a validity mask so the padding never counts.
    """
    n_ref = d_t.shape[1]
    padded = torch.nn.functional.pad(d_t, (half, half))  # (C, R + 2 half)
    pos = torch.arange(n_ref, device=d_t.device)
    total = torch.zeros_like(d_t)
    count = torch.zeros(n_ref, dtype=d_t.dtype, device=d_t.device)
    valid = []
    for shift in range(2 * half + 1):
        ok = ((pos + shift - half >= 0) & (pos + shift - half < n_ref)).to(d_t.dtype)  # (R,)
        valid.append(ok)
        total += padded[:, shift:shift + n_ref]
        count += ok
    mean = total / count
    var = torch.zeros_like(d_t)
    for shift in range(2 * half + 1):
        dev = padded[:, shift:shift + n_ref] - mean
        var += dev * dev * valid[shift]
    std = (var / (count - 1)).sqrt()
    num = d_t - mean
    # a window of equal values (std 0) has a zero numerator too: define the result as 0
    return torch.where(std > 0, num / torch.where(std > 0, std, torch.ones_like(std)),
                       torch.zeros_like(num))


def enhance_contrast(
    difference: torch.Tensor,
    window: int = 10,
    subtract_min: bool = True,
    max_chunk_elements: int = 2**26,
) -> torch.Tensor:
    """Normalise each entry by the mean and sample std of its local window of reference rows.

    ``D'[i, j] = (D[i, j] - mean(D[a:b+1, j])) / std(D[a:b+1, j])`` with
    ``a = max(0, i - window // 2)``, ``b = min(R - 1, i + window // 2)`` and the sample
    (N - 1) std; entries whose window has std 0 become 0. With ``subtract_min`` the global
    minimum is then subtracted so every entry is >= 0 (OpenSeqSLAM).

    Args:
        difference: ``(R, Q)`` difference matrix.
        window: window length R in rows (OpenSeqSLAM: 10); 0 returns the input unchanged
            apart from the minimum subtraction.
        subtract_min: subtract the global minimum afterwards.
        max_chunk_elements: bound on the elements of each temporary block.

    Returns:
        ``(R, Q)`` enhanced matrix, same dtype and device (transposed view of a ``(Q, R)``
        buffer).
    """
    check_shape(difference, ("R", "Q"), "difference matrix")
    check_not_empty(difference, "difference matrix")
    check_finite(difference, "difference matrix")
    if window < 0 or window == 1:
        raise ValueError(f"window must be 0 (off) or >= 2, got {window}")
    n_ref, n_query = difference.shape
    if window and n_ref < 2:
        raise ValueError(f"contrast enhancement needs >= 2 reference rows, got {n_ref}")
    d_t = difference.T  # (Q, R): windows run along the last, contiguous axis
    out_t = torch.empty(n_query, n_ref, dtype=difference.dtype, device=difference.device)
    half = window // 2
    # about six (C, R) temporaries live at once; on CPU blocks are kept cache-sized
    budget = max_chunk_elements // 6
    if difference.device.type != "cuda":
        budget = min(budget, CPU_BLOCK_ELEMENTS)
    cols = max(1, budget // (n_ref + 2 * half))
    for q0 in range(0, n_query, cols):
        block = d_t[q0:q0 + cols]
        out_t[q0:q0 + cols] = _enhance_rows(block, half) if window else block
    if subtract_min:
        out_t -= out_t.min()
    return out_t.T

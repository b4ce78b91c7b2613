"""Difference matrix between two traverses of descriptors, by batched tensor ops.

Computed query-major: a ``(Q, R)`` buffer filled one block of queries at a time (so the
temporaries stay under ``max_chunk_elements``) and returned as its ``(R, Q)`` transposed view.

``l1`` has an exact fast path for integer-valued descriptors with a small range, which is
what OpenSeqSLAM's patch normalisation produces (grey levels 127 +- 8): with the thermometer
code ``A[n, d, t] = [x[n, d] > lo + t]``, ``|a - b| = sum_t [a > t] + [b > t] - 2 [a > t][b > t]``,
so ``L1 = |A|_1 + |B|_1 - 2 A B^T``: one int8 matrix product with exact int32 accumulation.
Other inputs use ``torch.cdist(p=1)`` (exact summation, slower).
"""

from __future__ import annotations

import torch

from torchseq._checks import check_finite, check_not_empty, check_shape
from torchseq.seqslam.config import METRICS

# Largest grey-level range (max - min) the thermometer path handles; beyond it cdist is used.
THERMOMETER_MAX_LEVELS = 64


def _thermometer(x: torch.Tensor, lo: float, levels: int) -> torch.Tensor:
    """``(N, D)`` integer-valued -> ``(N, D * levels)`` int8 thermometer code."""
    steps = lo + torch.arange(levels, device=x.device, dtype=x.dtype)
    return (x[:, :, None] > steps).view(torch.int8).reshape(x.shape[0], -1)


def _int_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(M, K) int8 @ (N, K)^T int8 -> (M, N)`` exact int32 (float fallback when unsupported)."""
    try:
        return torch._int_mm(a, b.T)
    except RuntimeError:  # shape or device constraints of the int8 kernel
        # 0/1 products summed in float32 stay exact below 2**24 (checked by the caller)
        return (a.float() @ b.float().T).round().to(torch.int32)


def _l1_thermometer(ref: torch.Tensor, query: torch.Tensor, out_t: torch.Tensor,
                    lo: float, levels: int, budget: int) -> None:
    """Fill ``out_t (Q, R)`` with exact L1 distances through thermometer codes."""
    width = ref.shape[1] * levels
    # int8 codes: a block of rows holds budget * 4 bytes (the bytes of budget float32s);
    # the int32 product of two blocks holds block**2 elements: keep it within budget too
    block = max(1, min((4 * budget) // width, int(budget**0.5)))
    ref_norm = (ref - lo).sum(1)  # (R,) = |A|_1
    query_norm = (query - lo).sum(1)
    for r0 in range(0, ref.shape[0], block):
        a = _thermometer(ref[r0:r0 + block], lo, levels)
        for q0 in range(0, query.shape[0], block):
            b = _thermometer(query[q0:q0 + block], lo, levels)
            out = out_t[q0:q0 + block, r0:r0 + block]  # (q, r), filled in place
            out.copy_(_int_matmul(b, a)).mul_(-2)
            out.add_(query_norm[q0:q0 + block, None]).add_(ref_norm[None, r0:r0 + block])


def _small_integer_range(ref: torch.Tensor, query: torch.Tensor) -> tuple[float, int] | None:
    """``(lo, levels)`` when both inputs are integer-valued within a small range, else None."""
    lo = float(torch.minimum(ref.min(), query.min()))
    hi = float(torch.maximum(ref.max(), query.max()))
    levels = int(hi - lo)
    if levels > THERMOMETER_MAX_LEVELS or ref.shape[1] * levels >= 2**24:
        return None
    for x in (ref, query):
        if not torch.equal(x, torch.round(x)):
            return None
    return lo, levels


def check_descriptors(reference: torch.Tensor, query: torch.Tensor) -> None:
    """Check a descriptor pair: ``ValueError`` unless both are non-empty, finite, 2-D.

    ``reference`` ``(R, D)`` and ``query`` ``(Q, D)`` must agree on ``D``.
    """
    check_not_empty(reference, "reference descriptors")
    check_not_empty(query, "query descriptors")
    check_shape(reference, ("R", "D"), "reference descriptors")
    check_shape(query, ("Q", reference.shape[1]), "query descriptors")
    check_finite(reference, "reference descriptors")
    check_finite(query, "query descriptors")


def difference_matrix(
    reference: torch.Tensor,
    query: torch.Tensor,
    metric: str = "l1",
    max_chunk_elements: int = 2**26,
) -> torch.Tensor:
    """Distance between every reference and every query descriptor.

    Args:
        reference: ``(R, D)`` float descriptors.
        query: ``(Q, D)`` float descriptors, same dtype and device.
        metric: ``"l1"`` sum of absolute differences (OpenSeqSLAM), ``"l2"`` Euclidean
            distance, ``"cosine"`` 1 - cosine similarity (a zero vector has similarity 0).
        max_chunk_elements: bound on the elements of each temporary block.

    Returns:
        ``(R, Q)`` distances, reference rows by query columns (a transposed view of a
        contiguous ``(Q, R)`` buffer).
    """
    check_descriptors(reference, query)
    if metric not in METRICS:
        raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")
    if not reference.is_floating_point():
        reference = reference.float()
    query = query.to(reference.dtype)
    n_ref, dim = reference.shape
    n_query = query.shape[0]
    out_t = torch.empty(n_query, n_ref, dtype=reference.dtype, device=reference.device)
    rows = max(1, max_chunk_elements // max(n_ref, dim))  # queries per block
    if metric == "l1":
        small = _small_integer_range(reference, query)
        if small is not None and small[1] == 0:
            return out_t.zero_().T
        if small is not None:
            _l1_thermometer(reference, query, out_t, small[0], small[1], max_chunk_elements)
        else:
            for q0 in range(0, n_query, rows):
                out_t[q0:q0 + rows] = torch.cdist(query[q0:q0 + rows], reference, p=1)
        return out_t.T
    if metric == "l2":
        # L2 is translation-invariant: centring (on an integer centre, so integer data stays
        # integer) keeps the dot products small and exact
        centre = reference.mean(0).round()
        ref_c, query_c = reference - centre, query - centre
        ref_sq = (ref_c * ref_c).sum(1)
        for q0 in range(0, n_query, rows):
            q = query_c[q0:q0 + rows]
            sq = (q * q).sum(1)[:, None] + ref_sq[None, :] - 2 * (q @ ref_c.T)
            out_t[q0:q0 + rows] = sq.clamp_min(0).sqrt()
        return out_t.T
    tiny = torch.finfo(reference.dtype).tiny
    ref_n = reference / reference.norm(dim=1, keepdim=True).clamp_min(tiny)
    query_n = query / query.norm(dim=1, keepdim=True).clamp_min(tiny)
    for q0 in range(0, n_query, rows):
        out_t[q0:q0 + rows] = 1.0 - query_n[q0:q0 + rows] @ ref_n.T
    return out_t.T

"""Difference matrix between two traverses of descriptors, by batched tensor ops.

Computed query-major: a ``(Q, R)`` buffer filled one block at a time (so the temporaries stay
under ``max_chunk_elements``) and returned as its ``(R, Q)`` transposed view.

``l1`` has two kernels, both exact, chosen from the data (:func:`thermometer_levels`;
:func:`difference_with_kernel` says which ran):

- ``"thermometer"`` for integer-valued descriptors taking few distinct values, which is what
  OpenSeqSLAM's patch normalisation produces (127 +- 8, and 0 for flat blocks under its uint8
  rule). With the distinct values ``v_0 < ... < v_k``, thresholds ``v_0 .. v_{k-1}`` and gaps
  ``w_t = v_{t+1} - v_t``, the code ``A[n, d, t] = [x[n, d] > v_t]`` gives
  ``|a - b| = sum_t w_t ([a > v_t] + [b > v_t] - 2 [a > v_t][b > v_t])``, so
  ``L1 = |A|_w + |B|_w - 2 (A w) B^T``: one int8 matrix product (``A w`` fits int8 while every
  gap is <= 127) with exact int32 accumulation.
- ``"cdist"``: ``torch.cdist(p=1)`` for everything else (exact summation, slower).

On this project's AMD EPYC (Zen 5, AVX-512 VNNI) the thermometer product at 3,576^2 and one
thread took 0.56 s against 1.31 s for a direct sum of absolute differences compiled by Numba
(LLVM, uint8 loops; ``benchmarks/bench_seqslam.py --kernels``), so it stays the kernel there
in spite of doing 16x the arithmetic.

The thermometer product itself has two forms (:func:`thermometer_product`), both exact: the
int8 GEMM (``torch._int_mm``) on CUDA and on CPUs with AVX-512, and a float32 product
elsewhere. On an AVX2-only AMD EPYC (Zen 3) one thread took 8.1 s for a 512 x 512 product of
32,768-wide codes with ``torch._int_mm`` against 0.46 s in float32 (conversions included):
oneDNN's int8 GEMM has no fast path there.
"""

from __future__ import annotations

import torch

from torchseq._checks import check_finite, check_not_empty, check_shape
from torchseq.seqslam._parallel import run_blocks
from torchseq.seqslam.config import METRICS

# Most thresholds (distinct values - 1) the thermometer kernel handles; beyond it cdist is used.
THERMOMETER_MAX_LEVELS = 64
# Largest value range (max - min) the level scan looks at.
THERMOMETER_MAX_RANGE = 4096
# Rows of reference codes per block (a block of work for one thread).
THERMOMETER_BLOCK_ROWS = 1024


def _thermometer(x: torch.Tensor, thresholds: torch.Tensor,
                 weights: torch.Tensor | None = None) -> torch.Tensor:
    """``(N, D)`` -> ``(N, D * k)`` int8 code ``[x > thresholds]`` (times ``weights``)."""
    code = (x[:, :, None] > thresholds).view(torch.int8)
    if weights is not None:
        code = code * weights
    return code.reshape(x.shape[0], -1)


def int_mm_supported(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Whether ``torch._int_mm`` takes ``(M, K) int8 @ (N, K)^T``.

    Always on CPU; on CUDA when ``M > 16`` and ``K``, ``N`` are multiples of 8 (the int8
    kernel's constraints).
    """
    if a.device.type == "cpu":
        return True
    return a.shape[0] > 16 and a.shape[1] % 8 == 0 and b.shape[0] % 8 == 0


def thermometer_product(device: torch.device | str) -> str:
    """How the thermometer kernel multiplies its codes on ``device``: ``"int8"`` or ``"float32"``.

    ``"int8"`` (``torch._int_mm``) on CUDA and on CPUs where torch reports AVX-512 (VNNI or
    its int8 paths); ``"float32"`` on other CPUs (AVX2 alone, Arm), where oneDNN's int8 GEMM
    measured 18x slower than the float32 product (module docstring). Both are exact.
    """
    if torch.device(device).type != "cpu":
        return "int8"
    return "int8" if torch.backends.cpu.get_cpu_capability().startswith("AVX512") else "float32"


def _int_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(M, K) int8 @ (N, K)^T int8 -> (M, N)`` exact int32.

    ``torch._int_mm`` (private API, int32 accumulation) where :func:`thermometer_product` is
    ``"int8"`` and :func:`int_mm_supported`, else a float32 product, exact because the caller
    keeps every sum below 2**24.
    """
    if thermometer_product(a.device) == "int8" and int_mm_supported(a, b):
        return torch._int_mm(a, b.T)
    return (a.float() @ b.float().T).round().to(torch.int32)


def thermometer_codes(x: torch.Tensor, thresholds: torch.Tensor,
                      weights: torch.Tensor | None, rows: int = 1024) -> torch.Tensor:
    """The weighted reference codes ``(N, D * k)`` int8 of :func:`_l1_thermometer`.

    Built ``rows`` rows at a time (the only full-size tensor is the result), to be reused.
    """
    thr = thresholds.to(x.dtype)
    out = torch.empty(x.shape[0], x.shape[1] * thresholds.numel(), dtype=torch.int8,
                      device=x.device)
    for r0 in range(0, x.shape[0], rows):
        out[r0:r0 + rows] = _thermometer(x[r0:r0 + rows], thr, weights)
    return out


def _l1_thermometer(ref: torch.Tensor, query: torch.Tensor, out_t: torch.Tensor,
                    thresholds: torch.Tensor, weights: torch.Tensor | None, budget: int,
                    workers: int, ref_codes: torch.Tensor | None = None) -> None:
    """Fill ``out_t (Q, R)`` with exact L1 distances through weighted thermometer codes.

    ``ref_codes``: the reference's :func:`thermometer_codes`, when already built.
    """
    lo = thresholds[0]
    width = ref.shape[1] * thresholds.numel()
    # int8 codes: a block of rows holds budget * 4 bytes (the bytes of budget float32s);
    # the int32 product of two blocks holds block**2 elements: keep it within budget too
    block = max(1, min((4 * budget) // width, int(budget**0.5), THERMOMETER_BLOCK_ROWS))
    ref_norm = (ref - lo).sum(1)  # (R,) = |A|_w
    query_norm = (query - lo).sum(1)
    thr = thresholds.to(ref.dtype)

    # the query codes once when they fit the budget, else per block
    codes = _thermometer(query, thr) if query.shape[0] * width <= 4 * budget else None

    def fill(r0: int) -> None:
        a = ref_codes[r0:r0 + block] if ref_codes is not None else \
            _thermometer(ref[r0:r0 + block], thr, weights)
        for q0 in range(0, query.shape[0], block):
            b = codes[q0:q0 + block] if codes is not None else \
                _thermometer(query[q0:q0 + block], thr)
            out = out_t[q0:q0 + block, r0:r0 + block]  # (q, r), filled in place
            out.copy_(_int_matmul(b, a)).mul_(-2)
            out.add_(query_norm[q0:q0 + block, None]).add_(ref_norm[None, r0:r0 + block])

    run_blocks(fill, range(0, ref.shape[0], block), workers, ref.device)


def _is_integer(x: torch.Tensor, rows: int) -> bool:
    """Whether every value of ``x`` is an integer, checked ``rows`` rows at a time."""
    for r0 in range(0, x.shape[0], rows):
        v = x[r0:r0 + rows]
        if not torch.equal(v, v.round()):
            return False
    return True


def _present_values(x: torch.Tensor, lo: float, span: int, rows: int) -> torch.Tensor:
    """``(span + 1,)`` bool: which integers ``lo .. lo + span`` occur in integer-valued ``x``.

    Works in blocks of ``rows`` rows (bounded memory).
    """
    seen = torch.zeros(span + 1, dtype=torch.bool, device=x.device)
    for r0 in range(0, x.shape[0], rows):
        idx = (x[r0:r0 + rows] - lo).to(torch.int64).flatten()
        seen |= torch.bincount(idx, minlength=span + 1) > 0
    return seen


def thermometer_levels(reference: torch.Tensor, query: torch.Tensor,
                       max_chunk_elements: int = 2**26
                       ) -> tuple[torch.Tensor, torch.Tensor | None] | None:
    """Thresholds and int8 gap weights of the thermometer kernel, or None when it cannot run.

    It runs when both inputs are integer-valued, ``D * (max - min) < 2**24`` (exact int32 and
    float32 sums) and either the range ``max - min`` is at most ``THERMOMETER_MAX_LEVELS``
    (then every integer of the range is a threshold, all weights 1: no scan for the values
    present) or the values present are at most ``THERMOMETER_MAX_LEVELS + 1`` with every gap
    <= 127 (OpenSeqSLAM's flat blocks: 0 beside 119..135).

    Returns:
        ``(k,)`` float64 thresholds ``v_0 .. v_{k-1}`` and ``(k,)`` int8 gaps (None: all 1),
        ``k >= 0``.
    """
    lo = float(torch.minimum(reference.min(), query.min()))
    hi = float(torch.maximum(reference.max(), query.max()))
    span = hi - lo
    if span > THERMOMETER_MAX_RANGE or reference.shape[1] * span >= 2**24:
        return None
    rows = max(1, max_chunk_elements // (8 * reference.shape[1]))
    if not (_is_integer(reference, rows) and _is_integer(query, rows)):
        return None
    if span <= THERMOMETER_MAX_LEVELS:
        return lo + torch.arange(int(span), dtype=torch.float64), None
    seen = _present_values(reference, lo, int(span), rows)
    seen |= _present_values(query, lo, int(span), rows)
    values = torch.nonzero(seen)[:, 0].to(torch.float64) + lo
    gaps = values[1:] - values[:-1]
    if values.numel() - 1 > THERMOMETER_MAX_LEVELS or bool((gaps > 127).any()):
        return None
    return values[:-1], gaps.to(torch.int8)


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
    threads: int = 1,
) -> torch.Tensor:
    """Distance between every reference and every query descriptor.

    Args:
        reference: ``(R, D)`` float descriptors.
        query: ``(Q, D)`` float descriptors, same dtype and device.
        metric: ``"l1"`` sum of absolute differences (OpenSeqSLAM), ``"l2"`` Euclidean
            distance, ``"cosine"`` 1 - cosine similarity (a zero vector has similarity 0).
        max_chunk_elements: bound on the elements of each temporary block.
        threads: CPU worker threads, each taking whole blocks (see ``_parallel``).

    Returns:
        ``(R, Q)`` distances, reference rows by query columns (a transposed view of a
        contiguous ``(Q, R)`` buffer).
    """
    return difference_with_kernel(reference, query, metric, max_chunk_elements, threads)[0]


def difference_with_kernel(
    reference: torch.Tensor, query: torch.Tensor, metric: str = "l1",
    max_chunk_elements: int = 2**26, threads: int = 1,
) -> tuple[torch.Tensor, str]:
    """:func:`difference_matrix` and the name of the kernel that computed it.

    Returns:
        ``(R, Q)`` distances and one of ``"thermometer"``, ``"cdist"``, ``"constant"`` (all
        inputs equal), ``"l2"``, ``"cosine"``.
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
        levels = thermometer_levels(reference, query, max_chunk_elements)
        if levels is not None and levels[0].numel() == 0:
            return out_t.zero_().T, "constant"
        if levels is not None:
            weights = levels[1].to(reference.device) if levels[1] is not None else None
            _l1_thermometer(reference, query, out_t, levels[0], weights, max_chunk_elements,
                            threads)
            return out_t.T, "thermometer"

        def cdist(q0: int) -> None:
            out_t[q0:q0 + rows] = torch.cdist(query[q0:q0 + rows], reference, p=1)

        run_blocks(cdist, range(0, n_query, rows), threads, reference.device)
        return out_t.T, "cdist"
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
        return out_t.T, "l2"
    tiny = torch.finfo(reference.dtype).tiny
    ref_n = reference / reference.norm(dim=1, keepdim=True).clamp_min(tiny)
    query_n = query / query.norm(dim=1, keepdim=True).clamp_min(tiny)
    for q0 in range(0, n_query, rows):
        out_t[q0:q0 + rows] = 1.0 - query_n[q0:q0 + rows] @ ref_n.T
    return out_t.T, "cosine"

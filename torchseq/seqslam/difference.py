"""Difference matrix between two traverses of descriptors, by batched tensor ops.

Computed query-major: a ``(Q, R)`` buffer filled one block at a time (so the temporaries stay
under ``max_chunk_elements``) and returned as its ``(R, Q)`` transposed view.

``l1`` has three kernels, all exact, chosen from the data, the size and the CPU
(:func:`l1_kernel`; :func:`difference_with_kernel` says which ran, and its ``kernel=`` forces
one for tests and benchmarks):

- ``"thermometer"`` for integer-valued descriptors taking few distinct values, which is what
  OpenSeqSLAM's patch normalisation produces (127 +- 8, and 0 for flat blocks under its uint8
  rule). With the distinct values ``v_0 < ... < v_k``, thresholds ``v_0 .. v_{k-1}`` and gaps
  ``w_t = v_{t+1} - v_t``, the code ``A[n, d, t] = [x[n, d] > v_t]`` gives
  ``|a - b| = sum_t w_t ([a > v_t] + [b > v_t] - 2 [a > v_t][b > v_t])``, so
  ``L1 = |A|_w + |B|_w - 2 (A w) B^T``: one int8 matrix product (``A w`` fits int8 while every
  gap is <= 127) with exact int32 accumulation.
- ``"sad"``: the sum of absolute differences itself, a loop compiled by numba
  (``_l1_numba.py``) over the values minus their minimum as uint8, for integer-valued
  descriptors spanning at most 255 (:func:`sad_offset`); wider data keep the thermometer or
  cdist kernel. Chosen on CPU where the time it saves pays numba's start-up (importing numba
  and loading the compiled loop from its cache cost 0.4-2 s once per process, by the host's
  load; compiling it the first time about 1.5 s more; a run below the size never imports
  numba). Against cdist or the thermometer's float32 product (no AVX-512, below) from
  ``R * Q * D >= SAD_MIN_WORK`` (2**31: 1,024^2 x 2,048): on nordland-b on an AVX2 host it
  broke even at 800 places (1.3e9) and took 0.71x the thermometer's CPU at 1,000 places,
  0.42x at 1,788 (``benchmarks/bench_l1_size_rule.py``). Against the int8 product (AVX-512),
  whose time grows with the thresholds ``k`` while ``"sad"``'s does not, from
  ``R * Q * D * (k - SAD_INT8_TIE_LEVELS) >= SAD_INT8_MIN_SAVING`` (6 and 6e10).
- ``"cdist"``: ``torch.cdist(p=1)`` for everything else (exact summation, slower).

The int8 rule's figures, on this project's 2-core AMD EPYC with AVX-512 VNNI (the Zen 4/5
kind), one thread, a host shared with other jobs: at 2,000^2 x 2,048 values 127 +- k/2 the
thermometer took 0.31, 0.46, 0.71, 0.87 s at 4, 8, 12, 16 thresholds against 0.38-0.40 s for
``"sad"`` (start-up excluded; they tie near 6 thresholds); on nordland-b (16 thresholds) the
whole match, numba's start-up included, took with ``"sad"`` 2.04x the thermometer's CPU at
1,000 places, 1.27x at 1,400, 0.91x at 1,788, 0.87x at 2,400 and 0.71x at 3,576
(``bench_l1_size_rule.py --places 1000 1400 1788 2400 3576``). The rule switches at 1,712
places on nordland-b's 16 thresholds and at 3,828 on the synthetic demo's 8 (on a Zen 4 the
two tied at 3,576^2 on 7 distinct values, start-up excluded, and at 1,788^2 on nordland-b's
descriptors the thermometer took 0.72 s against 0.30 s). An earlier Zen 5 measurement with
an older ``"sad"`` (no register blocking) had the thermometer ahead, 0.56 s against 1.31 s.

The thermometer product itself has two forms (:func:`thermometer_product`), both exact: the
int8 GEMM (``torch._int_mm``) on CUDA and on CPUs with AVX-512, and a float32 product
elsewhere. On an AVX2-only AMD EPYC (Zen 3) one thread took 8.1 s for a 512 x 512 product of
32,768-wide codes with ``torch._int_mm`` against 0.46 s in float32 (conversions included):
oneDNN's int8 GEMM has no fast path there. On that CPU the ``"sad"`` kernel took 2.7-3.8 s
against 7.9-10.4 s for the float32 thermometer product at 3,576^2, D = 2,048, one thread
(``bench_seqslam.py --kernels``), equal matrices, so it is the kernel there for large runs.
"""

from __future__ import annotations

import importlib.util
import math

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
# The "sad" kernel: largest value range (max - min, so the values fit uint8 after subtracting
# the minimum), the R * Q * D from which it is chosen, and rows per block of work.
SAD_MAX_RANGE = 255
SAD_MIN_WORK = 2**31
# Where the thermometer's product is int8 (AVX-512): "sad" from R * Q * D * (thresholds -
# SAD_INT8_TIE_LEVELS) >= SAD_INT8_MIN_SAVING (the two kernels tie at about 6 thresholds; the
# saving must pay numba's start-up; module docstring).
SAD_INT8_TIE_LEVELS = 6
SAD_INT8_MIN_SAVING = 6 * 10**10
SAD_BLOCK_ROWS = 256
L1_KERNELS = ("thermometer", "sad", "cdist")


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


def _as_uint8(x: torch.Tensor, lo: float) -> torch.Tensor:
    """``x - lo`` as contiguous uint8 (exact: ``x`` is integer-valued within ``lo .. lo + 255``)."""
    return (x - lo).to(torch.uint8).contiguous()


def sad_codes(x: torch.Tensor, lo: float, rows: int = 1024) -> torch.Tensor:
    """The uint8 reference ``x - lo`` of :func:`_l1_sad`, ``(N, D)``, to be reused.

    Built ``rows`` rows at a time (the only full-size tensor is the result).
    """
    out = torch.empty(x.shape, dtype=torch.uint8, device=x.device)
    for r0 in range(0, x.shape[0], rows):
        out[r0:r0 + rows] = _as_uint8(x[r0:r0 + rows], lo)
    return out


def levels_span(levels: tuple[torch.Tensor, torch.Tensor | None]) -> float:
    """``max - min`` of the values behind :func:`thermometer_levels`' non-empty thresholds."""
    thresholds, weights = levels
    top = 1 if weights is None else int(weights[-1])
    return float(thresholds[-1] - thresholds[0]) + top


def sad_offset(reference: torch.Tensor, query: torch.Tensor,
               levels: tuple[torch.Tensor, torch.Tensor | None] | None,
               max_chunk_elements: int = 2**26) -> float | None:
    """The minimum ``lo`` the ``"sad"`` kernel subtracts to hold the values in uint8, or None.

    None unless both inputs are integer-valued with ``max - min <= SAD_MAX_RANGE`` (255) and
    ``D * (max - min) < 2**24`` (exact int32 sums and float32 results). ``levels``: the
    inputs' :func:`thermometer_levels` (non-empty thresholds), which settles it without a scan.
    """
    if levels is not None:
        return float(levels[0][0]) if levels_span(levels) <= SAD_MAX_RANGE else None
    lo = float(torch.minimum(reference.min(), query.min()))
    span = float(torch.maximum(reference.max(), query.max())) - lo
    if span > SAD_MAX_RANGE or reference.shape[1] * span >= 2**24:
        return None
    rows = max(1, max_chunk_elements // (8 * reference.shape[1]))
    return lo if _is_integer(reference, rows) and _is_integer(query, rows) else None


def sad_available() -> bool:
    """Whether numba is installed (found, not imported: it is imported when ``"sad"`` runs)."""
    return importlib.util.find_spec("numba") is not None


def l1_choice(reference: torch.Tensor, query: torch.Tensor,
              levels: tuple[torch.Tensor, torch.Tensor | None] | None,
              max_chunk_elements: int = 2**26) -> tuple[str, float | None]:
    """The exact L1 kernel for ``(R, D)`` references and ``(Q, D)`` queries (module docstring).

    ``"sad"`` on CPU where numba is installed, the data qualify (:func:`sad_offset`) and
    the run is large enough for the time saved to pay numba's start-up: against ``cdist``
    (``levels`` None) or the thermometer's float32 product, from ``R * Q * D >=
    SAD_MIN_WORK``; against its int8 GEMM (AVX-512; :func:`thermometer_product`), whose cost
    grows with the thresholds ``k``, from ``R * Q * D * (k - SAD_INT8_TIE_LEVELS) >=
    SAD_INT8_MIN_SAVING``. Else ``"thermometer"`` when ``levels`` is not None, else ``"cdist"``.

    Args:
        reference: ``(R, D)``.
        query: ``(Q, D)``.
        levels: the inputs' :func:`thermometer_levels` (non-empty thresholds or None).
        max_chunk_elements: bound on the rows scanned at a time by :func:`sad_offset`.

    Returns:
        ``(kernel, lo)``: ``lo`` the minimum ``"sad"`` subtracts (:func:`sad_offset`, found
        while deciding, so callers need not scan the data again), None for the other kernels.
    """
    fallback = "thermometer" if levels is not None else "cdist"
    device = reference.device
    work, needed = reference.shape[0] * query.shape[0] * reference.shape[1], SAD_MIN_WORK
    if levels is not None and thermometer_product(device) == "int8":
        work *= levels[0].numel() - SAD_INT8_TIE_LEVELS
        needed = SAD_INT8_MIN_SAVING
    if device.type != "cpu" or work < needed or not sad_available():
        return fallback, None
    lo = sad_offset(reference, query, levels, max_chunk_elements)
    return ("sad", lo) if lo is not None else (fallback, None)


def l1_kernel(reference: torch.Tensor, query: torch.Tensor,
              levels: tuple[torch.Tensor, torch.Tensor | None] | None,
              max_chunk_elements: int = 2**26) -> str:
    """The name :func:`l1_choice` gives: ``"sad"``, ``"thermometer"`` or ``"cdist"``."""
    return l1_choice(reference, query, levels, max_chunk_elements)[0]


def _l1_sad(ref: torch.Tensor, query: torch.Tensor, out_t: torch.Tensor, lo: float,
            budget: int, workers: int, ref_codes: torch.Tensor | None = None) -> None:
    """Fill ``out_t (Q, R)`` (CPU) with exact L1 distances by the compiled uint8 loop.

    ``ref_codes``: the reference's :func:`sad_codes`, when already built. Every uint8 block
    holds at most ``budget`` elements (one row at least).
    """
    from torchseq.seqslam import _l1_numba  # numba's import and compilation: only here

    n_ref, dim = ref.shape
    n_query = query.shape[0]
    rows = max(1, min(budget // dim, SAD_BLOCK_ROWS))  # rows per block of either side
    out = out_t.numpy()
    whole = _as_uint8(query, lo).numpy() if n_query * dim <= budget else None

    def fill(r0: int) -> None:
        a = (ref_codes[r0:r0 + rows] if ref_codes is not None
             else _as_uint8(ref[r0:r0 + rows], lo)).numpy()
        if whole is not None:
            _l1_numba.sad(a, whole, out, r0, 0)
            return
        for q0 in range(0, n_query, rows):
            _l1_numba.sad(a, _as_uint8(query[q0:q0 + rows], lo).numpy(), out, r0, q0)

    run_blocks(fill, range(0, n_ref, rows), workers, ref.device)


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
    check_magnitude(reference, "reference descriptors")
    check_magnitude(query, "query descriptors")


def check_magnitude(x: torch.Tensor, name: str) -> None:
    """Raise ``ValueError`` when ``(N, D)`` descriptors are too large to difference.

    The largest difference (``2 |x| D`` under l1) squared and summed over a contrast window
    must stay finite in ``x``'s dtype (float32 for integers): beyond it l2 overflows and l1
    and cosine match every query to one place.
    """
    if not x.is_floating_point() or x.numel() == 0:
        return
    limit = math.sqrt(torch.finfo(x.dtype).max) / (2 * x.shape[-1] * 2**10)
    top = float(x.abs().max())
    if top > limit:
        raise ValueError(f"{name} hold values up to {top:.3g}, beyond the {limit:.3g} "
                         f"{str(x.dtype)[6:]} differences of {x.shape[-1]} values stay "
                         f"finite in: rescale them")


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
    max_chunk_elements: int = 2**26, threads: int = 1, kernel: str | None = None,
) -> tuple[torch.Tensor, str]:
    """:func:`difference_matrix` and the name of the kernel that computed it.

    Args:
        reference: as :func:`difference_matrix`.
        query: as :func:`difference_matrix`.
        metric: as :func:`difference_matrix`.
        max_chunk_elements: as :func:`difference_matrix`.
        threads: as :func:`difference_matrix`.
        kernel: ``"l1"`` only: run this kernel (``"thermometer"``, ``"sad"`` or ``"cdist"``;
            for tests and benchmarks) instead of :func:`l1_kernel`'s choice; ``ValueError``
            where the data do not qualify for it. Constant inputs still give ``"constant"``.

    Returns:
        ``(R, Q)`` distances and one of ``"thermometer"``, ``"sad"``, ``"cdist"``,
        ``"constant"`` (all inputs equal), ``"l2"``, ``"cosine"``.
    """
    check_descriptors(reference, query)
    if metric not in METRICS:
        raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")
    if kernel is not None and (metric != "l1" or kernel not in L1_KERNELS):
        raise ValueError(f"kernel must be None or, for metric 'l1', one of {L1_KERNELS}; got "
                         f"{kernel!r} for metric {metric!r}")
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
        chosen, lo = (kernel, None) if kernel else l1_choice(reference, query, levels,
                                                             max_chunk_elements)
        if chosen == "thermometer" and levels is None:
            raise ValueError("the 'thermometer' L1 kernel needs integer-valued descriptors "
                             "with few distinct values (thermometer_levels); these have not")
        if chosen == "sad":
            if lo is None:  # forced: the data not checked yet
                lo = sad_offset(reference, query, levels, max_chunk_elements)
            if reference.device.type != "cpu" or lo is None:
                why = "values that do not qualify" if lo is None else "not on CPU"
                raise ValueError(f"the 'sad' L1 kernel needs CPU tensors of integer values "
                                 f"spanning at most {SAD_MAX_RANGE} (sad_offset); got {why}")
            _l1_sad(reference, query, out_t, lo, max_chunk_elements, threads)
            return out_t.T, "sad"
        if chosen == "thermometer":
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

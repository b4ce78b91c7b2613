"""The online step as one compiled pass (numba): the ``"numba"`` step kernel of ``NeuralInference``.

Private kernel behind :meth:`torchseq.neural.NeuralInference.step` (``kernels={"step":
"numba"}``, or ``"stages_or_numba"`` below ``SMALL_BATCH`` frames). The maths is the stages'
(``docs/guide/neural.md``, "Step maths"); each part below names the stage kernel whose
arithmetic it repeats, operation for operation, so the two give the same bits:

1. patch z-score of the grey frame on the ``1 / input_steps`` grid:
   :func:`torchseq.preprocess.zscore_pixel_major` (its sums run over a block's pixels first
   to last), then ``rint(z * steps)`` as in ``NeuralInference.evidence``;
2. the L1 product as an int8 GEMV with int32 sums: the integers of the ``int8_gemm`` kernel
   (L1 weights ``n * 2**e``, ``|n| <= 64``, inputs on a power-of-two grid, so the float32
   product is these sums times one power of two, exactly: ``NeuralInference`` offers this
   kernel only where every partial sum stays below ``2**24`` units);
3. k-WTA on those integer sums: the ``k``-th largest value ``v``; winners are the entries
   ``> v`` and the lowest-index entries ``== v`` until there are ``k`` (``kwta``'s tie rule);
4. the L3 evidence as the sum of the winners' rows in ascending index order
   (:func:`torchseq.layers.kernels.sum_rows`, one row after another in float32);
5. one cohort's z-score and rectify with NumPy's pairwise float32 sums
   (:func:`torchseq.layers.kernels.cohort_normalise_numpy`);
6. the banded ring step, lag after lag (``ring._move_banded``, then
   ``decay * moved + gain * e``);
7. the decision: first maximum, the best rival outside the window (``readout._decide_numpy``).

``tests/test_neural_step_numba.py`` checks the bits against the stage kernels on real
corridor frames and on random ones. Imported only when the kernel is chosen; compiled on first
use and cached beside this file (``cache=True``).
"""

from __future__ import annotations

import numba
import numpy as np

_PW_BLOCK = 128  # NumPy's PW_BLOCKSIZE (numpy/_core/src/umath/loops_utils.h.src)


@numba.njit(cache=True, nogil=True)
def _pairwise_leaf(a, lo, n):  # pragma: no cover - compiled
    """NumPy's pairwise sum of ``a[lo:lo + n]`` for ``n <= 128``: eight running sums."""
    if n < 8:
        res = a[lo]  # NumPy starts from -0.0 and adds in order: the same bits
        for i in range(1, n):
            res = res + a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - (n % 8):
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@numba.njit(cache=True, nogil=True)
def pairwise_sum(a, lo, n):  # pragma: no cover - compiled
    """NumPy's float32 ``add.reduce`` of ``a[lo:lo + n]`` (contiguous, ``n >= 1``).

    NumPy's ``pairwise_sum``: blocks of at most 128 by :func:`_pairwise_leaf`, longer runs
    split at half (rounded down to a multiple of 8) and the halves' sums added. Written with
    an explicit stack (a recursive function does not load from numba's cache).
    """
    los = np.empty(64, np.int64)
    ns = np.empty(64, np.int64)
    combine = np.empty(64, np.bool_)
    vals = np.empty(64, a.dtype)
    sp, vp = 1, 0
    los[0], ns[0], combine[0] = lo, n, False
    while sp:
        sp -= 1
        lo_, n_, c = los[sp], ns[sp], combine[sp]
        if c:  # both halves done: left + right
            vals[vp - 2] = vals[vp - 2] + vals[vp - 1]
            vp -= 1
        elif n_ <= _PW_BLOCK:
            vals[vp] = _pairwise_leaf(a, lo_, n_)
            vp += 1
        else:
            n2 = n_ // 2
            n2 -= n2 % 8
            los[sp], ns[sp], combine[sp] = lo_, n_, True
            los[sp + 1], ns[sp + 1], combine[sp + 1] = lo_ + n2, n_ - n2, False
            los[sp + 2], ns[sp + 2], combine[sp + 2] = lo_, n2, False
            sp += 3
    return vals[0]


@numba.njit(cache=True, nogil=True)
def kth_largest(values, k, count):  # pragma: no cover - compiled
    """The ``k``-th largest of int32 ``values`` (``1 <= k <= len``), by radix selection.

    Four passes over the values, one byte each from the top (the sign bit flipped, so the
    unsigned order is the signed one); ``count`` is a scratch ``(256,)`` int64. Linear time
    whatever the data (no pivot to go wrong on ties).
    """
    prefix = np.uint32(0)
    mask = np.uint32(0)
    for shift in (24, 16, 8, 0):
        count[:] = 0
        for i in range(values.shape[0]):
            u = np.uint32(values[i]) ^ np.uint32(0x80000000)
            if (u & mask) == prefix:
                count[(u >> np.uint32(shift)) & np.uint32(255)] += 1
        byte = 255
        while count[byte] < k:  # the byte of the k-th largest among the candidates
            k -= count[byte]
            byte -= 1
        prefix |= np.uint32(byte) << np.uint32(shift)
        mask |= np.uint32(255) << np.uint32(shift)
    return np.int32(prefix ^ np.uint32(0x80000000))


@numba.njit(cache=True, nogil=True, inline="always")
def _frame(grey, patch, steps, w1, k, w3_t, eps, rectify, diag, decay, gain, prev,
           unit_centre, window, x, acc, count, e, act):  # pragma: no cover - compiled
    """One frame: grey ``(h, w)`` and the previous activity ``(N,)`` -> ``act``, (ref, conf).

    ``x`` (K,) int8, ``acc`` (M,) int32, ``count`` (256,) int64, ``e`` (N,) float32: scratch.
    """
    h, w = grey.shape
    bw = w // patch
    n = patch * patch
    nf = np.float32(n)
    nm1 = np.float32(n - 1)
    one = np.float32(1.0)
    # 1. patch z-score, block-major, pixel order within a block (zscore_pixel_major)
    for by in range(h // patch):
        for bx in range(bw):
            base = (by * bw + bx) * n
            s = grey[by * patch, bx * patch]
            for p in range(1, n):
                s = s + grey[by * patch + p // patch, bx * patch + p % patch]
            mean = s / nf
            ss = np.float32(0.0)
            for p in range(n):
                d = grey[by * patch + p // patch, bx * patch + p % patch] - mean
                ss = d * d if p == 0 else ss + d * d
            std = np.sqrt(ss / nm1)
            if not std > 0:
                std = one
            for p in range(n):
                d = grey[by * patch + p // patch, bx * patch + p % patch] - mean
                x[base + p] = np.int8(np.rint((d / std) * steps))
    # 2. L1: int8 GEMV, int32 sums (rows of w1 are contiguous)
    m, kk = w1.shape
    for j in range(m):
        t = np.int32(0)
        for i in range(kk):
            t += np.int32(x[i]) * np.int32(w1[j, i])
        acc[j] = t
    # 3. k-WTA: the k-th largest sum, ties to the lowest index
    v = kth_largest(acc, k, count)
    room = k
    for j in range(m):
        if acc[j] > v:
            room -= 1
    # 4. L3: the winners' rows, ascending index
    nu = w3_t.shape[1]
    e[:] = 0.0
    first = True
    for j in range(m):
        a = acc[j]
        win = a > v
        if not win and a == v and room > 0:
            win = True
            room -= 1
        if win:
            if first:
                e[:] = w3_t[j]
                first = False
            else:
                for u in range(nu):
                    e[u] = e[u] + w3_t[j, u]
    # 5. one cohort: z-score, rectify (NumPy's pairwise sums)
    nuf = np.float32(nu)
    mean = pairwise_sum(e, 0, nu) / nuf
    for u in range(nu):
        e[u] = e[u] - mean
    for u in range(nu):  # act as scratch for dev * dev
        act[u] = e[u] * e[u]
    sd = np.sqrt(pairwise_sum(act, 0, nu) / nuf) + eps
    for u in range(nu):
        z = e[u] / sd
        e[u] = (z if z >= 0 else np.float32(0.0)) if rectify else z  # np.maximum's rule
    # 6. banded ring: moved = d0 * a, then lag after lag
    for u in range(nu):
        act[u] = prev[u] * diag[0, u]
    for lag in range(1, diag.shape[0]):
        for u in range(lag, nu):
            act[u] = act[u] + diag[lag, u] * prev[u - lag]
    for u in range(nu):
        act[u] = decay * act[u] + gain * e[u]
    # 7. decision: first maximum, best rival outside the window
    best = 0
    for u in range(1, nu):
        if act[u] > act[best]:
            best = u
    lo, hi = max(best - window, 0), min(best + window + 1, nu)
    if lo == 0 and hi == nu:
        second = act[0]
        for u in range(1, nu):
            second = min(second, act[u])
    else:
        second = np.float32(-np.inf)
        for u in range(lo):
            second = max(second, act[u])
        for u in range(hi, nu):
            second = max(second, act[u])
    return unit_centre[best], np.float32(act[best] - second)


@numba.njit(cache=True, nogil=True)
def step(grey, state, w1, w3_t, diag, unit_centre, reals, ints, act, ref,
         conf):  # pragma: no cover - compiled
    """Every stream of a batch; False (outputs unfinished) when a frame is not finite.

    Args:
        grey: ``(B, h, w)`` float32 grey frames at the input size.
        state: ``(B, N)`` float32 previous activity.
        w1: ``(M, K)`` int8 L1 integers, columns in block-major input order.
        w3_t: ``(M, N)`` float32 folded L3 weights, transposed.
        diag: ``(L + 1, N)`` float32 diagonals of the banded shift matrix.
        unit_centre: ``(N,)`` int64.
        reals: float32 ``(input_steps, eps, decay, gain)``.
        ints: int64 ``(patch, k, window, rectify)`` (window at most ``N``).
        act: ``(B, N)`` float32 output: the new activity (the new state).
        ref: ``(B,)`` int64 output: the reference frame decided.
        conf: ``(B,)`` float32 output: the confidence margin.
    """
    m, kk = w1.shape
    x = np.empty(kk, np.int8)
    acc = np.empty(m, np.int32)
    count = np.empty(256, np.int64)
    e = np.empty(w3_t.shape[1], np.float32)
    for b in range(grey.shape[0]):  # checked_grey's rule: a sum first, elements if it fails
        if not np.isfinite(grey[b].sum()):
            for v in grey[b].ravel():
                if not np.isfinite(v):
                    return False
    for b in range(grey.shape[0]):
        ref[b], conf[b] = _frame(grey[b], ints[0], reals[0], w1, ints[1], w3_t, reals[1],
                                 ints[3] != 0, diag, reals[2], reals[3], state[b], unit_centre,
                                 ints[2], x, acc, count, e, act[b])
    return True

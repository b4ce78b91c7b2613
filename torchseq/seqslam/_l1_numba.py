"""Sums of absolute differences of uint8 descriptors, compiled (numba): the ``"sad"`` kernel.

Private kernel behind :func:`torchseq.seqslam.difference.difference_with_kernel` (its module
docstring says when it is chosen). The maths is the L1 distance ``sum_d |a_d - b_d|`` itself,
summed exactly in int32 (at most ``D * 255``, which the caller keeps below ``2**24`` so the
float32 output is exact too).

The loops are written so that LLVM vectorises the sum over ``d`` (``|int32(a) - int32(b)|``
becomes unsigned max - min on bytes, widened and added eight lanes at a time on AVX2; the
``int32(...)`` of every partial sum keeps numba from widening the sums to int64, which halves
the lanes). Two reference rows against two query rows per pass share each loaded byte, and
``TILE`` x ``TILE`` tiles keep both sets of rows in the L2 cache.

``tests/test_seqslam_l1_kernels.py`` checks it against a plain float64 loop and the
thermometer kernel. Imported only when the kernel runs; compiled on first use and cached
beside this file (``cache=True``).
"""

from __future__ import annotations

import numba
import numpy as np

TILE = 64  # rows of each side per tile: 2 x 64 x D bytes (256 KiB at D = 2048) stay in L2


@numba.njit(cache=True, nogil=True, inline="always")
def _ad(x, y):  # pragma: no cover - compiled
    """``|x - y|`` of two bytes as int32."""
    return abs(np.int32(x) - np.int32(y))


@numba.njit(cache=True, nogil=True)
def sad(a, b, out, r0, q0):  # pragma: no cover - compiled
    """``out[q0 + j, r0 + i] = sum_d |a[i, d] - b[j, d]|`` for every row pair.

    Args:
        a: ``(r, D)`` uint8 reference rows, C-contiguous.
        b: ``(q, D)`` uint8 query rows, C-contiguous.
        out: ``(Q, R)`` float32 or float64 output, written at rows ``q0 .. q0 + q - 1`` and
            columns ``r0 .. r0 + r - 1`` only.
        r0: first output column.
        q0: first output row.
    """
    n_a, dim = a.shape
    n_b = b.shape[0]
    for i0 in range(0, n_a, TILE):
        i_end = min(i0 + TILE, n_a)
        for j0 in range(0, n_b, TILE):
            j_end = min(j0 + TILE, n_b)
            for i in range(i0, i_end, 2):
                i1 = min(i + 1, i_end - 1)  # an odd last row is done twice, same sums
                for j in range(j0, j_end, 2):
                    j1 = min(j + 1, j_end - 1)
                    s00 = np.int32(0)
                    s01 = np.int32(0)
                    s10 = np.int32(0)
                    s11 = np.int32(0)
                    for d in range(dim):
                        x0, x1, y0, y1 = a[i, d], a[i1, d], b[j, d], b[j1, d]
                        s00 = np.int32(s00 + _ad(x0, y0))
                        s01 = np.int32(s01 + _ad(x0, y1))
                        s10 = np.int32(s10 + _ad(x1, y0))
                        s11 = np.int32(s11 + _ad(x1, y1))
                    out[q0 + j, r0 + i] = s00
                    out[q0 + j1, r0 + i] = s01
                    out[q0 + j, r0 + i1] = s10
                    out[q0 + j1, r0 + i1] = s11

"""Private fast kernels behind the functions of :mod:`torchseq.layers.functional`.

Each kernel computes one stage's definition (named in its docstring) another way; callers
choose it explicitly (``kwta(..., kernel="partition")``, the kernels of
:class:`torchseq.neural.inference.NeuralInference`), and ``tests/test_neural_dispatch.py``
checks which one ran.

- :func:`kwta_numpy` / :func:`kwta_partition`: the binary code of ``kwta`` from NumPy's
  introselect.
- :func:`kwta_topk`: the winners of ``kwta`` from ``torch.topk`` (any device, exportable
  ops, the gradient path of the valued code).
- :func:`topk_indices`: the winners' indices of ``kwta`` from ``torch.topk``.
- :func:`sum_rows`: a binary code times a matrix as the sum of the winners' rows
  (``F.embedding_bag``): ``k * N`` reads per frame instead of ``M * N``.
- :class:`Int8Linear`: oneDNN's int8 GEMM for products whose operands sit on integer grids.
"""

from __future__ import annotations

import numpy as np
import torch

# Tie-break step for a low-precision L1 product: far below a bfloat16 ulp at the k-WTA
# threshold (|h| ~ 1, ulp 2^-7), so it only orders values that rounded to the same number.
TIE_STEP = 2.0**-24


def kwta_numpy(values: np.ndarray, k: int) -> np.ndarray:
    """The binary code of :func:`kwta` for NumPy rows ``(B, M)``, as a bool array.

    The ``k``-th largest value ``v`` of each row comes from ``numpy.partition``
    (introselect, several times faster than ``torch.topk`` on one CPU thread); the winners
    are the entries ``>= v``, except in rows with a tie at ``v``, which keep the entries
    ``> v`` and the lowest-index entries ``== v``. Any real or integer dtype, no NaN.

    Float rows are selected on their bits read as signed integers (faster to partition):
    positive floats sort like those integers and every negative float reads as a negative
    one, so the result is the same whenever each row's ``v`` is above ``+0.0``; otherwise
    the floats themselves are partitioned.
    """
    m = values.shape[1]
    keys = values
    if values.dtype.kind == "f":
        keys = values.view(np.dtype(f"i{values.itemsize}"))
    v = np.partition(keys, m - k, axis=1)[:, m - k : m - k + 1]  # (B, 1)
    if keys is not values and not bool((v > 0).all()):
        keys = values
        v = np.partition(keys, m - k, axis=1)[:, m - k : m - k + 1]
    win = keys >= v  # (B, M)
    tied = np.flatnonzero(win.view(np.uint8).sum(1, dtype=np.int32) != k)
    if tied.size:
        row, vt = keys[tied], v[tied]
        greater, equal = row > vt, row == vt
        room = k - greater.sum(1, keepdims=True, dtype=np.int32)
        win[tied] = greater | (equal & (equal.cumsum(1, dtype=np.int32) <= room))
    return win



def kwta_topk(x: torch.Tensor, k: int) -> torch.Tensor:
    """Winners of ``kwta`` as a bool tensor ``(..., N)``, from ``torch.topk`` (any device).

    Kernel of :func:`torchseq.layers.functional.kwta` (``kernel="topk"``): the ``k``-th
    largest value ``v``; winners are the entries ``> v`` and the lowest-index entries ``== v``
    until there are ``k``.
    """
    v = torch.topk(x, k, dim=-1).values[..., -1:]  # (..., 1) the k-th largest value
    greater = x > v
    equal = x == v
    room = k - greater.sum(-1, keepdim=True)  # how many tied entries still win
    return greater | (equal & (equal.to(torch.int64).cumsum(-1) <= room))


def kwta_partition(x: torch.Tensor, k: int) -> torch.Tensor:
    """Binary k-WTA code of ``kwta`` as a bool tensor, for CPU rows ``(..., N)`` (no NaN).

    Kernel of :func:`torchseq.layers.functional.kwta` (``kernel="partition"``).
    """
    n = x.shape[-1]
    win = kwta_numpy(x.detach().reshape(-1, n).numpy(), k)
    return torch.from_numpy(win).reshape(x.shape)


def kwta_partition_indices(x: torch.Tensor, k: int) -> torch.Tensor:
    """Winners' indices ``(B, k)`` (ascending) of ``kwta``'s partition kernel, rows ``(B, N)``."""
    values = x.detach().numpy()
    if values.shape[0] == 1 and values.dtype == np.float32:  # one row: no per-row bookkeeping
        row = values[0]
        keys = row.view(np.int32)  # positive floats sort like their bits (see kwta_numpy)
        v = np.partition(keys, row.size - k)[row.size - k]
        if v > 0:
            idx = np.flatnonzero(keys >= v)
            if idx.size == k:  # no tie at the threshold
                return torch.from_numpy(idx[None])
    win = kwta_numpy(values, k)
    return torch.from_numpy(np.nonzero(win)[1].reshape(x.shape[0], k))


def cohort_normalise_numpy(evidence: torch.Tensor, eps: float, rectify: bool) -> torch.Tensor:
    """One cohort of :func:`torchseq.layers.functional.cohort_normalise` in NumPy (CPU)."""
    if evidence.device.type != "cpu" or evidence.requires_grad:
        raise ValueError("cohort_normalise's numpy kernel needs a CPU tensor without gradients")
    e = evidence.numpy()
    n = e.dtype.type(e.shape[1])
    dev = e - np.add.reduce(e, axis=1, keepdims=True) / n
    z = dev / (np.sqrt(np.add.reduce(dev * dev, axis=1, keepdims=True) / n) + e.dtype.type(eps))
    if rectify:
        np.maximum(z, 0, out=z)
    return torch.from_numpy(z)


def sum_rows(idx: torch.Tensor, w_t: torch.Tensor) -> torch.Tensor:
    """``code @ w_t`` for binary codes given by their ones' indices ``idx`` ``(B, k)``.

    Args:
        idx: ``(B, k)`` int64 column indices of each row's ones.
        w_t: ``(M, N)``.

    Returns:
        ``(B, N)`` sum of the ``k`` rows of ``w_t`` picked by each row of ``idx``.
    """
    b, k = idx.shape
    offsets = torch.arange(0, b * k, k, device=idx.device)
    # torch.embedding_bag without F.embedding_bag's argument handling (mode 0 = sum)
    return torch.embedding_bag(w_t, idx.reshape(-1), offsets, False, 0)[0]


def topk_indices(h: torch.Tensor, k: int) -> torch.Tensor:
    """Indices ``(B, k)`` of the k-WTA winners of each row (in no particular order).

    The same winners as :func:`torchseq.layers.kwta`: the ``k``-th largest value ``v``
    from ``torch.topk``; without a tie at ``v`` the topk indices are the winners; with one, all
    entries ``> v`` plus the lowest-index entries ``== v`` (the order of indices within a
    row does not matter to the evidence sum).

    Args:
        h: ``(B, M)`` L2 input.
        k: winners per row.
    """
    vals, idx = torch.topk(h, k, dim=1, sorted=False)
    v = vals.amin(dim=1, keepdim=True)  # (B, 1)
    if not has_tie(h, v, k):
        return idx
    return kwta_topk(h, k).nonzero()[:, 1].reshape(h.shape[0], k)  # kwta's tie rule


def has_tie(h: torch.Tensor, v: torch.Tensor, k: int) -> bool:
    """Whether some row of ``h`` has more than ``k`` entries ``>= v`` (or ``v`` is NaN).

    Every row holds at least ``k`` entries ``>= v`` when ``v`` is the smallest of the row's
    ``k`` largest values (and not NaN), so one global count equal to ``B * k`` means exactly
    ``k`` per row: one ``count_nonzero`` over the whole ``(B, M)`` instead of per-row sums
    (about half the time on one CPU thread, same answer).

    Args:
        h: ``(B, M)``.
        v: ``(B, 1)`` each row's ``k``-th largest value.
        k: winners per row.
    """
    if bool(v.isnan().any()):
        return True
    return int(torch.count_nonzero(h >= v)) != h.shape[0] * k


class Int8Linear:
    """``y = ((x - x_zero) @ n.T) * x_scale * scale`` with uint8 ``x`` and int8 ``n``, as float32.

    oneDNN's int8 GEMM (``torch.ops.onednn.qlinear_pointwise``, the kernel behind PyTorch's
    x86 quantisation; VNNI/AMX where the CPU has them) with int32 accumulation. Build with
    :meth:`create`, which returns None when the operator is missing or does not reproduce a
    float32 product of the same integers on a check batch drawn from the inputs it will be fed.

    Args:
        n: ``(N, K)`` int8 weights (``|n| <= 64`` keeps pairs of products inside int16 on
            CPUs without VNNI, so no kernel saturates).
        scale: ``(N,)`` float32 per-row scales.
        x_scale: scale of the input integers.
        x_zero: zero point of the input integers.
    """

    def __init__(self, n: torch.Tensor, scale: torch.Tensor, x_scale: float, x_zero: int):
        self.x_scale, self.x_zero = float(x_scale), int(x_zero)
        self.scale = scale.to(torch.float32).contiguous()
        self.zeros = torch.zeros(n.shape[0], dtype=torch.int64)
        self.packed = torch.ops.onednn.qlinear_prepack(n.contiguous(), None)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, K)`` uint8 -> ``(B, N)`` float32."""
        return torch.ops.onednn.qlinear_pointwise(
            x, self.x_scale, self.x_zero, self.packed, self.scale, self.zeros, None, 1.0, 0,
            torch.float32, "none", [], "")

    @classmethod
    def create(cls, n: torch.Tensor, scale: torch.Tensor, x_scale: float,
               x_zero: int, x_max: int = 255) -> Int8Linear | None:
        """An :class:`Int8Linear`, or None when the int8 GEMM is unavailable or inexact here.

        ``x_max`` is the largest input it will be fed (1 for a binary k-WTA code): the check
        batch spans ``0..x_max``. On CPUs without VNNI the kernel adds pairs of products in
        int16, so rows up to 127 are exact on a binary code but may saturate on bytes.
        """
        if not hasattr(torch.ops.onednn, "qlinear_pointwise"):
            return None
        try:
            lin = cls(n, scale, x_scale, x_zero)
            gen = torch.Generator().manual_seed(0)
            x = torch.randint(0, int(x_max) + 1, (37, n.shape[1]), generator=gen,
                              dtype=torch.uint8)
            got = lin(x)
        except (RuntimeError, NotImplementedError, TypeError, ValueError, AttributeError):
            return None  # an optional kernel: any failure means the float path
        acc = (x.to(torch.float64) - x_zero) @ n.to(torch.float64).T  # exact integers
        want = (acc * x_scale * scale.to(torch.float64)).to(torch.float32)
        return lin if torch.allclose(got, want, rtol=1e-6, atol=0.0) else None

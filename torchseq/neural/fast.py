"""Fast inference paths of Neural SeqSLAM (same maths as ``NeuralSeqSLAM.step``).

- :func:`feedforward`: preprocessing, L1 -> L2 -> L3 and cohort normalisation for a batch
  of frames with folded (dense) weights; the binary k-WTA code is never materialised: the
  L3 evidence is the sum of the ``k`` winners' columns of ``l3.weight * l3.mask``
  (``F.embedding_bag`` in sum mode).
- :func:`feedforward_uint8`: the same for a model on its integer grids
  (:mod:`torchseq.neural.fixed_point`): L1 and L3 as oneDNN int8 GEMMs (:class:`Int8Linear`)
  and the k-WTA threshold from NumPy's introselect (:func:`kwta_code`). The L2 code is
  identical to the float path's; the evidence equal up to float rounding.
- :func:`ring_scan`: the ring recurrence over a whole single-stream sequence, in blocks of
  frames (a few dozen tensor operations per block instead of several per frame); when the
  shift matrix is banded (units recruited in order, no wrap) it runs on diagonals instead of
  ``N x N`` products.

Results equal the step-by-step path up to float rounding (sums in another order).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from torchseq.layers.functional import cohort_normalise, kwta_numpy

# Tie-break step for a low-precision L1 product: far below a bfloat16 ulp at the k-WTA
# threshold (|h| ~ 1, ulp 2^-7), so it only orders values that rounded to the same number.
TIE_STEP = 2.0**-24


def winners(h: torch.Tensor, k: int) -> torch.Tensor:
    """Indices ``(B, k)`` of the k-WTA winners of each row (in no particular order).

    The same winners as :func:`torchseq.layers.kwta`: the ``k``-th largest value ``v`` from
    ``torch.topk``; without a tie at ``v`` the topk indices are the winners; with one, all
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
    greater, equal = h > v, h == v
    room = k - greater.sum(1, keepdim=True)
    win = greater | (equal & (equal.to(torch.int64).cumsum(1) <= room))
    return win.nonzero()[:, 1].reshape(h.shape[0], k)


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


def feedforward(x: torch.Tensor, w1_t: torch.Tensor, w3_t: torch.Tensor, k: int,
                cohorts: torch.Tensor, eps: float, rectify: bool = True) -> torch.Tensor:
    """Normalised L3 evidence of preprocessed frames.

    Args:
        x: ``(B, D)`` L1 activity (after patch normalisation).
        w1_t: ``(D, M)`` ``(l1.weight * l1.mask).T``, contiguous (in ``x``'s dtype for the
            exact step; a lower-precision copy makes the L1 product approximate).
        w3_t: ``(M, N)`` ``(l3.weight * l3.mask).T``, contiguous.
        k: L2 winners.
        cohorts: ``(N, C)`` membership.
        eps: normalisation floor.
        rectify: clamp the z-scores at 0 (only above-average evidence drives the ring).

    Returns:
        ``(B, N)`` z-scored (and rectified) evidence.
    """
    if w1_t.dtype == x.dtype:
        h = x @ w1_t  # (B, M)
    else:  # approximate: low-precision product; its many exact ties go to the lowest index
        h = (x.to(w1_t.dtype) @ w1_t).to(x.dtype)
        h = h - torch.arange(h.shape[1], device=h.device, dtype=h.dtype) * TIE_STEP
    idx = winners(h, k)  # (B, k)
    # sum the k winners' rows of w3_t: k * N reads per frame instead of M * N
    e = F.embedding_bag(idx, w3_t, mode="sum")  # (B, N)
    z = cohort_normalise(e, cohorts, eps)
    return z.clamp_min(0.0) if rectify else z


class Int8Linear:
    """``y = ((x - x_zero) @ n.T) * x_scale * scale`` with uint8 ``x`` and int8 ``n``, as float32.

    oneDNN's int8 GEMM (``torch.ops.onednn.qlinear_pointwise``, the kernel behind PyTorch's
    x86 quantisation; VNNI/AMX where the CPU has them) with int32 accumulation. Build with
    :meth:`create`, which returns None when the operator is missing or does not reproduce a
    float32 product of the same integers on a check batch.

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
               x_zero: int) -> Int8Linear | None:
        """An :class:`Int8Linear`, or None when the int8 GEMM is unavailable or inexact here."""
        if not hasattr(torch.ops.onednn, "qlinear_pointwise"):
            return None
        try:
            lin = cls(n, scale, x_scale, x_zero)
            gen = torch.Generator().manual_seed(0)
            x = torch.randint(0, 256, (37, n.shape[1]), generator=gen, dtype=torch.uint8)
            got = lin(x)
        except (RuntimeError, NotImplementedError, TypeError, ValueError, AttributeError):
            return None  # an optional kernel: any failure means the float path
        acc = (x.to(torch.float64) - x_zero) @ n.to(torch.float64).T  # exact integers
        want = (acc * x_scale * scale.to(torch.float64)).to(torch.float32)
        return lin if torch.allclose(got, want, rtol=1e-6, atol=0.0) else None


def kwta_code(h: torch.Tensor, k: int) -> torch.Tensor:
    """Binary k-WTA code ``(B, M)`` uint8 of float32 CPU rows (no NaN).

    The same code as :func:`torchseq.layers.kwta`, through
    :func:`~torchseq.layers.functional.kwta_numpy`.
    """
    return torch.from_numpy(kwta_numpy(h.numpy(), k).view(np.uint8))


def feedforward_uint8(xq: torch.Tensor, l1: Int8Linear, l3: Int8Linear, k: int,
                      cohorts: torch.Tensor, eps: float, rectify: bool = True) -> torch.Tensor:
    """:func:`feedforward` of a model on its integer grids, with int8 GEMMs.

    Args:
        xq: ``(B, D)`` uint8 L1 input: ``x * steps + 128`` (exact on the model's grid), in the
            column order of ``l1``.
        l1: L1 weights (zero point 128, scale ``1 / steps``).
        l3: L3 weights (zero point 0, scale 1).
        k: L2 winners.
        cohorts: ``(N, C)`` membership.
        eps: normalisation floor.
        rectify: clamp the z-scores at 0.

    Returns:
        ``(B, N)`` z-scored (and rectified) evidence.
    """
    h = l1(xq)  # (B, M) float32: exact integer sums times a power of two
    e = l3(kwta_code(h, k))  # (B, N)
    z = cohort_normalise(e, cohorts, eps)
    return z.clamp_min(0.0) if rectify else z


def band_diagonals(shift: torch.Tensor, max_lag: int) -> torch.Tensor | None:
    """Diagonals ``(L + 1, N)`` of a banded shift matrix, or None when it is not banded.

    ``d[l, i] = shift[i, i - l]``; None unless every non-zero entry has a lag
    ``0 <= i - j <= max_lag``.
    """
    n = shift.shape[0]
    i = torch.arange(n, device=shift.device)
    lag = i[:, None] - i[None, :]  # (N, N) next - current
    if bool((shift[(lag < 0) | (lag > max_lag)] != 0).any()):
        return None
    d = torch.zeros(max_lag + 1, n, dtype=shift.dtype, device=shift.device)
    for m in range(max_lag + 1):
        d[m, m:] = torch.diagonal(shift, -m)
    return d


RING_BLOCK = 16  # frames per block of ring_scan


def ring_steps(shift: torch.Tensor, decay: float, diagonals: torch.Tensor | None,
               columns: int) -> torch.Tensor:
    """The advance operator of :func:`ring_advance` for ``(N, columns)`` states.

    ``decay * shift`` ``(N, N)``, or with ``diagonals`` ``(L + 1, N)``
    (:func:`band_diagonals`) each diagonal repeated per column: ``(L + 1, N * columns)``.
    """
    if diagonals is None:
        return shift * decay
    return (diagonals * decay).repeat_interleave(columns, dim=1)


def ring_advance(a, steps, banded: bool):
    """``decay * shift @ a`` for states in columns, ``a`` ``(N, columns)`` contiguous.

    NumPy arrays or tensors alike. ``steps`` from :func:`ring_steps`; when ``banded``, the
    product runs on the diagonals: row ``i`` of the state moved down by ``lag`` rows is
    the flat state moved by ``lag * columns`` elements, so each lag is one multiply-add
    over contiguous memory.
    """
    if not banded:
        return steps @ a
    flat = a.reshape(-1)
    m = flat * steps[0]
    for lag in range(1, steps.shape[0]):
        o = lag * a.shape[1]
        m[o:] += steps[lag, o:] * flat[:-o]
    return m.reshape(a.shape)


def ring_power(shift: torch.Tensor, decay: float, diagonals: torch.Tensor | None = None,
               block: int = RING_BLOCK) -> torch.Tensor:
    """``(decay * shift)**block`` ``(N, N)``: ``block`` advances of the identity's columns."""
    n = shift.shape[0]
    steps = ring_steps(shift, decay, diagonals, n)
    x = torch.eye(n, dtype=shift.dtype, device=shift.device)
    for _ in range(block):
        x = ring_advance(x, steps, diagonals is not None)
    return x


def ring_scan(drive: torch.Tensor, activity: torch.Tensor, shift: torch.Tensor, decay: float,
              diagonals: torch.Tensor | None = None, block: int = RING_BLOCK,
              power: torch.Tensor | None = None) -> torch.Tensor:
    """Run ``a_t = decay * a_{t-1} @ shift.T + drive_t`` over a single stream.

    The linear recurrence runs in blocks of ``C`` frames: (1) each block's response to its
    own drive from a zero start, all blocks at once (``C`` steps); (2) the state entering
    each block, block after block, through ``(decay * shift)**C`` (one matrix-vector product
    per block); (3) each block's response to that entering state, all blocks at once (``C``
    steps). About ``4 C + T / C`` small operations instead of several per frame; on the CPU
    they run in NumPy (a fraction of a tensor call's overhead at these sizes). Sums run in
    another order than frame by frame, so results are equal up to float rounding.

    Args:
        drive: ``(T, N)`` ``gain * evidence``.
        activity: ``(N,)`` activity before the first step.
        shift: ``(N, N)``.
        decay: ring decay.
        diagonals: output of :func:`band_diagonals` (None: dense products).
        block: frames per block ``C``.
        power: :func:`ring_power` for these arguments (None: computed here).

    Returns:
        ``(T, N)`` activity after each step.
    """
    t_len, n = drive.shape
    c = max(1, min(block, t_len))
    n_blocks = -(-t_len // c)
    if power is None or c != block:
        power = ring_power(shift.to(drive.dtype), decay, diagonals, c)
    d = drive.new_zeros(n_blocks * c, n)
    d[:t_len] = drive
    d = d.view(n_blocks, c, n).permute(1, 2, 0).contiguous()  # (C, N, blocks): states in columns
    steps = ring_steps(shift.to(drive.dtype), decay,
                       None if diagonals is None else diagonals.to(drive.dtype), n_blocks)
    local, entering = torch.empty_like(d), d.new_empty(n, n_blocks)
    arrays = (d, local, entering, activity.to(drive.dtype), steps, power.to(drive.dtype))
    if drive.device.type == "cpu" and not any(x.requires_grad for x in arrays):
        arrays = tuple(x.numpy() for x in arrays)  # local is filled in place either way
    _scan_blocks(*arrays, diagonals is not None)
    return local.permute(2, 0, 1).reshape(-1, n)[:t_len]


def _scan_blocks(d, local, entering, s, steps, power, banded: bool) -> None:
    """Steps (1)-(3) of :func:`ring_scan` on ``(C, N, blocks)`` arrays (NumPy or torch).

    Args:
        d: ``(C, N, blocks)`` drive, frame ``b * C + i`` in ``d[i, :, b]``.
        local: ``(C, N, blocks)`` output, same layout.
        entering: ``(N, blocks)`` work space.
        s: ``(N,)`` activity before the first frame.
        steps: :func:`ring_steps` for ``blocks`` columns.
        power: ``(N, N)`` ``(decay * shift)**C``.
        banded: ``steps`` holds diagonals.
    """
    c, _, n_blocks = d.shape
    a = d[0]
    local[0] = a
    for i in range(1, c):  # (1) zero-start response of every block
        a = ring_advance(a, steps, banded)
        a += d[i]
        local[i] = a
    for b in range(n_blocks):  # (2) state entering each block
        entering[:, b] = s
        s = local[c - 1, :, b] + power @ s
    for i in range(c):  # (3) add the entering state's response
        entering = ring_advance(entering, steps, banded)
        local[i] += entering

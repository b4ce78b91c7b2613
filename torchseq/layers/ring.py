"""The output ring: one step (:func:`ring_step`) and its sequence form (:func:`ring_scan`).

``a_t = decay * a_{t-1} @ shift.T + gain * evidence_t``, state ``(B, N)``, time-first
sequences ``(T, N)``. :func:`ring_step` is the definition; :func:`ring_scan` runs the same
recurrence over a whole single stream in blocks of frames and is tested against it.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F


class RingState(NamedTuple):
    """State of the output ring.

    Attributes:
        activity: ``(B, N)`` activity after the last step.
    """

    activity: torch.Tensor


class RingParams(NamedTuple):
    """Ring dynamics: ``a_t = decay * (a_{t-1} @ shift.T) + gain * evidence_t``."""

    decay: float = 0.9
    gain: float = 0.1


def ring_step(
    evidence: torch.Tensor, state: RingState, shift: torch.Tensor, params: RingParams,
    diagonals: torch.Tensor | None = None,
) -> tuple[torch.Tensor, RingState]:
    """One step of the output ring: shift the old activity along the ring, add new evidence.

    ``activity = params.decay * state.activity @ shift.T + params.gain * evidence``.

    Kernels (chosen by the caller): ``diagonals=None`` is one dense ``F.linear``;
    ``diagonals`` from :func:`band_diagonals` (a banded shift matrix: units recruited in
    order, no wrap) moves the activity one diagonal at a time, ``L + 1`` multiply-adds over
    ``N`` values instead of ``N * N`` (in NumPy for CPU tensors without gradients). Equal up
    to float rounding (sums in another order).

    Args:
        evidence: ``(B, N)`` feed-forward evidence of the new frame.
        state: previous :class:`RingState` with ``(B, N)`` activity.
        shift: ``(N, N)`` ``W[next, current]``.
        params: :class:`RingParams`.
        diagonals: ``(L + 1, N)`` diagonals of ``shift`` (None: dense product).

    Returns:
        ``(activity (B, N), new state)``.
    """
    if diagonals is None:
        moved = F.linear(state.activity, shift)  # (B, N): moved[b, i] = sum_j shift[i, j] a[b, j]
        activity = params.decay * moved + params.gain * evidence
    else:
        activity = _ring_step_banded(evidence, state.activity, diagonals, params)
    return activity, RingState(activity)


def ring_move(activity: torch.Tensor, shift: torch.Tensor,
              diagonals: torch.Tensor | None = None) -> torch.Tensor:
    """The shift alone: ``activity @ shift.T`` ``(B, N) -> (B, N)`` (no decay, no evidence).

    The same products as :func:`ring_step` (its two kernels: dense ``F.linear``, or the
    diagonals of :func:`band_diagonals`), for callers that move the activity more than once
    per frame (:func:`torchseq.layers.ring_velocity.ring_step_velocity`).
    """
    if diagonals is None:
        return F.linear(activity, shift)
    numpy = activity.device.type == "cpu" and not activity.requires_grad
    a = activity.numpy() if numpy else activity
    moved = _move_banded(a, diagonals.numpy() if numpy else diagonals)
    return torch.from_numpy(moved) if numpy else moved


def _move_banded(a, d):
    """``moved[:, i] = sum_l d[l, i] a[:, i - l]`` (NumPy arrays or tensors)."""
    moved = a * d[0]
    for lag in range(1, d.shape[0]):
        moved[:, lag:] += d[lag, lag:] * a[:, :-lag]
    return moved


def _ring_step_banded(evidence: torch.Tensor, a: torch.Tensor, diagonals: torch.Tensor,
                      params: RingParams) -> torch.Tensor:
    """Kernel of :func:`ring_step` on diagonals: ``moved[:, i] = sum_l d[l, i] a[:, i - l]``."""
    numpy = a.device.type == "cpu" and not (a.requires_grad or evidence.requires_grad)
    if numpy:
        a, e, d = a.numpy(), evidence.numpy(), diagonals.numpy()
    else:
        e, d = evidence, diagonals
    moved = _move_banded(a, d)
    out = params.decay * moved + params.gain * e
    return torch.from_numpy(out) if numpy else out


def band_diagonals(shift: torch.Tensor, max_lag: int) -> torch.Tensor | None:
    """Diagonals ``(L + 1, N)`` of a banded shift matrix, or None when it is not banded.

    ``d[l, i] = shift[i, i - l]``; None unless every non-zero entry has a lag
    ``0 <= i - j <= max_lag``.
    """
    n = shift.shape[0]
    max_lag = min(int(max_lag), n - 1)  # no lag reaches past the ring: bounds the allocation
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
              power: torch.Tensor | None = None, kernel: str = "auto") -> torch.Tensor:
    """Run ``a_t = decay * a_{t-1} @ shift.T + drive_t`` over a single stream.

    The sequence form of :func:`ring_step` (with ``drive = gain * evidence``).

    The linear recurrence runs in blocks of ``C`` frames: (1) each block's response to its
    own drive from a zero start, all blocks at once (``C`` steps); (2) the state entering
    each block, block after block, through ``(decay * shift)**C`` (one matrix-vector product
    per block); (3) each block's response to that entering state, all blocks at once (``C``
    steps). About ``4 C + T / C`` small operations instead of several per frame. Sums run in
    another order than frame by frame, so results are equal up to float rounding.

    Args:
        drive: ``(T, N)`` ``gain * evidence``.
        activity: ``(N,)`` activity before the first step.
        shift: ``(N, N)``.
        decay: ring decay.
        diagonals: output of :func:`band_diagonals` (None: dense products).
        block: frames per block ``C``.
        power: :func:`ring_power` for these arguments (None: computed here).
        kernel: ``"numpy"`` (CPU tensors without gradients: a fraction of a tensor call's
            overhead at these sizes), ``"torch"`` (any device, differentiable) or ``"auto"``
            (``"numpy"`` exactly when it applies).

    Returns:
        ``(T, N)`` activity after each step.
    """
    if kernel not in ("auto", "numpy", "torch"):
        raise ValueError(f"kernel must be 'auto', 'numpy' or 'torch', got {kernel!r}")
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
    numpy_ok = drive.device.type == "cpu" and not any(x.requires_grad for x in arrays)
    if kernel == "numpy" and not numpy_ok:
        raise ValueError("ring_scan's numpy kernel needs CPU tensors without gradients")
    if kernel == "numpy" or (kernel == "auto" and numpy_ok):
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

"""Timed spiking Neural SeqSLAM: many time steps per frame, every stage by spike timing.

The one-step model (:mod:`torchseq.neural.spiking`) approximates three stages of the rate
model with calibrated constants (an L2 threshold for k-WTA, a fixed spread per cohort, a
ladder of ring neurons); its decisions agree with the rate model's on 0.69-0.82 of the
frames of the corridor and LENS (``docs/results/nir.md``). This model computes the same
three stages *exactly in the limit of many steps*, with integrate-and-fire (IF) units,
non-spiking integrators and 0/1 spikes, in three phases per frame of fixed length
(``steps_per_frame = l2_steps + norm_max_steps + ring_steps``, 5,888 by default); its
decisions agree with the rate model's on at least 0.964 (corridor) and 0.970 (LENS) of the
frames over seeds 0-7, with 8-bit weights. Each phase's populations start from zero at its
first step (a runtime reset: NIR has no node for it, nor for the reset by subtraction of
phases B and C, so this model has no NIR form; ``docs/guide/nir.md``).

Phase A, k-winners-take-all by inhibition (``l2_steps`` ``T_A`` steps). ``M`` IF units
(threshold 1, reset to 0) get the frame once, at step 1, as ``(h - hi) / span + 1``
(``h = x @ W1.T`` the L1 sums) and a ramp ``1 / T_A`` every step, so unit ``i`` fires at
the first ``t`` with ``h_i > hi - t span / T_A``: the largest sums first. Each unit
inhibits itself once it has fired (it fires once); one counter IF unit (weight 1 from every
L2 unit, threshold ``k - 1/2``) inhibits the whole layer from the step after the ``k``-th
spike. The winners are every unit that fired: the ``k`` largest sums, more where several
cross in the step that reaches ``k`` (ties), fewer where the ``k``-th sum is below ``lo``.
``[lo, hi]`` is the range of the reference's ``k``-th largest sums widened by ``widen`` of
itself on each side.

Phase B, division by each frame's cohort std by timing (up to ``norm_max_steps`` steps).
A non-spiking L3 integrator per output unit holds the winners' cohort-centred evidence
``c = z2 @ (W3 - cohort mean).T``. Per unit ``2 R`` IF units (reset by subtraction) are fed
``rate (+-c_j - k_r)`` every step and ``1/2`` at step 1: rungs ``k_0 = 0 < k_1 < ...``
whose spikes, weighted ``w_r / n_c``, make the chord interpolant of ``c_j ** 2``
(:func:`square_rungs`). One non-spiking integrator per cohort sums them (its membrane grows
as ``rate * var * t``); one window IF unit per cohort is fed that membrane (a double
integrator: it crosses ``theta`` near ``t = sqrt(2 theta / (rate var))``, one over the
std) and, once it fires, inhibits its cohort's ``+`` units of rung 0 from the next step.
The count ``p_j`` of those is ``max(c_j, 0) / std`` up to a calibrated constant: the rate
model's normalised, rectified evidence ``e_j = gain * p_j / s_c``. ``theta`` makes the
reference's median window ``norm_steps`` steps; a window still open after
``norm_max_steps`` steps stops counting there (``windows`` reports 0: clipped).

Phase C, the ring by rate (``ring_steps`` ``T_C`` steps). Output unit ``j`` is one IF
unit (reset by subtraction) fed ``e_j / top + (decay S n_prev)_j / T_C`` every step,
``n_prev`` the previous frame's ring counts (held for the frame: a host-side copy or a
one-frame delay on the chip). Its count ``n_j``, about ``T_C a_j / top`` clamped to
``[0, T_C]``, is the rate model's ring activity ``a = max(e + decay S a, 0)`` on ``T_C``
uniform levels up to ``top`` (the largest activity of the exact ring on the reference).
The place is the unit with the most spikes (first on ties),
:func:`~torchseq.neural.readout.decide`.

Calibration reads the reference only (no learning, no query). Simulated in float64 with
0/1 spikes; phases A and B do not depend on the ring, so :meth:`TimedSpikingSeqSLAM.run`
steps them for many frames at once and the ring frame by frame (the same functions as
:meth:`~TimedSpikingSeqSLAM.forward`). Measured agreement and the hardware budget:
``docs/results/nir.md`` ("The timed model").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np
import torch
from torch import nn

from torchseq.neural.readout import decide
from torchseq.neural.spiking import SpikingError, check_convertible, quantise_rows

INHIBIT = 1e9  # the inhibitory current of a fired L2 unit on itself and of the counter
RING_KERNELS = ("closed", "stepped")
NORM_KERNELS = ("torch", "numba")
SPIKING_POPULATIONS = ("l2", "counter", "rate", "window", "ring")  # IF; the rest integrate
DRIVE_GRID = 2.0 ** -32  # phase C's currents are multiples of this (exact sums in float64)
DRIVE_MAX = 2.0 ** 16  # and clamped here (>= 2 fires every step, <= 0 never)


@dataclass(frozen=True)
class TimedConfig:
    """Settings of the timed conversion (``docs/results/nir.md``, "The timed model").

    Attributes:
        l2_steps: phase A's steps (the k-WTA's time resolution).
        norm_steps: the reference's median window of phase B (its resolution).
        norm_max_steps: phase B's length; None: ``6 * norm_steps``.
        ring_steps: phase C's steps (the ring's uniform levels).
        widen: phase A's range is the reference's ``k``-th sums widened by this much of
            itself on each side.
        first: phase B's first rung above 0, in reference median stds.
        ratio: phase B's rungs grow by this factor.
        chunk: frames stepped together through phases A and B.
        weight_bits: None: float weights. An int ``b`` in 2..16: the graph's weight
            matrices on signed ``b``-bit grids, one power-of-two scale per row.
        ring_kernel: phase C's kernel, ``"closed"`` (its spike count in closed form) or
            ``"stepped"`` (step by step): the same counts (:func:`ring_by_rate`).
        norm_kernel: phase B's kernel, ``"numba"`` (compiled, frame by frame) or
            ``"torch"`` (frames stepped together): the same spikes (:func:`divide_by_timing`).
    """

    l2_steps: int = 256
    norm_steps: int = 256
    norm_max_steps: int | None = None
    ring_steps: int = 4096
    widen: float = 0.25
    first: float = 0.25
    ratio: float = 2.0
    chunk: int = 64
    ring_kernel: str = "closed"
    norm_kernel: str = "numba"
    weight_bits: int | None = None

    def validate(self) -> None:
        """Raise :class:`SpikingError` on an impossible setting."""
        for name in ("l2_steps", "norm_steps", "ring_steps", "chunk"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 2**20:
                raise SpikingError(f"{name} must be an int in 1..2**20, got {v!r}")
        b = self.weight_bits
        if b is not None and (isinstance(b, bool) or not isinstance(b, int) or not 2 <= b <= 16):
            raise SpikingError(f"weight_bits must be None or an int in 2..16, got {b!r}")
        if self.norm_kernel not in NORM_KERNELS:
            raise SpikingError(f"norm_kernel must be one of {NORM_KERNELS}, got "
                               f"{self.norm_kernel!r}")
        if self.ring_kernel not in RING_KERNELS:
            raise SpikingError(f"ring_kernel must be one of {RING_KERNELS}, got "
                               f"{self.ring_kernel!r}")
        m = self.norm_max_steps
        if m is not None and (isinstance(m, bool) or not isinstance(m, int)
                              or not self.norm_steps <= m <= 2**20):
            raise SpikingError(f"norm_max_steps must be None or an int in norm_steps.."
                               f"2**20, got {m!r}")
        for name, lo in (("widen", 0.0), ("first", 0.0)):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not lo <= float(v) < math.inf:
                raise SpikingError(f"{name} must be a finite number >= {lo}, got {v!r}")
        if self.first == 0:
            raise SpikingError("first must be > 0")
        if not isinstance(self.ratio, (int, float)) or not 1.0 < float(self.ratio) < math.inf:
            raise SpikingError(f"ratio must be a finite number > 1, got {self.ratio!r}")

    @property
    def phase_b_steps(self) -> int:
        """Phase B's length."""
        return self.norm_max_steps or 6 * self.norm_steps

    @property
    def steps_per_frame(self) -> int:
        """Time steps of one frame, all three phases."""
        return self.l2_steps + self.phase_b_steps + self.ring_steps


class TimedStep(NamedTuple):
    """One frame for ``B`` streams.

    Attributes:
        reference: ``(B,)`` int64 decided reference frame.
        confidence: ``(B,)`` its margin over the rivals outside the uniqueness window.
        counts: ``(B, N)`` ring spikes per output unit (the next frame's ``state``).
        winners: ``(B,)`` L2 units that fired in phase A.
        windows: ``(B, C)`` phase B's window per cohort, steps (0: clipped).
        spikes: ``{"l2", "norm", "ring"}`` ``(B,)`` spikes per phase.
        ops: ``{"a", "b", "c"}`` ``(B,)`` synaptic operations per phase
            (:meth:`TimedSpikingSeqSLAM.synaptic_ops`).
    """

    reference: torch.Tensor
    confidence: torch.Tensor
    counts: torch.Tensor
    winners: torch.Tensor
    windows: torch.Tensor
    spikes: dict
    ops: dict


def square_rungs(top: float, first: float,
                 ratio: float = 2.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Knots ``k_0 = 0 < k_1 < ...`` and weights of the rungs that square by parts.

    ``sum_r w_r max(x - k_r, 0)`` is the chord interpolant of ``x ** 2`` through the knots
    ``0, first, first * ratio, first * ratio ** 2, ...`` (``w_0 = k_1``,
    ``w_r = k_{r+1} - k_{r-1}``) up to the first knot at or above ``top``; past the last
    rung it grows linearly.

    Returns:
        ``(knots (R,), weights (R,))`` float64.
    """
    if not (0.0 < first < math.inf and 1.0 < ratio < math.inf and 0.0 < top < math.inf):
        raise SpikingError(f"square rungs need 0 < first, 1 < ratio, 0 < top, all finite; got "
                           f"{first}, {ratio}, {top}")
    k = [0.0, first]
    while k[-1] < top:
        k.append(k[-1] * ratio)
    w = [k[1]] + [k[i + 1] - k[i - 1] for i in range(1, len(k) - 1)]
    return torch.tensor(k[:-1], dtype=torch.float64), torch.tensor(w, dtype=torch.float64)


def rung_squares(c: torch.Tensor, knots: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """``sum_r w_r max(|c| - k_r, 0)`` elementwise ``(..., N)``: the rungs' ``c ** 2``."""
    return ((c.abs()[..., None] - knots).clamp_min(0.0) * weights).sum(-1)


def kwta_by_inhibition(first: torch.Tensor, k: int,
                       steps: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Phase A stepped: the L2 winners ``(F, M)`` 0/1 and the counter's spikes ``(F,)``.

    Args:
        first: ``(F, M)`` the frame's current at step 1, ``(h - hi) / span + 1``.
        k: the counter's threshold is ``k - 1/2``.
        steps: ``T_A``; every step adds ``1 / T_A``.
    """
    v = torch.zeros_like(first)
    fired = torch.zeros_like(first)
    counter = first.new_zeros(first.shape[0], 1)
    stop = first.new_zeros(first.shape[0], 1)  # the counter has fired (inhibits next step)
    counter_spikes = first.new_zeros(first.shape[0])
    for t in range(1, steps + 1):
        current = (first if t == 1 else 0.0) + 1.0 / steps
        v = v + current - INHIBIT * (stop + fired)
        z = (v > 1.0).to(first.dtype)
        v = v * (1.0 - z)
        fired = fired + z
        counter = counter + z.sum(1, keepdim=True)
        zc = (counter > k - 0.5).to(first.dtype)
        counter = counter * (1.0 - zc)
        counter_spikes = counter_spikes + zc[:, 0]
        stop = torch.maximum(stop, zc)
        if bool(stop.all()):  # every layer inhibited: nothing fires any more
            break
    return fired, counter_spikes


def l2_winners(x: torch.Tensor, w1: torch.Tensor, lo: float, hi: float, k: int,
               steps: int) -> torch.Tensor:
    """Phase A of encoded frames ``(F, D)``: their L2 winners ``(F, M)`` 0/1.

    :func:`kwta_by_inhibition` fed the step-1 current ``(x @ w1.T - hi) / (hi - lo) + 1``
    (``w1`` ``(M, D)``, ``[lo, hi]`` the ramp's range).
    """
    return kwta_by_inhibition((x @ w1.T - hi) / (hi - lo) + 1.0, k, steps)[0]


def divide_by_timing(c: torch.Tensor, cohorts: torch.Tensor, rate: float, knots: torch.Tensor,
                     weights: torch.Tensor, theta: torch.Tensor, steps: int,
                     kernel: str = "torch") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Phase B stepped: ``+`` counts ``(F, N)``, windows ``(F, C)`` (0: clipped), spikes ``(F,)``.

    Per step: every rate unit ``v <- v + x`` (``+ 1/2`` at step 1), ``z = v > 1``,
    ``v <- v - z``; a ``+`` unit of rung 0 counts while its cohort's window is open (it is
    inhibited from the step after the window fires); per cohort the increment
    ``sum_r n_r w_r / n_c`` (``n_r`` the rung's spikes, added rung by rung from 0),
    ``acc += increment``, ``window_v += acc``; the window fires once, at the first step
    ``window_v > theta``. ``spikes`` counts the rate units' (less the inhibited ``+``
    units') and windows' spikes up to the step the frame's last window closes.

    Kernels: ``"torch"`` (the definition, any batch of frames stepped together) and
    ``"numba"`` (compiled, frame by frame, firing units only: :mod:`._timed_numba`); the
    same float64 operations in the same order, so the same spikes.

    Args:
        c: ``(F, N)`` cohort-centred evidence (the L3 integrators' membranes).
        cohorts: ``(N, C)`` 0/1 membership, one cohort per unit.
        rate: spikes per step per unit of ``c``.
        knots: ``(R,)`` the rungs' thresholds (:func:`square_rungs`).
        weights: ``(R,)`` their weights.
        theta: ``(C,)`` the window units' thresholds.
        steps: the phase's length.
        kernel: ``"torch"`` or ``"numba"``.
    """
    if kernel == "torch":
        return _divide_torch(c, cohorts, rate, knots, weights, theta, steps)
    if kernel == "numba":
        return _divide_numba(c, cohorts, rate, knots, weights, theta, steps)
    raise SpikingError(f"division kernel must be one of {NORM_KERNELS}, got {kernel!r}")


def _divide_torch(c, cohorts, rate, knots, weights, theta, steps):
    n_c = cohorts.sum(0).clamp_min(1.0)
    wn = weights[None, :] / n_c[:, None]  # (C, R)
    sign = c.new_tensor([1.0, -1.0])
    x = rate * (sign[:, None, None] * c[:, None, :, None] - knots)  # (F, 2, N, R)
    v = torch.zeros_like(x)
    plus = torch.zeros_like(c)
    acc = c.new_zeros(c.shape[0], cohorts.shape[1])
    window_v = torch.zeros_like(acc)
    windows = torch.zeros_like(acc)
    open_ = torch.ones_like(c)  # the + units not yet inhibited by their window
    spikes = c.new_zeros(c.shape[0])
    for t in range(1, steps + 1):
        running = (windows == 0).any(1).to(c.dtype)  # frames with a window still open
        v = v + x + (0.5 if t == 1 else 0.0)  # the phase's start pulse: counts round
        z = (v > 1.0).to(c.dtype)
        v = v - z
        plus = plus + z[:, 0, :, 0] * open_
        counts = z.sum(1).transpose(1, 2) @ cohorts  # (F, R, C) integer spike counts
        inc = torch.zeros_like(acc)
        for r in range(knots.numel()):
            inc = inc + counts[:, r, :] * wn[:, r]
        acc = acc + inc
        window_v = window_v + acc
        fire = (window_v > theta) & (windows == 0)
        windows = torch.where(fire, torch.full_like(windows, float(t)), windows)
        # spikes that exist: a + unit of rung 0 is silent once its window inhibits it
        spikes = spikes + running * (z.sum((1, 2, 3)) - (z[:, 0, :, 0] * (1.0 - open_)).sum(1)
                                     + fire.sum(1))
        open_ = ((windows == 0).to(c.dtype) @ cohorts.T).clamp(max=1.0)
        if bool((windows > 0).all()):  # every + unit inhibited: the counts are final
            break
    return plus, windows, spikes


def _divide_numba(c, cohorts, rate, knots, weights, theta, steps):
    from torchseq.neural import _timed_numba

    g = cohorts.detach().cpu().double()
    if not bool((g.sum(1) == 1).all()):
        raise SpikingError("the numba division kernel needs one cohort per unit")
    n_c = g.sum(0).clamp_min(1.0)
    wn = (weights.detach().cpu().double()[None, :] / n_c[:, None]).numpy()
    cd = c.detach().cpu().double().contiguous().numpy()
    plus = np.zeros(cd.shape)
    windows = np.zeros((cd.shape[0], g.shape[1]))
    spikes = np.zeros(cd.shape[0])
    _timed_numba.divide(cd, g.argmax(1).numpy().astype(np.int64), float(rate),
                        knots.detach().cpu().double().numpy(), np.ascontiguousarray(wn),
                        theta.detach().cpu().double().numpy(), int(steps), plus, windows, spikes)
    return (torch.from_numpy(plus).to(c), torch.from_numpy(windows).to(c),
            torch.from_numpy(spikes).to(c))


def ring_drive(current: torch.Tensor) -> torch.Tensor:
    """Phase C's current ``(B, N)`` on its fixed-point grid: ``DRIVE_GRID`` steps, clamped.

    On the grid every membrane of :func:`ring_by_rate` is exact in float64 (at most
    ``2**16 * 2**20`` in steps of ``2**-32``), so its kernels agree spike for spike.
    """
    return torch.round(current.clamp(-DRIVE_MAX, DRIVE_MAX) / DRIVE_GRID) * DRIVE_GRID


def ring_by_rate(drive: torch.Tensor, steps: int, kernel: str = "closed") -> torch.Tensor:
    """Phase C: spike counts ``(B, N)`` of IF units (threshold 1, subtraction reset) fed ``drive``.

    ``v <- v + drive``, ``z = v > 1``, ``v <- v - z`` for ``steps`` steps from ``v = 0``.
    Kernels: ``"stepped"`` (the definition, step by step) and ``"closed"``: a constant
    current fires ``clamp(ceil(steps * drive) - 1, 0, steps)`` times (from ``v = t d - n``:
    at most one spike per step while ``d <= 1``, one every step once ``d > 1``). The same
    counts for a ``drive`` on :func:`ring_drive`'s grid (``tests/test_spiking_timed.py``).

    Args:
        drive: ``(B, N)`` the current every step.
        steps: ``T_C`` (at most ``2**20``).
        kernel: ``"closed"`` or ``"stepped"``.
    """
    if kernel == "closed":
        return _ring_closed(drive, steps)
    if kernel == "stepped":
        return _ring_stepped(drive, steps)
    raise SpikingError(f"ring kernel must be one of {RING_KERNELS}, got {kernel!r}")


def _ring_closed(drive: torch.Tensor, steps: int) -> torch.Tensor:
    return (torch.ceil(steps * drive) - 1.0).clamp(0.0, float(steps))


def _ring_stepped(drive: torch.Tensor, steps: int) -> torch.Tensor:
    v = torch.zeros_like(drive)
    n = torch.zeros_like(drive)
    for _ in range(steps):
        v = v + drive
        z = (v > 1.0).to(drive.dtype)
        v = v - z
        n = n + z
    return n


class TimedSpikingSeqSLAM(nn.Module):
    """A fitted :class:`~torchseq.neural.NeuralSeqSLAM` as a timed spiking network.

    Build it with :meth:`convert`. Buffers (float64), the graph's weights: ``w1 (M, D)``
    L1 (phase A's step-1 current is ``(x @ w1.T - hi) / span + 1``: on a chip, L2's
    threshold and ramp are ``span`` times larger), ``w3 (N, M)`` cohort-centred L3,
    ``cohorts (N, C)``, ``knots``/``rung_weights (R,)``, ``theta (C,)``, ``ring_weight
    (N,)`` (``gain / (s_c top)``: a ``+`` spike's current into the ring every step of phase
    C), ``shift (N, N)``
    (``decay * S``), ``unit_centre (N,)`` int64. With ``weight_bits`` the matrices ``w1``,
    ``w3``, ``shift`` and ``ring_weight`` are on signed ``b``-bit grids with one
    power-of-two scale per row (:func:`~torchseq.neural.spiking.quantise_rows`).
    :attr:`calibration` records the scalars.
    """

    def __init__(self, tensors: dict, calibration: dict, config: TimedConfig, k: int,
                 window: int, encode: Callable | None = None) -> None:
        super().__init__()
        for name in ("w1", "w3", "cohorts", "knots", "rung_weights", "theta",
                     "ring_weight", "shift"):
            self.register_buffer(name, tensors[name].detach().to(torch.float64).contiguous())
        self.register_buffer("unit_centre", tensors["unit_centre"].detach().clone())
        self._fans()
        self.calibration = dict(calibration)
        self.config = config
        self.ring_kernel = config.ring_kernel  # chosen here: "closed" (fast) or "stepped"
        self.norm_kernel = config.norm_kernel  # and "numba" (fast) or "torch"
        self.k = int(k)
        self.window = int(window)
        self._encode = encode

    @property
    def n_units(self) -> int:
        """Output units ``N``."""
        return self.w3.shape[0]

    def _fans(self) -> None:
        """Synapse counts for :meth:`synaptic_ops` (derived from the weights, not state)."""
        self.register_buffer("_fan_l2", (self.w3 != 0).sum(0).double() + 2.0, persistent=False)
        self._synapses_l1 = float((self.w1 != 0).sum())
        self._synapses_shift = float((self.shift != 0).sum())

    # ------------------------------------------------------------------ conversion
    @classmethod
    @torch.no_grad()
    def convert(cls, model, reference: torch.Tensor,
                config: TimedConfig | None = None) -> TimedSpikingSeqSLAM:
        """Convert a fitted rate model, calibrating on its reference traverse only.

        ``[lo, hi]``: the reference's ``k``-th L1 sums, widened. On the reference's phase-A
        winners: ``rate = 1 / max |c|``; rungs from ``first`` median cohort stds up to
        ``max |c|``; per cohort ``theta = norm_steps ** 2 * rate * median(Q) / 2`` (``Q``
        the mean rung square) and ``s_c = median(std / sqrt(Q)) sqrt(2 theta rate)``; ``top``
        the largest activity of the exact ring fed the reference's phase-B evidence.

        Args:
            model: a fitted :class:`~torchseq.neural.NeuralSeqSLAM` (centre readout, fixed
                ring, no unit search).
            reference: ``(R, H, W)`` (or RGB) frames: the traverse it learnt, ``R >= 2``.
            config: :class:`TimedConfig` (None: defaults).

        Raises:
            SpikingError: as :meth:`SpikingSeqSLAM.convert`, or a degenerate calibration
                (a blank reference, a ring that never becomes active). The reference's
                clipped phase-B windows are recorded (``calibration["reference_clipped"]``).
        """
        cfg = config or TimedConfig()
        cfg.validate()
        check_convertible(model, reference)
        mc = model.config
        w1 = model.l1.folded_weight().detach().double().cpu()  # (M, D)
        w3f = model.l3.folded_weight().detach().double().cpu()  # (N, M)
        g = model.cohorts.detach().double().cpu()  # (N, C)
        decay, gain = (float(v) for v in model.ring.params)
        s = model.ring.shift.detach().double().cpu()
        n_c = g.sum(0).clamp_min(1.0)
        try:
            x = torch.cat([model.encode(reference[i:i + cfg.chunk]).double().cpu()
                           for i in range(0, reference.shape[0], cfg.chunk)])
        except ValueError as err:
            raise SpikingError(f"reference cannot be encoded: {err}") from None
        bits = cfg.weight_bits
        h = x @ w1.T
        kth = h.topk(min(mc.k, h.shape[1]), dim=1).values[:, -1]
        lo, hi = float(kth.min()), float(kth.max())
        spread = hi - lo if hi > lo else abs(hi) or 1.0  # one reference level: any span
        lo, hi = lo - cfg.widen * spread, hi + cfg.widen * spread
        w1g = quantise_rows(w1, bits).double()  # the rate model's L1 integers fit 8 bits
        w3 = quantise_rows(w3f - g @ ((g / n_c).T @ w3f), bits).double()  # minus cohort means
        z2 = torch.cat([l2_winners(x[i:i + cfg.chunk], w1g, lo, hi, mc.k, cfg.l2_steps)
                        for i in range(0, x.shape[0], cfg.chunk)])
        c = z2 @ w3.T
        sd = (((c ** 2) @ g) / n_c).sqrt()  # (R, C)
        c_max, sd_med = float(c.abs().max()), float(sd.median())
        if not (c_max > 0 and sd_med > 0):
            raise SpikingError("the reference's L3 evidence has no spread (a blank reference?)")
        # the l3 -> rate weight: <= 1 spike per step on the reference (on the weight grid)
        rate = float(quantise_rows(torch.tensor([[1.0 / c_max]]), bits)[0, 0])
        knots, weights = square_rungs(c_max, cfg.first * sd_med, float(cfg.ratio))
        q = (rung_squares(c, knots, weights) @ g) / n_c  # (R, C)
        ratio_sq = torch.quantile(sd / q.sqrt().clamp_min(1e-300), 0.5, dim=0)
        theta = cfg.norm_steps ** 2 * rate * torch.quantile(q, 0.5, dim=0) / 2.0
        scale = g @ (gain / (ratio_sq * (2.0 * theta * rate).sqrt()))  # (N,) e = p * scale
        shift = quantise_rows(decay * s, bits).double()
        tensors = {"w1": w1g, "w3": w3, "cohorts": g, "shift": shift,
                   "knots": knots, "rung_weights": weights, "theta": theta,
                   "ring_weight": scale, "unit_centre": model.unit_centre.detach().cpu()}
        calibration = {"lo": lo, "hi": hi, "rate": rate, "top": 1.0, "decay": decay,
                       "gain": gain, "k": mc.k, "rungs": int(knots.numel()),
                       "weight_bits": bits, "reference_frames": int(reference.shape[0]),
                       "config": vars(cfg)}
        net = cls(tensors, calibration, cfg, mc.k, mc.uniqueness_window, model.encode)
        parts = [net.divide(z2[i:i + cfg.chunk]) for i in range(0, z2.shape[0], cfg.chunk)]
        e = torch.cat([p[0] for p in parts]) * scale
        windows = torch.cat([p[1] for p in parts])
        net.calibration["reference_clipped"] = int((windows == 0).sum())
        a, top = torch.zeros(e.shape[1], dtype=torch.float64), 0.0
        for t in range(e.shape[0]):  # the exact ring on the reference's evidence
            a = (e[t] + shift @ a).clamp_min(0.0)
            top = max(top, float(a.max()))
        if not top > 0:
            raise SpikingError("the ring never becomes active on the reference: nothing to scale")
        net.calibration["top"] = top
        net.ring_weight.copy_(quantise_rows((scale / top)[:, None], bits)[:, 0].double())
        return net

    # ------------------------------------------------------------------ the phases
    def winners(self, x: torch.Tensor) -> torch.Tensor:
        """Phase A: L2 winners ``(F, M)`` 0/1 of encoded frames ``(F, D)``."""
        return l2_winners(x.to(self.w1.dtype), self.w1, self.calibration["lo"],
                          self.calibration["hi"], self.k, self.config.l2_steps)

    def divide(self, z2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Phase B: ``(+ counts (F, N), windows (F, C), spikes (F,))`` of L2 winners ``(F, M)``.

        ``p_j * gain / s_c`` is the rate model's normalised, rectified L3 evidence.
        """
        return divide_by_timing(z2 @ self.w3.T, self.cohorts, self.calibration["rate"],
                                self.knots, self.rung_weights, self.theta,
                                self.config.phase_b_steps, self.norm_kernel)

    def ring(self, plus: torch.Tensor, previous: torch.Tensor) -> torch.Tensor:
        """Phase C: ring counts ``(B, N)`` from phase B's counts and the previous ring counts."""
        t = self.config.ring_steps
        drive = ring_drive(plus * self.ring_weight + (previous @ self.shift.T) / t)
        return ring_by_rate(drive, t, self.ring_kernel)

    # ------------------------------------------------------------------ frames
    def zero_state(self, batch: int) -> torch.Tensor:
        """The previous ring counts at the start of ``batch`` streams: zeros ``(B, N)``."""
        return self.w3.new_zeros(batch, self.n_units)

    def _check_x(self, x: torch.Tensor) -> torch.Tensor:
        d = self.w1.shape[1]
        if not isinstance(x, torch.Tensor) or x.dim() != 2 or x.shape[1] != d:
            raise SpikingError(f"x must be (B, {d}) encoded frames, got "
                               f"{tuple(getattr(x, 'shape', ()))}")
        if not bool(torch.isfinite(x).all()):
            raise SpikingError("x holds NaN or infinite values")
        return x.to(torch.float64)

    @torch.no_grad()
    def forward(self, x: torch.Tensor,
                state: torch.Tensor | None = None) -> tuple[TimedStep, torch.Tensor]:
        """One frame (``steps_per_frame`` time steps) for ``B`` streams.

        Args:
            x: ``(B, D)`` encoded frames (:meth:`encode`).
            state: ``(B, N)`` the previous frame's ring counts (None: zeros).

        Returns:
            ``(TimedStep, new state)``.
        """
        x = self._check_x(x)
        state = self.zero_state(x.shape[0]) if state is None else state
        if tuple(state.shape) != (x.shape[0], self.n_units):
            raise SpikingError(f"state must be ({x.shape[0]}, {self.n_units}), got "
                               f"{tuple(state.shape)}")
        z2 = self.winners(x)
        plus, windows, norm_spikes = self.divide(z2)
        return self._ring_step(z2, plus, windows, norm_spikes, state)

    def _ring_step(self, z2, plus, windows, norm_spikes, state):
        counts = self.ring(plus, state)
        reference, confidence = decide(counts, self.unit_centre, self.window)
        spikes = {"l2": z2.sum(1), "norm": norm_spikes, "ring": counts.sum(1)}
        ops = self.synaptic_ops(z2, norm_spikes, plus, windows, counts)
        return TimedStep(reference, confidence, counts, z2.sum(1), windows, spikes, ops), counts

    def synaptic_ops(self, z2: torch.Tensor, norm_spikes: torch.Tensor, plus: torch.Tensor,
                     windows: torch.Tensor, counts: torch.Tensor) -> dict:
        """Synaptic operations of one frame per stream ``(B,)``, by phase.

        Spikes cost their fan-out, integrators (graded outputs) their synapses on every step
        of their phase: ``"a"``: the input (every L1 synapse, once), each L2 spike's
        non-zero ``w3`` column and 2 (itself, the counter), the counter's spike ``M``;
        ``"b"``: ``2 N R`` (L3 -> rate) and ``C`` (accumulator -> window) every step until
        the last window closes (phase B's length where one is clipped), each rate spike 1,
        each counted ``+`` spike 1 more (the evidence integrator), each window spike ``n_c``;
        ``"c"``: ``N`` (evidence -> ring) and ``nnz(S)`` (held counts -> ring) every step of
        phase C, each ring spike 1.

        Args:
            z2: ``(B, M)`` phase A's winners.
            norm_spikes: ``(B,)`` phase B's spikes.
            plus: ``(B, N)`` phase B's ``+`` counts.
            windows: ``(B, C)`` phase B's windows (0: clipped).
            counts: ``(B, N)`` phase C's ring counts.
        """
        n, c, r = self.n_units, self.cohorts.shape[1], self.knots.numel()
        counter = (z2.sum(1) >= self.k).to(z2.dtype)
        a = self._synapses_l1 + z2 @ self._fan_l2 + counter * self.w1.shape[0]
        steps_b = torch.where((windows > 0).all(1), windows.max(1).values,
                              torch.full_like(windows[:, 0], float(self.config.phase_b_steps)))
        fired_windows = (windows > 0).to(windows.dtype) @ self.cohorts.sum(0)
        b = steps_b * (2 * n * r + c) + norm_spikes + plus.sum(1) + fired_windows
        t = self.config.ring_steps
        cc = t * (n + self._synapses_shift) + counts.sum(1)
        return {"a": a, "b": b, "c": cc}

    step = forward

    @torch.no_grad()
    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        """Frames ``(T, H, W)`` -> encoded inputs ``(T, D)`` (the rate model's encode)."""
        if self._encode is None:
            raise SpikingError("this timed model was built without the rate model's encode")
        try:
            return self._encode(frames).double().cpu()
        except ValueError as err:
            raise SpikingError(f"frames cannot be encoded: {err}") from None

    @torch.no_grad()
    def run(self, query: torch.Tensor, encoded: bool = False) -> dict:
        """Run one stream over a traverse from a zero state.

        Phases A and B of ``chunk`` frames at a time (they do not depend on the ring), the
        ring frame by frame: the same functions as :meth:`forward`, the same decisions.

        Args:
            query: ``(T, H, W)`` frames, or ``(T, D)`` encoded inputs with ``encoded=True``.
            encoded: whether ``query`` is already encoded.

        Returns:
            ``{"reference" (T,), "confidence" (T,), "counts" (T, N), "winners" (T,),
            "windows" (T, C) (0: clipped), "spikes" {"l2", "norm", "ring"} (T,) each,
            "synaptic_ops" {"a", "b", "c"} (T,) each, "steps_per_frame"}``.
        """
        x = self._check_x(query if encoded else self.encode(query))
        if x.shape[0] < 1:
            raise SpikingError("query must hold at least one frame")
        chunk = self.config.chunk
        state, out = self.zero_state(1), []
        for i in range(0, x.shape[0], chunk):
            z2 = self.winners(x[i:i + chunk])
            plus, windows, norm_spikes = self.divide(z2)
            for t in range(z2.shape[0]):
                step, state = self._ring_step(z2[t:t + 1], plus[t:t + 1], windows[t:t + 1],
                                              norm_spikes[t:t + 1], state)
                out.append(step)
        return {"reference": torch.cat([o.reference for o in out]),
                "confidence": torch.cat([o.confidence for o in out]),
                "counts": torch.cat([o.counts for o in out]),
                "winners": torch.cat([o.winners for o in out]),
                "windows": torch.cat([o.windows for o in out]),
                "spikes": {k: torch.cat([o.spikes[k] for o in out]) for k in out[0].spikes},
                "synaptic_ops": {k: torch.cat([o.ops[k] for o in out]) for k in out[0].ops},
                "steps_per_frame": self.config.steps_per_frame}

    def budget(self) -> dict:
        """The network's hardware budget, in :func:`torchseq.export.hardware_budget.check`'s form.

        Populations (neurons): ``l2`` ``M`` IF, ``counter`` 1 IF, ``l3`` ``N`` integrators,
        ``rate`` ``2 N R`` IF (the evidence pair and the rungs), ``accumulator`` ``C``
        integrators, ``window`` ``C`` IF, ``evidence`` ``N`` integrators (phase B's ``+``
        counts, held through phase C), ``ring`` ``N`` IF, ``ring_hold`` ``N`` integrators
        (the previous frame's counts). Synapses: the non-zero weights of every edge (``l2``
        inhibits itself and is inhibited by the counter: ``M`` each). Inputs: ``D`` plus
        two start channels (phase A's ramp and step-1 offset, phase B's start pulse).
        """
        m, d = self.w1.shape
        n, c = self.n_units, self.cohorts.shape[1]
        r = self.knots.numel()
        n_c = self.cohorts.sum(0)
        pops = {"l2": m, "counter": 1, "l3": n, "rate": 2 * n * r, "accumulator": c,
                "window": c, "evidence": n, "ring": n, "ring_hold": n}
        nz = {"w1": self.w1 != 0, "w3": self.w3 != 0, "shift": self.shift != 0}
        pairs = {"input->l2": int(nz["w1"].sum()), "l2->l2": m, "l2->counter": m,
                 "counter->l2": m, "l2->l3": int(nz["w3"].sum()), "l3->rate": 2 * n * r,
                 "rate->accumulator": 2 * n * r, "accumulator->window": c,
                 "window->rate": n, "rate->evidence": n, "evidence->ring": n,
                 "ring->ring_hold": n, "ring_hold->ring": int(nz["shift"].sum())}
        fan_in = {"l2": int(nz["w1"].sum(1).max()) + 2, "counter": m,
                  "l3": int(nz["w3"].sum(1).max()), "rate": 2,
                  "accumulator": int(2 * r * n_c.max()), "window": 1, "evidence": 1,
                  "ring": 1 + int(nz["shift"].sum(1).max()), "ring_hold": 1}
        fan_out = {"input": int(nz["w1"].sum(0).max()), "l2": int(nz["w3"].sum(0).max()) + 2,
                   "counter": m, "l3": 2 * r, "rate": 2, "accumulator": 1,
                   "window": int(n_c.max()), "evidence": 1, "ring": 1,
                   "ring_hold": int(nz["shift"].sum(0).max())}
        neurons = sum(pops.values())
        syn = sum(pairs.values())
        sources: dict[str, list[str]] = {}
        for pair in pairs:
            a, b = pair.split("->")
            sources.setdefault(b, []).append(a)
        sizes = dict(pops, input=d + 2)
        return {"neurons": neurons, "populations": pops, "inputs": d + 2, "outputs": n,
                "effective_synapses": syn, "effective_synapses_by_pair": pairs,
                "recurrent_synapses": pairs["l2->l2"],
                "max_fan_in": max(fan_in.values()), "max_fan_in_by_population": fan_in,
                "max_fan_out": max(fan_out.values()), "max_fan_out_by_population": fan_out,
                "population_sources": {k: sorted(v) for k, v in sources.items()},
                "population_destinations": {s: sorted(b for b, v in sources.items() if s in v)
                                            for s in sizes},
                "population_input_channels": {b: int(sum(sizes[a] for a in v))
                                              for b, v in sources.items()},
                "weight_bits": self.calibration.get("weight_bits"), "input_kind": "analog",
                # check()'s hints for this model
                "config": "convert with TimedConfig",
                "event_input": "(the timed model has no event input)",
                "memory_bytes_8bit": syn + 2 * neurons,
                "spiking_layers": sum(1 for p in pops if p in SPIKING_POPULATIONS),
                "steps_per_frame": self.config.steps_per_frame}

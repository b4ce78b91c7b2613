"""Spiking Neural SeqSLAM: the fitted rate model as leaky integrate-and-fire units (NIR semantics).

One more definition of the step beside the float (``docs/guide/neural.md`` "Step maths") and
the integer one (``docs/reference/integer_format.md``). It reads the fitted model's weights,
masks, cohorts and learnt ring shift (nothing is relearnt: whatever ``fit`` learns flows
through) plus three scales calibrated on the reference traverse, and runs **one time step
per frame**:

1. ``x`` ``(B, D)``: the model's own ``encode`` of the frame (an analog input current).
2. L1 -> L2: ``z2 = lif(x @ w1.T)``, ``w1 = l1.folded_weight() / theta2``: binary spikes of
   the L2 units whose L1 sum exceeds the calibrated threshold ``theta2`` (the rate model keeps
   exactly the ``k`` largest: this is the approximation of k-WTA, see ``docs/guide/nir.md``).
3. L3 evidence, cohort-centred and scaled, one linear map: ``e = z2 @ w3.T`` with
   ``w3 = gain * (I - G diag(1/n_c) G^T) (l3.weight * l3.mask) / sigma_c``, i.e.
   ``gain * (l3 - cohort mean) / sigma_c`` with ``sigma_c`` calibrated (the rate model
   divides by each frame's own cohort std). The centring makes ``w3`` dense.
4. Ring, a thermometer population of ``K = levels`` neurons per output unit, on a ladder of
   values ``0 = g_0 < g_1 < ... < g_K`` with thresholds ``theta_1 < ... < theta_K`` between
   them: ``u = e + (decay * S) @ q_prev`` (the learnt shift: the graph's cycle), neuron
   ``(j, k)`` gets ``u_j / theta_k``, so ``count_j = #{k : u_j > theta_k}`` and the unit's
   value is ``q_j = g_{count_j} = sum_k (g_k - g_{k-1}) * spike_jk``: the rate model's
   ``a = decay * S a + gain * z`` with ``a`` rounded onto the ladder (clamped at 0 and
   ``g_K``). Ladders: ``"geometric"`` (default) ``g_k = a_max * low^((K - k) / (K - 1))``,
   thresholds at the geometric midpoints (``g_1 / 2`` below the first); ``"uniform"``
   ``g_k = k * a_max / K``, thresholds at ``(k - 1/2) * a_max / K``.
5. Decision: the unit with the most ring spikes (first index on ties),
   :func:`~torchseq.neural.readout.decide` on the counts.

Every neuron is NIR's ``LIF`` with ``tau = dt`` (``r = 1``, ``v_leak = 0``, threshold 1,
reset to 0), stepped with Euler as snnTorch and Norse step it:
``v <- v + dt / tau * (I - v)``, ``z = v > 1``, ``v <- v * (1 - z)`` (:func:`lif_step`).
With ``tau = dt`` the units are memoryless; the network's memory is the ring's cycle.
Why one step per frame and levels in space: see ``docs/guide/nir.md`` ("Why one time step").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, NamedTuple

import torch
from torch import nn

from torchseq.neural.readout import decide
from torchseq.neural.search import refuse_export
from torchseq.quantise import factor_power_of_two

DT = 1e-4  # seconds per time step written into the NIR graph (snnTorch's importer assumes it)


class SpikingError(ValueError):
    """Bad input to the spiking model (unfitted model, bad calibration data, wrong shapes)."""


@dataclass(frozen=True)
class SpikingConfig:
    """Settings of the rate -> spiking conversion.

    The defaults (``K = 128`` rungs down to ``low = 0.01``, about 3.6% apart) follow the
    dense L2 -> L3 default of the rate model, whose winning unit leads the next one by a
    median 1.9% on the corridor (2.9% with the former 20% mask): the former ``K = 64``,
    ``low = 0.03`` (5.4% apart) tied them too often (``docs/guide/nir.md``, "Choosing the ladder").

    Attributes:
        levels: ring neurons per output unit (the thermometer code's ``K``).
        spacing: the ring's ladder of values, ``"geometric"`` or ``"uniform"``.
        low: the geometric ladder's lowest rung as a fraction of the highest.
        chunk: reference frames encoded at once during calibration.
        weight_bits: None: float32 weights. An int ``b``: every weight matrix of the graph
            (``l1``, ``l3``, ``levels``, ``shift``) quantised to signed ``b``-bit integers
            times one power-of-two scale per row (:func:`torchseq.quantise.quantise`), and
            the model runs on exactly those weights (:func:`quantise_rows`).
        input_threshold: None: the input is the analog encoded frame. A number ``t``: the
            input is events, an ON spike where the encoded pixel is above ``t`` and an OFF
            spike where it is below ``-t`` (``2 D`` input channels, :func:`input_events`);
            L1 weighs OFF spikes by ``-W1``.
    """

    levels: int = 128
    spacing: str = "geometric"
    low: float = 0.01
    chunk: int = 256
    weight_bits: int | None = None
    input_threshold: float | None = None

    def validate(self) -> None:
        """Raise :class:`SpikingError` on an impossible setting."""
        if self.weight_bits is not None and (
                isinstance(self.weight_bits, bool) or not isinstance(self.weight_bits, int)
                or not 2 <= self.weight_bits <= 16):
            raise SpikingError(f"weight_bits must be None or an int in 2..16, got "
                               f"{self.weight_bits!r}")
        if self.input_threshold is not None and (
                isinstance(self.input_threshold, bool)
                or not isinstance(self.input_threshold, (int, float))
                or not 0.0 <= float(self.input_threshold) < math.inf):
            raise SpikingError(f"input_threshold must be None or a finite number >= 0, got "
                               f"{self.input_threshold!r}")
        if not isinstance(self.levels, int) or not 1 <= self.levels <= 1024:
            raise SpikingError(f"levels must be an int in 1..1024, got {self.levels!r}")
        if self.spacing not in ("geometric", "uniform"):
            raise SpikingError(f"spacing must be 'geometric' or 'uniform', got {self.spacing!r}")
        if not isinstance(self.low, float) or not 0.0 < self.low < 1.0:
            raise SpikingError(f"low must be a float in (0, 1), got {self.low!r}")
        if not isinstance(self.chunk, int) or self.chunk < 1:
            raise SpikingError(f"chunk must be a positive int, got {self.chunk!r}")


class SpikingState(NamedTuple):
    """State between time steps (one step per frame).

    Attributes:
        v2: ``(B, M)`` L2 membranes after the step.
        v_ring: ``(B, N * K)`` ring membranes after the step.
        ring: ``(B, N * K)`` ring spikes of the step (the cycle's input to the next step).
    """

    v2: torch.Tensor
    v_ring: torch.Tensor
    ring: torch.Tensor


class SpikingStep(NamedTuple):
    """One step's output: ``reference (B,)``, ``confidence (B,)``, ``counts (B, N)``, spikes."""

    reference: torch.Tensor
    confidence: torch.Tensor
    counts: torch.Tensor
    l2_spikes: torch.Tensor
    ring_spikes: torch.Tensor


def lif_step(current: torch.Tensor, v: torch.Tensor, leak: float = 1.0,
             threshold: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """One Euler step of NIR's LIF (``v_leak = 0``, ``r = 1``, reset to 0), any shape.

    ``v <- v + leak * (current - v)`` with ``leak = dt / tau``; ``z = v > threshold``;
    ``v <- v * (1 - z)``.

    Args:
        current: ``(..., n)`` input current.
        v: ``(..., n)`` membrane before the step.
        leak: ``dt / tau`` (1: memoryless).
        threshold: firing threshold.

    Returns:
        ``(spikes (..., n) float 0/1, v after the step (..., n))``.
    """
    v = v + leak * (current - v)
    z = (v > threshold).to(current.dtype)
    return z, v * (1.0 - z)


def ladder(config: SpikingConfig, a_max: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The ring's values ``g_1..g_K`` and thresholds ``theta_1..theta_K`` (float64, ``(K,)``).

    Args:
        config: its ``levels``, ``spacing`` and ``low``.
        a_max: the top value ``g_K``.
    """
    k = config.levels
    c = torch.arange(1, k + 1, dtype=torch.float64)
    if config.spacing == "uniform":
        return c * (a_max / k), (c - 0.5) * (a_max / k)
    g = a_max * config.low ** ((k - c) / max(k - 1, 1))
    below = torch.cat([g[:1] / 2, g[:-1]])
    theta = torch.cat([g[:1] / 2, (below[1:] * g[1:]).sqrt()])
    return g, theta


def input_events(x: torch.Tensor, threshold: float) -> torch.Tensor:
    """ON/OFF events of encoded frames: ``[x > t, x < -t]`` as 0/1 floats.

    Args:
        x: ``(..., D)`` encoded frames.
        threshold: ``t >= 0``.

    Returns:
        ``(..., 2 D)``: ON events of the ``D`` pixels, then OFF events.
    """
    return torch.cat([(x > threshold), (x < -threshold)], dim=-1).to(torch.float32)


def quantise_rows(w: torch.Tensor, bits: int | None) -> torch.Tensor:
    """``w`` on a signed ``bits``-bit grid with one power-of-two scale per row (float32).

    The one quantiser (:func:`torchseq.quantise.quantise`, ``per_row=True``,
    ``power_of_two=True``, halves away from zero). Power-of-two scales keep every sum of
    spikes times weights an integer times the row's scale: exact in float32 whatever the
    summation order (below ``2**24`` steps), so the consumers' sums equal torchseq's.
    ``bits`` None returns ``w`` unchanged.

    Args:
        w: ``(rows, cols)`` weights.
        bits: 2..16, or None.
    """
    if bits is None:
        return w
    from torchseq.quantise import dequantise, quantise

    q = quantise(w.detach().cpu(), bits, per_row=True, power_of_two=True)
    return torch.from_numpy(dequantise(q)).to(torch.float32)


def l1_sum_grid(w1: torch.Tensor, input_steps: int, l1_levels: int,
                row_grids: bool = False) -> float | None:
    """The step ``q`` every L1 sum is a multiple of, or None where the sums are not on a grid.

    With the model's integer grids (:mod:`torchseq.quantise`: inputs multiples of
    ``1 / input_steps``, weights integers times one power of two ``s``) every sum is an
    integer times ``q = s / input_steps``, exact in float32 whatever the order.

    Args:
        w1: ``(M, D)`` folded L1 weights.
        input_steps: the model's ``input_steps`` (0: float input, no grid).
        l1_levels: the model's ``l1_levels`` (0: float weights, no grid).
        row_grids: the rows were quantised on power-of-two grids of their own
            (:func:`quantise_rows`): the step is the finest row step over ``input_steps``.
    """
    if not input_steps:
        return None
    factored = factor_power_of_two(w1, l1_levels) if l1_levels else None
    if factored is not None:
        return factored[1] / input_steps
    if not row_grids:
        return None
    # rows on power-of-two grids of their own (quantise_rows): every sum is a multiple of the
    # finest row step
    a = w1.detach().double().abs()
    nz = a[a > 0]
    if nz.numel() == 0:
        return None
    e = torch.floor(torch.log2(nz.min())).item()
    for _ in range(64):  # the largest power-of-two step every weight is a multiple of
        q = a / 2.0 ** e
        if torch.equal(q, torch.round(q)):
            return 2.0 ** e / input_steps
        e -= 1
    return None


def check_convertible(model, reference: torch.Tensor) -> None:
    """Raise :class:`SpikingError` unless ``model`` and ``reference`` can be made spiking.

    A fitted rate model with the centre readout, a fixed ring and no unit search, and a
    reference of ``R >= 2`` frames ``(R, H, W)`` (or RGB).
    """
    refuse_export(model, "the spiking (NIR) form", SpikingError)
    if not getattr(model, "fitted", False):
        raise SpikingError("the model has not learnt a route yet: call fit(reference) first")
    if not isinstance(reference, torch.Tensor) or reference.dim() not in (3, 4) \
            or reference.shape[0] < 2:
        raise SpikingError("reference must be a (R, H, W) tensor of R >= 2 frames, got "
                           f"{getattr(reference, 'shape', type(reference).__name__)}")
    mc = model.config
    if mc.readout != "centre":  # the decision would silently differ from the rate model's
        raise SpikingError(f"the spiking network reads each unit's centre frame; the rate "
                           f"model's readout={mc.readout!r} has no spiking (or NIR) form "
                           f"yet: convert a model with readout='centre'")
    if getattr(mc, "ring_velocity", "fixed") != "fixed":  # a silently fixed ring otherwise
        raise SpikingError(f"ring_velocity={mc.ring_velocity!r} has no spiking (or NIR) form "
                           "(the spiking ring moves at the reference speed): convert a "
                           "model with ring_velocity='fixed'")


class SpikingSeqSLAM(nn.Module):
    """A fitted :class:`~torchseq.neural.NeuralSeqSLAM` as a spiking network (one step per frame).

    Build it with :meth:`convert`. Buffers (all float32): ``w1 (M, D)``, ``w3 (N, M)``,
    ``inv_theta (K,)`` (``1 / theta_k``), ``rung_step (K,)`` (``g_k - g_{k-1}``),
    ``shift (N, N)`` (the learnt shift times ``decay``), ``unit_centre (N,)`` int64.
    :attr:`calibration` records ``theta2``, ``sigma (C,)``, ``a_max``, the ladder and what
    they came from.

    Args: see :meth:`convert`.
    """

    def __init__(self, w1, w3, inv_theta, step, shift, unit_centre, window: int,
                 calibration: dict, encode: Callable | None = None,
                 shift_dense: torch.Tensor | None = None,
                 input_threshold: float | None = None) -> None:
        super().__init__()
        for name, t in (("w1", w1), ("w3", w3), ("inv_theta", inv_theta),
                        ("rung_step", step), ("shift", shift)):
            self.register_buffer(name, t.detach().to(torch.float32).contiguous())
        # the cycle's kernel, chosen here: "factored" (shift (N, N) times the rung steps
        # (K,), float weights) or "dense" (the (N, N K) matrix of the graph's shift node,
        # quantised row by row: it does not factor)
        self.register_buffer("shift_dense", None if shift_dense is None else
                             shift_dense.detach().to(torch.float32).contiguous())
        self.shift_kernel = "factored" if shift_dense is None else "dense"
        self.input_threshold = None if input_threshold is None else float(input_threshold)
        self.register_buffer("unit_centre", unit_centre.detach().clone())
        # synapse counts for synaptic_ops (derived, not state)
        self.register_buffer("_fan_l2", (self.w3 != 0).sum(0).float(), persistent=False)
        fan_ring = ((self.shift != 0).sum(0).float().repeat_interleave(self.inv_theta.shape[0])
                    if shift_dense is None else (self.shift_dense != 0).sum(0).float())
        self.register_buffer("_fan_ring", fan_ring, persistent=False)
        self._synapses_l1 = float((self.w1 != 0).sum())
        self.register_buffer("_fan_input", (self.w1 != 0).sum(0).float(), persistent=False)
        self.window = int(window)
        self.calibration = dict(calibration)
        self._encode = encode

    # ------------------------------------------------------------------ sizes
    @property
    def n_units(self) -> int:
        """Output units ``N``."""
        return self.w3.shape[0]

    @property
    def levels(self) -> int:
        """Ring neurons per unit ``K``."""
        return self.inv_theta.shape[0]

    @property
    def sizes(self) -> dict[str, int]:
        """``input D``, ``l2 M``, ``units N``, ``levels K``, ``ring N * K``."""
        m, d = self.w1.shape
        return {"input": d, "l2": m, "units": self.n_units, "levels": self.levels,
                "ring": self.n_units * self.levels}

    # ------------------------------------------------------------------ conversion
    @classmethod
    @torch.no_grad()
    def convert(cls, model, reference: torch.Tensor,
                config: SpikingConfig | None = None) -> SpikingSeqSLAM:
        """Convert a fitted rate model, calibrating three scales on its reference traverse.

        Calibration (no learning): ``theta2`` = median over reference frames of the midpoint
        between the ``k``-th and ``k+1``-th largest L1 sums (so about ``k`` L2 units fire),
        moved to the middle of its cell of the L1 sums' grid where they have one
        (:func:`l1_sum_grid`): no sum can then sit on the threshold, so the L2 code is the
        same in float32, float64 and any consumer's summation order;
        ``sigma_c`` = median over reference frames of cohort ``c``'s std of the L3 evidence
        of those spikes; the ladder's top ``g_K = a_max``, the largest activity of the
        unquantised ring ``a = max(e + decay * S a, 0)`` over the reference.

        Args:
            model: a fitted :class:`~torchseq.neural.NeuralSeqSLAM`.
            reference: ``(R, H, W)`` (or RGB) frames: the traverse it learnt, ``R >= 2``.
            config: :class:`SpikingConfig` (None: defaults).

        Raises:
            SpikingError: an unfitted model, a readout other than ``"centre"``, a bad
                reference, or a degenerate calibration.
        """
        cfg = config or SpikingConfig()
        cfg.validate()
        check_convertible(model, reference)
        mc = model.config
        w1 = model.l1.folded_weight().detach().float().cpu()  # (M, D)
        w3f = model.l3.folded_weight().detach().float().cpu()  # (N, M)
        g = model.cohorts.detach().float().cpu()  # (N, C)
        decay, gain = (float(v) for v in model.ring.params)
        s = model.ring.shift.detach().float().cpu()  # (N, N)
        k = mc.k
        try:
            x = torch.cat([model.encode(reference[i:i + cfg.chunk]).float().cpu()
                           for i in range(0, reference.shape[0], cfg.chunk)])
        except ValueError as err:
            raise SpikingError(f"reference cannot be encoded: {err}") from None
        events = cfg.input_threshold is not None
        if events:  # ON/OFF events in, OFF weighted by -W1
            x = input_events(x, float(cfg.input_threshold))
            w1 = torch.cat([w1, -w1], dim=1)
        bits = cfg.weight_bits
        # quantised before theta2 is calibrated, so theta2 sees the deployed sums (the rate
        # model's L1 integers (|n| <= 64 times a power of two) already fit 8 bits: unchanged)
        w1 = quantise_rows(w1, bits)
        h = x @ w1.T  # (R, M)
        top = h.topk(min(k + 1, h.shape[1]), dim=1).values
        theta2 = float(torch.quantile((top[:, k - 1] + top[:, -1]) / 2, 0.5))
        if not theta2 > 0:
            raise SpikingError(f"degenerate L2 threshold {theta2} (a blank reference?)")
        steps = 1 if events else mc.input_steps
        grid = l1_sum_grid(w1, steps, mc.l1_levels, row_grids=bits is not None)
        if grid is not None:  # halfway between two attainable sums: no sum ever ties with it
            theta2 = (math.floor(theta2 / grid) + 0.5) * grid
        z2 = (h > theta2).float()
        w1n = w1 / theta2  # the graph's l1 (threshold 1)
        n_c = g.sum(0).clamp_min(1.0)  # (C,)
        e = z2 @ w3f.T  # (R, N)
        mu = (e @ g) / n_c  # (R, C)
        var = (((e - mu @ g.T) ** 2) @ g) / n_c
        sigma = torch.quantile(var.sqrt(), 0.5, dim=0).clamp_min(mc.eps)  # (C,)
        centred = w3f - g @ ((g / n_c).T @ w3f)  # (N, M): minus the cohort's mean row
        w3 = quantise_rows(centred * (g @ (gain / sigma))[:, None], bits)
        ev = z2 @ w3.T  # (R, N)
        a, a_max = torch.zeros(ev.shape[1]), 0.0
        for t in range(ev.shape[0]):  # unquantised ring on the reference
            a = (ev[t] + decay * (s @ a)).clamp_min(0.0)
            a_max = max(a_max, float(a.max()))
        if not a_max > 0:
            raise SpikingError("the ring never becomes active on the reference: nothing to scale")
        g, theta = ladder(cfg, a_max)
        calibration = {"theta2": theta2, "l1_grid": grid, "sigma": [float(v) for v in sigma],
                       "weight_bits": bits, "input_threshold": cfg.input_threshold,
                       "a_max": a_max,
                       "decay": decay, "gain": gain, "k": k, "levels": cfg.levels,
                       "spacing": cfg.spacing, "low": cfg.low,
                       "ladder": [float(v) for v in g], "thresholds": [float(v) for v in theta],
                       "reference_frames": int(reference.shape[0])}
        step = g - torch.cat([g.new_zeros(1), g[:-1]])
        inv_theta = quantise_rows((1.0 / theta).float()[:, None], bits)[:, 0]
        dense = None
        if bits is not None:  # the graph's (N, N K) shift matrix, quantised row by row
            dense = quantise_rows(torch.kron(s * decay, step.float()[None, :]), bits)
        return cls(w1n, w3, inv_theta, step.float(), s * decay,
                   model.unit_centre.detach().cpu(), mc.uniqueness_window, calibration,
                   model.encode, shift_dense=dense, input_threshold=cfg.input_threshold)

    # ------------------------------------------------------------------ the step
    def zero_state(self, batch: int) -> SpikingState:
        """The state at the start of ``batch`` streams (all membranes and spikes 0)."""
        n = self.n_units * self.levels
        z = self.w1.new_zeros
        return SpikingState(z(batch, self.w1.shape[0]), z(batch, n), z(batch, n))

    def forward(self, x: torch.Tensor,
                state: SpikingState | None = None) -> tuple[SpikingStep, SpikingState]:
        """One time step (one frame) for ``B`` streams.

        Args:
            x: ``(B, D)`` encoded frames (the rate model's ``encode``).
            state: from the previous step (None: zeros).

        Returns:
            ``(SpikingStep, new state)``.
        """
        if x.dim() != 2 or x.shape[1] != self.w1.shape[1]:
            raise SpikingError(f"x must be (B, {self.w1.shape[1]}), got {tuple(x.shape)}")
        if state is None:
            state = self.zero_state(x.shape[0])
        b, n, k = x.shape[0], self.n_units, self.levels
        if tuple(state.ring.shape) != (b, n * k) or tuple(state.v2.shape) != (b, self.w1.shape[0]):
            raise SpikingError(f"state is for {tuple(state.ring.shape)} ring neurons, the step "
                               f"needs ({b}, {n * k})")
        z2, v2 = lif_step(x.to(self.w1.dtype) @ self.w1.T, state.v2)
        if self.shift_dense is None:  # (B, N): last step's ring values, then the shift
            cycle = (state.ring.view(b, n, k) @ self.rung_step) @ self.shift.T
        else:
            cycle = state.ring @ self.shift_dense.T
        u = z2 @ self.w3.T + cycle
        drive = (u[:, :, None] * self.inv_theta).reshape(b, n * k)  # (B, N * K)
        zr, vr = lif_step(drive, state.v_ring)
        counts = zr.view(b, n, k).sum(-1)
        reference, confidence = self.decide(counts)
        return SpikingStep(reference, confidence, counts, z2, zr), SpikingState(v2, vr, zr)

    step = forward

    def decide(self, counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(reference (B,), confidence (B,))`` from ring spike counts ``(B, N)``."""
        return decide(counts, self.unit_centre, self.window)

    def _input_ops(self, x: torch.Tensor | None, batch: int) -> torch.Tensor:
        if self.input_threshold is not None and x is not None:  # events: their synapses
            return x @ self._fan_input
        return self.w1.new_full((batch,), self._synapses_l1)  # analog: every L1 synapse

    def synaptic_ops(self, l2_spikes: torch.Tensor, ring_spikes: torch.Tensor,
                     x: torch.Tensor | None = None) -> torch.Tensor:
        """Synaptic operations of one step per stream ``(B,)``, on the exported graph.

        ``nnz(w1)`` (the analog input drives every L1 synapse; event input: the L1 synapses
        of the events ``x``) + the non-zero ``w3`` entries of the L2 units that fired +
        ``N * K`` (each unit's current to its ``K`` levels) + the non-zero shift entries of
        the ring neurons that fired (per spike).

        Args:
            l2_spikes: ``(B, M)``.
            ring_spikes: ``(B, N * K)``.
            x: ``(B, D)`` the step's input (needed for event input), or None.
        """
        return (self._input_ops(x, l2_spikes.shape[0]) + l2_spikes @ self._fan_l2
                + self.n_units * self.levels + ring_spikes @ self._fan_ring)

    def chip_ops(self, l2_spikes: torch.Tensor, ring_spikes: torch.Tensor,
                 x: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Synaptic operations of one step ``(B,)`` on a chip holding the effective synapses.

        A chip without analog intermediate layers holds ``levels @ l3`` and
        ``levels @ shift`` multiplied out (``hardware_budget``): an L2 spike reaches the
        ``K`` ring neurons of every unit its ``w3`` column reaches, a ring spike the ``K``
        ring neurons of every unit its shift column reaches.

        Returns:
            ``{"input", "l2", "ring"}``: the operations driven by the input, by L2 spikes
            and by ring spikes.
        """
        return {"input": self._input_ops(x, l2_spikes.shape[0]),
                "l2": (l2_spikes @ self._fan_l2) * self.levels,
                "ring": (ring_spikes @ self._fan_ring) * self.levels}

    def counts(self, ring_spikes: torch.Tensor) -> torch.Tensor:
        """Spike counts per unit ``(..., N)`` of ring spikes ``(..., N * K)``."""
        return ring_spikes.reshape(*ring_spikes.shape[:-1], self.n_units, self.levels).sum(-1)

    @torch.no_grad()
    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        """The graph's input: frames ``(T, H, W)`` -> ``(T, D)`` (the rate model's encode).

        With ``input_threshold`` the encoded frames become ON/OFF events ``(T, 2 D)``
        (:func:`input_events`).
        """
        if self._encode is None:
            raise SpikingError("this spiking model was built without the rate model's encode")
        try:
            x = self._encode(frames).float().cpu()
        except ValueError as err:  # the rate model's NeuralError: shapes, NaN, ...
            raise SpikingError(f"frames cannot be encoded: {err}") from None
        return x if self.input_threshold is None else input_events(x, self.input_threshold)

    @torch.no_grad()
    def run(self, query: torch.Tensor, encoded: bool = False, raster: bool = False) -> dict:
        """Run one stream over a traverse from a zero state.

        Args:
            query: ``(T, H, W)`` frames, or ``(T, D)`` encoded inputs with ``encoded=True``.
            encoded: whether ``query`` is already encoded.
            raster: also return the ring spikes ``"raster"`` ``(T, N * K)``.

        Returns:
            ``{"reference" (T,), "confidence" (T,), "l2_spikes" (T,), "ring_spikes" (T,),
            "input_events" (T,) (0 for analog input), "synaptic_ops" (T,) (on the graph),
            "chip_ops" {"input", "l2", "ring"} (T,) each (:meth:`chip_ops`), "counts"
            (T, N)}`` (totals per frame), and ``"raster"`` if asked.
        """
        x = query.float() if encoded else self.encode(query)
        if x.dim() != 2 or x.shape[0] < 1:
            raise SpikingError(f"query must hold at least one frame, got {tuple(x.shape)}")
        state, out = None, []
        for t in range(x.shape[0]):
            step, state = self.forward(x[t:t + 1], state)
            out.append(step)
        chip = [self.chip_ops(o.l2_spikes, o.ring_spikes, x[t:t + 1]) for t, o in enumerate(out)]
        return {"reference": torch.cat([o.reference for o in out]),
                "confidence": torch.cat([o.confidence for o in out]),
                "l2_spikes": torch.stack([o.l2_spikes.sum() for o in out]),
                "ring_spikes": torch.stack([o.ring_spikes.sum() for o in out]),
                "input_events": (x.sum(1) if self.input_threshold is not None
                                 else torch.zeros(x.shape[0])),
                "synaptic_ops": torch.cat([self.synaptic_ops(o.l2_spikes, o.ring_spikes,
                                                             x[t:t + 1])
                                           for t, o in enumerate(out)]),
                "chip_ops": {k: torch.cat([c[k] for c in chip]) for k in chip[0]},
                "counts": torch.cat([o.counts for o in out]),
                **({"raster": torch.cat([o.ring_spikes for o in out])} if raster else {})}

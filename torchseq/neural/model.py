"""``NeuralSeqSLAM``: a rate-coded place-recognition network whose memory is bounded.

L1 (patch-normalised pixels) -> fixed random ``MaskedLinear`` -> L2 binary k-WTA code ->
Hebbian ``MaskedLinear`` -> L3 evidence, z-scored within cohorts -> ``OutputRing`` that
shifts activity along the learnt route -> the most active unit is the place. The exact
equations of one step are in ``docs/guide/neural.md`` ("Step maths").
"""

from __future__ import annotations

import math
import warnings
from dataclasses import replace
from pathlib import Path

import torch
from torch import nn

from torchseq._checks import as_frames
from torchseq.layers import KWinnersTakeAll, MaskedLinear, OutputRing, RingState
from torchseq.layers.functional import cohort_normalise
from torchseq.neural import advice, memory
from torchseq.neural.checkpoint import load_model, save_checkpoint
from torchseq.neural.checks import checked_grey, checked_state
from torchseq.neural.config import NeuralConfig, NeuralError
from torchseq.neural.inference import NeuralInference
from torchseq.neural.learning import (
    cohort_membership,
    learn_readout,
    recruit_by_novelty,
    recruit_units,
)
from torchseq.neural.memory import seqslam_bytes
from torchseq.neural.progress import Progress, as_progress
from torchseq.neural.progress import chunks as _chunks
from torchseq.neural.readout import decide
from torchseq.neural.results import NeuralFitLog, NeuralResult, NeuralStep
from torchseq.neural.search import (
    UnitSearch,
    decision_stage,
    resolve_search,
    search_active,
    search_step,
    sequence_frames,
)
from torchseq.neural.selfcheck import disturbed, self_recall
from torchseq.neural.velocity import VelocityTracker, adaptive_step
from torchseq.preprocess import patch_normalise, quantise_input, zscore_blocks
from torchseq.quantise import integer_weights

__all__ = ["NeuralFitLog", "NeuralResult", "NeuralSeqSLAM", "NeuralStep", "seqslam_bytes"]


class NeuralSeqSLAM(nn.Module):
    """Neural SeqSLAM: learn a route in one pass with local rules, recognise it streaming.

    Args:
        config: settings (None: :class:`NeuralConfig` defaults).
        device: where buffers live.
    """

    def __init__(self, config: NeuralConfig | None = None, device=None) -> None:
        super().__init__()
        self.config = (config or NeuralConfig()).validate()
        cfg = self.config
        self._unit_search = cfg.unit_search  # as asked: fit resolves "auto" per route
        self.l1 = MaskedLinear(cfg.n_input, cfg.hidden, cfg.density, bias=False, seed=cfg.seed,
                               device=device)
        self.l1.weight.requires_grad_(False)
        if cfg.l1_levels:
            with torch.no_grad():
                bound = math.sqrt(3.0 / self.l1.fan_in)  # MaskedLinear's uniform init
                self.l1.weight.copy_(integer_weights(self.l1.weight, bound, cfg.l1_levels))
        self.l2 = KWinnersTakeAll(k=cfg.k, binary=True)
        self.l3: MaskedLinear | None = None
        self.ring: OutputRing | None = None
        self.self_check: float | None = None  # set by fit (selfcheck.py)
        self.search: UnitSearch | None = None  # set by fit where the route needs it (search.py)

    # ------------------------------------------------------------------ structure
    @property
    def n_units(self) -> int:
        """Output units in use (0 before :meth:`fit`)."""
        return 0 if self.l3 is None else self.l3.out_features

    @property
    def fitted(self) -> bool:
        """True once the model has learnt a route."""
        return self.l3 is not None

    def _build_output(self, n_units: int) -> None:
        cfg, dev = self.config, self.l1.weight.device
        self.l3 = MaskedLinear(cfg.hidden, n_units, cfg.density_out, bias=False,
                               seed=cfg.seed + 1, device=dev)
        self.l3.weight.requires_grad_(False)
        self.ring = OutputRing(n_units, cfg.ring_decay, cfg.gain, cfg.ring_spread,
                               cfg.ring_spread_decay, cfg.ring_stay, cfg.ring_wrap, device=dev)
        self.register_buffer("cohorts", cohort_membership(n_units, cfg.n_cohorts).to(dev))
        self.register_buffer("unit_to_reference", torch.zeros(n_units, 2, dtype=torch.int64,
                                                              device=dev))
        self.register_buffer("unit_centre", torch.zeros(n_units, dtype=torch.int64, device=dev))

    @property
    def stage(self) -> str:
        """The stage that decides: ``"ring"``, ``"adaptive ring"`` or ``"unit search"`` (fit)."""
        return decision_stage(self.config, self.search is not None)

    @property
    def sequence_frames(self) -> float:
        """Query frames a decision integrates (:func:`~torchseq.neural.search.sequence_frames`)."""
        return sequence_frames(self.config, self.stage)

    @property
    def readout_spans(self) -> torch.Tensor | None:
        """``unit_to_reference`` when the config reads positions within units, else None."""
        return self.unit_to_reference if self.config.readout == "interpolate" else None

    def _require_fit(self) -> None:
        if not self.fitted:
            raise NeuralError("the model has not learnt a route yet: call fit(reference) first")

    # ------------------------------------------------------------------ the step maths
    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        """Preprocess raw frames into L1 activity.

        Args:
            frames: ``(B, H, W)`` grey or ``(B, H, W, 3)`` RGB, any size, 0..255.

        Returns:
            ``(B, input_size[0] * input_size[1])`` float32 (on the ``1 / input_steps`` grid).
        """
        cfg = self.config
        x = self._grey(frames)  # (B, h, w)
        if cfg.patch_size and cfg.patch_mode == "zscore":
            z = zscore_blocks(x, cfg.patch_size)  # (B, blocks, p*p), block-major
            p, (h, w) = cfg.patch_size, cfg.input_size
            x = z.reshape(-1, h // p, w // p, p, p).permute(0, 1, 3, 2, 4)  # back to rows
        elif cfg.patch_size:
            # OpenSeqSLAM's 127 + round(z), centred on 0
            x = patch_normalise(x, cfg.patch_size, cfg.patch_mode) - 127.0
        return quantise_input(x.reshape(x.shape[0], -1), cfg.input_steps)

    def _grey(self, frames: torch.Tensor) -> torch.Tensor:
        """Checked raw frames -> float32 grey ``(B, h, w)`` at the input size."""
        return checked_grey(frames, self.config.input_size, self.l1.weight.device)

    def code(self, x: torch.Tensor) -> torch.Tensor:
        """L1 -> L2: random masked projection then binary k-WTA. ``(B, 768) -> (B, hidden)``."""
        return self.l2(self.l1(x))

    def evidence(self, code: torch.Tensor) -> torch.Tensor:
        """L2 -> L3 evidence, z-scored within cohorts, rectified. ``(B, hidden) -> (B, N)``."""
        z = cohort_normalise(self.l3(code), self.cohorts, self.config.eps)
        return z.clamp_min(0.0) if self.config.rectify else z

    def step(self, frames: torch.Tensor,
             state: RingState | None = None) -> tuple[NeuralStep, RingState]:
        """One streaming step for ``B`` independent streams, through the model's layers.

        This is the definition (eager ``nn.Module`` layers, any device and grad mode). For
        streaming, hold :meth:`inference`'s module and call its ``step``: the same numbers
        through one named fast kernel per stage, about five times faster at batch 1
        (``docs/results/neural-step.md``). Nothing the model was called with before changes
        what this method runs.

        Args:
            frames: ``(B, H, W)`` (or ``(B, H, W, 3)``) one new frame per stream.
            state: ring state from the previous step (None: start of the streams): a
                :class:`~torchseq.layers.RingState` (a
                :class:`~torchseq.neural.VelocityState` is taken too: its ``activity``), or
                with ``ring_velocity="adaptive"`` a :class:`~torchseq.neural.VelocityState`
                (activity, speed estimates and the window of recent decisions); another type
                is a :class:`NeuralError`.

        Returns:
            ``(NeuralStep, new state)``.
        """
        self._require_fit()
        adaptive = self.config.ring_velocity == "adaptive"
        tracker = VelocityTracker.from_model(self) if adaptive else None
        if self.search is not None:  # the unit search decides (neural/search.py)
            return search_step(self, frames, state)
        state = checked_state(state, frames.shape[0], self.n_units, tracker)
        e = self.evidence(self.code(self.encode(frames)))  # (B, N)
        if adaptive:  # the ring at each stream's speed estimate (neural/velocity.py)
            activity, reference, confidence, state = adaptive_step(
                e, state if state is not None else tracker.initial(e),
                self.ring.shift.to(e.dtype), self.ring.params, None,
                lambda a: decide(a, self.unit_centre, self.config.uniqueness_window,
                                 spans=self.readout_spans), tracker)
            return NeuralStep(reference, confidence, activity), state
        activity, state = self.ring(e, state)
        reference, confidence = decide(activity, self.unit_centre,
                                       self.config.uniqueness_window, spans=self.readout_spans)
        return NeuralStep(reference, confidence, activity), state

    forward = step

    # ------------------------------------------------------------------ learning
    @torch.no_grad()
    def fit(self, reference: torch.Tensor, progress: bool | Progress | None = None,
            log: bool = True, check: bool = True) -> NeuralFitLog:
        """Learn a route from one pass over its reference traverse (local rules, no backprop).

        Units are recruited along the route in order (unit ``u`` stands for a contiguous
        stretch of frames, :func:`~torchseq.neural.learning.recruit_units`, or with
        ``recruit="novelty"`` :func:`~torchseq.neural.learning.recruit_by_novelty`, which
        first keeps the route's L2 codes as ``(T, k)`` winner indices); L2 -> L3 weights
        follow the configured Hebbian rule (:func:`~torchseq.neural.learning.hebbian_weights`);
        the ring's shift matrix learns from the order in which units fired. The stage that
        decides is resolved here from the reference's length
        (:func:`~torchseq.neural.search.resolve_search`) and kept in :attr:`config`
        (``unit_search`` ``"on"`` or ``"off"``; :attr:`stage` names it).

        Args:
            reference: ``(T, H, W)`` or ``(T, H, W, 3)`` frames, any size, 0..255, ``T >= 2``
                (a tensor or a NumPy array).
            progress: a callback ``(frames done, frames in all)`` (``True``: a tqdm bar).
            log: also compute the reference evidence raster (a second feed-forward pass).
            check: the self-check (:mod:`torchseq.neural.selfcheck`, one more feed-forward
                pass): the share of the reference frames, lightly disturbed, whose winning unit
                holds them, kept as :attr:`self_check` and in the log; under
                :data:`~torchseq.neural.selfcheck.SELF_CHECK_FLOOR` it warns once.

        Returns:
            :class:`NeuralFitLog`.
        """
        reference = as_frames(reference, "reference")
        if reference.dim() not in (3, 4) or reference.shape[0] < 2:
            raise NeuralError(f"reference must be (T, H, W) with T >= 2 frames, got "
                              f"{tuple(reference.shape)}")
        t_len = reference.shape[0]
        n_units = min(t_len, self.config.n_output)
        # the stage that decides, resolved once from the reference and kept in the config
        stage = resolve_search(replace(self.config, unit_search=self._unit_search), t_len,
                               n_units)
        self.config = cfg = replace(self.config, unit_search=stage)
        self._build_output(n_units)
        _warn(advice.coarse_units(t_len, n_units, cfg.readout, stage == "on"),
              advice.adaptive_units(t_len, n_units, cfg.ring_velocity),
              advice.novelty_without_effect(t_len, cfg.n_output, cfg.recruit))
        dev = self.l1.weight.device
        codes = ((lo, hi, self.code(self.encode(reference[lo:hi])))
                 for lo, hi in _chunks(t_len, cfg.chunk, as_progress(progress, "fit")))
        if cfg.recruit == "novelty" and n_units < t_len:
            winners = _winners(codes, cfg.k)  # (T, k): the codes, kept for the second use
            unit_of_frame, spans = recruit_by_novelty(winners, n_units)
            codes = _codes_of(winners, cfg.hidden, cfg.chunk, dev)
        else:
            unit_of_frame, spans = recruit_units(t_len, n_units)
        self.l3.weight.copy_(learn_readout(codes, unit_of_frame, spans, self.l3.mask,
                                           cfg.hebbian, cfg.eps, cfg.l3_levels))
        self.ring.learn(unit_of_frame)
        self.unit_to_reference.copy_(spans.to(dev))
        self.unit_centre.copy_(((spans[:, 0] + spans[:, 1] - 1) // 2).to(dev))
        self._build_search()
        evidence = torch.empty(0, n_units)
        if log:
            parts = [self.evidence(self.code(self.encode(reference[lo:hi])))
                     for lo, hi in _chunks(t_len, cfg.chunk)]
            evidence = torch.cat(parts).cpu()
        self.self_check = self._self_check(reference) if check else None
        if check:
            _warn(advice.self_check(self.self_check, t_len, n_units, self.search is not None))
        return NeuralFitLog(unit_of_frame, evidence, spans, self.self_check)

    def _self_check(self, reference: torch.Tensor) -> float:
        """:func:`~torchseq.neural.selfcheck.self_recall` of the reference, disturbed."""
        gen = torch.Generator().manual_seed(self.config.seed % 2**63)
        units = [self.l3(self.code(disturbed(self.encode(reference[lo:hi]), gen))).argmax(1)
                 for lo, hi in _chunks(reference.shape[0], self.config.chunk)]
        return self_recall(torch.cat(units), self.unit_to_reference)

    # ------------------------------------------------------------------ recognition
    def inference(self, kernels: str | dict = "auto") -> NeuralInference:
        """The fast form of this fitted model: a new :class:`NeuralInference` to hold.

        Streaming: ``inf = model.inference()``, then ``out, state = inf.step(frame[None],
        state)`` per frame; a whole traverse: ``inf.run(query)``. The module copies what it
        needs when it is built (later changes to the model do not reach it) and names its
        kernel per stage in ``inf.kernels``.

        Args:
            kernels: ``"auto"``, ``"portable"`` or ``{stage: kernel}`` (see
                :mod:`torchseq.neural.inference`).
        """
        self._require_fit()
        return NeuralInference(self, kernels)

    def run(self, query: torch.Tensor, progress: bool | Progress | None = None,
            l1_dtype: torch.dtype | None = None) -> NeuralResult:
        """Stream a whole query traverse through the network (one stream).

        Builds ``self.inference()`` (``"auto"`` kernels) and calls its
        :meth:`~NeuralInference.run`; callers that run several traverses hold the module
        themselves and save the build. Same numbers as :meth:`step` once per frame, up to
        float rounding.

        Args:
            query: ``(T, H, W)`` or ``(T, H, W, 3)`` frames (a tensor or a NumPy array).
            progress: a callback ``(frames done, frames in all)`` (``True``: a tqdm bar).
            l1_dtype: ``torch.bfloat16`` runs the L1 product in bfloat16 (the
                ``"bfloat16_gemm"`` kernel) - an approximation: rounding moves a few L2
                units across the k-WTA threshold, so some decisions differ from the float32
                model (99.7% identical on the benchmark route). None: exact.

        Returns:
            :class:`NeuralResult`.
        """
        self._require_fit()
        if l1_dtype is not None and l1_dtype not in (torch.bfloat16, torch.float32):
            raise NeuralError(f"l1_dtype must be torch.bfloat16 or None, got {l1_dtype}")
        kernels = {"l1": "bfloat16_gemm"} if l1_dtype == torch.bfloat16 else "auto"
        return self.inference(kernels).run(query, progress)

    # ------------------------------------------------------------------ persistence
    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Load a state dict, first sizing the output layers from it."""
        if "unit_to_reference" in state_dict:
            n = int(state_dict["unit_to_reference"].shape[0])
            if n != self.n_units:
                self._build_output(n)
        out = super().load_state_dict(state_dict, strict=strict, assign=assign)
        self._build_search()
        return out

    def _build_search(self) -> None:
        """The unit search (:mod:`torchseq.neural.search`) where the config and route ask."""
        self.search = None
        if self.fitted and search_active(self.config, int(self.unit_to_reference[-1, 1]),
                                         self.n_units):
            self.search = UnitSearch(self.config, self.unit_to_reference)

    def save(self, path: str | Path, extra: dict | None = None) -> None:
        """Write the model atomically: ``{"format", "config", "state_dict", "extra"}``.

        Args:
            path: target file.
            extra: anything ``torch.load(weights_only=True)`` can read back (plain types).
        """
        self._require_fit()
        save_checkpoint(path, self.config.to_dict(), self.state_dict(), extra)

    @classmethod
    def load(cls, path: str | Path, map_location=None) -> NeuralSeqSLAM:
        """Read a model written by :meth:`save` (the config travels with it).

        The checkpoint's ``extra`` dict comes back as ``model.extra``.

        Raises:
            NeuralError: missing, truncated or foreign file, an unknown format, or a
                state_dict that does not fit its config.
        """
        return load_model(cls, path, map_location)

    # ------------------------------------------------------------------ memory
    def model_bytes(self, masked_only: bool = False) -> int:
        """Bytes of everything the model stores (see :mod:`torchseq.neural.memory`)."""
        return memory.model_bytes(self.state_dict(), masked_only)

    def memory_comparison(self, descriptor: int = 2048) -> dict:
        """Bytes stored beside classic SeqSLAM's (see :mod:`torchseq.neural.memory`)."""
        self._require_fit()
        return memory.memory_comparison(self, descriptor)


def _warn(*messages: str | None) -> None:
    """Warn each message of :mod:`torchseq.neural.advice` there is, at ``fit``'s caller."""
    for message in messages:
        if message:
            warnings.warn(message, stacklevel=4)  # this, fit, torch.no_grad's wrapper, caller


def _winners(codes, k: int) -> torch.Tensor:
    """``(T, k)`` int32 indices of the active L2 units of each binary code, on the CPU."""
    parts = []
    for _, _, c in codes:
        if bool(((c != 0).sum(1) != k).any()):
            raise NeuralError(f"an L2 code does not have exactly k = {k} winners")
        idx = c.nonzero()[:, 1]  # row-major: each row's k winners in ascending order
        parts.append(idx.reshape(c.shape[0], k).to("cpu", torch.int32))
    return torch.cat(parts)


def _codes_of(winners: torch.Tensor, hidden: int, chunk: int, device):
    """The binary codes back from :func:`_winners`, as ``(lo, hi, code)`` batches."""
    for lo in range(0, winners.shape[0], chunk):
        idx = winners[lo:lo + chunk].to(device, torch.int64)
        code = torch.zeros(idx.shape[0], hidden, device=device)
        yield lo, lo + idx.shape[0], code.scatter_(1, idx, 1.0)

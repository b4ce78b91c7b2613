"""``NeuralSeqSLAM``: a rate-coded place-recognition network whose memory is bounded.

L1 (patch-normalised pixels) -> fixed random ``MaskedLinear`` -> L2 binary k-WTA code ->
Hebbian ``MaskedLinear`` -> L3 evidence, z-scored within cohorts -> ``OutputRing`` that
shifts activity along the learnt route -> the most active unit is the place. The exact
equations of one step are in ``docs/neural.md`` ("Step maths").
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import torch
from torch import nn

from torchseq.layers import KWinnersTakeAll, MaskedLinear, OutputRing, RingState
from torchseq.layers.functional import cohort_normalise
from torchseq.matches import Matches
from torchseq.neural.checkpoint import load_model, save_checkpoint
from torchseq.neural.config import NeuralConfig, NeuralError
from torchseq.neural.fast import (
    Int8Linear,
    band_diagonals,
    feedforward,
    feedforward_uint8,
    ring_power,
    ring_scan,
)
from torchseq.neural.fixed_point import (
    block_order,
    factor_power_of_two,
    factor_rows,
    integer_weights,
    quantise_input,
    round_rows,
    zscore_blocks,
    zscore_pixel_major,
)
from torchseq.neural.learning import (
    cohort_membership,
    decide,
    hebbian_weights,
    recruit_units,
)
from torchseq.neural.results import NeuralFitLog, NeuralResult, NeuralStep
from torchseq.preprocess import patch_normalise, resize, to_grey

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
        self._folded: dict[str, torch.Tensor | None] | None = None

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
        self._folded = None

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
        if frames.dim() not in (3, 4) or (frames.dim() == 4 and frames.shape[-1] != 3):
            raise NeuralError(f"frames must be (B, H, W) or (B, H, W, 3), got "
                              f"{tuple(frames.shape)}")
        if frames.shape[0] == 0:
            raise NeuralError("frames are empty (no frame in the batch)")
        x = to_grey(frames.to(self.l1.weight.device)).to(torch.float32)
        # one sum first (NaN and inf propagate), the element-wise test only when it fails
        if not bool(torch.isfinite(x.sum())) and not bool(torch.isfinite(x).all()):
            raise NeuralError("frames hold NaN or infinite values")
        return resize(x, self.config.input_size)

    def code(self, x: torch.Tensor) -> torch.Tensor:
        """L1 -> L2: random masked projection then binary k-WTA. ``(B, 768) -> (B, hidden)``."""
        w1 = self._folded["w1"] if self._folded is not None else None
        h = torch.nn.functional.linear(x, w1) if w1 is not None else self.l1(x)
        return self.l2(h)

    def evidence(self, code: torch.Tensor) -> torch.Tensor:
        """L2 -> L3 evidence, z-scored within cohorts, rectified. ``(B, hidden) -> (B, N)``."""
        w3 = self._folded["w3"] if self._folded is not None else None
        e = torch.nn.functional.linear(code, w3) if w3 is not None else self.l3(code)
        z = cohort_normalise(e, self.cohorts, self.config.eps)
        return z.clamp_min(0.0) if self.config.rectify else z

    def step(self, frames: torch.Tensor,
             state: RingState | None = None) -> tuple[NeuralStep, RingState]:
        """One streaming step for ``B`` independent streams.

        Args:
            frames: ``(B, H, W)`` (or ``(B, H, W, 3)``) one new frame per stream.
            state: ring state from the previous step (None: start of the streams).

        Returns:
            ``(NeuralStep, new state)``.

        After :meth:`fold` (done by :meth:`run`) and with gradients off, the feed-forward
        part takes the fast path of :func:`torchseq.neural.fast.feedforward`.
        """
        self._require_fit()
        if state is not None and (state.activity.dim() != 2
                                  or state.activity.shape[1] != self.n_units
                                  or state.activity.shape[0] != frames.shape[0]):
            raise NeuralError(f"state must be ({frames.shape[0]}, {self.n_units}), got "
                              f"{tuple(state.activity.shape)}")
        if self._folded is not None and not torch.is_grad_enabled():  # same maths, faster
            e = self._feedforward(frames)  # (B, N)
        else:
            e = self.evidence(self.code(self.encode(frames)))  # (B, N)
        activity, state = self.ring(e, state)
        reference, confidence = decide(activity, self.unit_centre,
                                       self.config.uniqueness_window)
        return NeuralStep(reference, confidence, activity), state

    forward = step

    # ------------------------------------------------------------------ learning
    @torch.no_grad()
    def fit(self, reference: torch.Tensor, progress: bool = False,
            log: bool = True) -> NeuralFitLog:
        """Learn a route from one pass over its reference traverse (local rules, no backprop).

        Units are recruited along the route in order (unit ``u`` stands for a contiguous
        stretch of frames); L2 -> L3 weights take the mean L2 code of the unit's frames
        within the mask (Hebbian, rows normalised); the ring's shift matrix learns from the
        order in which units fired.

        Args:
            reference: ``(T, H, W)`` or ``(T, H, W, 3)`` frames, any size, 0..255, ``T >= 2``.
            progress: show a progress bar.
            log: also compute the reference evidence raster (a second feed-forward pass).

        Returns:
            :class:`NeuralFitLog`.
        """
        t0 = time.perf_counter()
        if reference.dim() not in (3, 4) or reference.shape[0] < 2:
            raise NeuralError(f"reference must be (T, H, W) with T >= 2 frames, got "
                              f"{tuple(reference.shape)}")
        cfg = self.config
        t_len = reference.shape[0]
        n_units = min(t_len, cfg.n_output)
        self._build_output(n_units)
        unit_of_frame, spans = recruit_units(t_len, n_units)
        dev = self.l1.weight.device
        sums = torch.zeros(n_units, cfg.hidden, device=dev)
        total = torch.zeros(cfg.hidden, device=dev)
        for lo in _chunks(t_len, cfg.chunk, progress, "fit"):
            hi = min(lo + cfg.chunk, t_len)
            c = self.code(self.encode(reference[lo:hi]))
            sums.index_add_(0, unit_of_frame[lo:hi].to(dev), c)
            total += c.sum(0)
        counts = (spans[:, 1] - spans[:, 0]).to(dev, torch.float32)
        w = hebbian_weights(sums, counts, total / t_len, self.l3.mask, cfg.hebbian, cfg.eps)
        if cfg.l3_levels:
            w = round_rows(w, cfg.l3_levels)
        self.l3.weight.copy_(w)
        self.ring.learn(unit_of_frame)
        self.unit_to_reference.copy_(spans.to(dev))
        self.unit_centre.copy_(((spans[:, 0] + spans[:, 1] - 1) // 2).to(dev))
        evidence = torch.empty(0, n_units)
        if log:
            parts = [self.evidence(self.code(self.encode(reference[lo:lo + cfg.chunk])))
                     for lo in range(0, t_len, cfg.chunk)]
            evidence = torch.cat(parts).cpu()
        return NeuralFitLog(unit_of_frame, evidence, spans, time.perf_counter() - t0)

    # ------------------------------------------------------------------ recognition
    @torch.inference_mode()
    def run(self, query: torch.Tensor, progress: bool = False,
            l1_dtype: torch.dtype | None = None) -> NeuralResult:
        """Stream a whole query traverse through the network (one stream).

        The feed-forward part runs in batches of ``config.chunk`` frames (it does not
        depend on the state) with folded weights (:mod:`torchseq.neural.fast`); the ring then
        steps frame by frame. Same numbers as calling :meth:`step` once per frame, up to
        float rounding.

        Args:
            query: ``(T, H, W)`` or ``(T, H, W, 3)`` frames.
            progress: show a progress bar.
            l1_dtype: ``torch.bfloat16`` runs the L1 product in bfloat16 (about 1.5x faster
                on CPUs with AMX/AVX512-BF16) - an approximation: rounding moves a few L2
                units across the k-WTA threshold, so some decisions differ from the float32
                model (99.7% identical on the benchmark route). None: exact float32.

        Returns:
            :class:`NeuralResult`.
        """
        t0 = time.perf_counter()
        self._require_fit()
        if query.dim() not in (3, 4) or query.shape[0] == 0:
            raise NeuralError(f"query must be a non-empty (T, H, W), got {tuple(query.shape)}")
        cfg = self.config
        self.fold()
        f = self._folded
        decay, gain = self.ring.params
        w1_t = None
        if l1_dtype is not None and l1_dtype != f["w1_t"].dtype:
            w1_t = f.setdefault(f"w1_t.{l1_dtype}", f["w1_t"].to(l1_dtype))
        parts = [self._feedforward(query[lo:lo + cfg.chunk], w1_t)
                 for lo in _chunks(query.shape[0], cfg.chunk, progress, "run")]
        drive = torch.cat(parts) * gain  # (T, N)
        a0 = torch.zeros(self.n_units, device=drive.device)
        activity = ring_scan(drive, a0, self.ring.shift, decay, f["diagonals"],
                             power=f["ring_power"])
        reference, confidence = decide(activity, self.unit_centre, cfg.uniqueness_window)
        matches = Matches(reference.cpu(), confidence.cpu(), lower_is_better=False)
        return NeuralResult(matches, activity.cpu(), time.perf_counter() - t0)

    def _feedforward(self, frames: torch.Tensor,
                     w1_t: torch.Tensor | None = None) -> torch.Tensor:
        """Folded L1 -> L3 evidence of raw frames ``(B, ...) -> (B, N)`` (see :meth:`fold`).

        On the int8 path the z-scores go straight to uint8 in block-major order (the L1
        weights' columns were permuted to match), skipping the float grid of :meth:`encode`;
        the integers are the same. ``w1_t``: a low-precision L1 copy (``run(l1_dtype=...)``),
        which forces float products.
        """
        f, cfg = self._folded, self.config
        if f["l1_int8"] is not None and w1_t is None and frames.device.type == "cpu":
            z = zscore_pixel_major(self._grey(frames), cfg.patch_size)  # (p*p, B, blocks)
            xq = z.mul_(cfg.input_steps).round_().add_(128.0).to(torch.uint8).permute(1, 2, 0)
            return feedforward_uint8(xq.reshape(xq.shape[0], -1), f["l1_int8"], f["l3_int8"],
                                     cfg.k, self.cohorts, cfg.eps, cfg.rectify)
        return feedforward(self.encode(frames), f["w1_t"] if w1_t is None else w1_t, f["w3_t"],
                           cfg.k, self.cohorts, cfg.eps, cfg.rectify)

    def fold(self) -> None:
        """Cache ``weight * mask`` of both masked layers for fast inference.

        Dense float copies always; int8 copies for oneDNN's int8 GEMM when the model's
        numbers sit on its integer grids (:mod:`torchseq.neural.fixed_point`) and the GEMM
        reproduces the float products on a check batch. Called by :meth:`run`; cleared by
        :meth:`fit` and :meth:`load_state_dict`.
        """
        self._require_fit()
        if self._folded is None:
            with torch.inference_mode(False), torch.no_grad():
                w1, w3 = self.l1.folded_weight(), self.l3.folded_weight()
                self._folded = {
                    "w1": w1, "w3": w3, "w1_t": w1.T.contiguous(), "w3_t": w3.T.contiguous(),
                    "diagonals": None if self.config.ring_wrap else band_diagonals(
                        self.ring.shift, self.config.ring_spread),
                    "l1_int8": None, "l3_int8": None}
                self._folded["ring_power"] = ring_power(
                    self.ring.shift, self.ring.params.decay, self._folded["diagonals"])
                self._folded.update(self._int8_layers(w1, w3))

    def _int8_layers(self, w1: torch.Tensor, w3: torch.Tensor) -> dict:
        """``{"l1_int8", "l3_int8"}``: :class:`Int8Linear` copies, or nothing when unusable."""
        cfg = self.config
        steps, n = cfg.input_steps, cfg.patch_size ** 2
        if (w1.device.type != "cpu" or not steps or not n or cfg.patch_mode != "zscore"
                or (n - 1) / math.sqrt(n) * steps > 127):  # |z| <= (n-1)/sqrt(n): int8 fits
            return {}
        l1 = factor_power_of_two(w1, 64)  # |n| <= 64: no int16 pair overflow on any CPU
        l3 = factor_rows(w3, 127)
        if l1 is None or l3 is None:
            return {}
        n1, step1 = l1  # columns to block-major order: the int8 path's input order
        n1 = n1[:, block_order(*cfg.input_size, cfg.patch_size)].contiguous()
        lin1 = Int8Linear.create(n1, torch.full((n1.shape[0],), step1), 1.0 / steps, 128)
        lin3 = Int8Linear.create(*l3, 1.0, 0)
        if lin1 is None or lin3 is None:
            return {}
        return {"l1_int8": lin1, "l3_int8": lin3}

    def unfold(self) -> None:
        """Drop the folded weights (the next call recomputes ``weight * mask``)."""
        self._folded = None

    # ------------------------------------------------------------------ persistence
    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Load a state dict, first sizing the output layers from it."""
        if "unit_to_reference" in state_dict:
            n = int(state_dict["unit_to_reference"].shape[0])
            if n != self.n_units:
                self._build_output(n)
        self._folded = None
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

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
        """Bytes of everything the model stores (``state_dict``).

        Args:
            masked_only: count only the weights inside the masks (as a sparse store would,
                value only) plus every other buffer, instead of the dense tensors.
        """
        total = 0
        for name, t in self.state_dict().items():
            if masked_only and name.endswith(".weight"):
                mask = self.state_dict()[name[: -len("weight")] + "mask"]
                total += int(mask.sum()) * t.element_size()
            elif masked_only and name.endswith(".mask"):
                continue
            else:
                total += t.numel() * t.element_size()
        return total

    def memory_comparison(self, descriptor: int = 2048) -> dict:
        """Bytes this model stores beside the bytes classic SeqSLAM keeps for the same route.

        Args:
            descriptor: SeqSLAM descriptor length (2048 = 32x64 OpenSeqSLAM images).

        Returns:
            ``{"n_reference", "n_units", "neural_bytes", "neural_masked_bytes",
            "seqslam_bytes"}`` (see :meth:`model_bytes` and :func:`seqslam_bytes`).
        """
        self._require_fit()
        n_ref = int(self.unit_to_reference[-1, 1])
        return {"n_reference": n_ref, "n_units": self.n_units,
                "neural_bytes": self.model_bytes(),
                "neural_masked_bytes": self.model_bytes(masked_only=True),
                "seqslam_bytes": seqslam_bytes(n_ref, descriptor)}


def seqslam_bytes(n_reference: int, descriptor: int = 2048, itemsize: int = 4) -> int:
    """Bytes classic SeqSLAM keeps for a route: ``R x descriptor`` float32 descriptors."""
    return int(n_reference) * int(descriptor) * int(itemsize)


def _chunks(n: int, size: int, progress: bool, desc: str):
    starts = range(0, n, size)
    if progress:
        from tqdm import tqdm

        return tqdm(starts, desc=desc, unit="chunk")
    return starts

"""``NeuralInference``: a fitted Neural SeqSLAM folded for inference, kernels chosen at build.

It computes the step of ``docs/guide/neural.md`` ("Step maths") with the same functions as the
model's layers (:func:`~torchseq.preprocess.zscore_pixel_major`,
:func:`~torchseq.layers.kwta`, :func:`~torchseq.layers.cohort_normalise`,
:func:`~torchseq.layers.ring_step` / :func:`~torchseq.layers.ring_scan`,
:func:`~torchseq.neural.readout.decide`), with the masks folded into dense weights and one
named kernel per stage. The kernels are fixed when the module is built and visible as
:attr:`NeuralInference.kernels`; nothing else (grad mode, earlier calls) changes them.

Stages and kernels:

=========== ============================================================================
``input``   ``"torch"`` or ``"numpy"``: the patch z-score (same bits either way) on the
            ``1 / input_steps`` grid; ``"encode"``: the model's ``encode`` (other patch
            modes)
``l1``      ``"float32_gemm"``, ``"int8_gemm"`` (oneDNN; the model's integer grids make
            it exact), ``"int8_gemm_or_float32_gemm"`` (float32 for batches of fewer than
            ``SMALL_BATCH`` frames, int8 from there on: the auto choice on CPUs without
            AVX-512, :func:`int8_l1_at_batch_1`) or ``"bfloat16_gemm"`` (approximate, opt-in)
``kwta``    ``"topk"`` or ``"partition"`` (NumPy introselect)
``l3``      ``"embedding_bag"`` (sum of the winners' rows), ``"int8_gemm"``,
            ``"int8_gemm_or_embedding_bag"`` (the embedding-bag for batches of fewer than
            ``SMALL_BATCH`` frames, where it is about 3x faster, the int8 GEMM from
            there on) or ``"dense"`` (the 0/1 code times the weights: the exported graph)
``ring``    ``"banded"`` (diagonals of a banded shift matrix) or ``"dense"``
``scan``    ``"numpy"`` or ``"torch"``: :func:`~torchseq.layers.ring_scan`'s kernel in
            :meth:`NeuralInference.scan`; ``"velocity_loop"``, the adaptive ring's only one
            (``ring_velocity="adaptive"``: :meth:`NeuralInference.stream`, frame by frame)
``decide``  ``"numpy"`` or ``"torch"``
``step``    ``"stages"`` (the stage kernels above, one after another), ``"numba"`` (the
            whole online step of each frame, z-score to decision, as one compiled pass:
            ``torchseq/neural/_step_numba.py``, the same bits as the stage kernels) or
            ``"stages_or_numba"`` (the compiled pass for batches of fewer than
            ``SMALL_BATCH`` frames with float32 states, the stages from there on). Only
            :meth:`NeuralInference.step` reads it (``run`` batches the stages)
=========== ============================================================================

``kernels="auto"`` picks, on the CPU: NumPy input, int8 GEMMs when the model sits on its
integer grids and oneDNN reproduces the float products on a check batch (else float32 and
the embedding-bag), the NumPy partition, the banded ring, NumPy scan and read-out, and
``"stages_or_numba"`` for the step where numba is installed, the model fits the compiled
pass (integer L1 grids with ``input_steps`` a power of two, so that the float32 product is
exact, one cohort, banded ring, centre read-out, no unit search, fixed ring:
``NeuralInference._numba_fits``) and no stage kernel of the step is asked by name; on other
devices the torch kernels. ``"portable"`` is plain torch float32 throughout (what the float
ONNX graph is traced from). A dict overrides single stages.
"""

from __future__ import annotations

import importlib.util
import math
import platform

import numpy as np
import torch
from torch import nn

from torchseq._checks import as_frames
from torchseq.layers import RingState, cohort_normalise, kwta
from torchseq.layers import kernels as K
from torchseq.layers.kernels import TIE_STEP, Int8Linear
from torchseq.layers.ring import band_diagonals, ring_power, ring_scan, ring_step
from torchseq.matches import Matches
from torchseq.metrics import RECALL_KS
from torchseq.neural.checks import checked_grey, checked_state
from torchseq.neural.config import NeuralError
from torchseq.neural.progress import Progress, as_progress, chunks
from torchseq.neural.readout import decide, rank
from torchseq.neural.results import NeuralResult, NeuralStep
from torchseq.neural.search import (
    SearchState,
    UnitSearch,
    checked_search_state,
    decision_stage,
)
from torchseq.neural.velocity import VelocityTracker, adaptive_step
from torchseq.preprocess import block_order, zscore_pixel_major
from torchseq.quantise import factor_power_of_two, factor_rows

STAGES = ("input", "l1", "kwta", "l3", "cohorts", "ring", "scan", "decide", "step")
CHOICES = {
    "input": ("torch", "numpy", "encode"),
    "l1": ("float32_gemm", "int8_gemm", "int8_gemm_or_float32_gemm", "bfloat16_gemm"),
    "kwta": ("topk", "partition"),
    "l3": ("embedding_bag", "int8_gemm", "int8_gemm_or_embedding_bag", "dense"),
    "cohorts": ("torch", "numpy"),
    "ring": ("banded", "dense"),
    "scan": ("numpy", "torch", "velocity_loop"),
    "decide": ("numpy", "torch"),
    "step": ("stages", "numba", "stages_or_numba"),
}
SMALL_BATCH = 16  # below: the embedding-bag L3 beats the int8 GEMM (bench_neural.py)


def int8_l1_at_batch_1() -> bool:
    """Whether the int8 L1 GEMM beats the float32 one at batch 1 on this CPU.

    With AVX-512 (VNNI) yes; on AVX2 alone oneDNN's int8 GEMM took 1.35x the float32 one at
    batch 1 and 0.68x at batch 256 (one thread, Zen 3; ``docs/results/neural-step.md``), so
    there the auto choice is ``"int8_gemm_or_float32_gemm"`` (float32 below SMALL_BATCH).
    """
    return torch.backends.cpu.get_cpu_capability().startswith("AVX512")
PORTABLE = {"input": "torch", "l1": "float32_gemm", "kwta": "topk", "l3": "dense",
            "cohorts": "torch", "ring": "dense", "scan": "torch", "decide": "torch",
            "step": "stages"}


def numba_available() -> bool:
    """Whether numba is installed (found, not imported: it is imported on the first step)."""
    return importlib.util.find_spec("numba") is not None


def int8_expected() -> bool:
    """Whether this machine should have oneDNN's int8 GEMM (an x86-64 CPU build of torch)."""
    return (platform.machine().lower() in ("x86_64", "amd64")
            and torch.backends.mkldnn.is_available())


class NeuralInference(nn.Module):
    """A fitted :class:`~torchseq.neural.NeuralSeqSLAM` folded for inference.

    Build it with :meth:`NeuralSeqSLAM.inference` (or ``NeuralInference(model, kernels)``).
    It copies what it needs (folded weights, the shift matrix, cohorts, unit centres) as
    buffers: later changes to the model's tensors do not reach it (with a patch mode other
    than ``"zscore"`` its input stage is the model's own ``encode``). No autograd.

    Args:
        model: a fitted :class:`~torchseq.neural.NeuralSeqSLAM`.
        kernels: ``"auto"``, ``"portable"`` or a dict ``{stage: kernel}`` over ``"auto"``.

    Raises:
        NeuralError: an unfitted model, an unknown stage or kernel, or a kernel that cannot
            run here (int8 on a model off its integer grids or without oneDNN, NumPy kernels
            off the CPU, the banded ring on a shift matrix that is not banded).
    """

    def __init__(self, model, kernels: str | dict = "auto") -> None:
        super().__init__()
        if not model.fitted:
            raise NeuralError("the model has not learnt a route yet: call fit(reference) first")
        cfg = self.config = model.config
        with torch.inference_mode(False), torch.no_grad():
            w1 = model.l1.folded_weight().detach()
            w3 = model.l3.folded_weight().detach()
            shift = model.ring.shift.detach()
            cpu = w1.device.type == "cpu"
            self.block_major = bool(cfg.patch_size) and cfg.patch_mode == "zscore"
            w1_t = w1.T
            if self.block_major:  # the z-scores come block-major: permute L1's columns
                w1_t = w1_t[block_order(*cfg.input_size, cfg.patch_size).to(w1.device)]
            self.register_buffer("w1_t", w1_t.contiguous())
            self.register_buffer("w3_t", w3.T.contiguous())
            self.register_buffer("shift", shift.clone())
            diag = None if cfg.ring_wrap else band_diagonals(shift, cfg.ring_spread)
            self.register_buffer("diagonals", diag)
            self.register_buffer("cohorts", model.cohorts.detach().clone())
            self.register_buffer("unit_centre", model.unit_centre.detach().clone())
            spans = model.readout_spans
            self.register_buffer("spans", None if spans is None else spans.detach().clone())
            self.decay, self.gain = (float(v) for v in model.ring.params)
            self.tracker = (VelocityTracker.from_model(model)
                            if cfg.ring_velocity == "adaptive" else None)
            self.params = model.ring.params
            self.search = (None if model.search is None
                           else UnitSearch(model.config, model.unit_to_reference.detach()))
            self.l1_int8 = self.l3_int8 = self.w1_i8 = None
            self._int8_built = False
            self._kernels = self._resolve(kernels, cpu, w1, w3)
            self.register_buffer("ring_power", ring_power(
                shift, self.decay, diag if self._kernels["ring"] == "banded" else None))
            self.w1_bf16 = (self.w1_t.to(torch.bfloat16)
                            if self._kernels["l1"] == "bfloat16_gemm" else None)
            if self._kernels["step"] == "stages":
                self.w1_i8 = None
        self._encode = model.encode if self._kernels["input"] == "encode" else None
        # the step's constants, read once here rather than per call
        self._k, self._units = cfg.k, int(model.unit_centre.shape[0])
        self._window = cfg.uniqueness_window
        self._size, self._compiled, self._numba_args = torch.Size(cfg.input_size), None, None
        if self._kernels["step"] != "stages":  # the compiled step's operands (views, constants)
            self._numba_args = (
                self.w1_i8, self.w3_t.numpy(), self.diagonals.numpy(), self.unit_centre.numpy(),
                np.array([cfg.input_steps, cfg.eps, self.decay, self.gain], np.float32),
                np.array([cfg.patch_size, cfg.k, min(cfg.uniqueness_window, self._units),
                          cfg.rectify], np.int64))

    # ------------------------------------------------------------------ kernel choice
    @property
    def kernels(self) -> dict[str, str]:
        """The kernel of each stage, fixed at construction."""
        return dict(self._kernels)

    def _resolve(self, kernels, cpu: bool, w1, w3) -> dict[str, str]:
        if isinstance(kernels, str):
            if kernels not in ("auto", "portable"):
                raise NeuralError(f"kernels must be 'auto', 'portable' or a dict, got {kernels!r}")
            base, asked = kernels, {}
        else:
            base, asked = "auto", dict(kernels)
            unknown = set(asked) - set(STAGES)
            if unknown:
                raise NeuralError(f"unknown stages {sorted(unknown)}; stages are {STAGES}")
            for stage, name in asked.items():
                if name not in CHOICES[stage]:
                    raise NeuralError(f"stage {stage!r} has kernels {CHOICES[stage]}, "
                                      f"got {name!r}")
        cfg = self.config
        if not self.block_major:
            asked["input"] = "encode"
        if self.tracker is not None:  # the adaptive ring has one scan kernel
            asked.setdefault("scan", "velocity_loop")
        if base == "portable":
            out = {**PORTABLE, **({"input": "encode"} if not self.block_major else {}), **asked}
            return self._check(out, cpu, w1, w3)
        if cpu and not self._int8_built:
            self._build_int8(w1, w3)
        numpy = "numpy" if cpu else "torch"
        out = {
            "input": numpy if self.block_major else "encode",
            "l1": ("float32_gemm" if self.l1_int8 is None else "int8_gemm"
                   if int8_l1_at_batch_1() else "int8_gemm_or_float32_gemm"),
            "kwta": "partition" if cpu else "topk",
            "l3": ("int8_gemm_or_embedding_bag" if self.l3_int8 is not None
                   else "embedding_bag"),
            "cohorts": numpy, "ring": "banded" if self.diagonals is not None else "dense",
            "scan": numpy, "decide": numpy,
            # a stage kernel asked by name runs: then the step is the stages unless asked too
            "step": ("stages_or_numba" if cpu and numba_available() and self._numba_fits(w1, w3)
                     and not set(asked) & set(STAGES[:6] + ("decide",)) else "stages"),
        }
        out.update(asked)
        if not cfg.input_steps and out["l1"].startswith("int8_gemm"):
            raise NeuralError("the int8 L1 kernel needs input_steps > 0")
        return self._check(out, cpu, w1, w3)

    def _check(self, out: dict, cpu: bool, w1: torch.Tensor, w3: torch.Tensor) -> dict:
        if not cpu:
            bad = [s for s in ("input", "cohorts", "scan", "decide") if out[s] == "numpy"]
            bad += ["kwta"] if out["kwta"] == "partition" else []
            bad += [s for s in ("l1", "l3") if out[s].startswith("int8_gemm")]
            if bad:
                raise NeuralError(f"stages {bad} have CPU-only kernels; the model is elsewhere")
        if out["l1"].startswith("int8_gemm") and self.l1_int8 is None:
            raise NeuralError("the int8 L1 kernel is unavailable: oneDNN's int8 GEMM is missing "
                              "or inexact here, or the model is off its integer grids")
        int8_l3 = out["l3"] in ("int8_gemm", "int8_gemm_or_embedding_bag")
        if int8_l3 and self.l3_int8 is None:
            raise NeuralError("the int8 L3 kernel is unavailable: oneDNN's int8 GEMM is missing "
                              "or inexact here, or the L3 weights are off their int8 rows")
        if int8_l3 and out["kwta"] != "partition":
            raise NeuralError("the int8 L3 kernel takes the partition k-WTA's uint8 code")
        if out["l1"].startswith("int8_gemm") and out["input"] == "encode":
            raise NeuralError("the int8 L1 kernel needs patch_mode 'zscore' with a patch")
        if (out["scan"] == "velocity_loop") != (self.tracker is not None):
            raise NeuralError(f"the 'velocity_loop' scan is the adaptive ring's and only "
                              f"kernel (ring_velocity={self.config.ring_velocity!r}), got "
                              f"{out['scan']!r}")
        if out["ring"] == "banded" and self.diagonals is None:
            raise NeuralError("the banded ring needs a banded shift matrix (no ring_wrap)")
        if out["step"] != "stages":
            if not cpu:
                raise NeuralError(f"the {out['step']!r} step kernel is CPU-only; the model is "
                                  "elsewhere")
            if not numba_available():
                raise NeuralError(f"the {out['step']!r} step kernel needs numba: "
                                  "pip install numba")
            if not self._numba_fits(w1, w3):
                raise NeuralError(f"the {out['step']!r} step kernel needs the integer L1 grids "
                                  "(input_steps a power of two, patch_mode 'zscore'), one "
                                  "cohort, a banded ring, the centre read-out, no unit search "
                                  "and a fixed ring")
        return out

    def _numba_fits(self, w1: torch.Tensor, w3: torch.Tensor) -> bool:
        """Whether the compiled step (``_step_numba``) computes this model's step."""
        if not self._int8_built:  # the L1 integer grids (CPU only; portable builds them here)
            self._build_int8(w1, w3)
        return (self.w1_i8 is not None and self.cohorts.shape[1] == 1
                and self.diagonals is not None and self.spans is None and self.search is None
                and self.tracker is None)

    def _build_int8(self, w1: torch.Tensor, w3: torch.Tensor) -> None:
        """OneDNN int8 copies of both products when the weights sit on their grids."""
        self._int8_built = True
        cfg = self.config
        steps, n = cfg.input_steps, cfg.patch_size ** 2
        if (w1.device.type != "cpu" or not steps or not self.block_major
                or (n - 1) / math.sqrt(n) * steps > 127):  # |z| <= (n-1)/sqrt(n): int8 fits
            return
        l1 = factor_power_of_two(w1, 64)  # |n| <= 64: no int16 pair overflow on any CPU
        l3 = factor_rows(w3, 127)
        if l1 is None or l3 is None:
            return
        n1, step1 = l1  # columns to block-major order: the input order
        n1 = n1[:, block_order(*cfg.input_size, cfg.patch_size)].contiguous()
        if (steps & (steps - 1) == 0  # 1/steps a power of two, and every float32 partial sum
                and n1.shape[1] * 127 * int(n1.abs().max()) < 2**24):  # exact: same winners
            self.w1_i8 = n1.numpy()  # (M, K) int8: the compiled step's L1 (rows contiguous)
        self.l1_int8 = Int8Linear.create(n1, torch.full((n1.shape[0],), step1), 1.0 / steps, 128)
        self.l3_int8 = Int8Linear.create(*l3, 1.0, 0, x_max=1)  # the binary k-WTA code

    # ------------------------------------------------------------------ the stages
    def evidence(self, frames: torch.Tensor, grey: torch.Tensor | None = None) -> torch.Tensor:
        """Normalised (and rectified) L3 evidence of raw frames ``(B, ...) -> (B, N)``.

        Args:
            frames: ``(B, H, W)`` or ``(B, H, W, 3)`` raw frames, or None with ``grey``.
            grey: ``(B, h, w)`` float32 grey frames at the input size (checked already).
        """
        k, cfg = self._kernels, self.config
        l1 = k["l1"]
        if l1 == "int8_gemm_or_float32_gemm":  # by batch: the frames' or the grey frames'
            batch = (grey if grey is not None else frames).shape[0]
            l1 = "int8_gemm" if batch >= SMALL_BATCH else "float32_gemm"
        if k["input"] == "encode":
            x = self._encode(frames)
        else:
            if grey is None:
                grey = self._grey(frames)
            z = zscore_pixel_major(grey, cfg.patch_size, k["input"])  # (p*p, B, blocks)
            if l1 == "int8_gemm" and k["input"] == "numpy":  # uint8 x * steps + 128
                q = np.rint(z.numpy() * np.float32(cfg.input_steps))  # half to even
                q += 128
                x = torch.from_numpy(q.astype(np.uint8).transpose(1, 2, 0).reshape(
                    z.shape[1], -1))
            elif l1 == "int8_gemm":
                xq = z.mul_(cfg.input_steps).round_().add_(128.0).to(torch.uint8)
                x = xq.permute(1, 2, 0).reshape(z.shape[1], -1)
            else:
                x = z.permute(1, 2, 0).reshape(z.shape[1], -1)
                if cfg.input_steps:
                    x = torch.round(x * cfg.input_steps) / cfg.input_steps
        h = self._l1(x, l1)  # (B, M)
        e = self._l3(h)  # (B, N)
        return cohort_normalise(e, self.cohorts, cfg.eps, cfg.rectify, k["cohorts"])

    def _grey(self, frames: torch.Tensor) -> torch.Tensor:
        return checked_grey(frames, self.config.input_size, self.w1_t.device)

    def _l1(self, x: torch.Tensor, name: str) -> torch.Tensor:
        if name == "int8_gemm":
            return self.l1_int8(x)  # exact integer sums times a power of two
        if name == "bfloat16_gemm":  # approximate; its many exact ties go to the lowest index
            h = (x.to(torch.bfloat16) @ self.w1_bf16).to(x.dtype)
            return h - torch.arange(h.shape[1], device=h.device, dtype=h.dtype) * TIE_STEP
        if x.dtype != self.w1_t.dtype:  # (a static test: no Cast node in a traced graph)
            x = x.to(self.w1_t.dtype)
        return x @ self.w1_t

    def _l3(self, h: torch.Tensor) -> torch.Tensor:
        k = self._kernels
        n = self._k
        name = k["l3"]
        if name == "int8_gemm_or_embedding_bag":
            name = "int8_gemm" if h.shape[0] >= SMALL_BATCH else "embedding_bag"
        if name == "int8_gemm":  # kwta's partition kernel, its bool code read as uint8
            return self.l3_int8(K.kwta_partition(h, n).view(torch.uint8))
        if name == "dense":
            return kwta(h, n, True, kernel=k["kwta"]) @ self.w3_t
        if k["kwta"] == "partition":
            idx = K.kwta_partition_indices(h, n)
        else:
            idx = K.topk_indices(h, n)
        return K.sum_rows(idx, self.w3_t)

    # ------------------------------------------------------------------ step and run
    def step(self, frames: torch.Tensor,
             state: RingState | None = None) -> tuple[NeuralStep, RingState]:
        """One streaming step for ``B`` streams: :meth:`NeuralSeqSLAM.step`'s numbers.

        Args:
            frames: ``(B, H, W)`` (or ``(B, H, W, 3)``) one new frame per stream.
            state: the previous step's state (None: start of the streams), as for
                :meth:`NeuralSeqSLAM.step`: a :class:`~torchseq.layers.RingState` (or a
                :class:`~torchseq.neural.VelocityState`, whose activity a fixed ring reads),
                with ``ring_velocity="adaptive"`` a ``VelocityState``.

        Returns:
            ``(NeuralStep, new state)``.

        Raises:
            NeuralError: bad frames, or a state of another type or size.
        """
        if self.search is not None:
            state = checked_search_state(state, frames.shape[0], self._units)
        else:
            state = checked_state(state, frames.shape[0], self._units, self.tracker)
        if torch.is_grad_enabled():  # no autograd (inference_mode / no_grad: already off)
            with torch.no_grad():
                return self._step(frames, state)
        return self._step(frames, state)

    forward = step

    def _step(self, frames: torch.Tensor, state) -> tuple[NeuralStep, RingState]:
        """:meth:`step` after its checks, autograd off."""
        name = self._kernels["step"]
        if name != "stages" and (name == "numba" or frames.shape[0] < SMALL_BATCH):
            if state is None or state.activity.dtype == torch.float32:
                return self._step_numba(frames, state)
            if name == "numba":
                raise NeuralError(f"the 'numba' step kernel takes float32 states, got "
                                  f"{state.activity.dtype}")
        e = self.evidence(frames)
        diag = self.diagonals if self._kernels["ring"] == "banded" else None
        if self.search is not None:  # the ring runs, the unit search decides
            ring = RingState(torch.zeros_like(e)) if state is None else state.ring
            shift = self.shift if diag is not None else self.shift.to(e.dtype)
            activity, ring = ring_step(e, ring, shift, self.params, diag)
            reference, confidence, history = self.search.step(
                e, activity, None if state is None else state.search)
            return NeuralStep(reference, confidence, activity), SearchState(ring, history)
        if self.tracker is not None:  # adaptive velocity (neural/velocity.py)
            activity, reference, confidence, state = adaptive_step(
                e, self.tracker.initial(e) if state is None else state,
                self.shift.to(e.dtype), self.params, diag, self.decide, self.tracker)
            return NeuralStep(reference, confidence, activity), state
        if state is None:
            state = RingState(torch.zeros_like(e))
        shift = self.shift if diag is not None else self.shift.to(e.dtype)  # banded: unused
        activity, state = ring_step(e, state, shift, self.params, diag)
        reference, confidence = decide(activity, self.unit_centre, self._window,
                                       self._kernels["decide"], self.spans)
        return NeuralStep(reference, confidence, activity), state

    def _step_numba(self, frames: torch.Tensor,
                    state: RingState | None) -> tuple[NeuralStep, RingState]:
        """The ``"numba"`` step kernel: every stream's step as one compiled pass."""
        compiled = self._compiled
        if compiled is None:  # numba: imported (and compiled, or loaded from its cache) now
            from torchseq.neural import _step_numba

            compiled = self._compiled = _step_numba
        if (frames.dim() == 3 and frames.shape[0] and frames.dtype == torch.float32
                and frames.device.type == "cpu" and frames.shape[1:] == self._size):
            grey = frames.detach().numpy()  # the online case; the kernel checks finiteness
        else:
            grey = self._grey(frames).numpy()  # checks, grey, resize
        grey = np.ascontiguousarray(grey)
        b, n = grey.shape[0], self._units
        prev = (np.zeros((b, n), np.float32) if state is None
                else np.ascontiguousarray(state.activity.detach().numpy()))
        act = np.empty((b, n), np.float32)
        ref = np.empty(b, np.int64)
        conf = np.empty(b, np.float32)
        if not compiled.step(grey, prev, *self._numba_args, act, ref, conf):
            raise NeuralError("frames hold NaN or infinite values")
        activity = torch.from_numpy(act)
        return (NeuralStep(torch.from_numpy(ref), torch.from_numpy(conf), activity),
                RingState(activity))

    @torch.inference_mode()
    def run(self, query: torch.Tensor, progress: bool | Progress | None = None,
            top_k: int = max(RECALL_KS) + 1) -> NeuralResult:
        """A whole query traverse as one stream, from a zero state.

        The evidence runs in batches of ``config.chunk`` frames (it does not depend on the
        state), then the ring over all frames by the ``scan`` kernel (the blocked
        :func:`~torchseq.layers.ring_scan`; the adaptive ring frame by frame,
        :meth:`stream`), then the read-out: the decision stage's places, scores and ranked
        candidates. Same numbers as :meth:`step` once per frame, up to float rounding.

        Args:
            query: ``(T, H, W)`` or ``(T, H, W, 3)`` frames (a tensor or a NumPy array).
            progress: a callback ``(frames done, frames in all)`` (``True``: a tqdm bar).
            top_k: ranked candidates per frame (default 21: recall@20 and the tie past it).

        Returns:
            :class:`~torchseq.neural.NeuralResult`.
        """
        query = as_frames(query, "query")
        if query.dim() not in (3, 4) or query.shape[0] == 0:
            raise NeuralError(f"query must be a non-empty (T, H, W), got {tuple(query.shape)}")
        parts = [self.evidence(query[lo:hi])
                 for lo, hi in chunks(query.shape[0], self.config.chunk,
                                      as_progress(progress, "run"))]
        frames = self.unit_centre
        if self._kernels["scan"] == "velocity_loop":  # adaptive: decisions feed the ring
            activity, reference, confidence = self.stream(torch.cat(parts))
            scores = activity
        else:
            evidence = torch.cat(parts)
            activity = scores = self.scan(evidence)  # (T, N)
            if self.search is not None:  # the unit search decides (neural/search.py)
                reference, confidence, scores, frames = self.search.scan(evidence, activity)
            else:
                reference, confidence = self.decide(activity)
        ranked, ranked_score = rank(scores, frames, reference, top_k)
        matches = Matches(reference.cpu(), confidence.cpu(), lower_is_better=False)
        return NeuralResult(matches, activity.cpu(), self.stage, scores.cpu(), ranked.cpu(),
                            ranked_score.cpu())

    @property
    def stage(self) -> str:
        """The decision stage (:func:`~torchseq.neural.search.decision_stage`)."""
        return decision_stage(self.config, self.search is not None)

    @property
    def n_units(self) -> int:
        """Output units ``N``."""
        return self._units

    def scan(self, evidence: torch.Tensor) -> torch.Tensor:
        """Ring activity ``(T, N)`` of one stream's evidence ``(T, N)`` from a zero start."""
        drive = evidence * self.gain
        a0 = torch.zeros(evidence.shape[1], dtype=drive.dtype, device=drive.device)
        banded = self._kernels["ring"] == "banded"
        return ring_scan(drive, a0, self.shift, self.decay, self.diagonals if banded else None,
                         power=self.ring_power, kernel=self._kernels["scan"])

    def stream(self, evidence: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The adaptive ring over one stream's evidence ``(T, N)``, frame after frame.

        The ``"velocity_loop"`` scan kernel: each frame's decision feeds the speed estimate
        of the next, so there is no blocked form; the frames run through :meth:`forward`'s
        step (:func:`~torchseq.neural.velocity.adaptive_step`) one at a time.

        Returns:
            ``(activity (T, N), reference (T,) int64, confidence (T,))``.
        """
        if self._kernels["scan"] != "velocity_loop":
            raise NeuralError("stream() is the adaptive ring's scan; this module scans with "
                              f"{self._kernels['scan']!r}")
        diag = self.diagonals if self._kernels["ring"] == "banded" else None
        shift = self.shift.to(evidence.dtype)
        state = self.tracker.initial(evidence[:1])
        acts, refs, confs = [], [], []
        with torch.no_grad():
            for t in range(evidence.shape[0]):
                a, r, c, state = adaptive_step(evidence[t:t + 1], state, shift, self.params,
                                               diag, self.decide, self.tracker)
                acts.append(a)
                refs.append(r)
                confs.append(c)
        return torch.cat(acts), torch.cat(refs), torch.cat(confs)

    def decide(self, activity: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(reference, confidence)`` of activity ``(B, N)`` with this module's kernel."""
        return decide(activity, self.unit_centre, self.config.uniqueness_window,
                      self._kernels["decide"], self.spans)

    def extra_repr(self) -> str:
        """Summary for print(module)."""
        return ", ".join(f"{s}={n}" for s, n in self._kernels.items())

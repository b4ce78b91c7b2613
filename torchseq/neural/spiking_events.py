"""Event-driven input for the spiking model: a sensor's event counts into L1, linear maps only.

:class:`SpikingSeqSLAM` takes the rate model's ``encode`` of a frame (grey, resize, patch
z-score: nonlinear). :class:`EventSpikingSeqSLAM` takes instead, per time step, the events
of one time window from a sensor of ``(H, W)`` pixels as per-pixel counts ``(B, 2, H, W)``
(channel 0 OFF, 1 ON: :func:`torchseq.events.accumulate`'s ``"two_channel"`` layout, the
field's convention), and maps them into L1 with two linear maps, so the whole network
stays one NIR graph:

1. ``pool`` ``(D, 2 H W)``: sum pooling of both polarities from the sensor grid onto the
   model's ``(h, w)`` input grid over the windows of the rate model's own resize
   (``adaptive_avg_pool2d``: cell ``i`` covers rows ``floor(i H / h) .. ceil((i + 1) H / h)``,
   columns alike; :func:`pool_matrix`). Weights are 0/1, so integer counts stay exact
   integers in float32 whatever the summation order.
2. the linear stand-in for the patch z-score, folded into L1: ``x = S C diag(1 / n) p``
   with ``p`` the pooled counts, ``n`` each cell's pixels (so ``diag(1 / n) p`` is the
   resized count frame exactly), ``C`` the subtraction of each ``patch x patch`` block's
   mean (linear: exact) and ``S`` a scale in place of the division by each block's own std
   (not linear), calibrated on the **reference windows** only (:func:`block_scales`):
   ``"global"`` (default) one scale, 1 / the median block std; ``"patch"`` one per block,
   1 / the median of that block's std (measured worse on nordland-b:
   ``docs/results/spiking-events.md``). A global scale only rescales the L1 sums, which
   ``theta2`` absorbs: the default stand-in is the centring alone. The graph's ``l1`` is
   ``W1 S C diag(1 / n) / theta2`` (exact in real arithmetic; in float32 the folded weights
   are rounded once, and torchseq runs those same weights, so the consumers agree spike for
   spike).

Everything after L1 (the L2 threshold, the evidence scales, the ring ladder) is calibrated by
:meth:`SpikingSeqSLAM.convert` itself on the reference windows' pooled counts through the
folded ``W1 S C diag(1 / n)``: the one calibration, so a change there flows through here,
including ``weight_bits`` (the folded ``l1`` quantised row by row, ``theta2`` mid-cell of
its sums' grid; ``pool`` is 0/1 at any precision). What the stand-in loses: the
z-score normalises every window by its own contrast; the fixed scale does not, so a window
with twice the events drives L1 twice as hard (``docs/guide/nir.md``, "Camera events into
L1").
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from torchseq.neural.spiking import SpikingConfig, SpikingError, SpikingSeqSLAM

# the dense (D, 2 H W) pool: 2**27 float32 weights = 512 MiB (a DVS128 onto 24 x 32: 25 M)
MAX_POOL_ELEMENTS = 2**27


def pool_matrix(sensor: tuple[int, int],
                size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Sum pooling of both polarities from ``sensor = (H, W)`` onto ``size = (h, w)``.

    Cell ``(i, j)`` sums the pixels of the adaptive window of ``adaptive_avg_pool2d``:
    rows ``floor(i H / h) .. ceil((i + 1) H / h) - 1``, columns alike (windows may overlap
    by a pixel where ``h`` does not divide ``H``).

    Args:
        sensor: ``(H, W)`` sensor pixels, at least ``size`` in both directions.
        size: ``(h, w)`` the model's input grid.

    Returns:
        ``(pool (h w, 2 H W) float32 0/1, cells (h w,) float64 pixels per cell)``; the input
        is flattened channel-major: ``(2, H, W)`` row-major, channel 0 OFF, 1 ON.
    """
    (big_h, big_w), (h, w) = sensor, size
    if h > big_h or w > big_w:
        raise SpikingError(f"the sensor {big_h}x{big_w} is smaller than the model's input "
                           f"{h}x{w}: event input pools down only")
    if h * w * 2 * big_h * big_w > MAX_POOL_ELEMENTS:
        raise SpikingError(f"a {big_h}x{big_w} sensor onto a {h}x{w} input needs a pool "
                           f"matrix of {h * w * 2 * big_h * big_w:,} weights (at most "
                           f"{MAX_POOL_ELEMENTS:,}): bin the events onto a smaller grid first "
                           f"(torchseq.events.accumulate(..., downsample=(H', W')))")
    rows = np.zeros((h, big_h), dtype=np.float32)
    cols = np.zeros((w, big_w), dtype=np.float32)
    for out, n_out, n_in in ((rows, h, big_h), (cols, w, big_w)):
        for i in range(n_out):
            out[i, (i * n_in) // n_out:-(-(i + 1) * n_in // n_out)] = 1.0
    one = np.kron(rows, cols)  # (h w, H W): cell (i, j) <- pixel (r, c)
    pool = np.concatenate([one, one], axis=1)
    return torch.from_numpy(pool), torch.from_numpy(one.sum(1).astype(np.float64))


def check_counts(x: torch.Tensor, sensor: tuple[int, int]) -> torch.Tensor:
    """Checked event counts ``(B, 2, H, W)`` (or flattened ``(B, 2 H W)``) -> ``(B, 2 H W)``.

    Raises:
        SpikingError: another shape or sensor size, NaN or infinite values, negative or
            fractional counts.
    """
    h, w = sensor
    if not isinstance(x, torch.Tensor):
        raise SpikingError(f"event counts must be a tensor, got {type(x).__name__}")
    if x.dim() == 4 and tuple(x.shape[1:]) == (2, h, w):
        x = x.reshape(x.shape[0], 2 * h * w)
    elif not (x.dim() == 2 and x.shape[1] == 2 * h * w):
        raise SpikingError(f"event counts must be (B, 2, {h}, {w}) for the {h}x{w} sensor "
                           f"(OFF, ON), got {tuple(x.shape)}")
    if x.shape[0] == 0:
        raise SpikingError("event counts are empty (no window in the batch)")
    x = x.to(torch.float32)
    if not bool(torch.isfinite(x).all()):
        raise SpikingError("event counts hold NaN or infinite values")
    if bool((x < 0).any()):
        raise SpikingError("event counts must be >= 0 (counts of events per pixel and "
                           "polarity), got negative values")
    if not bool((x == torch.round(x)).all()):
        raise SpikingError("event counts must be whole numbers (events per pixel and "
                           "polarity in one window)")
    return x


def pooled_counts(x: torch.Tensor, sensor: tuple[int, int], pool: torch.Tensor) -> torch.Tensor:
    """The graph's ``pool`` stage: checked counts (:func:`check_counts`) ``@ pool.T``, ``(B, D)``.

    Sums of whole counts with 0/1 weights: exact integers in float32.
    """
    return check_counts(x, sensor) @ pool.T


def block_centring(size: tuple[int, int], patch: int) -> torch.Tensor:
    """``C (D, D)`` float64: minus each ``patch x patch`` block's mean, row-major ``(h, w)``."""
    h, w = size
    block = (torch.arange(h)[:, None] // patch * (w // patch)
             + torch.arange(w)[None, :] // patch).reshape(-1)  # (D,) block of each pixel
    same = (block[:, None] == block[None, :]).to(torch.float64)
    return torch.eye(h * w, dtype=torch.float64) - same / (patch * patch)


SCALES = ("global", "patch")


def block_scales(frames: torch.Tensor, patch: int, scale: str = "global") -> torch.Tensor:
    """Per-pixel scale ``(D,)`` standing in for the division by each block's own std.

    ``"global"``: one scale, 1 / the median of every block's sample std over all reference
    windows (blocks flat in a window left out). ``"patch"``: one scale per block, 1 / the
    median of that block's std over the windows (a block flat on every window takes the
    global median).

    Args:
        frames: ``(R, h, w)`` float64 resized count frames of the reference windows.
        patch: block side.
        scale: ``"global"`` or ``"patch"``.

    Raises:
        SpikingError: an unknown ``scale``, or every block flat on every reference window.
    """
    if scale not in SCALES:
        raise SpikingError(f"scale must be one of {SCALES}, got {scale!r}")
    r, h, w = frames.shape
    blocks = frames.reshape(r, h // patch, patch, w // patch, patch).permute(0, 1, 3, 2, 4)
    std = blocks.reshape(r, h // patch, w // patch, -1).std(-1)  # (R, bh, bw), n - 1
    live = std[std > 0]
    if live.numel() == 0:
        raise SpikingError("the reference windows hold no events (or only flat blocks): "
                           "nothing to calibrate the input scale on")
    overall = live.median()
    if scale == "global":
        return torch.full((h * w,), 1.0 / float(overall), dtype=torch.float64)
    med = std.median(0).values  # (bh, bw)
    med = torch.where(med > 0, med, overall)
    per_pixel = med.repeat_interleave(patch, 0).repeat_interleave(patch, 1)  # (h, w)
    return 1.0 / per_pixel.reshape(-1)


class _FoldedL1:
    """An L1 whose folded weight is given (``W1 S C diag(1 / n)``, the stand-in folded in)."""

    def __init__(self, weight: torch.Tensor) -> None:
        self._weight = weight

    def folded_weight(self) -> torch.Tensor:
        return self._weight


class _EventView:
    """The fitted rate model seen through the event input stage (for ``convert``).

    Its ``encode`` is the pooled event counts of a window (whole numbers), its ``l1`` the
    model's L1 with the linear stand-in of the patch z-score folded in; its config has
    ``input_steps = 1`` (the pooled counts are integers) and ``l1_levels = 0`` (the folded
    weights are on no grid of the model's); everything else is the model's own. So
    :meth:`SpikingSeqSLAM.convert` quantises (``weight_bits``) and calibrates ``theta2`` on
    the very weights the graph's ``l1`` holds.
    """

    def __init__(self, model, encode, folded_l1: torch.Tensor) -> None:
        self._model = model
        self.config = dataclasses.replace(model.config, input_steps=1, l1_levels=0)
        self.encode = encode
        self.l1 = _FoldedL1(folded_l1)

    def __getattr__(self, name):
        return getattr(self._model, name)


class EventSpikingSeqSLAM(SpikingSeqSLAM):
    """The spiking model driven by a sensor's events; build it with :meth:`convert_events`.

    Buffers beside :class:`SpikingSeqSLAM`'s: ``pool (D, 2 H W)`` (0/1); ``w1`` is the
    folded ``W1 S C diag(1 / n) / theta2`` ``(M, D)``. :attr:`sensor` is ``(H, W)``.
    One time step per window: :meth:`forward` takes ``(B, 2, H, W)`` counts (or the same
    flattened ``(B, 2 H W)``, as the NIR graph's input).
    """

    def __init__(self, *args, pool: torch.Tensor, sensor: tuple[int, int], **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.register_buffer("pool", pool.detach().to(torch.float32).contiguous())
        self.sensor = (int(sensor[0]), int(sensor[1]))
        self.register_buffer("_fan_events", (self.pool != 0).sum(0).float(), persistent=False)

    @property
    def sizes(self) -> dict[str, int]:
        """:class:`SpikingSeqSLAM`'s sizes, plus ``events`` ``2 H W`` (the graph's input)."""
        return {**super().sizes, "events": self.pool.shape[1]}

    @classmethod
    @torch.no_grad()
    def convert_events(cls, model, reference: torch.Tensor,
                       config: SpikingConfig | None = None,
                       scale: str = "global") -> EventSpikingSeqSLAM:
        """Convert a fitted rate model for event input, calibrating on the reference windows.

        Args:
            model: a fitted :class:`~torchseq.neural.NeuralSeqSLAM` with ``patch_mode``
                ``"zscore"`` (or ``patch_size`` 0), fitted on the reference windows' count
                frames (the polarities summed: what the frame-driven model sees).
            reference: ``(R, 2, H, W)`` event counts of the reference windows, ``R >= 2``.
            config: :class:`SpikingConfig` (None: defaults). ``weight_bits``: the folded
                ``l1`` (and ``l3``, ``levels``, ``shift``, as for frames) on signed
                ``b``-bit integers times a power of two per row; ``pool`` is 0/1, exact at
                any precision. ``input_threshold`` must be None (events are spikes already).
            scale: the stand-in for the z-score's division (:func:`block_scales`):
                ``"global"`` (default: one scale; measured better than ``"patch"`` on
                nordland-b, docs/results/spiking-events.md) or ``"patch"``.

        Raises:
            SpikingError: bad counts, a sensor smaller than the model's input, a patch mode
                or config without an event form, or :meth:`SpikingSeqSLAM.convert`'s errors.
        """
        cfg = config or SpikingConfig()
        if scale not in SCALES:
            raise SpikingError(f"scale must be one of {SCALES}, got {scale!r}")
        if cfg.input_threshold is not None:
            raise SpikingError("event input is spikes already: input_threshold (which turns "
                               "encoded frames into events) has no meaning here; use "
                               "input_threshold=None")
        if not isinstance(reference, torch.Tensor) or reference.dim() != 4 \
                or reference.shape[1] != 2 or reference.shape[0] < 2:
            raise SpikingError("reference must be (R, 2, H, W) event counts of R >= 2 windows, "
                               f"got {getattr(reference, 'shape', type(reference).__name__)}")
        mc = model.config
        patch = mc.patch_size
        if patch and mc.patch_mode != "zscore":
            raise SpikingError(f"event input stands in for patch_mode='zscore'; the model has "
                               f"{mc.patch_mode!r}")
        sensor = (int(reference.shape[2]), int(reference.shape[3]))
        size = tuple(mc.input_size)
        pool, cells = pool_matrix(sensor, size)
        counts = check_counts(reference, sensor)  # (R, 2 H W)
        resized = (counts.double() @ pool.double().T) / cells  # (R, D): the count frames
        if patch:
            scales = block_scales(resized.reshape(-1, *size), patch, scale)
            linear = scales[:, None] * block_centring(size, patch)
        else:
            scales = None
            linear = torch.eye(len(cells), dtype=torch.float64)
        linear = linear / cells[None, :]  # (D, D): pooled counts -> the stand-in of encode
        folded = (model.l1.folded_weight().detach().double().cpu() @ linear).float()  # (M, D)

        def encode(x: torch.Tensor) -> torch.Tensor:  # pooled counts: exact integers
            return pooled_counts(x, sensor, pool)

        sp = SpikingSeqSLAM.convert(_EventView(model, encode, folded), reference, cfg)
        calibration = {**sp.calibration, "event_input": {
            "sensor": list(sensor), "input_size": list(size), "patch": int(patch),
            "reference_windows": int(reference.shape[0]),
            "scale": scale if patch else "none (no patch normalisation)",
            "block_scales": None if scales is None else
            [float(v) for v in scales.reshape(size)[::patch, ::patch].reshape(-1)]}}
        return cls(sp.w1, sp.w3, sp.inv_theta, sp.rung_step, sp.shift, sp.unit_centre, sp.window,
                   calibration, None, shift_dense=sp.shift_dense, pool=pool, sensor=sensor)

    def forward(self, x: torch.Tensor, state=None):
        """One time step (one window) for ``B`` streams.

        Args:
            x: ``(B, 2, H, W)`` event counts (OFF, ON), or ``(B, 2 H W)`` flattened.
            state: from the previous step (None: zeros).

        Returns:
            ``(SpikingStep, new state)``.
        """
        return super().forward(pooled_counts(x, self.sensor, self.pool), state)

    step = forward

    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        """The graph's input: checked counts ``(T, 2, H, W)`` -> ``(T, 2 H W)`` float32."""
        return check_counts(frames, self.sensor)

    @torch.no_grad()
    def run(self, query: torch.Tensor, encoded: bool = False, raster: bool = False) -> dict:
        """:meth:`SpikingSeqSLAM.run` over event windows ``(T, 2, H, W)`` (or ``(T, 2 H W)``).

        ``"input_events"`` ``(T,)`` is each window's event count.
        """
        x = self.encode(query)
        return {**super().run(x, encoded=True, raster=raster), "input_events": x.sum(1)}

    def _input_ops(self, x: torch.Tensor | None, batch: int) -> torch.Tensor:
        # each event reaches its pool cells; the pooled values drive every L1 synapse
        dense = self.w1.new_full((batch,), self._synapses_l1)
        return dense if x is None else dense + x.reshape(batch, -1) @ self._fan_events


def count_frames(counts: torch.Tensor) -> torch.Tensor:
    """``(T, 2, H, W)`` counts -> ``(T, H, W)`` count frames (both polarities summed).

    What the frame-driven models see: the events accumulated on the host.
    """
    return counts.sum(1)


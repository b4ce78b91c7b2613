"""Convert a fitted float :class:`~torchseq.neural.NeuralSeqSLAM` into an :class:`IntegerModel`.

The fixed-point design (bit widths, shifts, constants) is specified in
``docs/reference/integer_format.md``; every integer comes from the export grids of the one
quantiser, :mod:`torchseq.quantise`.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchseq.export.int_format import (
    INPUT_RAW,
    INPUT_ZSCORE,
    READOUT_CENTRE,
    READOUT_INTERPOLATE,
    X_MAX,
    IntegerFormatError,
    IntegerModel,
)
from torchseq.export.int_stages import VEL_FRAC
from torchseq.neural.search import refuse_export
from torchseq.quantise import fixed_point, fixed_point_array, integer_grid, quantise

SQRT_FRAC = 8  # fractional bits of the patch standard deviation
STATE_FRAC = 16  # fractional bits of the ring activity (int32)
RING_FRAC = 15  # fractional bits of decay * shift (int16)
ROW_SCALE_FRAC = 15  # fractional bits of the L3 per-row scale ratios (int32)
GAIN_BITS = 24  # the gain constant stays below 2**GAIN_BITS


def _rows(mask: torch.Tensor) -> np.ndarray:
    """``(rows, fan_in)`` sorted column indices of a mask with equal ones per row."""
    m = mask.detach().cpu().numpy() != 0
    counts = m.sum(1)
    if counts.size and (counts != counts[0]).any():
        raise IntegerFormatError("mask rows hold different numbers of connections")
    return np.nonzero(m)[1].reshape(m.shape[0], -1)


def integer_model(model, pool: tuple[int, int] = (1, 1)) -> IntegerModel:
    """Quantise a fitted Neural SeqSLAM model into the integer format.

    Args:
        model: a fitted :class:`torchseq.neural.NeuralSeqSLAM`.
        pool: ``(ph, pw)``: the device's frames are ``(h * ph, w * pw)`` uint8 and are summed
            over ``ph x pw`` blocks (exactly the float model's area resize, up to a scale
            the patch z-score removes); ``(1, 1)``: frames arrive at the input size.

    Returns:
        A checked :class:`IntegerModel`.

    Raises:
        IntegerFormatError: the model is unfitted or uses a setting the format cannot hold.
    """
    if not getattr(model, "fitted", False):
        raise IntegerFormatError("the model has not learnt a route yet (fit it first)")
    refuse_export(model, "the integer format (integer_model)", IntegerFormatError)
    cfg = model.config
    if cfg.patch_size and cfg.patch_mode != "zscore":
        raise IntegerFormatError(f"patch_mode {cfg.patch_mode!r} has no integer form "
                                 "(use 'zscore' or patch_size=0)")
    adaptive = getattr(cfg, "ring_velocity", "fixed") == "adaptive"  # format version 3
    readouts = {"centre": READOUT_CENTRE, "interpolate": READOUT_INTERPOLATE}
    readout = getattr(cfg, "readout", "centre")
    if readout not in readouts:
        raise IntegerFormatError(f"readout {readout!r} has no integer form (the format holds "
                                 f"{sorted(readouts)})")
    h, w = cfg.input_size
    n_units = model.n_units
    if max(cfg.n_input, cfg.hidden, n_units) > 32767:
        raise IntegerFormatError("n_input, hidden and n_units must each be below 32768")
    patch = int(cfg.patch_size)
    if min(pool) < 1:
        raise IntegerFormatError(f"pool must be positive, got {pool}")
    p = {"height": h, "width": w, "pool_h": int(pool[0]), "pool_w": int(pool[1]), "patch": patch,
         "n_input": cfg.n_input, "hidden": cfg.hidden,
         "k": cfg.k, "n_units": n_units, "window": min(int(cfg.uniqueness_window), n_units),
         "readout": readouts[readout],
         "sqrt_frac": SQRT_FRAC, "state_frac": STATE_FRAC, "ring_frac": RING_FRAC}
    if patch:
        n = patch * patch
        z_max = (n - 1) / math.sqrt(n)  # largest |z| a block of n samples can hold
        p["x_frac"] = int(math.floor(math.log2(X_MAX / z_max)))
        steps = int(getattr(cfg, "input_steps", 0))
        if steps and 2 ** int(math.log2(steps)) == steps and math.log2(steps) < p["x_frac"]:
            p["x_frac"] = int(math.log2(steps))  # the float model's own input grid
        p["input_mode"] = INPUT_ZSCORE
        p["norm_const"] = fixed_point(math.sqrt((n - 1) / n), p["x_frac"] + SQRT_FRAC, 32)
    else:
        p.update(x_frac=0, input_mode=INPUT_RAW, norm_const=0)
    a = {}
    # L1 -> L2: 12 bits, one per-tensor scale (the k-WTA only needs the order of the sums).
    cols1 = _rows(model.l1.mask)
    w1 = model.l1.folded_weight().detach().cpu().numpy()
    q1 = integer_grid(np.take_along_axis(w1, cols1, 1), bits=12)
    a["l1.cols"], a["l1.values"] = cols1.astype("<u2"), q1.values.astype("<i2")
    p["l1_fan_in"] = cols1.shape[1]
    # L2 -> L3: per-row scales, stored as ratios to the largest on a 2**-15 grid.
    cols3 = _rows(model.l3.mask)
    w3 = model.l3.folded_weight().detach().cpu().numpy()
    q3 = quantise(np.take_along_axis(w3, cols3, 1), bits=8, per_row=True)
    nonzero = np.abs(q3.values).max(1) > 0
    top = q3.scale[nonzero].max() if nonzero.any() else 1.0
    ratio = np.where(nonzero, q3.scale / top, 0.0)
    a["l3.cols"], a["l3.values"] = cols3.astype("<u2"), q3.values
    a["l3.row_scale"] = fixed_point_array(ratio, ROW_SCALE_FRAC, 32)
    p["l3_fan_in"] = cols3.shape[1]
    p["e_shift"] = ROW_SCALE_FRAC + max(0, math.ceil(math.log2(cfg.k * 127 / 32767)))
    # cohorts and the gain: g = gain * z on the activity grid.
    a["cohort"] = model.cohorts.detach().cpu().numpy().argmax(1).astype("<u2")
    p["n_cohorts"] = int(model.cohorts.shape[1])
    p["rectify"] = int(bool(getattr(cfg, "rectify", False)))
    gain = float(model.ring.params.gain)
    p["gain_shift"] = GAIN_BITS - 1 - STATE_FRAC - math.floor(math.log2(gain))
    if p["gain_shift"] < 0:
        raise IntegerFormatError(f"ring gain {gain} is too large for the integer format")
    p["gain_const"] = fixed_point(gain, STATE_FRAC + p["gain_shift"], GAIN_BITS + 1)
    # the ring: decay * shift on a 2**-15 grid, stored row by row as (cols, values) lists.
    ring = fixed_point_array(model.ring.params.decay * model.ring.shift.detach().cpu().double(),
                             RING_FRAC, 16)
    # the adaptive ring also stores the shift alone (no decay), at the same columns
    shift = (fixed_point_array(model.ring.shift.detach().cpu().double(), RING_FRAC, 32)
             if adaptive else np.zeros_like(ring, np.int32))
    keep = (ring != 0) | (shift != 0)
    width = max(1, int(keep.sum(1).max()))
    cols = np.tile(np.arange(n_units)[:, None], (1, width))  # padding: own column, value 0
    vals = np.zeros((n_units, width), "<i2")
    shift_vals = np.zeros((n_units, width), "<i4")
    for u in range(n_units):
        nz = np.nonzero(keep[u])[0]
        cols[u, :nz.size], vals[u, :nz.size] = nz, ring[u, nz]
        shift_vals[u, :nz.size] = shift[u, nz]
    a["ring.cols"], a["ring.values"] = cols.astype("<u2"), vals
    p["ring_width"] = width
    if adaptive:
        p.update(_velocity_params(model))
        a["ring.shift"] = shift_vals
    a["unit_centre"] = model.unit_centre.detach().cpu().numpy().astype("<i4")
    a["unit_to_ref"] = model.unit_to_reference.detach().cpu().numpy().astype("<i4")
    return IntegerModel.from_params({k: int(v) for k, v in p.items()}, a)


def _velocity_params(model) -> dict:
    """The adaptive ring's version-3 parameters (speeds, tolerance and rate on ``2**-16``)."""
    from torchseq.neural.velocity import VelocityTracker

    tracker = VelocityTracker.from_model(model)
    rate = fixed_point(tracker.rate, VEL_FRAC)
    if rate < 1:
        raise IntegerFormatError(f"velocity_rate {tracker.rate} is below the integer "
                                 f"format's grid (2**-{VEL_FRAC})")
    return {"decay_const": fixed_point(float(model.ring.params.decay), RING_FRAC, 32),
            "velocity_window": int(tracker.window),
            "v_min": fixed_point(tracker.v_min, VEL_FRAC),
            "v_max": fixed_point(tracker.v_max, VEL_FRAC),
            "v_tolerance": fixed_point(tracker.tolerance, VEL_FRAC), "v_rate": rate}


def choose_pool(frame_size: tuple[int, int], input_size: tuple[int, int]) -> tuple[int, int]:
    """The pooling factor a device uses for camera frames of ``frame_size``.

    ``(H0 // h, W0 // w)`` when the frames are exact multiples of the input size (the device
    then sums pixel blocks, exactly the float model's area resize), else ``(1, 1)`` (the host
    resizes to the input size and rounds).
    """
    (h0, w0), (h, w) = frame_size, input_size
    if h0 % h == 0 and w0 % w == 0 and h0 >= h and w0 >= w:
        return h0 // h, w0 // w
    return 1, 1


def device_frames(frames, input_size: tuple[int, int], pool: tuple[int, int]) -> np.ndarray:
    """Host side: frames as the integer device takes them, uint8 ``(T, h * ph, w * pw)``.

    Args:
        frames: ``(T, H, W)`` grey or ``(T, H, W, 3)`` RGB, 0..255, any size.
        input_size: the model's ``(h, w)``.
        pool: ``(ph, pw)`` of the integer model.

    Returns:
        Grey frames resized (only when not already that size; area/bilinear as the float
        model) and rounded half away from zero to uint8.
    """
    from torchseq.preprocess import resize, round_half_away, to_grey

    grey = to_grey(torch.as_tensor(frames)).to(torch.float32)
    size = (input_size[0] * pool[0], input_size[1] * pool[1])
    grey = resize(grey, size)
    return round_half_away(grey).clamp(0, 255).to(torch.uint8).numpy()

"""The input checks of one step, shared by the model's layers and :class:`NeuralInference`.

Both forms of the step (``NeuralSeqSLAM.step``, the definition, and
``NeuralInference.step``, its kernels) refuse the same bad input with the same one-line
:class:`~torchseq.neural.NeuralError`: frames of the wrong shape, empty or not finite, and a
state of the wrong type or size.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchseq.layers.ring import RingState
from torchseq.neural.config import NeuralError
from torchseq.neural.velocity import VelocityState, VelocityTracker
from torchseq.preprocess import resize, to_grey


def checked_grey(frames: torch.Tensor, size: tuple[int, int], device) -> torch.Tensor:
    """Checked raw frames ``(B, H, W)`` / ``(B, H, W, 3)`` -> float32 grey ``(B, h, w)``."""
    if frames.dim() not in (3, 4) or (frames.dim() == 4 and frames.shape[-1] != 3):
        raise NeuralError(f"frames must be (B, H, W) or (B, H, W, 3), got "
                          f"{tuple(frames.shape)}")
    if frames.shape[0] == 0:
        raise NeuralError("frames are empty (no frame in the batch)")
    if (frames.dim() == 3 and frames.dtype == torch.float32 and frames.device.type == "cpu"
            and torch.device(device).type == "cpu" and tuple(frames.shape[1:]) == tuple(size)):
        # the online case (one float32 frame at the input size): one NumPy sum
        flat = frames.detach().numpy().reshape(-1)
        with np.errstate(over="ignore", invalid="ignore"):
            total = float(np.add.reduce(flat))
        if not math.isfinite(total) and not np.isfinite(flat).all():
            raise NeuralError("frames hold NaN or infinite values")
        return frames
    x = to_grey(frames.to(device)).to(torch.float32)
    # one sum first (NaN and inf propagate), the element-wise test only when it fails
    if not bool(torch.isfinite(x.sum())) and not bool(torch.isfinite(x).all()):
        raise NeuralError("frames hold NaN or infinite values")
    return resize(x, size)


def checked_state(state, batch: int, n_units: int, tracker: VelocityTracker | None):
    """The state a step starts from, checked; None stays None (the start of the streams).

    Args:
        state: what the caller passed.
        batch: ``B``, the frames' batch size.
        n_units: ``N``, the ring's units.
        tracker: the adaptive ring's estimator (None: a fixed ring).

    Returns:
        A fixed ring's :class:`~torchseq.layers.RingState` (from a ``RingState``, or a
        :class:`~torchseq.neural.VelocityState`'s activity), or the adaptive ring's
        ``VelocityState`` as given.

    Raises:
        NeuralError: another type, or shapes that do not fit ``B`` streams of ``N`` units.
    """
    if state is None:
        return None
    if tracker is not None:
        tracker.check(state, batch, n_units)
        return state
    if type(state) is not RingState or not isinstance(state.activity, torch.Tensor):
        state = _ring_state(state)
    if state.activity.shape != (batch, n_units):
        raise NeuralError(f"state must be ({batch}, {n_units}), got "
                          f"{tuple(state.activity.shape)}")
    return state


def _ring_state(state) -> RingState:
    """A fixed-velocity model's state: a RingState, or a VelocityState's activity."""
    if isinstance(state, VelocityState):
        return RingState(state.activity)
    if not isinstance(state, RingState) or not isinstance(state.activity, torch.Tensor):
        raise NeuralError(f"a fixed-velocity model steps with a RingState (or a VelocityState, "
                          f"whose activity it reads; None at the start), got "
                          f"{type(state).__name__}")
    return state

"""The onnxruntime side of the export: sessions and the loops that stream a traverse through them.

Every onnxruntime call of the package is here (the float, quantised and integer graphs are
run the same way: one session, the state fed back frame by frame), so the graph builders
(:mod:`torchseq.export.onnx_float`, :mod:`torchseq.export.int_onnx`) never import the runtime,
and the validation (:mod:`torchseq.export.validate`) imports both sides without a loop.
``onnxruntime`` itself is imported only when a session is made.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx

from torchseq.export.int_onnx import VELOCITY_INPUTS as INT_VELOCITY_INPUTS
from torchseq.export.int_velocity import initial_velocity_state
from torchseq.export.onnx_float import FIXED_INPUTS as FLOAT_INPUTS
from torchseq.export.onnx_float import VELOCITY_INPUTS as FLOAT_VELOCITY_INPUTS


def session(model: onnx.ModelProto | str | Path, threads: int = 1):
    """An onnxruntime CPU session (``threads`` intra-op threads, one inter-op thread)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    src = model.SerializeToString() if isinstance(model, onnx.ModelProto) else str(model)
    return ort.InferenceSession(src, opts, providers=["CPUExecutionProvider"])


def run_step_session(sess, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stream a traverse ``(T, H, W)`` through a step graph (float or integer), frame by frame.

    The state is fed back; its dtype (int32 or float32) is read off the graph.

    Returns:
        ``(reference (T,), confidence (T,), activity (T, N))``.
    """
    state_input = sess.get_inputs()[1]
    dtype = np.int32 if state_input.type == "tensor(int32)" else np.float32
    state = np.zeros((1, state_input.shape[1]), dtype)
    refs, confs, acts = [], [], []
    for t in range(frames.shape[0]):
        act, state, ref, conf = sess.run(None, {"frames": frames[t:t + 1], "state": state})
        refs.append(ref)
        confs.append(conf)
        acts.append(act)
    return np.concatenate(refs), np.concatenate(confs), np.concatenate(acts)


def run_integer_onnx(sess, frames: np.ndarray,
                     speeds: bool = False) -> tuple[np.ndarray, ...]:
    """Stream a ``(T, H, W)`` uint8 traverse through an integer session (int32 state).

    A graph of the adaptive ring (inputs ``velocity``, ``positions``, ``count``) is fed its
    estimator state back too.

    Args:
        sess: the integer graph's session.
        frames: the traverse.
        speeds: also return the speed after each frame (adaptive ring only).

    Returns:
        ``(reference (T,), confidence (T,), activity (T, N) int32)``, and ``speed (T,)``
        int64 (``2**-16`` grid) with ``speeds``.
    """
    names = [i.name for i in sess.get_inputs()]
    if not set(INT_VELOCITY_INPUTS) <= set(names):
        if speeds:
            raise ValueError("speeds: the graph has the fixed ring (no speed estimate)")
        return run_step_session(sess, frames)
    n_units, window = sess.get_inputs()[1].shape[1], sess.get_inputs()[3].shape[1]
    state = initial_velocity_state(1, n_units, window)
    feed = dict(zip(["state", *INT_VELOCITY_INPUTS], state))
    refs, confs, acts, vs = [], [], [], []
    for t in range(frames.shape[0]):
        act, new, ref, conf, v, pos, n = sess.run(None, {"frames": frames[t:t + 1], **feed})
        feed = {"state": new, "velocity": v, "positions": pos, "count": n}
        refs.append(ref)
        confs.append(conf)
        acts.append(act)
        vs.append(v)
    out = np.concatenate(refs), np.concatenate(confs), np.concatenate(acts)
    return (*out, np.concatenate(vs)) if speeds else out


def run_float_onnx(sess, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stream ``(T, h, w)`` float32 frames through a float session, feeding the state back.

    Adaptive-velocity graphs (a ``velocity`` input) run through :func:`run_velocity_onnx`.

    Returns:
        ``(reference (T,), confidence (T,), activity (T, N))``.
    """
    if "velocity" in [i.name for i in sess.get_inputs()]:
        return run_velocity_onnx(sess, frames)[:3]
    return run_step_session(sess, frames)


def run_velocity_onnx(sess, frames: np.ndarray):
    """Stream ``(T, h, w)`` float32 frames through an adaptive-velocity float session.

    The whole state (activity, velocity, positions, count) is fed back, from the start state
    of :meth:`~torchseq.neural.velocity.VelocityTracker.initial` (window read off the graph).

    Returns:
        ``(reference (T,), confidence (T,), activity (T, N), velocity (T,))``: ``velocity[t]``
        is the speed estimate after frame ``t`` (the one frame ``t + 1`` steps at).
    """
    inputs = {i.name: i for i in sess.get_inputs()}
    n_units, window = inputs["state"].shape[1], inputs["positions"].shape[1]
    state = [np.zeros((1, n_units), np.float32), np.ones(1), np.zeros((1, window)),
             np.zeros(1, np.int64)]
    names = FLOAT_INPUTS[1:] + FLOAT_VELOCITY_INPUTS
    refs, confs, acts, vels = [], [], [], []
    for t in range(frames.shape[0]):
        act, new_state, ref, conf, *rest = sess.run(
            None, {"frames": frames[t:t + 1], **dict(zip(names, state))})
        state = [new_state, *rest]
        refs.append(ref)
        confs.append(conf)
        acts.append(act)
        vels.append(rest[0])
    return (np.concatenate(refs), np.concatenate(confs), np.concatenate(acts),
            np.concatenate(vels))

"""Plain-Python references for event frames: events accumulated one at a time, pooled by loops."""

import numpy as np


def add_event(frame: np.ndarray, e, mode: str) -> None:
    """One event into a ``(H, W)`` frame by ``mode``: +-1 signed, 1 binary, +1 count."""
    if mode == "signed":
        frame[e["y"], e["x"]] += 1 if e["p"] else -1
    elif mode == "binary":
        frame[e["y"], e["x"]] = 1
    else:
        frame[e["y"], e["x"]] += 1

def loop_frames(ev, w, h, window_us=None, event_count=None, mode="signed", origin=None):
    """Plain-Python reference: one event at a time into a list of frames."""
    t0 = int(ev["t"].min()) if origin is None else origin
    ev = [e for e in ev if int(e["t"]) >= t0]
    chans = 2 if mode == "two_channel" else 1
    frames = {}
    for i, e in enumerate(ev):
        k = i // event_count if event_count else (int(e["t"]) - t0) // window_us
        f = frames.setdefault(k, np.zeros((chans, h, w)))
        add_event(f[int(e["p"]) if chans == 2 else 0], e, mode)
    n = max(frames) + 1
    out = np.stack([frames.get(k, np.zeros((chans, h, w))) for k in range(n)])
    return out if chans == 2 else out[:, 0]


def loop_pool(frames, out_h, out_w):
    """Block mean for integer factors, written as loops."""
    h, w = frames.shape[-2:]
    fh, fw = h // out_h, w // out_w
    out = np.zeros(frames.shape[:-2] + (out_h, out_w))
    for i in range(out_h):
        for j in range(out_w):
            block = frames[..., i * fh:(i + 1) * fh, j * fw:(j + 1) * fw]
            out[..., i, j] = block.mean(axis=(-2, -1))
    return out


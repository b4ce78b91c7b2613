"""Event traverses of one route at chosen speeds, with exact ground truth.

A route is a sequence of frames at known positions (pixels along the demo strip, or frame
indices of an image traverse). A run drives along it at ``speed`` times the reference run's
speed: frame ``i`` at position ``pos[i]`` is seen at time ``pos[i] / (speed * units_per_s)``,
and :func:`~torchseq.events.simulator.frames_to_events` fills in the events. Window ``k``
of a run (``window_us`` long) is centred at route position
``(k + 0.5) * window_us * speed * units_per_s / 1e6``, so the ground truth between two runs
follows from the positions exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from torchseq.events.frames import accumulate
from torchseq.events.simulator import frames_to_events
from torchseq.events.stream import EventStream


@dataclass
class EventRun:
    """One simulated traverse.

    Attributes:
        stream: its events (first frame at t = 0).
        speed: speed relative to the reference run.
        units_per_s: the reference run's speed, in route units (pixels, frames) per second.
    """

    stream: EventStream
    speed: float
    units_per_s: float

    def window_positions(self, n_windows: int, window_us: int) -> np.ndarray:
        """``(n_windows,)`` route position at the centre of each window."""
        return (np.arange(n_windows) + 0.5) * window_us * 1e-6 * self.speed * self.units_per_s

    def windows(self, n_windows: int, window_us: int) -> torch.Tensor:
        """Event counts of the first ``n_windows`` windows from time 0, ``(n, 2, H, W)``.

        :func:`~torchseq.events.accumulate` (``"two_channel"``: channel 0 OFF, 1 ON,
        ``anchor="zero"``); events after the last window (a threshold crossing on the last
        frame's time) are counted in the last one, so a run of ``T`` frames one window apart
        gives ``T - 1`` windows holding every event. Float32.
        """
        w, h = self.stream.sensor_size
        out = torch.zeros(n_windows, 2, h, w)
        if len(self.stream) == 0 or n_windows < 1:
            return out
        c = accumulate(self.stream, window_us=window_us, mode="two_channel", anchor="zero")
        n = min(n_windows, c.shape[0])
        out[:n] = c[:n]
        if c.shape[0] > n_windows:
            out[n_windows - 1] += c[n_windows:].sum(0)
        return out


def simulate_run(frames: np.ndarray, positions: np.ndarray, speed: float, units_per_s: float,
                 seed: int = 0, **simulator_options) -> EventRun:
    """Simulate driving along a route at ``speed`` (1 = the reference run).

    Args:
        frames: ``(T, H, W)`` views of the route in 0..255.
        positions: ``(T,)`` strictly increasing route position of each frame.
        speed: relative speed (0.66 = 66% of the reference run's speed).
        units_per_s: the reference run's speed in route units per second.
        seed: simulator seed (threshold and background noise).
        **simulator_options: passed to :func:`frames_to_events`.
    """
    positions = np.asarray(positions, dtype=np.float64)
    times = (positions - positions[0]) / (speed * units_per_s) * 1e6
    stream = frames_to_events(frames, timestamps_us=times, seed=seed, **simulator_options)
    return EventRun(stream, float(speed), float(units_per_s))


def ground_truth(reference_positions: np.ndarray, query_positions: np.ndarray,
                 tolerance: float) -> np.ndarray:
    """``(R, Q)`` bool: reference window within ``tolerance`` route units of the query's.

    Positions are products of floats (:meth:`EventRun.window_positions`), so two windows
    exactly ``tolerance`` apart can differ by a rounding more: differences within a few ulps
    of the positions' magnitude above ``tolerance`` count as within it.
    """
    r = np.asarray(reference_positions, dtype=np.float64)
    q = np.asarray(query_positions, dtype=np.float64)
    scale = max(float(np.abs(r).max(initial=0.0)), float(np.abs(q).max(initial=0.0)), 1.0)
    slack = 16 * np.finfo(np.float64).eps * scale
    return np.abs(r[:, None] - q[None, :]) <= tolerance + slack

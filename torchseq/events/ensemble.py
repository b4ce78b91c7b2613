"""Temporal-window ensembles: frames at several window lengths from one pass over the events.

Fischer and Milford (2020) matched event traverses with an *ensemble* of window lengths:
one frame per place and window length, one difference matrix per length, the matrices
combined. Here every member shares the frame times: frame ``k`` of every member is centred
at ``c_k = origin + (k + 0.5) * step_us`` and covers ``[c_k - L/2, c_k + L/2)`` for its
length ``L``, so frame ``k`` describes the same place in every member and ground truth is
the same for all (with ``L = step_us`` it is exactly :func:`accumulate`'s frame ``k``).

One pass: the events are binned once into base windows of ``gcd`` length (the step, the
lengths and their offsets ``(L - step) / 2``), and each member frame is a difference of a
float64 prefix sum over base windows (exact for integer counts). Events before the anchor
are dropped, as in :func:`accumulate`; windows reaching before the anchor or past the last
event simply hold fewer events.

:func:`match_ensemble` combines the members for SeqSLAM: each member's difference matrix is
contrast-enhanced on its own (SeqSLAM's local z-score, so no member dominates by scale),
the enhanced matrices are averaged, and the sequence search runs on the average.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np
import torch

from torchseq.events.filters import check_events_present
from torchseq.events.frames import MODES, accumulate, window_origin
from torchseq.events.stream import EventStream, as_event_array, infer_sensor_size
from torchseq.matches import Matches
from torchseq.seqslam import (
    SeqSLAM,
    SeqSLAMConfig,
    SeqSLAMResult,
    difference_matrix,
    enhance_contrast,
    search,
)


def ensemble_base(step_us: int, windows_us: Sequence[int]) -> int:
    """Length of the base windows every member frame is a whole number of (us)."""
    if step_us <= 0 or not windows_us or min(windows_us) <= 0:
        raise ValueError("step_us and every window length must be > 0")
    g = int(step_us)
    for L in windows_us:
        if (int(L) - int(step_us)) % 2:
            raise ValueError(f"window {L} us and step {step_us} us must differ by an even number "
                             f"of microseconds (frames share their centres)")
        g = math.gcd(g, int(L), abs(int(L) - int(step_us)) // 2)
    return g


def accumulate_ensemble(events: EventStream | np.ndarray, windows_us: Sequence[int],
                        step_us: int = 10_000, sensor_size: tuple[int, int] | None = None,
                        mode: str = "count", downsample: tuple[int, int] | None = None,
                        anchor: str | int = "first", device: torch.device | str | None = None,
                        dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Frames at several window lengths sharing their centres, in one pass over the events.

    Args:
        events: an :class:`EventStream` or structured array.
        windows_us: the member window lengths ``L`` (us), e.g. ``(10_000, 20_000, 40_000)``;
            each must differ from ``step_us`` by an even number of us.
        step_us: time between consecutive frame centres (us).
        sensor_size: ``(W, H)`` (default: the stream's).
        mode: as :func:`accumulate` (``"binary"`` is taken per member window).
        downsample: ``(H', W')`` area pooling, as :func:`accumulate`.
        anchor: ``"first"``, ``"zero"`` or an int sensor time (us); events before it are
            dropped.
        device: where to build the frames.
        dtype: output dtype.

    Returns:
        ``(M, T, H, W)`` (``(M, T, 2, H, W)`` for ``"two_channel"``), ``M = len(windows_us)``,
        ``T`` the number of ``step_us`` windows :func:`accumulate` gives for the same anchor.
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    base = ensemble_base(step_us, windows_us)
    if isinstance(events, EventStream):
        sensor_size = sensor_size or events.sensor_size
        events = events.events
    events = as_event_array(events)
    check_events_present(events)
    sensor_size = tuple(sensor_size) if sensor_size else infer_sensor_size(events)
    origin = window_origin(events["t"], anchor)  # accumulate below drops events before it
    n_frames = (int(events["t"].max()) - origin) // int(step_us) + 1
    base_mode = "count" if mode == "binary" else mode
    frames = accumulate(events, sensor_size, window_us=base, mode=base_mode,
                        downsample=None if mode == "binary" else downsample, anchor=origin,
                        device=device, dtype=torch.float64)  # (B, ...) exact integers
    n_base = frames.shape[0]
    prefix = torch.zeros((n_base + 1,) + frames.shape[1:], dtype=torch.float64,
                         device=frames.device)
    torch.cumsum(frames, 0, out=prefix[1:])
    del frames
    k = torch.arange(n_frames, device=prefix.device)
    members = []
    for L in windows_us:
        start = (k * int(step_us) + (int(step_us) - int(L)) // 2) // base
        stop = start + int(L) // base
        m = prefix[stop.clamp(0, n_base)] - prefix[start.clamp(0, n_base)]
        if mode == "binary":
            m = (m > 0).to(torch.float64)
            if downsample is not None:
                m = torch.nn.functional.adaptive_avg_pool2d(m, tuple(int(v) for v in downsample))
        members.append(m.to(dtype))
    return torch.stack(members)


def match_ensemble(reference: Sequence[torch.Tensor], query: Sequence[torch.Tensor],
                   config: SeqSLAMConfig | None = None,
                   device: torch.device | str | None = None) -> SeqSLAMResult:
    """SeqSLAM on an ensemble: per-member enhanced difference matrices, averaged, searched.

    Args:
        reference: ``M`` reference traverses ``(R, H, W)`` (one per window length, e.g. the
            members of :func:`accumulate_ensemble`, made grey as for single windows).
        query: ``M`` query traverses ``(Q, H, W)``, same member order.
        config: SeqSLAM parameters (image size, patch normalisation, ds, velocities, ...).
        device: where to compute.

    Returns:
        A :class:`~torchseq.seqslam.SeqSLAMResult` whose ``difference`` is the mean of the
        members' difference matrices and ``enhanced`` the averaged enhanced matrix searched.
    """
    if len(reference) != len(query) or len(reference) == 0:
        raise ValueError(f"need the same number (>= 1) of reference and query members, got "
                         f"{len(reference)} and {len(query)}")
    engine = SeqSLAM(config, device)
    c = engine.config
    t0 = time.perf_counter()
    diffs, enhanced = [], []
    for ref, qry in zip(reference, query):
        if len(qry) < c.sequence_length + 1:
            raise ValueError(f"need at least ds + 1 = {c.sequence_length + 1} query frames")
        d = difference_matrix(engine.descriptors(ref), engine.descriptors(qry), c.metric,
                              c.max_chunk_elements)
        diffs.append(d)
        enhanced.append(enhance_contrast(d, c.enhance_window, True, c.max_chunk_elements))
    shapes = {tuple(d.shape) for d in diffs}
    if len(shapes) != 1:
        raise ValueError(f"members give difference matrices of different shapes {shapes}")
    combined = torch.stack(enhanced).mean(0)
    match, best, ratio, ranked = search(combined, c.sequence_length, engine.speeds, c.rwindow,
                                        c.top_k, c.max_chunk_elements, False, c.match_rule,
                                        edges=c.edges)
    return SeqSLAMResult(
        matches=Matches(match.cpu(), ratio.cpu(), lower_is_better=True),
        difference=torch.stack(diffs).mean(0).cpu(), enhanced=combined.cpu(),
        ranked=ranked.cpu(), best_score=best.cpu(),
        seconds={"total": time.perf_counter() - t0})

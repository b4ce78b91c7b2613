"""A built-in demo data set: traverses of one synthetic route, with exact ground truth.

The world is a long textured panorama strip (smooth multi-scale noise, "buildings" and
"poles"); a camera looks at a ``W``-pixel-wide window of it and moves along the strip. The
reference traverse moves ``step`` pixels per frame; the query moves ``speed * step`` pixels per
frame, under different lighting (gain, gamma, a brightness gradient) with sensor noise. Every
frame's position along the strip is known, so the ground truth is exact. Deterministic under
``seed``; needs no download.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch


@dataclass
class DemoRoute:
    """Two traverses of the demo route.

    Attributes:
        reference: ``(R, H, W)`` float32 grey frames, 0..255.
        query: ``(Q, H, W)`` float32 grey frames, 0..255.
        reference_position: ``(R,)`` float64 position of each reference frame, in reference frames.
        query_position: ``(Q,)`` float64 position of each query frame, in reference frames.
        ground_truth: ``(R, Q)`` bool, True where reference ``i`` is within ``tolerance``
            reference frames of query ``j`` (None when made with ``dense_ground_truth=False``).
        tolerance: the ground truth's tolerance in reference frames.
    """

    reference: torch.Tensor
    query: torch.Tensor
    reference_position: np.ndarray
    query_position: np.ndarray
    ground_truth: np.ndarray | None
    tolerance: float


def make_world(length: int, height: int, seed: int = 0) -> np.ndarray:
    """Draw a textured panorama strip.

    Args:
        length: strip length in pixels.
        height: strip height in pixels.
        seed: random seed.

    Returns:
        ``(height, length)`` float32 in 0..255.
    """
    rng = np.random.default_rng(seed)
    world = np.zeros((height, length), np.float32)
    for cell, weight in ((32, 0.5), (12, 0.3), (4, 0.2)):  # smooth noise at three scales
        coarse = rng.random((height // cell + 2, length // cell + 2), dtype=np.float32)
        world += weight * cv2.resize(coarse, (length, height), interpolation=cv2.INTER_CUBIC)
    world = (world - world.min()) / max(float(np.ptp(world)), 1e-6) * 120 + 40
    x = 0
    while x < length:  # buildings: flat blocks of random height, width and shade
        w = int(rng.integers(height // 4, height))
        top = int(rng.integers(0, height // 2))
        world[top:, x : x + w] = 0.5 * world[top:, x : x + w] + 0.5 * rng.uniform(10, 245)
        x += w + int(rng.integers(0, height // 3))
    for _ in range(length // 40):  # poles: thin dark or bright vertical bars
        x = int(rng.integers(0, length - 3))
        world[:, x : x + int(rng.integers(1, 4))] = rng.choice([15.0, 235.0])
    return np.clip(world, 0, 255)


def render(world: np.ndarray, left_edges: np.ndarray, width: int) -> np.ndarray:
    """Cut camera views out of the strip at sub-pixel positions (linear interpolation).

    Args:
        world: ``(H, L)`` strip.
        left_edges: ``(T,)`` float left edge of each view, in pixels.
        width: view width in pixels.

    Returns:
        ``(T, H, width)`` float32.
    """
    cols = left_edges[:, None] + np.arange(width)[None, :]  # (T, W)
    lo = np.floor(cols).astype(np.int64)
    frac = (cols - lo).astype(np.float32)[:, None, :]
    lo = np.clip(lo, 0, world.shape[1] - 2)
    left = world[:, lo].transpose(1, 0, 2)  # (T, H, W)
    right = world[:, lo + 1].transpose(1, 0, 2)
    return left * (1 - frac) + right * frac


def relight(frames: np.ndarray, gain: float, gamma: float, gradient: float, noise: float,
            rng: np.random.Generator) -> np.ndarray:
    """Change the lighting of frames and add Gaussian sensor noise.

    Args:
        frames: ``(T, H, W)`` in 0..255.
        gain: multiplicative brightness.
        gamma: exponent on normalised intensity.
        gradient: left-to-right brightness ramp, as a fraction of full scale.
        noise: std of the additive Gaussian noise, in grey levels.
        rng: random generator.

    Returns:
        ``(T, H, W)`` float32 in 0..255.
    """
    out = 255.0 * (frames / 255.0) ** gamma * gain
    out = out + gradient * 255.0 * np.linspace(-0.5, 0.5, frames.shape[2])[None, None, :]
    out = out + rng.normal(0.0, noise, frames.shape)
    return np.clip(out, 0, 255).astype(np.float32)


def make_demo(
    n_reference: int = 200,
    speed: float = 0.8,
    size: tuple[int, int] = (96, 128),
    step: float = 8.0,
    tolerance: float = 2.0,
    gain: float = 0.8,
    gamma: float = 1.3,
    gradient: float = 0.15,
    noise: float = 6.0,
    seed: int = 0,
    repeat: int = 1,
    dense_ground_truth: bool = True,
) -> DemoRoute:
    """Make a reference and a query traverse of one synthetic route.

    Args:
        n_reference: frames in the reference traverse.
        speed: query speed relative to the reference (reference frames per query frame), so
            the query has about ``n_reference / speed`` frames.
        size: ``(H, W)`` of the frames.
        step: reference camera motion per frame, in pixels.
        tolerance: ground-truth tolerance in reference frames.
        gain: the query's brightness gain (see :func:`relight`).
        gamma: the query's gamma.
        gradient: the query's left-to-right brightness ramp.
        noise: the query's sensor noise std in grey levels (the reference gets 2.0).
        seed: random seed; the same seed gives the same traverses.
        repeat: repetitive scenery: with ``repeat = r >= 2`` the middle half of the route
            (from 25% to 75% of the reference frames) shows ``r`` identical copies of one
            stretch of scenery (a whole number of reference frames long; with integer
            ``step``, frames one copy apart are identical up to sensor noise), so places
            there differ only by where the route came from.
            ``1`` (the default) leaves the world as drawn.
        dense_ground_truth: build the ``(R, Q)`` ground-truth matrix; False leaves
            ``ground_truth`` None (long routes: 20,000 frames would need a 500 MB matrix and
            a 4 GB temporary; the positions give the ground truth exactly).

    Returns:
        A :class:`DemoRoute`.
    """
    if n_reference < 2 or speed <= 0 or step <= 0:
        raise ValueError("need n_reference >= 2, speed > 0 and step > 0")
    if int(repeat) != repeat or repeat < 1:
        raise ValueError(f"repeat must be a positive integer, got {repeat}")
    h, w = size
    world = make_world(int(np.ceil(n_reference * step)) + w + 2, h, seed)
    if repeat > 1:
        lo = int(round(round(0.25 * n_reference) * step))
        seg = int(round(max(1, round(0.5 * n_reference / repeat)) * step))
        for i in range(1, int(repeat)):
            world[:, lo + i * seg: lo + (i + 1) * seg] = world[:, lo: lo + seg]
    rng = np.random.default_rng(seed + 1)
    ref_pos = np.arange(n_reference, dtype=np.float64)
    n_query = int(np.floor((n_reference - 1) / speed)) + 1
    query_pos = np.arange(n_query, dtype=np.float64) * speed
    ref = relight(render(world, ref_pos * step, w), 1.0, 1.0, 0.0, 2.0, rng)
    query = relight(render(world, query_pos * step, w), gain, gamma, gradient, noise, rng)
    gt = np.abs(ref_pos[:, None] - query_pos[None, :]) <= tolerance if dense_ground_truth else None
    return DemoRoute(torch.from_numpy(ref), torch.from_numpy(query), ref_pos, query_pos, gt,
                     tolerance)

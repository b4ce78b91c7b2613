"""The eval report's figures drawn straight into images with NumPy and OpenCV (no matplotlib).

A SeqSLAM eval's figures are images with a few marks on them: the difference matrix (the
area-reduced matrix, the ground-truth band, the matches as dots), matched frame pairs and the
precision-recall curves. Drawing them here costs milliseconds and imports nothing beyond
OpenCV, which reads the frames anyway; :mod:`torchseq.cli.plots` (matplotlib) stays for the
neural activity raster and the training figures, and is imported only by runs that draw those.

Each ``draw_*`` function draws a matplotlib-style figure (title, axis labels and ticks, legend,
matplotlib's tab10 colours) and returns an ``(H, W, 3)`` uint8 RGB image for
:func:`torchseq.cli.plots.save_image` and TensorBoard.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch

from torchseq.cli.plots import PLOT_SIDE  # matrices are area-reduced as the plots reduce them
from torchseq.ground_truth import GroundTruthRanges, admits
from torchseq.matches import Matches
from torchseq.metrics import PRCurve, auc

WHITE = (255, 255, 255)
BLACK = (0, 0, 0)
# matplotlib's tab10 colours (RGB), which the matplotlib figures use
BLUE, GREEN, RED = (31, 119, 180), (44, 160, 44), (214, 39, 40)
TAB10 = [BLUE, (255, 127, 14), GREEN, RED, (148, 103, 189), (140, 86, 75)]
FONT = cv2.FONT_HERSHEY_SIMPLEX


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _text(img: np.ndarray, text: str, x: float, y: float, scale: float = 0.4,
          colour=BLACK, align: str = "left", valign: str = "baseline") -> None:
    """Write ``text`` at ``(x, y)``: ``align`` left/centre/right, ``valign`` baseline/centre."""
    (w, h), _ = cv2.getTextSize(text, FONT, scale, 1)
    x0 = x - {"left": 0, "centre": w / 2, "right": w}[align]
    y0 = y + (h / 2 if valign == "centre" else 0)
    cv2.putText(img, text, (int(round(x0)), int(round(y0))), FONT, scale, colour, 1, cv2.LINE_AA)


def _vertical_text(img: np.ndarray, text: str, x: int, y: int, scale: float = 0.45) -> None:
    """Write ``text`` rotated 90 degrees (reading upwards), centred on ``(x, y)``."""
    (w, h), base = cv2.getTextSize(text, FONT, scale, 1)
    strip = np.full((h + base + 2, w + 2, 3), 255, np.uint8)
    cv2.putText(strip, text, (1, h + 1), FONT, scale, BLACK, 1, cv2.LINE_AA)
    strip = np.ascontiguousarray(np.rot90(strip))
    top, left = y - strip.shape[0] // 2, x - strip.shape[1] // 2
    img[top:top + strip.shape[0], left:left + strip.shape[1]] = np.minimum(
        img[top:top + strip.shape[0], left:left + strip.shape[1]], strip)


def nice_ticks(lo: float, hi: float, most: int = 9) -> np.ndarray:
    """Round tick values in ``[lo, hi]`` (steps 1, 2, 2.5 or 5 times a power of ten)."""
    span = max(hi - lo, 1e-12)
    raw = span / max(most - 1, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step - 1e-9) * step
    return np.arange(first, hi + step * 1e-9, step)


def _tick_labels(values: np.ndarray) -> list[str]:
    """Tick labels with as many decimals as the step needs (0.0, 0.2, ...; 0, 500, ...)."""
    step = float(values[1] - values[0]) if len(values) > 1 else 1.0
    decimals = max(0, -math.floor(math.log10(step) + 1e-9)) if step < 1 else 0
    decimals += step * 10 ** decimals % 1 > 1e-6  # 2.5, 0.25: one more
    return [f"{v:.{decimals}f}" for v in values]


class _Axes:
    """A plot area inside an image, mapping data coordinates to pixels."""

    def __init__(self, img, box, xlim, ylim):
        self.img, (self.x0, self.y0, self.x1, self.y1) = img, box
        self.xlim, self.ylim = xlim, ylim  # ylim = (bottom value, top value)

    def px(self, x, y):
        (a, b), (c, d) = self.xlim, self.ylim
        u = self.x0 + (np.asarray(x, float) - a) / (b - a) * (self.x1 - self.x0)
        v = self.y1 - (np.asarray(y, float) - c) / (d - c) * (self.y1 - self.y0)
        return u, v

    def frame(self, xlabel: str, ylabel: str, title: str, grid: bool = False) -> None:
        img = self.img
        ticks = nice_ticks(*sorted(self.xlim))
        for value, label in zip(ticks, _tick_labels(ticks)):
            u, _ = self.px(value, self.ylim[0])
            u = int(round(float(u)))
            if grid:
                cv2.line(img, (u, self.y0), (u, self.y1), (230, 230, 230), 1)
            cv2.line(img, (u, self.y1), (u, self.y1 + 4), BLACK, 1)
            _text(img, label, u, self.y1 + 16, 0.35, align="centre")
        ticks = nice_ticks(*sorted(self.ylim))
        for value, label in zip(ticks, _tick_labels(ticks)):
            _, v = self.px(self.xlim[0], value)
            v = int(round(float(v)))
            if grid:
                cv2.line(img, (self.x0, v), (self.x1, v), (230, 230, 230), 1)
            cv2.line(img, (self.x0 - 4, v), (self.x0, v), BLACK, 1)
            _text(img, label, self.x0 - 6, v, 0.35, align="right", valign="centre")
        cv2.rectangle(img, (self.x0, self.y0), (self.x1, self.y1), BLACK, 1)
        _text(img, xlabel, (self.x0 + self.x1) / 2, self.y1 + 34, 0.45, align="centre")
        _vertical_text(img, ylabel, 12, (self.y0 + self.y1) // 2)
        _text(img, title, (self.x0 + self.x1) / 2, self.y0 - 10, 0.45, align="centre")

    def legend(self, entries: list[tuple[str, tuple, str]], corner: str = "upper left") -> None:
        """Entries ``(label, colour, kind)``, kind ``"dot"``, ``"band"`` or ``"line"``."""
        if not entries:
            return
        scale, row = 0.35, 14
        width = max(cv2.getTextSize(t, FONT, scale, 1)[0][0] for t, _, _ in entries) + 34
        height = row * len(entries) + 8
        left = self.x0 + 6 if corner.endswith("left") else self.x1 - 6 - width
        top = self.y0 + 6 if corner.startswith("upper") else self.y1 - 6 - height
        box = self.img[top:top + height, left:left + width]
        box[:] = (0.2 * box + 0.8 * 255).astype(np.uint8)  # matplotlib's translucent frame
        cv2.rectangle(self.img, (left, top), (left + width, top + height), (204, 204, 204), 1)
        for i, (label, colour, kind) in enumerate(entries):
            cy = top + 4 + row * i + row // 2
            if kind == "dot":
                cv2.circle(self.img, (left + 14, cy), 3, colour, -1, cv2.LINE_AA)
            elif kind == "band":
                cv2.rectangle(self.img, (left + 6, cy - 4), (left + 22, cy + 4),
                              _blend(colour, 0.25), -1)
            else:
                cv2.line(self.img, (left + 4, cy), (left + 24, cy), colour, 2, cv2.LINE_AA)
            _text(self.img, label, left + 28, cy, scale, valign="centre")


def _dots(img: np.ndarray, x: np.ndarray, y: np.ndarray, colour) -> None:
    """3x3-pixel dots at ``(x, y)`` (matplotlib's ``s=4`` markers at 100 dpi), set at once."""
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            xs, ys = x + dx, y + dy
            inside = (xs >= 0) & (xs < img.shape[1]) & (ys >= 0) & (ys < img.shape[0])
            img[ys[inside], xs[inside]] = colour


def _blend(colour, alpha: float, under=WHITE) -> tuple:
    return tuple(int(round(alpha * c + (1 - alpha) * u)) for c, u in zip(colour, under))


def draw_difference_matrix(matrix, matches: Matches | None = None, gt=None,
                           title: str = "contrast-enhanced difference matrix",
                           shape: tuple[int, int] | None = None) -> np.ndarray:
    """The difference matrix with its ground truth and matches, a ``(500, 600, 3)`` uint8 image.

    The matrix is area-reduced (:func:`torchseq.cli.plots.reduce_matrix`) and shown on a grey
    scale from its 1st to its 99th percentile, stretched over full-matrix coordinates;
    ground truth as a translucent blue band, matches as dots (green correct, red wrong).

    Args:
        matrix: ``(R, Q)`` dense or sparse COO, or a reduced ``(R', Q')`` copy (give
            ``shape``).
        matches: the engine's matches.
        gt: ``(R, Q)`` bool ground truth or :class:`~torchseq.ground_truth.GroundTruthRanges`.
        title: image title.
        shape: ``(R, Q)`` of the full matrix when ``matrix`` is a reduced copy.
    """
    from torchseq.cli.plots import (  # NumPy/torch only (no drawing)
        _any_pool,
        checked_matrix,
        matched_points,
        reduce_matrix,
    )

    m, n_ref, n_query = checked_matrix(matrix, gt, shape)
    small = reduce_matrix(m, PLOT_SIDE)
    img = np.full((500, 600, 3), 255, np.uint8)
    ax = _Axes(img, (62, 30, 590, 448), (-0.5, n_query - 0.5), (n_ref - 0.5, -0.5))
    w, h = ax.x1 - ax.x0, ax.y1 - ax.y0
    finite = small[np.isfinite(small)]
    lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
    grey = np.clip((small - lo) / (hi - lo if hi > lo else 1.0), 0, 1) * 255
    grey = np.where(np.isfinite(small), grey, 255.0).astype(np.uint8)  # NaN: blank
    plot = cv2.resize(grey, (w, h), interpolation=cv2.INTER_NEAREST)
    area = np.repeat(plot[:, :, None], 3, axis=2).astype(np.float32)
    band = None
    if isinstance(gt, GroundTruthRanges):
        cols = np.minimum((np.arange(w) + 0.5) / w * n_query, n_query - 1).astype(np.int64)
        rows = (np.arange(h) + 0.5) / h * n_ref - 0.5  # reference coordinate of each pixel row
        lo_r, hi_r = np.asarray(gt.lo)[cols] - 0.5, np.asarray(gt.hi)[cols] - 0.5
        band = (rows[:, None] >= lo_r[None]) & (rows[:, None] < hi_r[None])
        alpha = 0.25
    elif gt is not None:
        pooled = _any_pool(gt, small.shape) if gt.shape[0] * gt.shape[1] > PLOT_SIDE ** 2 \
            else np.asarray(gt, bool)
        band = cv2.resize(pooled.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
        alpha = 0.25
    if band is not None:
        area[band] = area[band] * (1 - alpha) + np.float32(BLUE) * alpha
    img[ax.y0:ax.y1, ax.x0:ax.x1] = area.astype(np.uint8)
    entries = []
    if gt is not None:
        entries.append(("ground truth", BLUE, "band"))
    if matches is not None:
        q, r, ok = matched_points(matches, gt, n_ref, n_query)
        for good, colour in ((True, GREEN), (False, RED)):
            u, v = ax.px(q[ok == good], r[ok == good])
            _dots(img, np.rint(u).astype(np.int64), np.rint(v).astype(np.int64), colour)
        entries += [("correct match", GREEN, "dot"), ("wrong match", RED, "dot")]
    ax.frame("query frame", "reference frame", title)
    ax.legend(entries)
    return img


def draw_pr_curves(curves: dict[str, PRCurve]) -> np.ndarray:
    """Each engine's precision-recall curve, its AUC in the legend: a ``(400, 500, 3)`` image."""
    img = np.full((400, 500, 3), 255, np.uint8)
    ax = _Axes(img, (58, 30, 488, 348), (0.0, 1.0), (0.0, 1.02))
    ax.frame("recall", "precision", "precision-recall", grid=True)
    entries = []
    for i, (name, c) in enumerate(curves.items()):
        recall = np.r_[0.0, c.recall]
        precision = np.r_[c.precision[:1] if len(c.precision) else [1.0], c.precision]
        u, v = ax.px(recall, precision)
        pts = np.stack([u, v], 1)
        colour = TAB10[i % len(TAB10)]
        cv2.polylines(img, [np.rint(pts * 16).astype(np.int32)], False, colour, 1, cv2.LINE_AA,
                      shift=4)
        entries.append((f"{name} (AUC {auc(c):.3f})", colour, "line"))
    ax.legend(entries, "lower left")
    return img


def draw_matched_pairs(reference, query, matches: Matches, gt=None, n: int = 6,
                       title: str = "matched frames") -> np.ndarray:
    """Query frames above the reference frames they matched: a ``(420, 200 n, 3)`` image.

    Query frames (top row) above the reference frames they matched, ``n`` pairs evenly
    spaced over the matched queries, each reference's label green (correct), red (wrong) or
    black (no ground truth); grey scale as :func:`torchseq.cli.plots._grey_range`.
    """
    from torchseq.cli.plots import pick_pairs  # NumPy only (no drawing)

    ref, qry, idx = _np(reference), _np(query), _np(matches.reference)
    pick, title = pick_pairs(idx, len(ref), n, title)
    cols = max(len(pick), 1)
    img = np.full((420, 200 * cols, 3), 255, np.uint8)
    _text(img, title, img.shape[1] / 2, 22, 0.5, align="centre")
    for col, q in enumerate(pick):
        r = int(idx[q])
        good = bool(admits(gt, np.array([r]), np.array([q]))[0]) \
            if gt is not None and r < gt.shape[0] else None
        colour = {True: (0, 128, 0), False: (255, 0, 0), None: BLACK}[good]
        for row, (frame, label, c) in enumerate(((qry[q], f"query {q}", BLACK),
                                                 (ref[r], f"reference {r}", colour))):
            y = _paste_frame(img, frame, col * 200 + 8, 50 + row * 185, 184, 160)
            _text(img, label, col * 200 + 100, y - 6, 0.35, colour=c, align="centre")
    return img


def _paste_frame(img: np.ndarray, frame, left: int, top: int, width: int, height: int) -> int:
    """Draw a grey frame into the box, aspect kept and centred, on its display range.

    Returns:
        the frame's top row in ``img`` (its label goes above it).
    """
    from torchseq.cli.plots import _grey_range

    f = np.asarray(frame, dtype=np.float64)
    if f.ndim == 3:  # RGB thumbnails
        f = f @ np.array([0.299, 0.587, 0.114])
    rng = _grey_range(f)
    g = np.clip((np.nan_to_num(f) - rng["vmin"]) / (rng["vmax"] - rng["vmin"]), 0, 1) * 255
    scale = min(width / f.shape[1], height / f.shape[0])
    w, h = max(1, int(f.shape[1] * scale)), max(1, int(f.shape[0] * scale))
    g = cv2.resize(g.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
    x, y = left + (width - w) // 2, top + (height - h) // 2
    img[y:y + h, x:x + w] = g[:, :, None]
    return y

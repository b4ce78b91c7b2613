"""The neural figures for reports and TensorBoard, and the helpers the report's images share.

The activity raster and the ring matrix are drawn here (matplotlib); the eval report's
difference matrix, PR curves and frame pairs by :mod:`torchseq.cli.report_images`, with the
NumPy helpers below (:func:`reduce_matrix`, :func:`checked_matrix`, :func:`pick_pairs`).
Every ``plot_*`` function returns a matplotlib figure; :func:`save_figure` writes it atomically
as PNG and :func:`figure_to_array` turns it into an ``(H, W, 3)`` uint8 image for TensorBoard;
:func:`save_image` writes such an image as PNG without drawing the figure again.
Figures are made with the non-interactive Agg canvas directly (``matplotlib.figure.Figure``),
so importing this module leaves matplotlib's backend and ``pyplot``'s figure list alone;
matplotlib itself is imported by the first figure drawn, not by ``import torchseq.cli.plots``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchseq.area import area_mean
from torchseq.atomic import atomic_path
from torchseq.ground_truth import admits
from torchseq.matches import Matches

if TYPE_CHECKING:  # matplotlib is imported by the first figure (_figure)
    from matplotlib.figure import Figure


def _figure(figsize, nrows: int = 1, ncols: int = 1, **kw):
    """A figure on its own Agg canvas and its axes (pyplot is never involved).

    matplotlib is imported here, by the first figure: importing this module for its NumPy
    helpers (:func:`reduce_matrix`, used by :mod:`torchseq.cli.report_images`) loads none of it.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, **kw)
    return fig, axes


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


PLOT_SIDE = 512  # matrices are area-reduced to at most this on a side before drawing


def reduce_matrix(matrix, side: int = PLOT_SIDE) -> np.ndarray:
    """Area-average a ``(R, Q)`` matrix to at most ``side`` on a side (non-finite cells skipped).

    Each output cell is the mean of the finite entries of its block (adaptive pooling, the
    blocks of :func:`torch.nn.functional.adaptive_avg_pool2d`); NaN where a block has none:
    :func:`torchseq.area.area_mean`, the definition the SeqSLAM engine's preview uses too.
    A sparse COO tensor (candidate mode's evaluated entries) is read as NaN where it holds no
    entry, without building the dense matrix (:func:`_reduce_sparse`, tested equal).

    Args:
        matrix: ``(R, Q)``, dense or a sparse COO tensor.
        side: the longest side kept.

    Returns:
        ``(min(R, side), min(Q, side))`` float64 (averaged in float32 when reduced).
    """
    if isinstance(matrix, torch.Tensor) and matrix.is_sparse:
        return _reduce_sparse(matrix, side)
    m = torch.as_tensor(_np(matrix))
    out_size = (min(m.shape[0], side), min(m.shape[1], side))
    if tuple(out_size) == tuple(m.shape):
        return m.to(torch.float64).numpy()
    return area_mean(m, out_size).to(torch.float64).numpy()  # float32 sums: a display copy


def _bins(idx: torch.Tensor, n: int, out: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Adaptive-pooling blocks holding each index, ``(first, second or -1)``.

    ``first = floor(idx out / n)``; the next block too where the blocks overlap (with
    ``out <= n`` an index lies in at most two).
    """
    first = (idx * out) // n
    last = ((idx + 1) * out + n - 1) // n - 1
    return first, torch.where(last > first, last, -1)


def _reduce_sparse(matrix: torch.Tensor, side: int) -> np.ndarray:
    """:func:`reduce_matrix` of a sparse COO ``(R, Q)`` tensor, absent entries as NaN."""
    n_r, n_q = (int(v) for v in matrix.shape)
    out_r, out_q = min(n_r, side), min(n_q, side)
    m = matrix.coalesce()
    rows, cols = m.indices()
    vals = m.values().to(torch.float64)
    keep = torch.isfinite(vals)
    rows, cols, vals = rows[keep], cols[keep], vals[keep]
    total = torch.zeros(out_r * out_q, dtype=torch.float64)
    count = torch.zeros(out_r * out_q, dtype=torch.float64)
    for r_bin in _bins(rows, n_r, out_r):
        for c_bin in _bins(cols, n_q, out_q):
            ok = (r_bin >= 0) & (c_bin >= 0)
            cell = r_bin[ok] * out_q + c_bin[ok]
            total.index_add_(0, cell, vals[ok])
            count.index_add_(0, cell, torch.ones_like(vals[ok]))
    # each block's mean over its finite entries, as the dense pooling's total / count
    mean = torch.where(count > 0, total / count.clamp_min(1.0), np.nan)
    return mean.reshape(out_r, out_q).numpy()


def _any_pool(gt: np.ndarray, out_size: tuple[int, int]) -> np.ndarray:
    """``(R, Q)`` bool -> ``out_size`` bool: a cell is set when any entry of its block is."""
    m = torch.as_tensor(np.asarray(gt, dtype=bool)).to(torch.float32)[None]
    return (torch.nn.functional.adaptive_max_pool2d(m, out_size)[0] > 0).numpy()


def checked_matrix(matrix, gt, shape: tuple[int, int] | None):
    """``(matrix, R, Q)`` of a difference-matrix figure, after its checks.

    ``matrix`` stays a sparse tensor (candidate mode) or becomes a NumPy array; ``(R, Q)`` is
    ``shape`` (the full matrix's, when ``matrix`` is a reduced copy) or the matrix's own.
    """
    sparse = isinstance(matrix, torch.Tensor) and matrix.is_sparse  # candidate mode
    m = matrix if sparse else _np(matrix)
    n_ref, n_query = (int(v) for v in (shape if shape is not None else m.shape))
    if m.ndim != 2 or m.shape[0] > n_ref or m.shape[1] > n_query:
        raise ValueError(f"matrix {m.shape} does not reduce a ({n_ref}, {n_query}) matrix")
    if gt is not None and tuple(gt.shape) != (n_ref, n_query):
        raise ValueError(f"ground truth {tuple(gt.shape)} does not fit the matrix's "
                         f"({n_ref}, {n_query})")
    return m, n_ref, n_query


def matched_points(matches: Matches, gt, n_ref: int,
                   n_query: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The matches a difference-matrix figure draws: ``(query, reference, correct)``.

    Queries whose match lies inside the ``(R, Q)`` matrix, their references and whether the
    ground truth admits each (all False without ground truth).

    Raises:
        ValueError: the matches do not have ``Q`` queries.
    """
    ref = _np(matches.reference).astype(np.int64)
    if len(ref) != n_query:
        raise ValueError(f"{len(ref)} matches for a matrix of {n_query} queries")
    q = np.nonzero((ref >= 0) & (ref < n_ref))[0]
    ok = admits(gt, ref[q], q) if gt is not None else np.zeros(len(q), bool)
    return q, ref[q], ok


def plot_activity_raster(activity, winners=None, title: str = "output activity",
                         truth=None) -> Figure:
    """Output-unit activity over time with the winning unit marked (the seed's Figures 7 and 9).

    Args:
        activity: ``(T, N)`` unit activity per frame (area-reduced to at most
            :data:`PLOT_SIDE` a side for drawing).
        winners: ``(T,)`` winning unit per frame (default: the argmax).
        title: figure title.
        truth: ``(T, N)`` bool, the units that stand for an admissible reference frame of
            each query frame (:func:`true_units`), drawn under the winners; None: not drawn.
    """
    a = _np(activity)
    w = _np(winners) if winners is not None else a.argmax(1)
    n_frames, n_units = a.shape
    fig, ax = _figure((7, 4))
    # long runs: area-reduced first (as the difference matrix), drawn in frame/unit coordinates
    ax.imshow(reduce_matrix(a.T), cmap="magma", aspect="auto", origin="lower",
              interpolation="nearest", extent=(-0.5, n_frames - 0.5, -0.5, n_units - 0.5))
    if truth is not None:
        frames, units = np.nonzero(np.asarray(truth))
        ax.plot(frames, units, "s", ms=3, c="lime", alpha=0.6, mec="none",
                label="ground truth")
    ax.plot(np.arange(len(w)), w, ".", ms=2, c="cyan", label="winner")
    ax.set_xlabel("frame")
    ax.set_ylabel("output unit")
    ax.set_title(title)
    ax.legend(loc="upper left", fontsize=7)
    fig.tight_layout()
    return fig


def plot_matrix(matrix, title: str, cmap: str = "viridis", xlabel: str | None = None,
                ylabel: str | None = None) -> Figure:
    """A plain heat map, e.g. the learnt ring shift matrix, with axis labels when given."""
    fig, ax = _figure((5, 5))
    im = ax.imshow(_np(matrix), cmap=cmap, interpolation="nearest")
    fig.colorbar(im, ax=ax, fraction=0.046)
    ax.set_title(title)
    if xlabel:
        ax.set_xlabel(xlabel)
    if ylabel:
        ax.set_ylabel(ylabel)
    fig.tight_layout()
    return fig


def _grey_range(frame: np.ndarray) -> dict:
    """Display range of one frame, as ``imshow`` keywords.

    Camera images show on 0..255 as they are. Event frames hold a few counts per pixel and a
    few hot pixels with many: on 0..255, or stretched to their maximum, they look black, so
    they are stretched to their 99.5th percentile.
    """
    f = np.asarray(frame, dtype=np.float64)
    finite = f[np.isfinite(f)]
    top = float(np.percentile(finite, 99.5)) if finite.size else 255.0
    return {"vmin": 0.0, "vmax": 255.0 if top >= 64 else max(top, 1.0)}


def pick_pairs(idx: np.ndarray, n_ref: int, n: int, title: str) -> tuple[np.ndarray, str]:
    """``n`` queries evenly spaced over the matched ones, and the title, for a pairs figure.

    A checkpoint of a longer route matches reference frames these frames do not hold: those
    matches are left out and the title says how many.
    """
    outside = int(((idx >= n_ref) | (idx < -1)).sum())
    matched = np.nonzero((idx >= 0) & (idx < n_ref))[0]
    if outside:
        title += (f" ({outside} of {len(idx)} matches point past the {n_ref} reference "
                  f"frames: not shown)")
    pick = matched[np.linspace(0, len(matched) - 1, min(n, len(matched))).round().astype(int)] \
        if len(matched) else np.array([], int)
    return pick, title


def figure_to_array(fig: Figure) -> np.ndarray:
    """Render a figure to an ``(H, W, 3)`` uint8 RGB array."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def save_figure(fig: Figure, path: str | Path, close: bool = True) -> None:
    """Save a figure as PNG atomically."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    if close:
        fig.clear()


def save_image(image: np.ndarray, path: str | Path) -> None:
    """Save an ``(H, W, 3)`` uint8 RGB image (e.g. from :func:`figure_to_array`) as PNG atomically.

    The figure is drawn once for TensorBoard and the file alike (``savefig`` would draw it
    again: about 0.3 s per figure).
    """
    import cv2

    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"need an (H, W, 3) uint8 image, got {image.shape} {image.dtype}")
    ok, png = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]))  # OpenCV is BGR
    if not ok:
        raise ValueError(f"cannot encode a {image.shape} image as PNG")
    with atomic_path(path) as tmp:
        tmp.write_bytes(png.tobytes())


def true_units(gt, spans, n_query: int, max_elements: int = 2**26) -> np.ndarray | None:
    """``(Q, N)`` bool: the units whose reference span holds an admissible frame of each query.

    Args:
        gt: ``(R, Q)`` 0/1 ground truth or a :class:`~torchseq.ground_truth.GroundTruthRanges`.
        spans: ``(N, 2)`` first and one-past-last reference frame of each unit (a checkpoint
            of a longer route may reach past ``R``: clipped).
        n_query: ``Q``.
        max_elements: above ``R * Q`` nothing is computed (None): a plot needs no more.
    """
    dense = gt.dense() if hasattr(gt, "dense") else None
    shape = gt.shape if dense is None else dense.shape
    if shape[0] * max(shape[1], n_query) > max_elements:
        return None
    m = np.asarray(dense if dense is not None else gt, dtype=bool)  # (R, Q)
    count = np.zeros((m.shape[0] + 1, m.shape[1]), np.int64)
    np.cumsum(m, axis=0, out=count[1:])
    s = np.clip(_np(spans).astype(np.int64), 0, m.shape[0])
    return (count[s[:, 1]] - count[s[:, 0]]).T > 0

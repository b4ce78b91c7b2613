"""Ground truth: which reference frames are admissible matches for each query frame.

Always a ``(R, Q)`` bool array, reference rows by query columns, like the difference matrix.
Files: a ``query,references`` CSV, a 0/1 ``(R, Q)`` ``.npy`` matrix, or VPR-Bench's per-query
``.npy`` object array of admissible reference indices (read without running any pickle).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from torchseq.npyfile import load_npy

MAX_CELLS = 2 ** 31  # largest (R x Q) ground truth built (bool: 2 GiB)


class GroundTruthError(ValueError):
    """The ground truth does not fit the traverses or cannot be read."""


def _check_counts(n_reference, n_query) -> tuple[int, int]:
    if not all(isinstance(n, (int, np.integer)) and not isinstance(n, bool)
               for n in (n_reference, n_query)) or n_reference < 1 or n_query < 1:
        raise GroundTruthError(f"need at least one frame per traverse, got {n_reference} "
                               f"reference and {n_query} query frames")
    if n_reference * n_query > MAX_CELLS:
        raise GroundTruthError(f"a {n_reference} x {n_query} ground truth is larger than "
                               f"{MAX_CELLS} cells")
    return int(n_reference), int(n_query)


def alignment_ground_truth(n_reference: int, n_query: int, tolerance: float,
                           offset: float = 0.0) -> np.ndarray:
    """Ground truth by index alignment: query ``j`` sits at reference ``offset + j * s``.

    ``s = (R - 1 - offset) / (Q - 1)``: the query starts at reference frame ``offset`` (the
    traverses start at different places) and ends with the reference.

    Args:
        n_reference: reference frames ``R``.
        n_query: query frames ``Q``.
        tolerance: admissible distance in reference frames.
        offset: reference frame where the query starts, ``0 <= offset <= R - 1``.

    Returns:
        ``(R, Q)`` bool.
    """
    n_reference, n_query = _check_counts(n_reference, n_query)
    if not (math.isfinite(tolerance) and tolerance >= 0):
        raise GroundTruthError(f"tolerance must be a finite number >= 0, got {tolerance}")
    if not (math.isfinite(offset) and 0 <= offset <= n_reference - 1):
        raise GroundTruthError(f"offset must be within the reference (0..{n_reference - 1}), "
                               f"got {offset}")
    scale = (n_reference - 1 - offset) / (n_query - 1) if n_query > 1 else 0.0
    centre = offset + np.arange(n_query) * scale
    return np.abs(np.arange(n_reference)[:, None] - centre[None, :]) <= tolerance + 1e-9


def widen_ground_truth(gt: np.ndarray, tolerance: float) -> np.ndarray:
    """Admit every reference within ``tolerance`` frames of an admissible one (per query).

    Args:
        gt: ``(R, Q)`` bool.
        tolerance: reference frames, finite and >= 0.

    Returns:
        ``(R, Q)`` bool, ``gt`` dilated along the reference axis.
    """
    if not (math.isfinite(tolerance) and tolerance >= 0):
        raise GroundTruthError(f"tolerance must be a finite number >= 0, got {tolerance}")
    r = min(int(math.floor(tolerance + 1e-9)), gt.shape[0])
    if r == 0:
        return gt
    # running OR over a window of 2r+1 rows via a cumulative count
    count = np.cumsum(np.r_[np.zeros((1, gt.shape[1]), np.int64), gt.astype(np.int64)], axis=0)
    rows = np.arange(gt.shape[0])
    hi = np.minimum(rows + r + 1, gt.shape[0])
    lo = np.maximum(rows - r, 0)
    return (count[hi] - count[lo]) > 0


def read_ground_truth_csv(path: Path, n_reference: int, n_query: int) -> np.ndarray:
    """Read a ``query,references`` CSV with space-separated admissible reference indices."""
    gt = np.zeros((n_reference, n_query), dtype=bool)
    seen = set()
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except (UnicodeDecodeError, csv.Error) as err:
        raise GroundTruthError(f"{path}: not a readable UTF-8 CSV ({err})") from None
    if not rows or [c.strip().lower() for c in rows[0][:2]] != ["query", "references"]:
        raise GroundTruthError(f"{path}: expected a 'query,references' header")
    for line, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        try:
            q = int(row[0])
            refs = [int(r) for r in (row[1].split() if len(row) > 1 else [])]
        except ValueError as err:
            raise GroundTruthError(f"{path}:{line}: not integer indices: {row}") from err
        if not 0 <= q < n_query:
            raise GroundTruthError(f"{path}:{line}: query {q} outside 0..{n_query - 1}")
        bad = [r for r in refs if not 0 <= r < n_reference]
        if bad:
            raise GroundTruthError(
                f"{path}:{line}: reference {bad[0]} outside 0..{n_reference - 1}")
        gt[refs, q] = True
        seen.add(q)
    if len(seen) != n_query:
        raise GroundTruthError(f"{path}: covers {len(seen)} queries but the query has {n_query}")
    return gt


def _index_list(value, path: Path, q: int, n_reference: int) -> list[int]:
    """One query's admissible references from a VPR-Bench entry (int, list or int array)."""
    items = value.tolist() if isinstance(value, np.ndarray) else value
    if isinstance(items, (int, np.integer)) and not isinstance(items, bool):
        items = [items]
    if not isinstance(items, (list, tuple)) or not all(
            isinstance(i, (int, np.integer)) and not isinstance(i, bool) for i in items):
        raise GroundTruthError(f"{path}: query {q}: admissible references must be integer "
                               f"indices, got {type(value).__name__}")
    bad = [int(i) for i in items if not 0 <= i < n_reference]
    if bad:
        raise GroundTruthError(f"{path}: query {q}: reference {bad[0]} outside "
                               f"0..{n_reference - 1}")
    return [int(i) for i in items]


def read_vpr_bench(m: np.ndarray, path: Path, n_reference: int, n_query: int) -> np.ndarray:
    """VPR-Bench per-query ground truth: ``(Q,)`` index lists or ``(Q, 2)`` (query, indices)."""
    if m.ndim == 2 and m.shape[1] == 2:
        entries = m[:, 1]
    elif m.ndim == 1:
        entries = m
    else:
        raise GroundTruthError(f"{path}: a per-query object array must be (Q,) or (Q, 2), "
                               f"got {m.shape}")
    if len(entries) != n_query:
        raise GroundTruthError(f"{path}: has {len(entries)} queries but the query has "
                               f"{n_query}")
    gt = np.zeros((n_reference, n_query), dtype=bool)
    for q, value in enumerate(entries):
        gt[_index_list(value, path, q, n_reference), q] = True
    return gt


def load_ground_truth(path: str | Path, n_reference: int, n_query: int,
                      widen: float = 0.0) -> np.ndarray:
    """Load ground truth from a CSV, a 0/1 ``(R, Q)`` matrix or a VPR-Bench ``.npy``.

    Args:
        path: the file: ``.csv``/``.txt`` (``query,references`` with space-separated
            indices), ``.npy`` 0/1 (or bool) ``(R, Q)`` matrix, or ``.npy`` object array of
            admissible reference indices per query (VPR-Bench; ``(Q,)`` or ``(Q, 2)`` rows of
            ``(query, indices)``), read by a restricted unpickler that runs no code.
        n_reference: frames in the reference traverse, to check the file against.
        n_query: frames in the query traverse.
        widen: also admit references within this many frames of an admissible one.

    Returns:
        ``(R, Q)`` bool.

    Raises:
        GroundTruthError: unreadable file, wrong shape or values (the file named).
    """
    n_reference, n_query = _check_counts(n_reference, n_query)
    path = Path(path)
    if not path.is_file():
        raise GroundTruthError(f"no such ground-truth file: {path}")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        m = load_npy(path, GroundTruthError, allow_object=True)
        if m.dtype.hasobject:
            gt = read_vpr_bench(m, path, n_reference, n_query)
        else:
            if m.ndim != 2 or m.shape != (n_reference, n_query):
                raise GroundTruthError(
                    f"{path}: matrix is {m.shape} but the traverses need (reference, query) = "
                    f"({n_reference}, {n_query})")
            if m.dtype.kind not in "biuf":
                raise GroundTruthError(f"{path}: matrix dtype {m.dtype} is not numeric")
            if not np.isin(m, (0, 1)).all():
                raise GroundTruthError(f"{path}: matrix must hold only 0 and 1")
            gt = m.astype(bool)
    elif suffix in (".csv", ".txt"):
        try:
            gt = read_ground_truth_csv(path, n_reference, n_query)
        except OSError as err:
            raise GroundTruthError(f"{path}: cannot read ({err})") from None
    else:
        raise GroundTruthError(f"{path}: ground truth must be a .csv or a .npy matrix")
    return widen_ground_truth(gt, widen) if widen else gt

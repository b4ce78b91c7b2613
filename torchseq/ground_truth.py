"""Ground truth: which reference frames are admissible matches for each query frame.

Always a ``(R, Q)`` bool array, reference rows by query columns, like the difference matrix.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


class GroundTruthError(ValueError):
    """The ground truth does not fit the traverses or cannot be read."""


def alignment_ground_truth(n_reference: int, n_query: int, tolerance: float) -> np.ndarray:
    """Ground truth by index alignment: query ``j`` sits at reference ``j * (R-1)/(Q-1)``.

    Args:
        n_reference: reference frames ``R``.
        n_query: query frames ``Q``.
        tolerance: admissible distance in reference frames.

    Returns:
        ``(R, Q)`` bool.
    """
    if n_reference < 1 or n_query < 1 or tolerance < 0:
        raise GroundTruthError("need at least one frame per traverse and tolerance >= 0")
    scale = (n_reference - 1) / (n_query - 1) if n_query > 1 else 0.0
    centre = np.arange(n_query) * scale
    return np.abs(np.arange(n_reference)[:, None] - centre[None, :]) <= tolerance + 1e-9


def read_ground_truth_csv(path: Path, n_reference: int, n_query: int) -> np.ndarray:
    """Read a ``query,references`` CSV with space-separated admissible reference indices."""
    gt = np.zeros((n_reference, n_query), dtype=bool)
    seen = set()
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
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


def load_ground_truth(path: str | Path, n_reference: int, n_query: int) -> np.ndarray:
    """Load ground truth from a ``query,references`` CSV or a 0/1 ``(R, Q)`` ``.npy`` matrix.

    Args:
        path: the file.
        n_reference: frames in the reference traverse, to check the file against.
        n_query: frames in the query traverse.

    Returns:
        ``(R, Q)`` bool.
    """
    path = Path(path)
    if not path.is_file():
        raise GroundTruthError(f"no such ground-truth file: {path}")
    if path.suffix.lower() == ".npy":
        m = np.load(path, allow_pickle=False)
        if m.ndim != 2 or m.shape != (n_reference, n_query):
            raise GroundTruthError(
                f"{path}: matrix is {m.shape} but the traverses need (reference, query) = "
                f"({n_reference}, {n_query})")
        if not np.isin(m, (0, 1)).all():
            raise GroundTruthError(f"{path}: matrix must hold only 0 and 1")
        return m.astype(bool)
    if path.suffix.lower() in (".csv", ".txt"):
        return read_ground_truth_csv(path, n_reference, n_query)
    raise GroundTruthError(f"{path}: ground truth must be a .csv or a .npy matrix")

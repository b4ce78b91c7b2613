"""Ground truth: which reference frames are admissible matches for each query frame.

A ``(R, Q)`` bool array, reference rows by query columns, like the difference matrix, or,
where each query admits one run of neighbouring references (index alignment), the sparse
:class:`GroundTruthRanges`: one ``[lo, hi)`` reference range per query, ``O(Q)`` memory
instead of ``O(R Q)``. :func:`admits` and :func:`positives` read either form; the metrics and
plots go through them.
Files: a ``query,references`` CSV, a 0/1 ``(R, Q)`` ``.npy`` matrix, or VPR-Bench's per-query
``.npy`` object array of admissible reference indices (read without running any pickle).
"""

from __future__ import annotations

import csv
import math
import warnings
from dataclasses import dataclass
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


@dataclass(frozen=True)
class GroundTruthRanges:
    """Sparse ground truth: query ``j`` admits the references ``lo[j] <= r < hi[j]``.

    The same ground truth as the dense ``(R, Q)`` matrix :meth:`dense` returns, in ``O(Q)``
    memory (a 35,768-frame route: 0.6 MB instead of 1.3 GB). A query with ``lo >= hi``
    admits nothing.

    Attributes:
        lo: ``(Q,)`` int64, first admissible reference.
        hi: ``(Q,)`` int64, one past the last admissible reference.
        n_reference: ``R``.
    """

    lo: np.ndarray
    hi: np.ndarray
    n_reference: int

    def __post_init__(self) -> None:
        lo = np.asarray(self.lo, dtype=np.int64)
        hi = np.asarray(self.hi, dtype=np.int64)
        if lo.ndim != 1 or lo.shape != hi.shape or len(lo) < 1 or self.n_reference < 1:
            raise GroundTruthError(f"ranges need (Q,) lo and hi and n_reference >= 1, got "
                                   f"{lo.shape}, {hi.shape}, {self.n_reference}")
        empty = lo >= hi
        lo, hi = np.where(empty, 0, lo), np.where(empty, 0, hi)  # one form for "none"
        if (lo < 0).any() or (hi > self.n_reference).any():
            raise GroundTruthError(f"ranges must lie within 0..{self.n_reference}")
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)
        object.__setattr__(self, "n_reference", int(self.n_reference))

    @property
    def shape(self) -> tuple[int, int]:
        """``(R, Q)``, as the dense matrix."""
        return self.n_reference, len(self.lo)

    def dense(self) -> np.ndarray:
        """The ``(R, Q)`` bool matrix (bounded like every dense ground truth)."""
        _check_counts(*self.shape)
        rows = np.arange(self.n_reference)[:, None]
        return (rows >= self.lo[None, :]) & (rows < self.hi[None, :])

    def admits(self, ref: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Whether query ``q`` admits reference ``ref`` (int arrays of one shape), bool."""
        return (ref >= self.lo[q]) & (ref < self.hi[q])

    def take(self, ref_indices, query_indices) -> GroundTruthRanges:
        """Rows ``ref_indices`` (increasing) and columns ``query_indices`` of this ground truth.

        The kept references inside a range are neighbours in the kept list, so the result is
        ranges again (as ``dense()[np.ix_(ref_indices, query_indices)]``).
        """
        rows = np.asarray(ref_indices, dtype=np.int64)
        cols = np.asarray(query_indices, dtype=np.int64)
        if len(rows) == 0 or (np.diff(rows) <= 0).any():
            raise GroundTruthError("selected reference indices must increase")
        lo, hi = self.lo[cols], self.hi[cols]
        return GroundTruthRanges(np.searchsorted(rows, lo, "left"),
                                 np.searchsorted(rows, hi, "left"), len(rows))


def admits(gt: np.ndarray | GroundTruthRanges, ref: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Whether the ground truth admits reference ``ref[i]`` for query ``q[i]``, either form.

    Args:
        gt: ``(R, Q)`` bool or :class:`GroundTruthRanges`.
        ref: int reference indices within ``0..R-1``.
        q: int query indices, same shape.

    Returns:
        bool, the shape of ``ref``.
    """
    if isinstance(gt, GroundTruthRanges):
        return gt.admits(ref, q)
    return gt[ref, q]


def positives(gt: np.ndarray | GroundTruthRanges) -> np.ndarray:
    """``(Q,)`` bool: the queries with at least one admissible reference, either form."""
    if isinstance(gt, GroundTruthRanges):
        return gt.hi > gt.lo
    return np.asarray(gt, dtype=bool).any(0)


def alignment_scale(n_reference: int, n_query: int, offset: float = 0.0) -> float:
    """Reference frames per query frame when the query is stretched over the reference.

    ``(R - 1 - offset) / (Q - 1)``: the query starts at ``offset`` and ends with the
    reference (index alignment's default, right when both traverses cover the same route).
    """
    return (n_reference - 1 - offset) / (n_query - 1) if n_query > 1 else 0.0


def _alignment_centres(n_reference: int, n_query: int, tolerance: float,
                       offset: float, scale: float | None) -> np.ndarray:
    if not (math.isfinite(tolerance) and tolerance >= 0):
        raise GroundTruthError(f"tolerance must be a finite number >= 0, got {tolerance}")
    if not (math.isfinite(offset) and 0 <= offset <= n_reference - 1):
        raise GroundTruthError(f"offset must be within the reference (0..{n_reference - 1}), "
                               f"got {offset}")
    if scale is None:
        scale = alignment_scale(n_reference, n_query, offset)
    elif not (math.isfinite(scale) and scale > 0):
        raise GroundTruthError(f"scale must be a finite number > 0, got {scale}")
    return offset + np.arange(n_query) * scale


def _aligned(r, centre: np.ndarray, tolerance: float) -> np.ndarray:
    """The one admissibility rule of index alignment: ``|r - centre| <= tolerance``."""
    return np.abs(r - centre) <= tolerance + 1e-9


def alignment_ranges(n_reference: int, n_query: int, tolerance: float,
                     offset: float = 0.0, scale: float | None = None) -> GroundTruthRanges:
    """:func:`alignment_ground_truth` as ranges: ``O(Q)`` memory, any route length.

    Each query's admissible references are the integers within ``tolerance`` of its centre,
    one run; its ends are found by testing the same rule (:func:`_aligned`) on the few
    integers around ``centre -/+ tolerance``, so the ranges equal the dense matrix exactly.

    Args:
        n_reference: reference frames ``R``.
        n_query: query frames ``Q``.
        tolerance: admissible distance in reference frames.
        offset: reference frame where the query starts, ``0 <= offset <= R - 1``.
        scale: reference frames per query frame; None: :func:`alignment_scale` (the query
            stretched over the reference).

    Returns:
        :class:`GroundTruthRanges` of shape ``(R, Q)``.
    """
    if not all(isinstance(n, (int, np.integer)) and not isinstance(n, bool)
               for n in (n_reference, n_query)) or n_reference < 1 or n_query < 1:
        raise GroundTruthError(f"need at least one frame per traverse, got {n_reference} "
                               f"reference and {n_query} query frames")
    centre = _alignment_centres(int(n_reference), int(n_query), tolerance, offset, scale)
    steps = np.arange(-2, 3)[:, None]  # (5, 1): the run's ends lie among these candidates
    low = np.floor(centre - tolerance)[None, :] + steps  # (5, Q)
    high = np.floor(centre + tolerance)[None, :] + steps
    # first admitted candidate at the low end; last admitted at the high end
    ok_low = _aligned(low, centre[None, :], tolerance)
    ok_high = _aligned(high, centre[None, :], tolerance)
    lo = np.where(ok_low.any(0), low[ok_low.argmax(0), np.arange(len(centre))], 0)
    last = len(steps) - 1 - ok_high[::-1].argmax(0)
    hi = np.where(ok_high.any(0), high[last, np.arange(len(centre))] + 1, 0)
    lo = np.clip(lo, 0, n_reference).astype(np.int64)
    hi = np.clip(hi, 0, n_reference).astype(np.int64)
    return GroundTruthRanges(lo, hi, int(n_reference))


def alignment_ground_truth(n_reference: int, n_query: int, tolerance: float,
                           offset: float = 0.0, scale: float | None = None) -> np.ndarray:
    """Ground truth by index alignment: query ``j`` sits at reference ``offset + j * s``.

    ``s = scale``, or by default ``(R - 1 - offset) / (Q - 1)``: the query starts at reference
    frame ``offset`` (the traverses start at different places) and ends with the reference
    (:func:`alignment_scale`). A query that covers a part of the reference at its speed
    needs ``scale=1``. For long routes,
    :func:`alignment_ranges` gives the same ground truth without the dense matrix.

    Args:
        n_reference: reference frames ``R``.
        n_query: query frames ``Q``.
        tolerance: admissible distance in reference frames.
        offset: reference frame where the query starts, ``0 <= offset <= R - 1``.
        scale: reference frames per query frame (default: stretched, as above).

    Returns:
        ``(R, Q)`` bool.
    """
    n_reference, n_query = _check_counts(n_reference, n_query)
    centre = _alignment_centres(n_reference, n_query, tolerance, offset, scale)
    return _aligned(np.arange(n_reference)[:, None], centre[None, :], tolerance)


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


HEADER = ["query", "references"]


def read_ground_truth_csv(path: Path, n_reference: int, n_query: int) -> np.ndarray:
    """Read a ground-truth CSV: the documented form, or a headerless pair table.

    Accepted (a UTF-8 byte-order mark, as Excel's "CSV UTF-8" writes, is allowed):

    - header ``query,references``, one row per query: its 0-based index, then its admissible
      references separated by spaces (``5,3 4 5 6 7``);
    - no header, every row ``query,reference`` or ``query,reference,N`` integers, one
      admissible reference per row (Nordland's ``sample_ground_truth.csv``): 0-based when the
      queries are exactly ``0..Q-1``, 1-based when they are ``1..Q``; a third column is not
      read. How such a file was read is said in a warning.

    Anything else is refused with the line and what was expected (a row ``5,3,4,5,6,7``
    under the header would otherwise lose references).
    """
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = [_trim(row) for row in csv.reader(f)]
    except (UnicodeDecodeError, csv.Error) as err:
        raise GroundTruthError(f"{path}: not a readable UTF-8 CSV ({err})") from None
    if rows and _integers(rows[0]) is not None:
        return _read_pairs(path, rows, n_reference, n_query)
    if not rows or [c.strip().lower() for c in rows[0]] != HEADER:
        got = ",".join(rows[0]) if rows else "an empty file"
        raise GroundTruthError(f"{path}:1: expected the header 'query,references' (or "
                               f"headerless integer 'query,reference' rows), got {got[:60]!r}")
    gt = np.zeros((n_reference, n_query), dtype=bool)
    seen = set()
    hint = _one_based_hint(rows[1:])
    for line, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) > 2:
            raise GroundTruthError(
                f"{path}:{line}: {len(row)} fields, expected 2 (query, then its references "
                f"separated by spaces: '{row[0]},{' '.join(row[1:])}')")
        try:
            q = int(row[0])
            refs = [int(r) for r in (row[1].split() if len(row) > 1 else [])]
        except ValueError as err:
            raise GroundTruthError(f"{path}:{line}: not integer indices: {row}") from err
        if not 0 <= q < n_query:
            raise GroundTruthError(f"{path}:{line}: query {q} outside 0..{n_query - 1}{hint}")
        bad = [r for r in refs if not 0 <= r < n_reference]
        if bad:
            raise GroundTruthError(
                f"{path}:{line}: reference {bad[0]} outside 0..{n_reference - 1}{hint}")
        gt[refs, q] = True
        seen.add(q)
    if len(seen) != n_query:
        raise GroundTruthError(f"{path}: covers {len(seen)} queries but the query has "
                               f"{n_query}{hint}")
    return gt


def _trim(row: list[str]) -> list[str]:
    """A CSV row without the empty fields a spreadsheet leaves at its end."""
    while row and not row[-1].strip():
        row = row[:-1]
    return row


def _integers(row: list[str]) -> list[int] | None:
    """The row's fields as integers, or None when one is not an integer."""
    try:
        return [int(c) for c in row]
    except ValueError:
        return None


def _read_pairs(path: Path, rows: list, n_reference: int, n_query: int) -> np.ndarray:
    """A headerless ``query,reference[,N]`` table (one admissible reference per row)."""
    pairs = []
    for line, row in enumerate(rows, start=1):
        if not row:
            continue
        values = _integers(row)
        if values is None or len(values) not in (2, 3):
            raise GroundTruthError(f"{path}:{line}: expected integer 'query,reference' or "
                                   f"'query,reference,N' like the lines above, got "
                                   f"{','.join(row)[:60]!r}")
        pairs.append(values[:2])
    columns = {len(r) for r in rows if r}
    q, r = np.asarray(pairs, dtype=np.int64).T
    queries = np.unique(q)
    if len(queries) == n_query and queries[0] == 0 and queries[-1] == n_query - 1:
        base = 0
    elif len(queries) == n_query and queries[0] == 1 and queries[-1] == n_query:
        base = 1
    else:
        raise GroundTruthError(
            f"{path}: a headerless table must list every query once or more, as 0..{n_query - 1} "
            f"or 1..{n_query}; its queries run {queries[0]}..{queries[-1]} ({len(queries)} "
            f"distinct)")
    r = r - base
    bad = r[(r < 0) | (r >= n_reference)]
    if len(bad):
        raise GroundTruthError(f"{path}: reference {int(bad[0]) + base} outside "
                               f"{base}..{n_reference - 1 + base}")
    gt = np.zeros((n_reference, n_query), dtype=bool)
    gt[r, q - base] = True
    warnings.warn(f"{path}: read as headerless {'1' if base else '0'}-based query,reference "
                  f"pairs" + (" (third column not used)" if 3 in columns else ""),
                  stacklevel=3)
    return gt


def _one_based_hint(rows: list) -> str:
    """``"; indices are 0-based ..."`` for CSV rows whose indices never use 0, else ``""``."""
    values = []
    for row in rows:
        try:
            values += [int(row[0]), *(int(r) for r in (row[1].split() if len(row) > 1 else []))]
        except (ValueError, IndexError):
            return ""
    if len(values) < 2 or min(values) < 1:
        return ""
    return ("; indices are 0-based (query 0 is the first frame) but this file never uses "
            "index 0: if it counts from 1, subtract 1 from every index")


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
    if path.is_dir():
        raise GroundTruthError(
            f"{path} is a folder; --ground-truth takes a file: a CSV 'query,references', a "
            f"(reference x query) 0/1 .npy matrix or a VPR-Bench per-query .npy")
    if not path.is_file():
        raise GroundTruthError(f"no such ground-truth file: {path}")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        m = load_npy(path, GroundTruthError, allow_object=True)
        if m.dtype.hasobject:
            gt = read_vpr_bench(m, path, n_reference, n_query)
        else:
            if m.ndim != 2 or m.shape != (n_reference, n_query):
                swapped = (m.ndim == 2 and n_reference != n_query
                           and m.shape == (n_query, n_reference))
                raise GroundTruthError(
                    f"{path}: matrix is {m.shape} but the traverses need (reference, query) = "
                    f"({n_reference}, {n_query})" + (
                        ": it is the transposed shape; were --reference and --query swapped? "
                        "(rows are reference frames, columns query frames)" if swapped else ""))
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

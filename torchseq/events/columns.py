"""Events stored column by column (HDF5 datasets, Parquet columns): names, units, checks.

Field datasets spell ``t, x, y, p`` in many ways; :data:`ALIASES` lists the spellings the
readers recognise (first match wins). Times become int64 microseconds exactly: integer
columns are taken as microseconds unless a unit says otherwise (``time_unit`` overrides);
floating-point columns follow the one float-time rule of :mod:`torchseq.events.times`
(a declared unit, else fractions under 1e5 are seconds, whole numbers microseconds, with a
warning; decided once per file by a :class:`~torchseq.events.times.FloatTimeRule`).
Coordinates must fit the int16 fields; polarity must be 0/1 (bool, or -1/+1).
"""

from __future__ import annotations

import numpy as np

from torchseq.events.stream import EVENT_DTYPE, EventFormatError
from torchseq.events.times import UNITS_PER_US, FloatTimeRule, float_times_to_us

ALIASES = {
    "t": ("t", "ts", "timestamp", "timestamps", "time", "times"),
    "x": ("x", "xs", "x_coordinates", "x_coordinate"),
    "y": ("y", "ys", "y_coordinates", "y_coordinate"),
    "p": ("p", "ps", "polarity", "polarities", "pol"),
}
MAX_EXPANSION = 1100  # deflate's best ratio is about 1032:1; a declared size beyond is a lie


def find_columns(names, columns: dict | None, where: str) -> dict[str, str]:
    """Map ``t, x, y, p`` to column names: ``columns`` overrides, else :data:`ALIASES`."""
    names = list(names)
    lower = {n.lower(): n for n in names}
    found = {}
    for field in "txyp":
        if columns and field in columns:
            if columns[field] not in names:
                raise EventFormatError(f"{where}: no column {columns[field]!r} (has {names})")
            found[field] = columns[field]
            continue
        hit = next((lower[a] for a in ALIASES[field] if a in lower), None)
        if hit is None:
            raise EventFormatError(
                f"{where}: no {field!r} column among {names} (looked for "
                f"{', '.join(ALIASES[field])}; pass columns={{'{field}': name}})")
        found[field] = hit
    return found


def unit_from_text(text) -> str | None:
    """``"s"``, ``"ms"``, ``"us"``, ``"ns"`` from a units string such as ``"nanoseconds"``."""
    if text is None:
        return None
    if isinstance(text, bytes):
        text = text.decode("ascii", "replace")
    s = str(text).strip().lower()
    for unit, words in (("ns", ("ns", "nanosecond", "nanoseconds", "nsec")),
                        ("us", ("us", "µs", "microsecond", "microseconds", "usec")),
                        ("ms", ("ms", "millisecond", "milliseconds", "msec")),
                        ("s", ("s", "sec", "second", "seconds"))):
        if s in words:
            return unit
    return None


def check_unit(unit: str | None) -> None:
    """Raise ``ValueError`` unless ``unit`` is None or one of :data:`UNITS_PER_US`."""
    if unit is not None and unit not in UNITS_PER_US:
        raise ValueError(f"time_unit must be one of {sorted(UNITS_PER_US)}, got {unit!r}")


def to_microseconds(t: np.ndarray, unit: str | FloatTimeRule | None, where: str
                    ) -> np.ndarray:
    """``(N,)`` int64 microseconds from times in ``unit``.

    ``unit`` None: integers are microseconds, floats follow
    :func:`~torchseq.events.times.float_times_to_us`; a file's ``FloatTimeRule`` carries
    its declared unit and its float decision across chunks.
    """
    t = np.asarray(t)
    if t.dtype.kind not in "iuf":
        raise EventFormatError(f"{where}: timestamps must be numbers, got dtype {t.dtype}")
    rule = unit if isinstance(unit, FloatTimeRule) else None
    if rule is not None:
        unit = None if rule.guessed else rule.unit
    if t.dtype.kind == "f":
        return rule(t) if rule is not None else float_times_to_us(t, where, unit)
    if unit is None:
        unit = "us"
    if len(t) and t.dtype.kind == "u" and int(t.max()) >= 2**63:
        raise EventFormatError(f"{where}: timestamp {int(t.max())} beyond int64")
    t = t.astype(np.int64)
    if unit == "ns":
        return t // 1000
    if unit == "us":
        return t
    scale = 1000 if unit == "ms" else 1_000_000
    if len(t) and max(abs(int(t.max())), abs(int(t.min()))) >= 2**63 // scale:
        raise EventFormatError(f"{where}: timestamps beyond int64 microseconds")
    return t * scale


def pack(t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray,
         unit: str | FloatTimeRule | None,
         where: str) -> np.ndarray:
    """Checked ``(N,)`` :data:`EVENT_DTYPE` array from one chunk of columns."""
    n = len(t)
    if not len(x) == len(y) == len(p) == n:
        raise EventFormatError(f"{where}: column lengths differ: t {n}, x {len(x)}, "
                               f"y {len(y)}, p {len(p)}")
    out = np.empty(n, EVENT_DTYPE)
    out["t"] = to_microseconds(t, unit, where)
    for name, v in (("x", x), ("y", y)):
        v = np.asarray(v)
        if v.dtype.kind not in "iub" and not (v.dtype.kind == "f" and _integral(v)):
            raise EventFormatError(f"{where}: {name} must be integers, got dtype {v.dtype}")
        if n and (v.min() < 0 or v.max() > 32767):
            raise EventFormatError(f"{where}: {name} outside 0..32767 "
                                   f"({v.min()}..{v.max()})")
        out[name] = v
    p = np.asarray(p)
    if p.dtype.kind not in "iubf":
        raise EventFormatError(f"{where}: polarity must be numbers, got dtype {p.dtype}")
    if n and not np.isin(p, (-1, 0, 1)).all():
        bad = p[~np.isin(p, (-1, 0, 1))][0]
        raise EventFormatError(f"{where}: polarity must be 0/1 or -1/+1, found {bad}")
    out["p"] = p > 0
    return out


def _integral(v: np.ndarray) -> bool:
    return bool(np.isfinite(v).all() and (v == np.round(v)).all())

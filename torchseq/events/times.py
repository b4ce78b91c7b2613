"""Event times stored as floats: the one rule every reader follows to reach int64 microseconds.

With a declared unit (``time_unit=``, an HDF5 ``units`` attribute, an Arrow timestamp
type) float times are scaled to microseconds and rounded; nothing is guessed. Without one
(:func:`float_time_unit`), the values decide:

- times with fractional parts and ``|t| < FLOAT_SECONDS_BELOW`` are **seconds** (tonic,
  ``events/ts`` HDF5 layouts), converted with a warning;
- whole-number times are **microseconds** (a float copy of integer times: seconds from a
  recording carry fractions), with a warning when they are also below
  ``FLOAT_SECONDS_BELOW``, where whole seconds cannot be ruled out;
- fractional times beyond ``FLOAT_SECONDS_BELOW`` are neither clearly seconds (27.7 hours
  or more after sensor time zero, or a Unix epoch) nor microseconds: refused with
  :class:`EventFormatError` (declare the unit, or store int64 microseconds).

Seconds are never read as microseconds. A file read in chunks decides once, on its first
chunk (:class:`FloatTimeRule`), and warns once; a later chunk with fractions after a
whole-number first chunk is refused. Reads with different chunk sizes agree unless their
first chunks decide differently (whole numbers in one, fractions in another; a recording
crossing ``FLOAT_SECONDS_BELOW`` seconds after its first chunk reads as seconds in chunks,
and is refused when the first chunk already spans the crossing).
"""

from __future__ import annotations

import warnings

import numpy as np

from torchseq.events.errors import EventFormatError

FLOAT_SECONDS_BELOW = 1e5  # float times with fractions under this are seconds (27.7 hours)
UNITS_PER_US = {"s": 1e-6, "ms": 1e-3, "us": 1.0, "ns": 1e3}


def _finite(t: np.ndarray, name: str) -> None:
    if not np.isfinite(t).all():
        raise EventFormatError(f"{name}: timestamps hold NaN or infinite values")


def float_time_unit(t: np.ndarray, name: str = "events") -> str:
    """``"s"`` or ``"us"``: the unit of ``(N,)`` float times with none declared (rule above).

    Warns when it reads seconds, or whole numbers small enough to be seconds.

    Raises:
        EventFormatError: non-finite times, or fractional times of unclear unit.
    """
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    _finite(t, name)
    if not len(t):
        return "us"
    top = float(np.abs(t).max())
    if (t == np.round(t)).all():
        if top < FLOAT_SECONDS_BELOW:
            warnings.warn(f"{name}: float timestamps without a unit are whole numbers "
                          f"({t.min():g}..{t.max():g}) read as microseconds, though they could "
                          f"be whole seconds; declare the unit or store int64 microseconds",
                          stacklevel=3)
        return "us"
    if top < FLOAT_SECONDS_BELOW:
        warnings.warn(f"{name}: float timestamps with fractions ({t.min():g}..{t.max():g}) read "
                      f"as seconds and converted to microseconds; declare the unit or store "
                      f"int64 microseconds to silence this", stacklevel=3)
        return "s"
    raise EventFormatError(
        f"{name}: float timestamps {t.min():g}..{t.max():g} have fractional parts but are too "
        f"large to be seconds after sensor time zero: declare the unit (time_unit='s', or "
        f"--time-unit s on the command line, for an epoch in seconds) or convert them to int64 "
        f"microseconds")


def float_times_to_us(t: np.ndarray, name: str = "events", unit: str | None = None
                      ) -> np.ndarray:
    """``(N,)`` int64 microseconds from ``(N,)`` floating-point event times.

    Args:
        t: ``(N,)`` float times.
        name: what to call them in warnings and errors (the file).
        unit: ``"s"``, ``"ms"``, ``"us"`` or ``"ns"``; None: :func:`float_time_unit` decides.

    Raises:
        EventFormatError: non-finite times, times beyond int64 microseconds, or (no unit)
            fractional times of unclear unit.
    """
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if unit is None:
        unit = float_time_unit(t, name)
    _finite(t, name)
    # exact constants: a product by 10**k or a quotient by 1000, each correctly rounded
    us = t / 1e3 if unit == "ns" else t * {"s": 1e6, "ms": 1e3, "us": 1.0}[unit]
    if len(us) and np.abs(us).max() >= 2.0 ** 62:
        raise EventFormatError(f"{name}: timestamps beyond int64 microseconds")
    return np.round(us).astype(np.int64)


class FloatTimeRule:
    """The float-time decision of one file read in chunks: made on its first chunk, kept.

    Args:
        name: the file, for warnings and errors.
        unit: the declared unit, or None to decide once by :func:`float_time_unit`.
    """

    def __init__(self, name: str, unit: str | None = None) -> None:
        self.name, self.unit, self.guessed = name, unit, False

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """``(N,)`` int64 microseconds from one chunk's ``(N,)`` float times.

        Raises:
            EventFormatError: as :func:`float_times_to_us`, or fractional times after a first
                chunk of whole numbers (read as microseconds).
        """
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        if self.unit is None and len(t):
            self.unit, self.guessed = float_time_unit(t, self.name), True
        elif self.guessed and self.unit == "us" and (t != np.round(t)).any():
            raise EventFormatError(
                f"{self.name}: float timestamps were whole numbers (read as microseconds) and "
                f"then have fractions ({t.min():g}..{t.max():g}): declare the unit")
        return float_times_to_us(t, self.name, self.unit or "us")


def with_us_times(events: np.ndarray, name: str = "events",
                  rule: FloatTimeRule | None = None) -> np.ndarray:
    """A structured event array whose float ``t`` field became int64 microseconds.

    Args:
        events: a structured array with a ``t`` field (other fields are copied).
        name: what to call the events in warnings and errors.
        rule: the file's :class:`FloatTimeRule` when it is read in chunks (None: this array
            alone decides, by :func:`float_times_to_us`).
    """
    t = np.asarray(events["t"])
    if t.dtype.kind != "f" or not np.isfinite(t).all():
        return events  # not finite: make_events names the first bad element
    us = rule(t) if rule is not None else float_times_to_us(t, name)
    fields = events.dtype.names
    out = np.empty(events.shape, [(f, "<i8" if f == "t" else events.dtype[f]) for f in fields])
    for f in fields:
        out[f] = us.reshape(events.shape) if f == "t" else events[f]
    return out

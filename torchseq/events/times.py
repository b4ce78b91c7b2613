"""Event times given as floats (tonic-style seconds): converted to int64 microseconds or refused.

Rule (:func:`float_times_to_us`): whole-number floats are microseconds already (a float copy
of int times); times with fractional parts and ``|t| < FLOAT_SECONDS_BELOW`` are seconds,
converted (rounded to the microsecond) with a warning; fractional times beyond that are
neither clearly seconds nor microseconds and raise :class:`EventFormatError`. Seconds are
never read as microseconds.
"""

from __future__ import annotations

import warnings

import numpy as np

from torchseq.events.stream import EventFormatError

FLOAT_SECONDS_BELOW = 1e5  # float times with fractions under this are seconds (27.7 hours)


def float_times_to_us(t: np.ndarray, name: str = "events") -> np.ndarray:
    """``(N,)`` int64 microseconds from ``(N,)`` floating-point event times (rule above).

    Raises:
        EventFormatError: non-finite times, or fractional times of unclear unit.
    """
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if not len(t):
        return t.astype(np.int64)
    if not np.isfinite(t).all():
        raise EventFormatError(f"{name}: timestamps hold NaN or infinite values")
    if (t == np.round(t)).all():
        if np.abs(t).max() >= 2.0 ** 62:
            raise EventFormatError(f"{name}: timestamps beyond int64 microseconds")
        return t.astype(np.int64)
    if np.abs(t).max() < FLOAT_SECONDS_BELOW:
        warnings.warn(f"{name}: float timestamps with fractions ({t.min():g}..{t.max():g}) read "
                      f"as seconds and converted to microseconds; store int64 microseconds to "
                      f"silence this", stacklevel=4)
        return np.round(t * 1e6).astype(np.int64)
    raise EventFormatError(
        f"{name}: float timestamps {t.min():g}..{t.max():g} have fractional parts but are too "
        f"large to be seconds: convert them to int64 microseconds")


def with_us_times(events: np.ndarray, name: str = "events") -> np.ndarray:
    """A structured event array whose float ``t`` field follows :func:`float_times_to_us`.

    Only fractional times are this module's business: an array whose float times are all
    whole numbers (or not finite) is returned as it is, for
    :func:`torchseq.events.make_events`' exact integer check.
    """
    t = np.asarray(events["t"])
    if not (np.isfinite(t).all() and (t != np.round(t)).any()):
        return events
    fields = events.dtype.names
    out = np.empty(events.shape, [(f, "<i8" if f == "t" else events.dtype[f]) for f in fields])
    for f in fields:
        out[f] = float_times_to_us(t, name).reshape(events.shape) if f == "t" else events[f]
    return out

"""The error of the event readers and checks, in a module of its own.

:mod:`torchseq.events.stream` (the event representation) and :mod:`torchseq.events.times`
(time units) both raise it; it lives here so that neither imports the other for it.
"""

from __future__ import annotations


class EventFormatError(ValueError):
    """An event file or array is malformed; the message says why in one line.

    Errors raised while reading a file name the file and, where the problem sits at a
    place in it, the byte offset.
    """


def file_error(path, offset: int | None, msg: str) -> EventFormatError:
    """An :class:`EventFormatError` ``"<path>: <msg> (at byte <offset>)"``."""
    where = f" (at byte {offset})" if offset is not None else ""
    return EventFormatError(f"{path}: {msg}{where}")

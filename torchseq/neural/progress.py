"""Progress callbacks for the engines' loops (the engines draw nothing themselves)."""

from __future__ import annotations

from collections.abc import Callable

Progress = Callable[[int, int], None]  # (frames done, frames in all)


def tqdm_progress(desc: str) -> Progress:
    """A callback that draws a ``tqdm`` bar of frames (for scripts and ``progress=True``)."""
    from tqdm import tqdm

    bar = None

    def update(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=total, desc=desc, unit="frame")
        bar.update(done - bar.n)
        if done >= total:
            bar.close()

    return update


def as_progress(progress: bool | Progress | None, desc: str) -> Progress | None:
    """``True``: :func:`tqdm_progress`; a callable as is; ``False``/None: no callback."""
    if progress is True:
        return tqdm_progress(desc)
    if not progress:
        return None
    if not callable(progress):
        raise TypeError(f"progress must be a bool or a callable(done, total), got {progress!r}")
    return progress


def chunks(n: int, size: int, progress: Progress | None = None):
    """``(lo, hi)`` bounds of batches of ``size``, reporting to ``progress``.

    ``progress(0, n)`` comes first (a bar starts its clock before the work), then
    ``progress(hi, n)`` after each batch.
    """
    if progress is not None:
        progress(0, n)
    for lo in range(0, n, size):
        hi = min(lo + size, n)
        yield lo, hi
        if progress is not None:
            progress(hi, n)

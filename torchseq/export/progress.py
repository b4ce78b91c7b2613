"""Progress of the export's long steps, on stderr (the exporter's own lines go to stdout).

On a terminal each step is a ``tqdm`` bar (of frames where the step has a count, else one
tick); when stderr is not a terminal (a log file, a pipe) a step writes one line when it
starts and one when it ends, with its seconds: no carriage returns in redirected logs.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

Update = Callable[[int], None]  # frames done so far in the step


def _noop(done: int) -> None:
    return None


class ExportProgress:
    """Draws the export's steps (see the module docstring); ``enabled=False`` draws nothing.

    Args:
        enabled: whether to draw anything.
        file: the stream (None: ``sys.stderr`` at the time of each step).
        bars: tqdm bars (True), plain lines (False) or None: bars when ``file`` is a tty.
    """

    def __init__(self, enabled: bool = True, file=None, bars: bool | None = None) -> None:
        self.enabled = bool(enabled)
        self._file = file
        self._bars = bars

    @property
    def file(self):
        """The stream the steps are written to."""
        return self._file if self._file is not None else sys.stderr

    def _use_bars(self) -> bool:
        if self._bars is not None:
            return self._bars
        isatty = getattr(self.file, "isatty", None)
        return bool(isatty and isatty())

    @contextmanager
    def step(self, desc: str, total: int | None = None,
             unit: str = "frames") -> Iterator[Update]:
        """A step named ``desc`` of ``total`` ``unit`` (None: no count); yields ``update(done)``."""
        if not self.enabled:
            yield _noop
            return
        t0 = time.perf_counter()
        if self._use_bars():
            from tqdm import tqdm

            bar = tqdm(total=total if total is not None else 1, desc=f"export: {desc}",
                       unit=unit if total is not None else "step", file=self.file,
                       leave=True, dynamic_ncols=True)
            try:
                yield lambda done: bar.update(done - bar.n)
                if total is None:
                    bar.update(1)
            finally:
                bar.close()
            return
        count = f" ({total} {unit})" if total is not None else ""
        print(f"export: {desc}{count} ...", file=self.file, flush=True)
        yield _noop
        print(f"export: {desc}: done in {time.perf_counter() - t0:.1f} s", file=self.file,
              flush=True)


QUIET = ExportProgress(enabled=False)

"""The warnings of one command-line run: said once each on stderr, counted, kept for its json.

Library code warns through :mod:`warnings` (a float-time conversion, a truncated file, events
dropped, empty windows, coarse output units, an old checkpoint). A script run under
:meth:`WarningLog.capture` turns each into one ``prog: warning: ...`` line on stderr the first
time it comes (repeats are counted, not reprinted) and keeps it, with the front end's own
warnings, for the ``"warnings"`` list of the run's ``metrics.json`` / ``train.json``.
Only warnings for users (``UserWarning``, ``RuntimeWarning``, ``FutureWarning`` and their
subclasses) are taken; developers' warnings (deprecations, ``ImportWarning``,
``ResourceWarning``) are left to Python's own handling.
"""

from __future__ import annotations

import contextlib
import sys
import warnings
from collections.abc import Iterator

# warnings for users: about this run's inputs or results (the rest are for developers)
TAKEN = (UserWarning, RuntimeWarning, FutureWarning)
SHORT = 80  # characters of a repeated warning quoted in the closing count


# the library's hints name its keyword arguments; a command-line user sets flags instead
FLAG_TERMS = (("pass sensor_size= to set it", "--sensor-size WxH sets it"),
              ("pass sensor_size=", "pass --sensor-size WxH"),
              ("pass truncated='drop'", "pass --truncated drop"),
              ("anchor='first' starts at the first event",
               "--window-anchor first starts at the first event"),
              ("declare the unit", "declare the unit (--time-unit)"),
              ("evt3_time='carry'", "--evt3-time carry"),
              ("evt3_kernel='numpy'", "--evt3-kernel numpy"),
              ("evt3_kernel='numba'", "--evt3-kernel numba"))


def cli_terms(text: str) -> str:
    """A library message with its keyword-argument hints said as command-line flags."""
    for api, flag in FLAG_TERMS:
        text = text.replace(api, flag)
    return text


def one_line(message: object) -> str:
    """A warning's text on one line (newlines and runs of spaces become single spaces)."""
    return " ".join(str(message).split())


class WarningLog:
    """Warnings of one run, in first-seen order, each with how often it came.

    Args:
        prog: the command's name, the prefix of every stderr line (``torchseq eval``).
    """

    def __init__(self, prog: str) -> None:
        self.prog = prog
        self.counts: dict[str, int] = {}

    def add(self, message: object) -> None:
        """Count ``message``; print ``prog: warning: message`` the first time it comes."""
        text = one_line(message)
        if text not in self.counts:
            print(f"{self.prog}: warning: {text}", file=sys.stderr)
            self.counts[text] = 0
        self.counts[text] += 1

    def entries(self) -> list[str]:
        """The json list: each warning once, ``"... (N times)"`` where it came N > 1 times."""
        return [t if n == 1 else f"{t} ({n} times)" for t, n in self.counts.items()]

    def __len__(self) -> int:
        return len(self.counts)

    def close(self) -> None:
        """Say on stderr how often each repeated warning came (it was printed once)."""
        for text, n in self.counts.items():
            if n > 1:
                quoted = text if len(text) <= SHORT else text[:SHORT - 3] + "..."
                print(f"{self.prog}: warning: {n} times in all: {quoted}", file=sys.stderr)

    @contextlib.contextmanager
    def capture(self) -> Iterator[WarningLog]:
        """Route Python warnings raised inside the block through :meth:`add`; then :meth:`close`.

        Every occurrence is counted (the ``"always"`` filter), unless the user set warning
        filters of their own (``python -W ...``, ``PYTHONWARNINGS``), which are kept.
        """
        with warnings.catch_warnings():
            if not sys.warnoptions:
                for category in TAKEN:
                    warnings.filterwarnings("always", category=category)
            shown = warnings.showwarning

            def show(message, category, filename, lineno, file=None, line=None):
                if not issubclass(category, TAKEN):
                    shown(message, category, filename, lineno, file, line)
                    return
                name = "" if category is UserWarning else f"{category.__name__}: "
                self.add(f"{name}{cli_terms(str(message))}")

            warnings.showwarning = show
            try:
                yield self
            finally:
                self.close()


def warning_list(notes: WarningLog | list) -> list[str]:
    """The ``"warnings"`` list of a run's json, from its log (or a plain list of messages)."""
    return notes.entries() if isinstance(notes, WarningLog) else [one_line(n) for n in notes]

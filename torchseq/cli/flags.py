"""Flags from config dataclasses, and the checks every command's flags share.

Scripts stay thin: a config dataclass, flags that override it (:func:`add_config_flags`, one
``--flag`` per field), :func:`config_from_args` back to the dataclass, and range checks.
Where each flag shows in ``--help`` (inputs, SeqSLAM, neural, events, outputs):
:mod:`torchseq.cli.help`; the event-file flags: :mod:`torchseq.cli.event_options`.
Nothing here is needed to use the library from Python.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re

import torch

from torchseq.cli.errors import UsageError
from torchseq.sources import FrameSelection

MAX_SIDE = 16384  # largest frame side a size flag accepts (pixels)


class Parser(argparse.ArgumentParser):
    """``argparse`` with the scripts' contract: a bad flag is one ``prog: error:`` line, exit 2."""

    def error(self, message: str):  # noqa: D102 - argparse's hook
        self.exit(2, f"{self.prog}: error: {message.splitlines()[0]}\n")

    help_layout = None  # a torchseq.cli.help.HelpLayout: grouped --help (organise_help)

    def format_help(self) -> str:  # noqa: D102 - argparse's hook
        if self.help_layout is None:
            return super().format_help()
        return self.help_layout.format(self, full=False)


def parse_size(text: str | None) -> tuple[int, int] | None:
    """Parse ``"HxW"`` (e.g. ``"16x12"``) into ``(H, W)``; a single ``"N"`` means ``N x N``."""
    if text is None or isinstance(text, tuple):
        return text
    parts = str(text).lower().split("x")
    try:
        if len(parts) not in (1, 2):
            raise ValueError(text)
        h, w = (int(parts[0]), int(parts[-1]))
    except ValueError as err:
        raise UsageError(f"size must look like HxW (e.g. 16x16) or N, got {text!r}") from err
    if not (0 < h <= MAX_SIDE and 0 < w <= MAX_SIDE):
        raise UsageError(f"size sides must be in 1..{MAX_SIDE}, got {text!r}")
    return h, w


def finite_float(text: str) -> float:
    """Flag type: a finite float (``nan`` and ``inf`` are refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def float_or_list(text: str) -> float | tuple[float, ...]:
    """Flag type: a finite float, or a comma-separated list of them (``5,10,20``)."""
    parts = [finite_float(part.strip()) for part in str(text).split(",")]
    return parts[0] if len(parts) == 1 else tuple(parts)


def bounded_int(text: str) -> int:
    """Flag type: an integer that fits in int64."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if abs(value) >= 2 ** 63:
        raise argparse.ArgumentTypeError(f"integer out of range: {text!r}")
    return value


def check_ranges(config, limits: dict[str, tuple[float | None, float | None]],
                 prefix: str = "") -> None:
    """Raise :class:`UsageError` unless every named field lies in its inclusive ``(lo, hi)``.

    None fields (unset options) pass; a None bound is open.
    """
    for name, (lo, hi) in limits.items():
        value = getattr(config, name)
        if value is None:
            continue
        flag = "--" + (prefix + name).replace("_", "-")
        if isinstance(value, float) and not math.isfinite(value):
            raise UsageError(f"{flag} must be a finite number, got {value}")
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            span = f"{'-inf' if lo is None else lo}..{'inf' if hi is None else hi}"
            raise UsageError(f"{flag} must be in {span}, got {value}")


def _flag_type(annotation: object, default: object) -> type:
    """The argparse type of a dataclass field, from its annotation (``"float | None"``)."""
    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", "")
    for name, kind in (("tuple[float, ...]", float_or_list), ("tuple", str), ("bool", bool),
                       ("float", finite_float),
                       ("int", bounded_int)):
        if name in str(text):
            return kind
    return type(default) if default is not None else str


def docstring_help(config_cls: type) -> dict[str, str]:
    """Field descriptions from a Google-style class docstring (``name: text`` lines)."""
    found: dict[str, str] = {}
    current = None
    for line in (config_cls.__doc__ or "").splitlines():
        m = re.match(r"^\s{4,8}(\w+): (.*)$", line)
        if m:
            current = m.group(1)
            found[current] = m.group(2).strip()
        elif current and line.startswith(" " * 12) and line.strip():
            found[current] += " " + line.strip()
        else:
            current = None
    return {k: _plain(v) for k, v in found.items()}


def _plain(text: str) -> str:
    """Docstring markup -> terminal text: ``x`` -> x, and ``%`` escaped for argparse."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"\1", text).replace("``", "")
    return text.replace("%", "%%")


def add_config_flags(parser, config_cls: type, help: dict[str, str], prefix: str = "",
                     skip: type | None = None) -> None:
    """Add one ``--flag`` per dataclass field, defaulting to the dataclass default.

    Tuple fields (sizes) take ``HxW`` strings; booleans get ``--flag/--no-flag``; floats must
    be finite. ``prefix`` namespaces the flags (``--neural-patch-size`` for ``patch_size``);
    the fields of a base dataclass ``skip`` are left out (added in a group of their own).
    """
    help = {**docstring_help(config_cls), **help}
    skipped = {f.name for f in dataclasses.fields(skip)} if skip is not None else set()
    for f in dataclasses.fields(config_cls):
        if f.name in skipped:
            continue
        flag = "--" + (prefix + f.name).replace("_", "-")
        default = f.default if f.default is not dataclasses.MISSING else None
        shown = "x".join(map(str, default)) if isinstance(default, tuple) else default
        text = help.get(f.name, f.name.replace("_", " "))
        kind = _flag_type(f.type, default)
        if kind is bool:  # BooleanOptionalAction states the default itself
            parser.add_argument(flag, action=argparse.BooleanOptionalAction,
                                default=default, dest=prefix + f.name, help=text)
            continue
        if default is not None and "(default" not in text:
            text += f" (default: {shown})"
        parser.add_argument(flag, type=kind, default=default, dest=prefix + f.name,
                            help=text)


def config_from_args(config_cls: type, args: argparse.Namespace, prefix: str = ""):
    """Build the dataclass from parsed flags (``HxW`` strings of size fields are parsed)."""
    values = {}
    for f in dataclasses.fields(config_cls):
        v = getattr(args, prefix + f.name)
        if f.name.endswith("_size") and f.name != "sensor_size" and isinstance(v, str):
            try:
                v = parse_size(v)
            except UsageError as err:
                raise UsageError(f"--{(prefix + f.name).replace('_', '-')}: {err}") from None
        values[f.name] = v
    return config_cls(**values)


def changed_fields(config, default) -> dict:
    """``{field: value}`` of the dataclass fields of ``config`` that differ from ``default``."""
    return {f.name: getattr(config, f.name) for f in dataclasses.fields(config)
            if getattr(config, f.name) != getattr(default, f.name)}


def given_flags(parser: argparse.ArgumentParser, argv: list[str],
                dests: set[str]) -> frozenset[str]:
    """Which of ``dests`` the command line ``argv`` gives (abbreviated or not, any value).

    argparse fills in a default only where the namespace lacks the name, so names set
    beforehand to a marker that survives parsing were not given.
    """
    unset = object()
    namespace = argparse.Namespace(**{d: unset for d in dests})
    parser.parse_args(argv, namespace)
    return frozenset(d for d in dests if getattr(namespace, d) is not unset)


def frame_selection(start: int, stop: int | None, step: int,
                    max_frames: int | None) -> FrameSelection:
    """Check and bundle ``--start``, ``--stop``, ``--frame-step`` and ``--max-frames``."""
    if start < 0:
        raise UsageError(f"--start must be >= 0, got {start}")
    if stop is not None and stop <= start:
        raise UsageError(f"--stop must be after --start ({start}), got {stop}")
    if step < 1:
        raise UsageError(f"--frame-step must be >= 1, got {step}")
    if max_frames is not None and max_frames < 1:
        raise UsageError(f"--max-frames must be >= 1, got {max_frames}")
    return FrameSelection(start, stop, step, max_frames)


def resolve_device(name: str) -> torch.device:
    """``"auto"`` picks CUDA when present; otherwise the named device, checked."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise UsageError("--device cuda asked for, but CUDA is not available here")
    return torch.device(name)


# ranges of the numbers the scripts accept, checked before any work (relations between fields
# stay with each config's own validate())
NEURAL_LIMITS = {
    "patch_size": (0, MAX_SIDE), "input_steps": (0, 2 ** 16), "hidden": (1, 2 ** 20),
    "density": (0.0, 1.0), "density_out": (0.0, 1.0), "l1_levels": (0, 64),
    "l3_levels": (0, 127), "k_fraction": (0.0, 1.0), "n_output": (1, 2 ** 16),
    "ring_decay": (0.0, 1.0), "ring_gain": (0.0, 1e6), "ring_spread": (0, 2 ** 16),
    "ring_spread_decay": (0.0, 1e6), "ring_stay": (0.0, 1e6), "n_cohorts": (1, 2 ** 16),
    "uniqueness_window": (0, 2 ** 20), "eps": (1e-30, 1.0), "chunk": (1, 2 ** 16),
    "seed": (0, 2 ** 32 - 1),
}
MAX_WEIGHTS = 2 ** 30  # elements of the largest weight matrix a script will build


def check_neural(ncfg, prefix: str = "") -> None:
    """Range-check a :class:`~torchseq.neural.NeuralConfig` from flags and size its weights."""
    check_ranges(ncfg, {k: v for k, v in NEURAL_LIMITS.items() if hasattr(ncfg, k)}, prefix)
    n_input = int(ncfg.input_size[0]) * int(ncfg.input_size[1])
    for what, n in (("L1 -> L2", n_input * ncfg.hidden), ("L2 -> L3", ncfg.hidden *
                    ncfg.n_output), ("ring", ncfg.n_output ** 2)):
        if n > MAX_WEIGHTS:
            raise UsageError(f"the {what} weights would hold {n} elements (more than "
                             f"{MAX_WEIGHTS}); lower --{prefix.replace('_', '-')}hidden, "
                             f"--{prefix.replace('_', '-')}n-output or the input size")

"""Pieces the command-line front ends (``train.py``, ``eval.py``) share.

Scripts stay thin: a config dataclass, flags that override it, and these helpers for inputs,
errors and logging. Nothing here is needed to use the library from Python.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import math
import re
import sys
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from torchseq.events.times import UNITS_PER_US
from torchseq.sources import (
    EventFrameOptions,
    FrameSelection,
    TraverseError,
    is_event_file,
    load_traverse,
)
from torchseq.versions import VERSIONS_KEY


class UsageError(ValueError):
    """A problem with what the user asked for; printed as one line."""


MAX_SIDE = 16384  # largest frame side a size flag accepts (pixels)


class Parser(argparse.ArgumentParser):
    """``argparse`` with the scripts' contract: a bad flag is one ``prog: error:`` line, exit 2."""

    def error(self, message: str):  # noqa: D102 - argparse's hook
        self.exit(2, f"{self.prog}: error: {message.splitlines()[0]}\n")

    help_layout = None  # a torchseq.cli_help.HelpLayout: grouped --help (organise_help)

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
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=default,
                                dest=prefix + f.name, help=text)
            continue
        if default is not None and "(default" not in text:
            text += f" (default: {shown})"
        parser.add_argument(flag, type=kind, default=default, dest=prefix + f.name, help=text)


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


DEFAULT_WINDOW_MS = 10.0  # --window-ms when not given
MAX_WINDOW_MS = 3.6e9  # 1000 hours: longer windows are surely a mistake
MAX_EVENT_COUNT = 2 ** 40


def parse_anchor(text: str | int) -> str | int:
    """``--window-anchor``: ``"first"``, ``"zero"`` or a sensor time in microseconds."""
    if isinstance(text, int) or text not in ("first", "zero"):
        try:
            value = int(text)
        except ValueError:
            raise UsageError(f"--window-anchor must be 'first', 'zero' or a time in "
                             f"microseconds, got {text!r}") from None
        if not 0 <= value < 2 ** 62:
            raise UsageError(f"--window-anchor time must be in 0..2**62 us, got {value}")
        return value
    return text


EVENT_MODES = ("count", "signed", "two-channel", "binary")
EVT3_KERNEL_CHOICES = ("auto", "numpy", "numba")  # auto: the readers' choice by file size
MAX_CROP_MS = 1e12  # about 31 years of sensor time
MAX_REFRACTORY_US = 2 ** 40


def parse_sensor_size(text: str | None) -> tuple[int, int] | None:
    """``--sensor-size``: ``WxH`` (or tonic's ``W,H,P``) -> ``(W, H)``."""
    if text is None:
        return None
    parts = str(text).lower().replace(",", "x").split("x")
    try:
        if len(parts) not in (2, 3):
            raise ValueError(text)
        w, h = int(parts[0]), int(parts[1])
    except ValueError:
        raise UsageError(f"--sensor-size must look like WxH (e.g. 128x128) or W,H,P, "
                         f"got {text!r}") from None
    if not (0 < w <= MAX_SIDE and 0 < h <= MAX_SIDE):
        raise UsageError(f"--sensor-size sides must be in 1..{MAX_SIDE}, got {text!r}")
    return w, h


def event_options(window_ms: float, event_count: int | None,
                  frame_size: tuple[int, int] | None, anchor: str | int = "first",
                  sensor_size: str | None = None, mode: str = "count",
                  evt3_time: str = "spec", truncated: str = "error", t_start: float = 0.0,
                  duration: float | None = None, hot_pixel: float | None = None,
                  refractory_us: int | None = None, time_unit: str | None = None,
                  evt3_kernel: str = "auto") -> EventFrameOptions:
    """Check and bundle the event-accumulation flags.

    ``--event-mode two-channel`` (or ``two_channel``) puts the OFF and ON counts side by side
    (``(H, 2W)`` frames); ``--t-start``/``--duration`` crop in milliseconds after the window
    anchor; ``--hot-pixel`` and ``--refractory-us`` switch the pixel filters on.
    """
    if evt3_time not in ("spec", "carry"):
        raise UsageError(f"--evt3-time must be spec or carry, got {evt3_time!r}")
    if truncated not in ("error", "drop"):
        raise UsageError(f"--truncated must be error or drop, got {truncated!r}")
    if evt3_kernel not in EVT3_KERNEL_CHOICES:
        raise UsageError(f"--evt3-kernel must be {', '.join(EVT3_KERNEL_CHOICES[:-1])} or "
                         f"{EVT3_KERNEL_CHOICES[-1]}, got {evt3_kernel!r}")
    if evt3_kernel == "numba" and importlib.util.find_spec("numba") is None:
        raise UsageError("--evt3-kernel numba needs numba: pip install torchseq[fast] (or "
                         "--evt3-kernel numpy: the same events)")
    if time_unit is not None and time_unit not in UNITS_PER_US:  # the readers' units
        raise UsageError(f"--time-unit must be s, ms, us or ns, got {time_unit!r}")
    if str(mode).replace("_", "-") not in EVENT_MODES:
        raise UsageError(f"--event-mode must be one of {', '.join(EVENT_MODES)}, got {mode!r}")
    window_ms, members = window_members(window_ms)
    if members is not None and event_count is not None:
        raise UsageError("--window-ms with several windows (an ensemble) needs time windows; "
                         "drop --event-count or give one window")
    if event_count is not None and not 0 < event_count <= MAX_EVENT_COUNT:
        raise UsageError(f"--event-count must be in 1..{MAX_EVENT_COUNT}, got {event_count}")
    if event_count is not None and window_ms != DEFAULT_WINDOW_MS:
        raise UsageError(f"--window-ms {window_ms:g} has no effect with --event-count (frames "
                         f"of {event_count} events each, whatever their time span); drop one")
    if not (math.isfinite(t_start) and 0 <= t_start <= MAX_CROP_MS):
        raise UsageError(f"--t-start must be in 0..{MAX_CROP_MS:g} ms, got {t_start}")
    if duration is not None and not (math.isfinite(duration) and 0 < duration <= MAX_CROP_MS):
        raise UsageError(f"--duration must be in (0, {MAX_CROP_MS:g}] ms, got {duration}")
    if hot_pixel is not None and not (math.isfinite(hot_pixel) and 0 < hot_pixel <= 1e9):
        raise UsageError(f"--hot-pixel must be a factor in (0, 1e9], got {hot_pixel}")
    if refractory_us is not None and not 0 <= refractory_us <= MAX_REFRACTORY_US:
        raise UsageError(f"--refractory-us must be in 0..{MAX_REFRACTORY_US}, got "
                         f"{refractory_us}")
    return EventFrameOptions(window_ms=window_ms, event_count=event_count, frame_size=frame_size,
                             anchor=parse_anchor(anchor),
                             sensor_size=parse_sensor_size(sensor_size),
                             mode=str(mode).replace("-", "_"), evt3_time=evt3_time,
                             truncated=truncated, start_ms=float(t_start),
                             duration_ms=duration, hot_pixel=hot_pixel,
                             refractory_us=refractory_us, time_unit=time_unit,
                             evt3_kernel=None if evt3_kernel == "auto" else evt3_kernel,
                             members_ms=members)


def window_members(window_ms) -> tuple[float, tuple[float, ...] | None]:
    """``--window-ms``: one window, or a temporal-window ensemble ``5,10,20``.

    Returns ``(step, members)``: frames come every ``step`` ms (the middle member, the lower
    of the two middle ones for an even count); with several windows ``members`` are their
    lengths in the order given (each frame of member ``L`` counts the ``L`` ms centred on
    its step), else None.
    """
    values = list(window_ms) if isinstance(window_ms, (list, tuple)) else [window_ms]
    if not values:
        raise UsageError("--window-ms needs at least one window")
    for w in values:
        if not (isinstance(w, (int, float)) and math.isfinite(w) and 0 < w <= MAX_WINDOW_MS):
            raise UsageError(f"--window-ms must be in (0, {MAX_WINDOW_MS:g}] ms, got {w}")
    if len(values) == 1:
        return float(values[0]), None
    if len(set(values)) != len(values):
        raise UsageError(f"--window-ms lists a window twice: {','.join(f'{w:g}' for w in values)}")
    step = sorted(values)[(len(values) - 1) // 2]
    from torchseq.events.ensemble import ensemble_base

    try:
        ensemble_base(int(round(step * 1000)), [int(round(w * 1000)) for w in values])
    except ValueError as err:
        raise UsageError(f"--window-ms {','.join(f'{w:g}' for w in values)}: {err}") from None
    return float(step), tuple(float(w) for w in values)


@dataclasses.dataclass
class EventFlags:
    """The flags of event-file inputs, shared by the scripts' config dataclasses.

    :func:`event_frame_options` checks and bundles them.
    """

    window_ms: float | tuple[float, ...] = DEFAULT_WINDOW_MS
    event_count: int | None = None
    frame_size: str | None = None
    window_anchor: str = "first"
    sensor_size: str | None = None
    event_mode: str = "count"
    evt3_time: str = "spec"
    evt3_kernel: str = "auto"
    truncated: str = "error"
    t_start: float = 0.0
    duration: float | None = None
    hot_pixel: float | None = None
    refractory_us: int | None = None
    time_unit: str | None = None


EVENT_HELP = {
    "window_ms": "event files: accumulation window in ms (not with --event-count); a list "
                 "(5,10,20) is a temporal-window ensemble (eval; docs/guide/events.md)",
    "event_count": "event files: events per frame instead of a time window",
    "frame_size": "event files: downsample frames to HxW (or N for NxN) by area pooling",
    "window_anchor": "event files: where the first window starts: 'first' (first event), "
                     "'zero' (sensor time 0) or a sensor time in microseconds",
    "sensor_size": "event files: sensor size WxH (or tonic's W,H,P), overriding the file's",
    "event_mode": "event files: pixel value of a frame: count (events), signed (|ON - OFF|), "
                  "binary (255 where a pixel fired) or two-channel (OFF and ON counts side "
                  "by side: HxW event frames reach the engines as Hx2W images)",
    "t_start": "event files: time crop start, in milliseconds after the window anchor (windows "
               "start there)",
    "duration": "event files: time crop length in milliseconds (default: to the end)",
    "hot_pixel": "event files: drop pixels firing more than this many times the median active "
                 "pixel (default: off)",
    "refractory_us": "event files: per-pixel refractory period in microseconds (default: off)",
    "evt3_time": "Prophesee EVT 3 .raw files: time rule, spec or carry (see docs/guide/events.md; "
                 "carry is refused for EVT 2.0 files)",
    "evt3_kernel": "Prophesee EVT 3 .raw files: decoder, auto (numba from 128 MiB when "
                   "installed, else numpy), numpy or numba; the same events either way (numpy "
                   "and numba are refused for EVT 2.0 files)",
    "time_unit": "CSV, HDF5 and Parquet event files: the time column's unit, s, ms, us or ns "
                 "(default: integers are us, fractions follow the float-time rule)",
    "truncated": "event files cut short (.aedat, .aedat4, .raw): error, or drop the last "
                 "incomplete record",
}


def event_frame_options(cfg: EventFlags) -> EventFrameOptions:
    """The event flags of a run, checked (:func:`event_options`)."""
    return event_options(cfg.window_ms, cfg.event_count, parse_size(cfg.frame_size),
                         cfg.window_anchor, cfg.sensor_size, cfg.event_mode, cfg.evt3_time,
                         cfg.truncated, cfg.t_start, cfg.duration, cfg.hot_pixel,
                         cfg.refractory_us, cfg.time_unit, cfg.evt3_kernel)


def changed_fields(config, default) -> dict:
    """``{field: value}`` of the dataclass fields of ``config`` that differ from ``default``."""
    return {f.name: getattr(config, f.name) for f in dataclasses.fields(config)
            if getattr(config, f.name) != getattr(default, f.name)}


def event_flags_set(cfg: EventFlags, given: frozenset[str] = frozenset()) -> list[str]:
    """The event flags given values other than their defaults, or named in ``given``.

    Args:
        cfg: the run's event flags.
        given: field names the command line gave (:func:`given_flags`), whatever their value.

    Returns:
        ``--flag`` names, in the fields' order.
    """
    default = EventFlags()
    return [f"--{f.name.replace('_', '-')}" for f in dataclasses.fields(EventFlags)
            if f.name in given or getattr(cfg, f.name) != getattr(default, f.name)]


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


EVENT_FIELDS = {f.name for f in dataclasses.fields(EventFlags)}


def _may_hold_events(source: str | None) -> bool:
    """False only for inputs surely not event files: the demo, folders, videos, frame arrays.

    A file that cannot be sniffed (missing, damaged) counts as possible: its own error comes
    when it is read.
    """
    if source is None:
        return False
    path = Path(source)
    if path.is_dir():
        return False
    if not path.is_file():
        return True
    try:
        return is_event_file(path)
    except (TraverseError, OSError):
        return True


def check_event_flags_apply(cfg: EventFlags, sources: dict[str, str | None],
                            given: frozenset[str] = frozenset()) -> None:
    """Refuse event flags when no input is an event file (they would be silently ignored).

    Args:
        cfg: the run's event flags.
        sources: ``{"--reference": path or None (demo), ...}``, every input they could
            apply to.
        given: event fields the command line gave (also at their default value).

    Raises:
        UsageError: an event flag was set and no input is an event file.
    """
    given = event_flags_set(cfg, given)
    if given and not any(_may_hold_events(s) for s in sources.values()):
        what = ", ".join(f"{k} {'demo' if v is None else v}" for k, v in sources.items())
        raise UsageError(f"{', '.join(given)} appl{'ies' if len(given) == 1 else 'y'} to "
                         f"event files only, and no input is one ({what}); drop "
                         f"{'it' if len(given) == 1 else 'them'}")


def load_frames(path: str, what: str, events: EventFrameOptions, progress: bool,
                select: FrameSelection | None = None) -> torch.Tensor:
    """Load a traverse, naming it in any error."""
    try:
        frames = load_traverse(path, events=events, progress=progress, select=select)
    except (ValueError, OSError) as err:
        raise UsageError(f"{what} traverse {path}: {err}") from err
    return frames


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


def load_model(path: str, device=None):
    """Read a Neural SeqSLAM checkpoint for a script; any failure is a :class:`UsageError`."""
    from torchseq.neural import NeuralSeqSLAM

    try:
        return NeuralSeqSLAM.load(path, map_location=device)
    except Exception as err:  # noqa: BLE001 - a hostile checkpoint must not end in a traceback
        text = str(err).splitlines()[0] if str(err) else ""
        where = "" if str(path) in text else f"{path}: "
        raise UsageError(f"checkpoint {where}{text or 'unreadable'} "
                         f"({type(err).__name__})") from err


def resolve_device(name: str) -> torch.device:
    """``"auto"`` picks CUDA when present; otherwise the named device, checked."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise UsageError("--device cuda asked for, but CUDA is not available here")
    return torch.device(name)


def to_jsonable(obj):
    """Dataclasses, tuples, paths, NumPy and tensor scalars -> plain JSON types."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(dataclasses.asdict(obj))
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (np.generic, torch.Tensor)):
        return obj.item()
    return obj


def config_text(config) -> str:
    """The config as indented JSON, for TensorBoard text and files."""
    return json.dumps(to_jsonable(config), indent=2)


def run_main(main: Callable[[list[str] | None], int], prog: str,
             argv: list[str] | None = None) -> int:
    """Run a script's main; expected failures become one line on stderr and exit code 2."""
    try:
        return main(argv)
    except (ValueError, OSError, RuntimeError) as err:
        from torchseq.cli.run_warnings import cli_terms

        message = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"{prog}: error: {cli_terms(message)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130


def warn(prog: str, message: str, sink=None) -> None:
    """Print ``prog: warning: message`` on stderr (and keep it in ``sink`` for the report).

    ``sink``: a list, or a run's :class:`~torchseq.cli.run_warnings.WarningLog` (which prints a
    repeated warning once and counts it).
    """
    if hasattr(sink, "add"):
        sink.add(message)
        return
    print(f"{prog}: warning: {message}", file=sys.stderr)
    if sink is not None:
        sink.append(message)


def run_folder(out: str | None, kind: str, overwrite: bool) -> Path:
    """The output folder of one run, created empty.

    ``out`` None: a new ``runs/<kind>-<UTC time>`` folder. An existing non-empty ``out`` is
    refused unless ``overwrite`` is set and it holds a previous run (its ``config.json``),
    which is then removed, so the outputs of two runs never mix.
    """
    import shutil
    import time

    if out is None:
        stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
        path = Path("runs") / f"{kind}-{stamp}"
        n = 1
        while path.exists():
            n += 1
            path = Path("runs") / f"{kind}-{stamp}-{n}"
    else:
        path = Path(out)
    if path.exists() and not path.is_dir():
        raise UsageError(f"--out {path} is a file, not a folder")
    if path.is_dir() and any(path.iterdir()):
        if not overwrite:
            raise UsageError(f"--out {path} already holds files; give a new folder or "
                             f"--overwrite to replace the previous run there")
        if not ((path / "config.json").is_file() or (path / "INCOMPLETE").is_file()):
            raise UsageError(f"--overwrite only replaces a previous run's folder (one with a "
                             f"config.json); {path} is not one")
        shutil.rmtree(path)
    path.mkdir(parents=True, exist_ok=True)
    return path


def config_file_defaults(parser: argparse.ArgumentParser, path: str,
                         sections: dict[str, str]) -> frozenset[str]:
    """Make a run's saved ``config.json`` the parser's defaults (flags still override it).

    Args:
        parser: the script's parser (its dests are the field names).
        path: a ``config.json`` a previous run wrote.
        sections: nested dicts of the file and the dest prefix of their fields
            (``{"neural": "neural_"}``); ``""`` keeps field names as they are.

    Values go through the same flag types as the command line (finite numbers, sizes).

    Returns:
        The dests the file gave.
    """
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise UsageError(f"--config {path}: not a readable JSON file ({err})") from None
    if not isinstance(data, dict):
        raise UsageError(f"--config {path}: expected a JSON object")
    dests = {a.dest: a for a in parser._actions}
    flat = {}
    for key, value in data.items():
        if key == VERSIONS_KEY:  # a record of what made the run, not a setting
            continue
        if key in sections:
            if not isinstance(value, dict):
                raise UsageError(f"--config {path}: {key!r} must be an object")
            flat.update({sections[key] + k: v for k, v in value.items()})
        else:
            flat[key] = value
    defaults = {}
    for dest, value in flat.items():
        if dest not in dests or dest in ("help", "config"):
            if {"inputs", "warnings"} <= set(data):
                raise UsageError(f"--config {path}: this is a run's metrics.json, not a "
                                 f"config; give the config.json beside it "
                                 f"({Path(path).with_name('config.json')})")
            raise UsageError(f"--config {path}: unknown setting {dest!r}"
                             + _near_name(dest, dests))
        action = dests[dest]
        if value is None or isinstance(action, argparse.BooleanOptionalAction):
            if value is not None and not isinstance(value, bool):
                raise UsageError(f"--config {path}: {dest} must be true or false")
            defaults[dest] = value
        elif isinstance(action, argparse._AppendAction) and isinstance(value, list) and all(
                isinstance(v, str) for v in value):
            defaults[dest] = list(value)
        elif isinstance(value, list) and dest.endswith("_size"):
            defaults[dest] = "x".join(str(v) for v in value)
        elif isinstance(value, (str, int, float)) and not isinstance(value, bool):
            defaults[dest] = str(value)  # argparse runs string defaults through the flag type
        else:
            raise UsageError(f"--config {path}: bad value for {dest}: {value!r}")
    parser.set_defaults(**defaults)
    return frozenset(defaults)


def _near_name(dest: str, dests) -> str:
    """``"; did you mean ds?"`` for the closest setting name, or ``""``."""
    import difflib

    names = [d for d in dests if d not in ("help", "config", "sweep")]
    near = difflib.get_close_matches(dest, names, n=1, cutoff=0.6)
    return f"; did you mean {near[0]}?" if near else ""


def sweep_grid(specs: list[str], parser: argparse.ArgumentParser) -> list[list[str]]:
    """``["ds=10,20", "vmax=1.2,1.5"]`` -> one list of extra flags per grid point."""
    import itertools

    if not specs:
        return []
    dests = {a.dest for a in parser._actions}
    axes = []
    for spec in specs:
        name, sep, values = spec.partition("=")
        dest = name.strip().lstrip("-").replace("-", "_")
        if not sep or not values.strip():
            raise UsageError(f"--sweep must look like name=v1,v2,..., got {spec!r}")
        if dest not in dests or dest in ("help", "config", "sweep", "out", "overwrite"):
            raise UsageError(f"--sweep: {name!r} is not a setting of this script"
                             + _near_name(dest, dests))
        flag = "--" + dest.replace("_", "-")
        axes.append([[flag, v.strip()] for v in values.split(",")])
    grid = [sum(point, []) for point in itertools.product(*axes)]
    if len(grid) > 1000:
        raise UsageError(f"--sweep grid has {len(grid)} settings; at most 1000")
    return grid


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

"""The event-file flags of every command: checked, bundled, refused where no input is events.

:class:`EventFlags` is the base of the commands' config dataclasses (``--window-ms``,
``--event-count``, ``--frame-size``, ...); :func:`event_frame_options` turns a run's flags into
the readers' :class:`~torchseq.sources.EventFrameOptions`.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
from pathlib import Path

from torchseq.cli.errors import UsageError
from torchseq.cli.flags import MAX_SIDE, parse_size
from torchseq.events.times import UNITS_PER_US
from torchseq.sources import EventFrameOptions, TraverseError, is_event_file

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
        raise UsageError("--evt3-kernel numba needs numba: pip install numba (or "
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

"""Pieces the command-line front ends (``train.py``, ``eval.py``) share.

Scripts stay thin: a config dataclass, flags that override it, and these helpers for inputs,
errors and logging. Nothing here is needed to use the library from Python.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from torchseq.sources import EventFrameOptions, load_traverse


class UsageError(ValueError):
    """A problem with what the user asked for; printed as one line."""


def parse_size(text: str | None) -> tuple[int, int] | None:
    """Parse ``"HxW"`` (e.g. ``"16x16"``) into ``(H, W)``."""
    if text is None:
        return None
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError as err:
        raise UsageError(f"size must look like HxW (e.g. 16x16), got {text!r}") from err
    if h <= 0 or w <= 0:
        raise UsageError(f"size must be positive, got {text!r}")
    return h, w


def _flag_type(annotation: object, default: object) -> type:
    """The argparse type of a dataclass field, from its annotation (``"float | None"``)."""
    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", "")
    for name, kind in (("tuple", str), ("bool", bool), ("float", float), ("int", int)):
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
    return found


def add_config_flags(parser, config_cls: type, help: dict[str, str]) -> None:
    """Add one ``--flag`` per dataclass field, defaulting to the dataclass default.

    Tuple fields (sizes) take ``HxW`` strings; booleans get ``--flag/--no-flag``.
    """
    help = {**docstring_help(config_cls), **help}
    for f in dataclasses.fields(config_cls):
        flag = "--" + f.name.replace("_", "-")
        default = f.default if f.default is not dataclasses.MISSING else None
        shown = "x".join(map(str, default)) if isinstance(default, tuple) else default
        text = help.get(f.name, f.name.replace("_", " ")) + f" (default: {shown})"
        kind = _flag_type(f.type, default)
        if kind is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=default,
                                help=text)
        else:
            parser.add_argument(flag, type=kind, default=default, help=text)


def config_from_args(config_cls: type, args: argparse.Namespace):
    """Build the dataclass from parsed flags (``HxW`` strings of size fields are parsed)."""
    values = {}
    for f in dataclasses.fields(config_cls):
        v = getattr(args, f.name)
        if f.name.endswith("_size") and isinstance(v, str):
            v = parse_size(v)
        values[f.name] = v
    return config_cls(**values)


def event_options(window_ms: float, event_count: int | None,
                  frame_size: tuple[int, int] | None) -> EventFrameOptions:
    """Check and bundle the event-accumulation flags."""
    if window_ms <= 0:
        raise UsageError(f"--window-ms must be positive, got {window_ms}")
    if event_count is not None and event_count <= 0:
        raise UsageError(f"--event-count must be positive, got {event_count}")
    return EventFrameOptions(window_ms=window_ms, event_count=event_count, frame_size=frame_size)


def load_frames(path: str, what: str, events: EventFrameOptions, progress: bool) -> torch.Tensor:
    """Load a traverse, naming it in any error."""
    try:
        frames = load_traverse(path, events=events, progress=progress)
    except (ValueError, OSError) as err:
        raise UsageError(f"{what} traverse {path}: {err}") from err
    return frames


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
        message = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"{prog}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130

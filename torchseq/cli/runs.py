"""A command's run: its folder, its config replayed, its errors and warnings.

Each run writes into a folder of its own (:func:`run_folder`), marked ``INCOMPLETE`` until
every file is written; its ``config.json`` replays it (:func:`config_file_defaults`);
``--sweep`` makes a grid of runs (:func:`sweep_grid`); :func:`run_main` turns expected failures
into one ``prog: error:`` line and exit status 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from torchseq.atomic import write_text
from torchseq.cli.errors import UsageError
from torchseq.cli.run_warnings import WarningLog
from torchseq.versions import VERSIONS_KEY

Notes = WarningLog | list  # where a run's warnings go (a plain list in tests of one step)


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


def progress_wanted(argv: list[str] | None, stream=None) -> bool:
    """Progress bars only on a terminal: redirected logs get no carriage-return lines.

    ``--progress`` given on the command line keeps them anywhere (eval, train, map build).
    """
    argv = sys.argv[1:] if argv is None else argv
    stream = sys.stderr if stream is None else stream
    return "--progress" in argv or bool(getattr(stream, "isatty", lambda: False)())


def run_folder(out: str | None, kind: str, overwrite: bool,
               own: tuple[str, ...] = ("config.json", "INCOMPLETE")) -> Path:
    """The output folder of one run, created empty.

    ``out`` None: a new ``runs/<kind>-<UTC time>`` folder. An existing non-empty ``out`` is
    refused unless ``overwrite`` is set and it holds a previous run (one of the files
    ``own``: a run's ``config.json``, an export's ``validation.json``), which is then
    removed, so the outputs of two runs never mix.
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
        if not any((path / name).is_file() for name in own):
            raise UsageError(f"--overwrite only replaces a previous run's folder (one with a "
                             f"{own[0]}); {path} is not one")
        shutil.rmtree(path)
    path.mkdir(parents=True, exist_ok=True)
    return path


INCOMPLETE = "INCOMPLETE"  # a run folder holding this file is partial: stopped or failed


def mark_incomplete(out: Path) -> None:
    """Leave ``OUT/INCOMPLETE`` until the run has written everything (see :func:`run`)."""
    write_text(out / INCOMPLETE, "this run stopped before it finished (interrupted or failed): "
               "its files are partial; metrics.json says \"status\": \"complete\" only "
               "when every file was written\n")


def mark_complete(out: Path) -> None:
    """Remove ``OUT/INCOMPLETE``: the run wrote everything."""
    (out / INCOMPLETE).unlink(missing_ok=True)


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

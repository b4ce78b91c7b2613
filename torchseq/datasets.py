"""Place-recognition datasets from local copies: reference, query and ground truth.

Nothing is downloaded: each opener reads a folder the user already has and says which
layout it expected when a piece is missing.

- ``nordland``: one image folder per season (``summer/``, ``winter/``, ``spring/``,
  ``fall/``), one image per place; splits are the season folders; ground truth by index
  alignment (frame ``i`` of every season is the same place), ``tolerance`` frames (default 2).
- ``gardens-point``: Gardens Point Walking's ``day_left/``, ``day_right/``, ``night_right/``
  image folders; index alignment, ``tolerance`` frames (default 2).
- ``vpr-bench``: VPR-Bench's ``ref/``, ``query/`` and ``ground_truth_new.npy`` (or
  ``ground_truth.npy`` / ``ground_truth.csv``), read by
  :func:`torchseq.ground_truth.load_ground_truth` and widened by ``tolerance`` if given.
- ``brisbane-event``: Brisbane-Event-VPR, one event file per traverse
  (``dvs_vpr_<date>.parquet``, ``.hdf5``/``.h5``, ``.aedat4`` or ``.npz``) named by the
  traverse (``sunset1``, ``night``, ...) or its recording, and a GPS log per traverse
  (``<traverse>.nmea`` or the dataset's ``<date>-<traverse>_concat.nmea``); windows within
  ``tolerance`` metres (default 25) match.

Each opener returns a :class:`PlaceDataset`: two map-style traverses (``len`` and
``[i]`` -> ``(H, W)`` float32 grey frame in 0..255, decoded when asked; ``.path`` for the
streaming loaders) and the ``(R, Q)`` ground truth.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchseq.ground_truth import GroundTruthRanges, alignment_ranges, load_ground_truth
from torchseq.sources import IMAGE_SUFFIXES, EventFrameOptions, TraverseError, natural_key


class DatasetError(TraverseError):
    """A dataset's local copy is missing a piece; the message names the expected layout."""


class FrameFolder(torch.utils.data.Dataset):
    """A folder of images as a map-style dataset of grey frames (decoded on access).

    Args:
        path: the folder.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.files = sorted((p for p in self.path.iterdir()
                             if p.suffix.lower() in IMAGE_SUFFIXES),
                            key=lambda p: natural_key(p.name))

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, i: int) -> torch.Tensor:
        """``(H, W)`` float32 grey frame ``i`` (0..255)."""
        from torchseq.sources import _decode

        return torch.from_numpy(_decode(self.files[i]))


class EventTraverse(torch.utils.data.Dataset):
    """An event recording as a map-style dataset of accumulated frames (read on first use).

    Args:
        path: the event file.
        options: how events become frames (window, size, ...).
    """

    def __init__(self, path: str | Path, options: EventFrameOptions | None = None) -> None:
        self.path = Path(path)
        self.options = options or EventFrameOptions()
        self._frames: torch.Tensor | None = None

    def frames(self) -> torch.Tensor:
        """``(T, H, W)`` all frames (read once)."""
        if self._frames is None:
            from torchseq.sources import load_traverse

            self._frames = load_traverse(self.path, self.options, progress=False)
        return self._frames

    def __len__(self) -> int:
        return len(self.frames())

    def __getitem__(self, i: int) -> torch.Tensor:
        """``(H, W)`` float32 event frame ``i``."""
        return self.frames()[i]


@dataclass
class PlaceDataset:
    """A reference traverse, a query traverse and which of their frames show the same place.

    Attributes:
        name: the dataset's name (:data:`DATASETS`).
        root: its local folder.
        reference: map-style reference traverse (``.path`` the folder or file).
        query: map-style query traverse.
        ground_truth: ``(R, Q)`` bool array or :class:`GroundTruthRanges`.
        description: how the ground truth was made, for reports.
        ground_truth_file: the file it came from, or None (index alignment, GPS).
        tolerance: the tolerance applied (frames, or metres for GPS).
    """

    name: str
    root: Path
    reference: torch.utils.data.Dataset
    query: torch.utils.data.Dataset
    ground_truth: np.ndarray | GroundTruthRanges
    description: str
    ground_truth_file: Path | None = None
    tolerance: float | None = None
    splits: tuple[str, str] = field(default=("", ""))


def _root(name: str, root, layout: str) -> Path:
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{name}: no folder {root}; expected {layout}")
    return root


MAX_SPLIT_NAME = 200  # bytes: a split or traverse name plus the layout's suffixes fits a name


def _splits(name: str, given: tuple, defaults: tuple[str, str]) -> tuple[str, str]:
    """The two split (or traverse) names, each one plain file name component."""
    splits = tuple(g or d for g, d in zip(given, defaults))
    for s in splits:
        if (not isinstance(s, str) or s in (".", "..") or "/" in s or "\0" in s
                or len(s.encode("utf-8", "surrogateescape")) > MAX_SPLIT_NAME):
            shown = s if not isinstance(s, str) or len(s) < 60 else s[:40] + "..."
            raise DatasetError(f"{name}: split {shown!r} is not a folder or file name (one "
                               f"name of at most {MAX_SPLIT_NAME} bytes)")
    return splits


def _folder(name: str, root: Path, split: str, layout: str) -> FrameFolder:
    path = root / split
    if not path.is_dir():
        have = sorted(p.name for p in root.iterdir() if p.is_dir())
        raise DatasetError(f"{name}: no split folder {path} (folders here: "
                           f"{', '.join(have) or 'none'}); expected {layout}")
    folder = FrameFolder(path)
    if len(folder) == 0:
        raise DatasetError(f"{name}: no images in {path}; expected {layout}")
    return folder


def _aligned(name: str, root, reference_split: str | None, query_split: str | None,
             tolerance: float | None, defaults: tuple[str, str], layout: str) -> PlaceDataset:
    root = _root(name, root, layout)
    splits = _splits(name, (reference_split, query_split), defaults)
    ref, query = (_folder(name, root, s, layout) for s in splits)
    if len(ref) != len(query):
        raise DatasetError(f"{name}: {splits[0]} has {len(ref)} images and {splits[1]} "
                           f"{len(query)}; index alignment needs one image per place in "
                           f"each ({layout})")
    tol = 2.0 if tolerance is None else float(tolerance)
    return PlaceDataset(name, root, ref, query, alignment_ranges(len(ref), len(query), tol),
                        f"index alignment, tolerance {tol:g} frames", None, tol, splits)


NORDLAND_LAYOUT = ("ROOT/<season>/ image folders (summer, winter, spring, fall), one image per "
                   "place, frame i of every season the same place")
GARDENS_POINT_LAYOUT = ("ROOT/day_left/, ROOT/day_right/, ROOT/night_right/ image folders "
                        "(Gardens Point Walking), frame i of each the same place")
VPR_BENCH_LAYOUT = ("ROOT/ref/ and ROOT/query/ image folders and ROOT/ground_truth_new.npy "
                    "(VPR-Bench; or ground_truth.npy / ground_truth.csv)")
VPR_BENCH_TRUTH = ("ground_truth_new.npy", "ground_truth.npy", "ground_truth.csv")


def nordland(root, reference_split: str | None = None, query_split: str | None = None,
             tolerance: float | None = None) -> PlaceDataset:
    """Nordland, a folder per season (default: summer reference, winter query, +-2 frames)."""
    return _aligned("nordland", root, reference_split, query_split, tolerance,
                    ("summer", "winter"), NORDLAND_LAYOUT)


def gardens_point(root, reference_split: str | None = None, query_split: str | None = None,
                  tolerance: float | None = None) -> PlaceDataset:
    """Gardens Point Walking (default: day_right reference, night_right query, +-2 frames)."""
    return _aligned("gardens-point", root, reference_split, query_split, tolerance,
                    ("day_right", "night_right"), GARDENS_POINT_LAYOUT)


def vpr_bench(root, reference_split: str | None = None, query_split: str | None = None,
              tolerance: float | None = None) -> PlaceDataset:
    """A dataset in VPR-Bench's layout (``ref/``, ``query/``, its ground-truth file)."""
    name = "vpr-bench"
    root = _root(name, root, VPR_BENCH_LAYOUT)
    splits = _splits(name, (reference_split, query_split), ("ref", "query"))
    ref, query = (_folder(name, root, s, VPR_BENCH_LAYOUT) for s in splits)
    truth = next((root / f for f in VPR_BENCH_TRUTH if (root / f).is_file()), None)
    if truth is None:
        raise DatasetError(f"{name}: no ground truth ({', '.join(VPR_BENCH_TRUTH)}) in "
                           f"{root}; expected {VPR_BENCH_LAYOUT}")
    gt = load_ground_truth(truth, len(ref), len(query), widen=tolerance or 0.0)
    what = f"{truth.name}" + (f", widened by {tolerance:g} frames" if tolerance else "")
    return PlaceDataset(name, root, ref, query, gt, what, truth, tolerance, splits)


# --------------------------------------------------------------------- Brisbane-Event-VPR
BRISBANE_TRAVERSES = {  # traverse -> recording (file stem) and GPS log date-time prefix
    "sunset1": ("dvs_vpr_2020-04-21-17-03-03", "20200421_170039"),
    "sunset2": ("dvs_vpr_2020-04-22-17-24-21", "20200422_172431"),
    "daytime": ("dvs_vpr_2020-04-24-15-12-03", "20200424_151015"),
    "morning": ("dvs_vpr_2020-04-28-09-14-11", "20200428_091154"),
    "sunrise": ("dvs_vpr_2020-04-29-06-20-23", "20200429_061912"),
    "night": ("dvs_vpr_2020-04-27-18-13-29", "20200427_181204"),
}
BRISBANE_SUFFIXES = (".parquet", ".hdf5", ".h5", ".aedat4", ".npz")
BRISBANE_LAYOUT = ("ROOT/<traverse or dvs_vpr_<date>>.parquet (or .hdf5, .h5, .aedat4, .npz) per "
                   "traverse and ROOT/<traverse>.nmea or the dataset's "
                   "<date>-<traverse>_concat.nmea GPS log beside it")


def read_nmea(path: Path) -> np.ndarray:
    """``(N, 3)`` float64 ``(UTC seconds of day, latitude, longitude)`` of a log's fixes.

    ``$GPRMC`` (status ``A``) and ``$GPGGA`` (quality > 0) sentences; one fix per second.
    """
    out = []
    for line in Path(path).read_text(errors="replace").splitlines():
        parts = line.strip().split("*")[0].split(",")
        kind = parts[0][-3:] if parts and parts[0].startswith("$") else ""
        try:
            if kind == "RMC" and len(parts) > 6 and parts[2] == "A":
                t, lat, ns, lon, ew = parts[1], parts[3], parts[4], parts[5], parts[6]
            elif kind == "GGA" and len(parts) > 6 and parts[6] not in ("", "0"):
                t, lat, ns, lon, ew = parts[1], parts[2], parts[3], parts[4], parts[5]
            else:
                continue
            sec = int(t[0:2]) * 3600 + int(t[2:4]) * 60 + float(t[4:])
            la = int(lat[:2]) + float(lat[2:]) / 60.0
            lo = int(lon[:3]) + float(lon[3:]) / 60.0
        except (ValueError, IndexError):
            continue
        out.append((sec, -la if ns == "S" else la, -lo if ew == "W" else lo))
    if not out:
        raise DatasetError(f"{path}: no GPS fix ($GPRMC or $GPGGA) in the log")
    track = np.array(out, dtype=np.float64)
    _, first = np.unique(track[:, 0], return_index=True)  # RMC and GGA of one second: once
    return track[np.sort(first)]


def gps_positions(track: np.ndarray, seconds_of_day: np.ndarray) -> np.ndarray:
    """``(T, 3)`` ECEF metres at UTC seconds of day (NaN outside the track: no place).

    The one interpolation and the one geodesy of :mod:`torchseq.events.positions`.
    """
    from torchseq.events.positions import geodetic_to_ecef, positions_at

    return positions_at(seconds_of_day, track[:, 0], geodetic_to_ecef(track[:, 1],
                                                                       track[:, 2]))


# Unix time (s) of each recording's start, for copies whose timestamps start at 0 (the
# values Event-LAB's datasets/brisbane_event.yaml gives as ``offset``).
BRISBANE_OFFSETS = {"sunset1": 1587452582.35, "sunset2": 1587540271.65,
                    "daytime": 1587705130.80, "morning": 1588029265.73,
                    "sunrise": 1588105232.91, "night": 1587975221.10}
UNIX_2001 = 978307200.0  # timestamps above this many seconds are taken as Unix times


def window_times(path: Path, traverse: str, n_frames: int, window_ms: float) -> np.ndarray:
    """UTC seconds of day at the centres of a recording's ``n_frames`` time windows.

    Windows start at the first event (the loaders' default anchor). Timestamps that are
    Unix times are used as they are; relative ones (starting near 0) get the recording's
    known start (:data:`BRISBANE_OFFSETS`), else a :class:`DatasetError`.
    """
    from torchseq.events import read_events

    first_s = float(read_events(path).events["t"][0]) / 1e6
    if first_s < UNIX_2001:
        if traverse not in BRISBANE_OFFSETS:
            raise DatasetError(f"brisbane-event: {path} has relative timestamps and "
                               f"{traverse!r} has no known start time; give the traverse by "
                               f"its name ({', '.join(BRISBANE_OFFSETS)}) or a copy with "
                               f"Unix timestamps")
        first_s += BRISBANE_OFFSETS[traverse]
    centres = first_s + (np.arange(n_frames) + 0.5) * window_ms / 1000.0
    return np.mod(centres, 86400.0)


def _brisbane_file(root: Path, traverse: str) -> Path:
    stems = [traverse]
    if traverse in BRISBANE_TRAVERSES:
        stems.append(BRISBANE_TRAVERSES[traverse][0])
    for stem in stems:
        for suffix in BRISBANE_SUFFIXES:
            if (root / (stem + suffix)).is_file():
                return root / (stem + suffix)
    raise DatasetError(f"brisbane-event: no event file for traverse {traverse!r} in {root} "
                       f"(tried {', '.join(s + x for s in stems for x in BRISBANE_SUFFIXES)}); "
                       f"expected {BRISBANE_LAYOUT}")


def _brisbane_nmea(root: Path, traverse: str) -> Path:
    candidates = [root / f"{traverse}.nmea"]
    if traverse in BRISBANE_TRAVERSES:
        candidates.append(root / f"{BRISBANE_TRAVERSES[traverse][1]}-{traverse}_concat.nmea")
    for c in candidates:
        if c.is_file():
            return c
    raise DatasetError(f"brisbane-event: no GPS log for traverse {traverse!r} (tried "
                       f"{', '.join(c.name for c in candidates)}); expected {BRISBANE_LAYOUT}")


def brisbane_event(root, reference_split: str | None = None, query_split: str | None = None,
                   tolerance: float | None = None,
                   events: EventFrameOptions | None = None) -> PlaceDataset:
    """Brisbane-Event-VPR from local event files and GPS logs (default sunset1 vs night).

    Frames are time windows of ``events.window_ms`` (default 10 ms: set a longer window for
    place-sized frames). Each window's position is the GPS track (UTC time of day, the
    NMEA logs' clock) interpolated at the window's centre in UTC (:func:`window_times`);
    windows outside the track have no place; frames within ``tolerance`` metres (default
    25) match.
    """
    name = "brisbane-event"
    root = _root(name, root, BRISBANE_LAYOUT)
    splits = _splits(name, (reference_split, query_split), ("sunset1", "night"))
    events = events or EventFrameOptions()
    if events.event_count is not None or events.anchor != "first":
        raise DatasetError(f"{name}: GPS ground truth needs time windows from the first "
                           f"event (no event count, default anchor)")
    files = [_brisbane_file(root, s) for s in splits]
    tracks = [read_nmea(_brisbane_nmea(root, s)) for s in splits]
    ref, query = (EventTraverse(f, events) for f in files)
    metres = 25.0 if tolerance is None else float(tolerance)
    from torchseq.events.positions import ground_truth_within

    pos = [gps_positions(track, window_times(f, s, len(d), events.window_ms))
           for track, f, s, d in zip(tracks, files, splits, (ref, query))]
    gt = ground_truth_within(pos[0], pos[1], metres)
    return PlaceDataset(name, root, ref, query, gt, f"GPS, within {metres:g} m", None,
                        metres, splits)


DATASETS: dict[str, Callable[..., PlaceDataset]] = {
    "nordland": nordland,
    "gardens-point": gardens_point,
    "vpr-bench": vpr_bench,
    "brisbane-event": brisbane_event,
}


def open_dataset(name: str, root, reference_split: str | None = None,
                 query_split: str | None = None, tolerance: float | None = None,
                 **kwargs) -> PlaceDataset:
    """Open a dataset by name (:data:`DATASETS`) from its local folder.

    Raises:
        DatasetError: an unknown name, or a missing piece (the message gives the layout).
    """
    key = re.sub(r"[_ ]", "-", str(name).lower())
    if key not in DATASETS:
        raise DatasetError(f"unknown dataset {name!r}; one of {', '.join(DATASETS)}")
    return DATASETS[key](root, reference_split, query_split, tolerance, **kwargs)

"""Load a traverse from wherever it lives: an image folder, a video, an array, an event file.

Every loader returns grey frames ``(T, H, W)`` float32 in 0..255 (event files: accumulated
event frames, see :mod:`torchseq.events`).
"""

from __future__ import annotations

import os
import re
import struct
import zipfile
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import islice
from pathlib import Path
from typing import Iterator, Union

import cv2
import numpy as np
import torch
from tqdm import tqdm

from torchseq._checks import torch_numbers
from torchseq.npyfile import load_npy, load_npz_member, npy_header, npz_members

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp"}
VIDEO_SUFFIXES = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".mpg", ".mpeg", ".m4v"}
EVENT_SUFFIXES = {".aedat", ".aedat4", ".raw", ".dat", ".csv", ".txt", ".npz", ".npy", ".h5",
                  ".hdf5", ".parquet"}

Source = Union[str, Path, np.ndarray, torch.Tensor]


# stacked frames that are mostly empty event windows: at most this many elements (512 MiB)
MAX_EMPTY_ELEMENTS = 2**27


class TraverseError(ValueError):
    """A traverse could not be loaded; the message says why in one line."""


@dataclass
class EventFrameOptions:
    """How event files become frames (see :func:`torchseq.events.load_event_frames`).

    Attributes:
        window_ms: accumulation window in milliseconds (ignored when ``event_count`` is set).
        event_count: accumulate a fixed number of events per frame instead of a time window.
        frame_size: ``(H, W)`` to downsample the frames to by area pooling, or None.
        anchor: where the first time window starts: ``"first"`` (the first event),
            ``"zero"`` (sensor time 0) or a sensor time in microseconds (windows then line up
            with ground truth given in sensor time).
        sensor_size: ``(W, H)`` of the sensor, overriding the file; tonic's ``(W, H, P)``
            is accepted (``P``, the polarity count, is dropped).
        mode: ``"count"`` (events per pixel), ``"signed"`` (``|ON - OFF|``), ``"binary"``
            (255 where a pixel fired) or ``"two_channel"`` (OFF and ON counts side by side:
            ``(H, 2W)`` frames).
        start_ms: time crop: skip this many milliseconds after the anchor; windows start there.
        duration_ms: time crop: keep this many milliseconds of events (None: to the end).
        hot_pixel: drop the events of pixels firing more than this many times the median
            active pixel (None: off).
        refractory_us: per-pixel refractory period in microseconds (None: off).
        evt3_time: Prophesee EVT 3 ``.raw`` time rule, ``"spec"`` or ``"carry"`` (see
            :func:`torchseq.events.prophesee.decode_evt3`).
        truncated: a recording cut short (AEDAT 2.0/4, ``.raw``): ``"error"`` or ``"drop"``
            its last incomplete record.
        time_unit: the time column's unit in CSV, HDF5 and Parquet files (``"s"``, ``"ms"``,
            ``"us"``, ``"ns"``); None: integers are microseconds, fractions follow the
            float-time rule (:mod:`torchseq.events.times`).
        evt3_kernel: the EVT 3 ``.raw`` decoder, ``"numba"`` or ``"numpy"`` (the same
            events); None: chosen by the file's size
            (:func:`torchseq.events.prophesee.default_evt3_kernel`).
        centred_ms: load one member of a temporal-window ensemble: frame ``k`` counts the
            ``centred_ms`` window centred on window ``k`` of ``window_ms`` (see
            :func:`torchseq.events.load_event_frames`); None: plain windows.
        members_ms: the window lengths of a temporal-window ensemble the caller loads member
            by member (``centred_ms`` each); loading with these options alone gives the
            plain ``window_ms`` frames.
    """

    window_ms: float = 10.0
    event_count: int | None = None
    frame_size: tuple[int, int] | None = None
    anchor: str | int = "first"
    sensor_size: tuple[int, ...] | None = None
    mode: str = "count"
    evt3_time: str = "spec"
    truncated: str = "error"
    start_ms: float = 0.0
    duration_ms: float | None = None
    hot_pixel: float | None = None
    refractory_us: int | None = None
    time_unit: str | None = None
    evt3_kernel: str | None = None
    centred_ms: float | None = None
    members_ms: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.sensor_size is not None:  # tonic's (W, H, P): the polarity count is not a size
            size = tuple(int(v) for v in self.sensor_size)
            if len(size) not in (2, 3) or min(size[:2]) < 1:
                raise TraverseError(f"sensor_size must be (W, H) or tonic's (W, H, P), got "
                                    f"{self.sensor_size}")
            self.sensor_size = size[:2]


def natural_key(name: str) -> list:
    """Sort key that orders ``img2`` before ``img10``."""
    return [int(s) if s.isdigit() else s.lower() for s in re.split(r"(\d+)", name)]


def _grey_uint(image: np.ndarray, name: object = "image") -> np.ndarray:
    """A decoded image (OpenCV BGR/BGRA/grey, 8 or 16 bit, or float) -> grey float32 0..255.

    16-bit images are scaled to 0..255 (``/ 257``); float images must already hold finite
    values in 0..255.
    """
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim == 3 and image.shape[2] == 4:
        image = image[..., :3]
    if image.ndim == 3 and image.shape[2] == 3:
        if image.dtype not in (np.uint8, np.uint16, np.float32):
            image = image.astype(np.float32)
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)  # ITU-R 601 weights
    if image.ndim != 2 or image.size == 0:
        raise TraverseError(f"{name}: unsupported image layout {image.shape}")
    if image.dtype == np.uint8:
        return image.astype(np.float32)
    if image.dtype == np.uint16:
        return image.astype(np.float32) / np.float32(257.0)  # 65535 -> 255
    if image.dtype.kind not in "iuf":
        raise TraverseError(f"{name}: unsupported pixel type {image.dtype}")
    grey = image.astype(np.float32)
    if not np.isfinite(grey).all():
        raise TraverseError(f"{name}: holds NaN or infinite pixels")
    if grey.min() < 0 or grey.max() > 255:
        raise TraverseError(f"{name}: {image.dtype} pixels span {grey.min():g}..{grey.max():g}, "
                            f"outside 0..255; convert the images to 8 or 16 bit")
    return grey


def _imread(path: Path) -> np.ndarray:
    try:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    except cv2.error as err:
        raise TraverseError(f"cannot read image {path} ({str(err).strip().splitlines()[-1]})"
                            ) from None
    if image is None:
        raise TraverseError(f"cannot read image {path}")
    return image


@dataclass
class FrameSelection:
    """Which frames of a traverse to keep (OpenSeqSLAM's image skip and indices).

    Attributes:
        start: first frame index kept (0-based).
        stop: frame index to stop before (None: the end).
        step: keep every ``step``-th frame from ``start``.
        max_frames: keep at most this many frames (None: no limit).
    """

    start: int = 0
    stop: int | None = None
    step: int = 1
    max_frames: int | None = None

    def validate(self) -> FrameSelection:
        """Raise :class:`TraverseError` for a selection that cannot hold frames; return self."""
        if self.start < 0 or self.step < 1:
            raise TraverseError(f"need start >= 0 and step >= 1, got {self.start}, {self.step}")
        if self.stop is not None and self.stop <= self.start:
            raise TraverseError(f"stop {self.stop} must be after start {self.start}")
        if self.max_frames is not None and self.max_frames < 1:
            raise TraverseError(f"max_frames must be >= 1, got {self.max_frames}")
        return self

    def keeps(self, i: int, kept: int) -> bool | None:
        """True: keep frame ``i``; False: skip it; None: no later frame is kept either."""
        if (self.stop is not None and i >= self.stop) or (
                self.max_frames is not None and kept >= self.max_frames):
            return None
        return i >= self.start and (i - self.start) % self.step == 0

    def indices(self, n: int) -> range:
        """The kept indices of a traverse of ``n`` frames."""
        r = range(self.start, n if self.stop is None else min(self.stop, n), self.step)
        return r if self.max_frames is None else r[:self.max_frames]


def _image_files(folder: Path) -> list[Path]:
    files = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES),
                   key=lambda p: natural_key(p.name))
    if not files:
        raise TraverseError(f"no images ({', '.join(sorted(IMAGE_SUFFIXES))}) in folder {folder}")
    return files


MAX_DECODE_WORKERS = 8


def decode_workers(workers: int | None = None) -> int:
    """Threads that decode an image folder: ``workers``, or the usable CPUs (at most 8).

    OpenCV releases the GIL while it reads and decodes a file, so a few Python threads decode
    images in parallel; they block (no spin-wait) when the machine is busy.
    """
    if workers is not None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise TraverseError(f"decode workers must be an integer >= 1, got {workers!r}")
        return workers
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    return max(1, min(MAX_DECODE_WORKERS, cpus))


def _decode(path: Path) -> np.ndarray:
    """One image file -> ``(H, W)`` float32 grey (runs in a decode thread)."""
    return _grey_uint(_imread(path), path)


DECODE_CHUNK = 16  # at most this many files per decode task: fewer hand-offs between threads
DECODE_CHUNK_BYTES = 8 * 2 ** 20  # and at most this much decoded float32 grey per task


def _decode_chunk(paths: list[Path]) -> tuple[list[np.ndarray], TraverseError | None]:
    """Decode consecutive files; stop at a damaged one: (the frames before it, its error)."""
    frames = []
    for p in paths:
        try:
            frames.append(_decode(p))
        except TraverseError as err:
            return frames, err
    return frames, None


def _decoded_in_order(files: list[Path], workers: int) -> Iterator[np.ndarray]:
    """Decode ``files`` with ``workers`` threads, yielding the frames in order.

    The first file is decoded here, to size the tasks: each task decodes up to
    :data:`DECODE_CHUNK` consecutive files (at most :data:`DECODE_CHUNK_BYTES` of frames), and
    at most ``2 * workers`` tasks run ahead of the consumer, so memory stays bounded by a few
    tasks' frames. A damaged file raises its :class:`TraverseError` in its turn, after the
    frames before it.
    """
    if not files:
        return
    first = _decode(files[0])
    yield first
    if workers == 1:
        for f in files[1:]:
            yield _decode(f)
        return
    chunk = max(1, min(DECODE_CHUNK, DECODE_CHUNK_BYTES // max(first.nbytes, 1)))
    pool = ThreadPoolExecutor(workers, thread_name_prefix="torchseq-decode")
    try:
        pending: deque = deque()
        tasks = (files[i:i + chunk] for i in range(1, len(files), chunk))
        for paths in islice(tasks, 2 * workers):
            pending.append(pool.submit(_decode_chunk, paths))
        while pending:
            frames, damaged = pending.popleft().result()
            nxt = next(tasks, None)
            if nxt is not None and damaged is None:
                pending.append(pool.submit(_decode_chunk, nxt))
            yield from frames
            if damaged is not None:  # in its turn, after the frames before it
                raise damaged
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _no_bar(progress: bool | None) -> bool | None:
    """The ``disable`` of tqdm: None (a bar only on a terminal), or the caller's own choice."""
    return None if progress is None else not progress


def iter_image_folder(folder: Path, progress: bool | None = None,
                      select: FrameSelection | None = None,
                      workers: int | None = None) -> Iterator[np.ndarray]:
    """Yield the (selected) images of a folder in natural order, one ``(H, W)`` float32 each.

    Args:
        folder: the image folder.
        progress: show a progress bar (None: only when stderr is a terminal).
        select: which frames to keep (default: all).
        workers: decode threads (see :func:`decode_workers`; None: the usable CPUs, at most
            8). The frames are the same for any count.
    """
    files = _image_files(folder)
    keep = (select or FrameSelection()).indices(len(files))
    if len(keep) == 0:
        raise TraverseError(_nothing_selected(folder, len(files), select))
    chosen = [files[i] for i in keep]
    first = None
    frames = _decoded_in_order(chosen, decode_workers(workers))
    for f, grey in zip(chosen, tqdm(frames, total=len(chosen), desc=f"reading {folder.name}",
                                    disable=_no_bar(progress), leave=False)):
        if first is None:
            first = (f, grey.shape)
        elif grey.shape != first[1]:
            raise TraverseError(
                f"mixed image sizes in {folder}: {first[0].name} is {first[1][1]}x"
                f"{first[1][0]} but {f.name} is {grey.shape[1]}x{grey.shape[0]}")
        yield grey


def iter_video(path: Path, progress: bool | None = None,
               select: FrameSelection | None = None) -> Iterator[np.ndarray]:
    """Yield the (selected) frames of a video, one ``(H, W)`` float32 grey each.

    Skipped frames are grabbed without decoding.
    """
    select = select or FrameSelection()
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise TraverseError(f"cannot open video {path}")
    total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or None
    kept = 0
    try:
        with tqdm(total=total, desc=f"reading {path.name}", disable=_no_bar(progress),
                  leave=False) as bar:
            i = 0
            while True:
                verdict = select.keeps(i, kept)
                if verdict is None:
                    break
                if not verdict:
                    if not cap.grab():
                        break
                else:
                    ok, image = cap.read()
                    if not ok:
                        break
                    kept += 1
                    yield _grey_uint(image, path)
                i += 1
                bar.update(1)
    finally:
        cap.release()
    if kept == 0:
        if select != FrameSelection() and i > 0:
            raise TraverseError(_nothing_selected(path, i, select))
        raise TraverseError(f"video {path} has no readable frames"
                            + (" in the selected range" if select != FrameSelection() else ""))


def _check_not_text(path: Path) -> None:
    """Refuse an empty or plain-text file named as a video before the decoder sees it."""
    with open(path, "rb") as f:
        head = f.read(512)
    if not head:
        raise TraverseError(f"{path}: an empty file, not a video")
    if all(32 <= b < 127 or b in b"\t\r\n" for b in head):
        raise TraverseError(f"{path}: a text file, not a video (it starts "
                            f"{head[:40].decode('ascii').splitlines()[0]!r})")


def _nothing_selected(name, n: int, select: FrameSelection) -> str:
    """The message for a frame selection that keeps nothing of ``n`` frames."""
    return (f"{name}: no frame selected: the traverse has {n} frame{'s' * (n != 1)} "
            f"(0..{n - 1}) and the selection starts at frame {select.start}; --start counts "
            f"frames from 0 and must be below {n}")


def load_image_folder(folder: Path, progress: bool | None = None,
                      workers: int | None = None) -> torch.Tensor:
    """Load every image of a folder in natural sort order as ``(T, H, W)`` float32 grey.

    ``workers``: decode threads, as :func:`iter_image_folder`.
    """
    return torch.from_numpy(np.stack(list(iter_image_folder(folder, progress,
                                                            workers=workers))))


def frames_from_array(array: np.ndarray | torch.Tensor, name: str = "array") -> torch.Tensor:
    """Check and convert a ``(T, H, W)`` or ``(T, H, W, 3)`` RGB array to grey float32 frames."""
    from torchseq.preprocess import to_grey

    if isinstance(array, np.ndarray):
        array = torch_numbers(array, name, TraverseError)
    x = torch.as_tensor(array)
    if x.dim() not in (3, 4) or (x.dim() == 4 and x.shape[-1] != 3):
        raise TraverseError(f"{name} must be (T, H, W) or (T, H, W, 3), got {tuple(x.shape)}")
    if x.shape[0] == 0:
        raise TraverseError(f"{name} has no frames")
    if x.shape[1] == 0 or x.shape[2] == 0:
        raise TraverseError(f"{name} has empty frames {tuple(x.shape)}")
    if x.dtype == torch.bool or x.is_complex():
        raise TraverseError(f"{name} has unsupported dtype {x.dtype}")
    x = to_grey(x).to(torch.float32)
    if not bool(torch.isfinite(x).all()):
        raise TraverseError(f"{name} holds NaN or infinite values")
    return x


def _frame_array(array: np.ndarray, path: Path) -> np.ndarray:
    """A frame array from a file: plain numbers (its values are taken as grey levels)."""
    if array.dtype.names is not None or array.dtype.kind not in "iuf":
        raise TraverseError(f"{path}: frame arrays must be numeric, got dtype {array.dtype}")
    return array


def _check_grey_levels(frames: torch.Tensor, path: Path) -> None:
    """Refuse a frame array file whose values are not grey levels in 0..255."""
    lo, hi = float(frames.min()), float(frames.max())
    if lo < 0 or hi > 255:
        raise TraverseError(
            f"{path}: frame arrays must hold grey levels in 0..255, found values "
            f"{lo:.6g}..{hi:.6g}; rescale them (x * 255 for floats in [0, 1], x / 257 for "
            f"16-bit counts) or save uint8 frames")


def _is_event_file(path: Path) -> bool:
    """Sniff an event file: structured ``.npy``, ``.npz`` without ``frames``, or a suffix."""
    if path.suffix.lower() == ".npy":
        _, dtype = npy_header(path, TraverseError)
        return dtype.names is not None
    if path.suffix.lower() == ".npz":
        return "frames" not in npz_members(path, TraverseError)
    return path.suffix.lower() in EVENT_SUFFIXES


def is_event_file(path: str | Path) -> bool:
    """Whether :func:`load_traverse` reads the existing file ``path`` as an event recording.

    Raises:
        TraverseError: a ``.npy``/``.npz`` whose header cannot be read.
    """
    return _is_event_file(Path(path))


def _event_frames(path: Path, opts: EventFrameOptions):
    """The event file's frames as a :class:`torchseq.events.traverse.WindowFrames`."""
    from torchseq.events.traverse import load_event_windows

    kwargs = {}
    if opts.sensor_size is not None:
        kwargs["sensor_size"] = tuple(opts.sensor_size)
    if opts.mode != "count":
        kwargs["mode"] = opts.mode
    for name in ("hot_pixel", "refractory_us", "duration_ms"):
        if getattr(opts, name) is not None:
            kwargs[name] = getattr(opts, name)
    if opts.start_ms:
        kwargs["start_ms"] = opts.start_ms
    suffix = path.suffix.lower()
    if opts.evt3_time != "spec":
        if suffix != ".raw":
            raise TraverseError(f"{path}: the EVT 3 time rule applies to .raw files only")
        kwargs["evt3_time"] = opts.evt3_time
    if opts.evt3_kernel is not None:
        if suffix != ".raw":
            raise TraverseError(f"{path}: the EVT 3 kernel applies to .raw files only")
        kwargs["evt3_kernel"] = opts.evt3_kernel
    if opts.truncated != "error":
        if suffix not in (".aedat", ".aedat4", ".raw"):
            raise TraverseError(f"{path}: 'truncated' applies to .aedat, .aedat4 and .raw")
        kwargs["truncated"] = opts.truncated
    if opts.anchor != "first":
        kwargs["anchor"] = opts.anchor
    if opts.time_unit is not None:  # a format without a time column refuses it by name
        kwargs["time_unit"] = opts.time_unit
    if opts.centred_ms is not None:
        kwargs["centred_ms"] = opts.centred_ms
    try:
        return load_event_windows(path, window_ms=opts.window_ms,
                                  event_count=opts.event_count, frame_size=opts.frame_size,
                                  **kwargs)
    except (ValueError, OSError, EOFError, IndexError, KeyError, TypeError, OverflowError,
            MemoryError, zipfile.BadZipFile, struct.error) as err:
        # whatever the event reader met in a damaged file, the traverse names it
        text = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise TraverseError(text if str(path) in text else f"{path}: {text}") from err


def iter_traverse(source: Source, events: EventFrameOptions | None = None,
                  progress: bool | None = None, select: FrameSelection | None = None,
                  total: dict | None = None) -> Iterator[np.ndarray | torch.Tensor]:
    """Yield the grey frames of a traverse one at a time, ``(H, W)`` float32 each.

    Image folders and videos are decoded frame by frame (only the selected frames: a video's
    skipped frames are not even decoded), so a long traverse never sits in memory at full
    resolution; arrays and event files are read whole, then selected.

    Args:
        source: as :func:`load_traverse`.
        events: how event files are accumulated into frames.
        progress: show a progress bar for long reads (None: only when stderr is a
            terminal, so redirected logs get none).
        select: which frames to keep (default: all).
        total: a dict that receives ``"n_total"``, the traverse's frame count before the
            selection (a video's container count; None when the container does not say).

    Raises:
        TraverseError: unreadable input, or no frame in the selection (the file named).
    """
    select = (select or FrameSelection()).validate()
    total = {} if total is None else total
    if isinstance(source, (np.ndarray, torch.Tensor)):
        frames, name = frames_from_array(source), "array"
    else:
        path = Path(source)
        name = str(path)
        if not path.exists():
            raise TraverseError(f"no such file or folder: {path}")
        if path.is_dir():
            total["n_total"] = len(_image_files(path))
            yield from iter_image_folder(path, progress, select)
            return
        suffix = path.suffix.lower()
        if suffix in VIDEO_SUFFIXES:
            _check_not_text(path)
            cap = cv2.VideoCapture(str(path))
            total["n_total"] = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or None
            cap.release()
            yield from iter_video(path, progress, select)
            return
        if _is_event_file(path):
            frames = _event_frames(path, events or EventFrameOptions())
            total["events"] = True
        elif suffix == ".npy":
            frames = frames_from_array(_frame_array(load_npy(path, TraverseError), path), name)
            _check_grey_levels(frames, path)
        elif suffix == ".npz":
            array = load_npz_member(path, "frames", TraverseError)
            frames = frames_from_array(_frame_array(array, path), name)
            _check_grey_levels(frames, path)
        elif suffix in IMAGE_SUFFIXES:
            raise TraverseError(f"{path} is a single image; give the folder that holds the "
                                f"traverse")
        else:
            raise TraverseError(f"unknown traverse format: {path}")
    total["n_total"] = len(frames)
    keep = select.indices(len(frames))
    if len(keep) == 0:
        raise TraverseError(_nothing_selected(name, len(frames), select))
    for i in keep:
        yield frames[i]


def thumbnail_size(frame_size: tuple[int, int], side: int = 160) -> tuple[int, int]:
    """``(h, w)`` with the frame's aspect and the longer side at most ``side`` pixels."""
    h, w = frame_size
    scale = min(1.0, side / max(h, w))
    return max(1, round(h * scale)), max(1, round(w * scale))


def load_traverse_sizes(source: Source, sizes: dict[str, tuple[int, int] | None],
                        events: EventFrameOptions | None = None, progress: bool | None = None,
                        select: FrameSelection | None = None, thumbnail: int | None = None
                        ) -> tuple[dict[str, torch.Tensor], dict]:
    """Load a traverse once, keeping only the frame sizes the engines need.

    Each frame is shrunk by :func:`torchseq.preprocess.resize` as it is decoded, so the result
    equals resizing the full-resolution traverse, without ever holding it: 3000 frames of
    720p video need about 30 MB at 32x64 instead of 11 GB.

    Args:
        source: as :func:`load_traverse`.
        sizes: name -> ``(H, W)`` to resize to, or None for the original size.
        events: how event files are accumulated into frames.
        progress: show a progress bar (None: only when stderr is a terminal).
        select: which frames to keep.
        thumbnail: also keep uint8 thumbnails (longer side at most this many pixels) under
            ``"thumbnail"``, for plots.

    Returns:
        ``({name: (T, h, w) float32}, info)``; ``info``: ``n_frames`` (T), ``frame_size``
        ``[H, W]`` (original), ``indices`` (the kept frames' original indices) and
        ``n_total`` (frames before the selection, None when unknown).
    """
    from torchseq.preprocess import resize

    out: dict[str, list] = {name: [] for name in sizes}
    thumbs: list = []
    frame_size = None
    thumb_size = None
    total: dict = {}
    select = select or FrameSelection()
    last = None  # (frame, its sizes): an event file's empty windows are one zero frame
    repeats = 0
    for frame in iter_traverse(source, events, progress, select, total):
        if last is not None and frame is last[0]:
            repeats += 1
            for name, resized in last[1].items():
                (thumbs if name is None else out[name]).append(resized)
            continue
        x = torch.as_tensor(frame, dtype=torch.float32)[None]  # (1, H, W)
        if frame_size is None:
            frame_size = tuple(int(v) for v in x.shape[1:])
            thumb_size = thumbnail_size(frame_size, thumbnail) if thumbnail else None
        made = {}
        for name, size in sizes.items():
            made[name] = x[0].clone() if size is None else resize(x, size)[0]
            out[name].append(made[name])
        if thumb_size is not None:
            made[None] = resize(x, thumb_size)[0].round().clamp(0, 255).to(torch.uint8)
            thumbs.append(made[None])
        last = (frame, made)
    _check_empty_windows(source, repeats, out)
    result = {name: torch.stack(v) for name, v in out.items()}
    if thumbs:
        result["thumbnail"] = torch.stack(thumbs)
    n = len(thumbs) if thumbs else len(next(iter(out.values()), []))
    indices = list(range(select.start, select.start + n * select.step, select.step))
    return result, {"n_frames": n, "frame_size": list(frame_size), "indices": indices,
                    "n_total": total.get("n_total"), "events": bool(total.get("events"))}


def _check_empty_windows(source, repeats: int, out: dict[str, list]) -> None:
    """Refuse to stack an event traverse whose frames are mostly empty windows and too many.

    Until stacked, the empty windows are one shared zero frame; stacked they follow the
    recording's time span, not its events (two flipped time bits in an AEDAT 2.0 cut of 4,000
    events asked for 13,475 frames of 128x128, 1.1 GB).
    """
    n = len(next(iter(out.values()), []))
    elements = sum(v[0].numel() * len(v) for v in out.values() if v)
    if 2 * repeats > n and elements > MAX_EMPTY_ELEMENTS:
        name = source if isinstance(source, (str, Path)) else "the traverse"
        raise TraverseError(
            f"{name}: {n:,} frames of which {repeats:,} are empty windows would need "
            f"{elements:,} elements ({elements * 4 / 2**30:.1f} GiB float32): crop the "
            f"recording (--t-start/--duration), use longer windows (--window-ms), a smaller "
            f"frame size or a fixed number of events per frame (--event-count)")


def load_traverse(source: Source, events: EventFrameOptions | None = None,
                  progress: bool | None = None, select: FrameSelection | None = None,
                  size: tuple[int, int] | None = None) -> torch.Tensor:
    """Load a traverse as grey frames.

    Args:
        source: an image folder, a video file, an event file (``.aedat``, ``.aedat4``,
            ``.raw``, ``.npy``/``.npz`` event arrays, ``.csv``/``.txt`` ``t,x,y,p``), a frame
            array file (``.npy`` ``(T, H, W)`` or ``.npz`` with a ``frames`` key), or an
            in-memory ``(T, H, W)`` / ``(T, H, W, 3)`` array or tensor.
        events: how event files are accumulated into frames.
        progress: show a progress bar for long reads (None: only when stderr is a
            terminal, so redirected logs get none).
        select: which frames to keep (start, stop, step, max_frames); default all.
        size: ``(H, W)`` to shrink each frame to as it is read (``torchseq.resize``);
            None keeps the original size.

    Returns:
        ``(T, H, W)`` float32 frames.
    """
    if isinstance(source, (np.ndarray, torch.Tensor)) and select is None and size is None:
        return frames_from_array(source)
    frames, _ = load_traverse_sizes(source, {"frames": size}, events, progress, select)
    return frames["frames"]

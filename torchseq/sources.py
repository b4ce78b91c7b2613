"""Load a traverse from wherever it lives: an image folder, a video, an array, an event file.

Every loader returns grey frames ``(T, H, W)`` float32 in 0..255 (event files: accumulated
event frames, see :mod:`torchseq.events`).
"""

from __future__ import annotations

import re
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Union

import cv2
import numpy as np
import torch
from tqdm import tqdm

from torchseq.npyfile import load_npy, load_npz_member, npy_header, npz_members

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp"}
VIDEO_SUFFIXES = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".mpg", ".mpeg", ".m4v"}
EVENT_SUFFIXES = {".aedat", ".aedat4", ".raw", ".dat", ".csv", ".txt", ".npz", ".npy", ".h5"}

Source = Union[str, Path, np.ndarray, torch.Tensor]


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
    """

    window_ms: float = 10.0
    event_count: int | None = None
    frame_size: tuple[int, int] | None = None
    anchor: str | int = "first"


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


def load_image_folder(folder: Path, progress: bool = True) -> torch.Tensor:
    """Load every image of a folder in natural sort order as ``(T, H, W)`` float32 grey."""
    files = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES),
                   key=lambda p: natural_key(p.name))
    if not files:
        raise TraverseError(f"no images ({', '.join(sorted(IMAGE_SUFFIXES))}) in folder {folder}")
    frames = []
    for f in tqdm(files, desc=f"reading {folder.name}", disable=not progress, leave=False):
        grey = _grey_uint(_imread(f), f)
        if frames and grey.shape != frames[0].shape:
            raise TraverseError(
                f"mixed image sizes in {folder}: {files[0].name} is {frames[0].shape[1]}x"
                f"{frames[0].shape[0]} but {f.name} is {grey.shape[1]}x{grey.shape[0]}")
        frames.append(grey)
    return torch.from_numpy(np.stack(frames))


def load_video(path: Path, progress: bool = True) -> torch.Tensor:
    """Load every frame of a video file as ``(T, H, W)`` float32 grey."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise TraverseError(f"cannot open video {path}")
    frames = []
    total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or None
    with tqdm(total=total, desc=f"reading {path.name}", disable=not progress, leave=False) as bar:
        while True:
            ok, image = cap.read()
            if not ok:
                break
            frames.append(_grey_uint(image, path))
            bar.update(1)
    cap.release()
    if not frames:
        raise TraverseError(f"video {path} has no readable frames")
    return torch.from_numpy(np.stack(frames))


def frames_from_array(array: np.ndarray | torch.Tensor, name: str = "array") -> torch.Tensor:
    """Check and convert a ``(T, H, W)`` or ``(T, H, W, 3)`` RGB array to grey float32 frames."""
    from torchseq.preprocess import to_grey

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


def _is_event_file(path: Path) -> bool:
    """Sniff an event file: structured ``.npy``, ``.npz`` without ``frames``, or a suffix."""
    if path.suffix.lower() == ".npy":
        _, dtype = npy_header(path, TraverseError)
        return dtype.names is not None
    if path.suffix.lower() == ".npz":
        return "frames" not in npz_members(path, TraverseError)
    return path.suffix.lower() in EVENT_SUFFIXES


def _event_frames(path: Path, opts: EventFrameOptions) -> torch.Tensor:
    import inspect

    from torchseq.events import load_event_frames

    kwargs = {}
    if opts.anchor != "first":  # today's behaviour needs no keyword
        if "anchor" not in inspect.signature(load_event_frames).parameters:
            raise TraverseError("window anchoring ('zero' or a time) needs a torchseq.events "
                                "with load_event_frames(anchor=...)")
        kwargs["anchor"] = opts.anchor
    try:
        return load_event_frames(path, window_ms=opts.window_ms, event_count=opts.event_count,
                                 frame_size=opts.frame_size, **kwargs)
    except (ValueError, OSError, EOFError, IndexError, KeyError, TypeError, OverflowError,
            MemoryError, zipfile.BadZipFile, struct.error) as err:
        # whatever the event reader met in a damaged file, the traverse names it
        text = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise TraverseError(text if str(path) in text else f"{path}: {text}") from err


def load_traverse(source: Source, events: EventFrameOptions | None = None,
                  progress: bool = True) -> torch.Tensor:
    """Load a traverse as grey frames.

    Args:
        source: an image folder, a video file, an event file (``.aedat``, ``.aedat4``,
            ``.raw``, ``.npy``/``.npz`` event arrays, ``.csv``/``.txt`` ``t,x,y,p``), a frame
            array file (``.npy`` ``(T, H, W)`` or ``.npz`` with a ``frames`` key), or an
            in-memory ``(T, H, W)`` / ``(T, H, W, 3)`` array or tensor.
        events: how event files are accumulated into frames.
        progress: show a progress bar for long reads.

    Returns:
        ``(T, H, W)`` float32 frames.
    """
    if isinstance(source, (np.ndarray, torch.Tensor)):
        return frames_from_array(source)
    path = Path(source)
    if not path.exists():
        raise TraverseError(f"no such file or folder: {path}")
    if path.is_dir():
        return load_image_folder(path, progress)
    suffix = path.suffix.lower()
    if suffix in VIDEO_SUFFIXES:
        return load_video(path, progress)
    if _is_event_file(path):
        return _event_frames(path, events or EventFrameOptions())
    if suffix == ".npy":
        return frames_from_array(_frame_array(load_npy(path, TraverseError), path), str(path))
    if suffix == ".npz":
        array = load_npz_member(path, "frames", TraverseError)
        return frames_from_array(_frame_array(array, path), str(path))
    if suffix in IMAGE_SUFFIXES:
        raise TraverseError(f"{path} is a single image; give the folder that holds the traverse")
    raise TraverseError(f"unknown traverse format: {path}")

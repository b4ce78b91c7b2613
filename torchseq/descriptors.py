"""Traverses of descriptors: ``(T, D)`` arrays from files, and a hook that makes them from frames.

Any per-frame vector is a traverse (pixels, a classic descriptor, NetVLAD, CosPlace, MixVPR,
SALAD, MegaLoc): :meth:`torchseq.SeqSLAM.match_descriptors` matches two of them with the
config's ``metric`` (``l1``, ``l2`` or ``cosine``), and :func:`neural_input` feeds one to
Neural SeqSLAM as its L1 input. Files read (nothing is unpickled):

- ``.npy``: a 2-D numeric ``(T, D)`` array (VPR-methods-evaluation's
  ``database_descriptors.npy`` / ``queries_descriptors.npy``, Event-LAB's ``(N, D)``
  descriptor banks).
- ``.npz``: the member ``descriptors`` (or the only member, when it is 2-D).
- ``.h5`` / ``.hdf5``: the dataset ``descriptors`` (or the only dataset in the file, when it
  is 2-D).
- a folder of VPR-methods-evaluation's kapture files (``--save_descriptors kapture``): one
  raw ``<image>.gfeat`` per frame, in natural order of the names, with
  ``global_features.txt`` (``name, dtype, dsize, metric_type``) in the folder or above it.

A descriptor hook (:func:`load_hook`, ``--descriptor module:callable``) is any callable or
``nn.Module`` taking ``(B, H, W)`` float32 grey frames in 0..255 (the traverse's own size)
on the chosen device and returning ``(B, D)``; :func:`describe` runs it in batches while the
frames stream in, so only the descriptors are kept.
"""

from __future__ import annotations

import dataclasses
import importlib
import re
import sys
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import torch

from torchseq._checks import torch_numbers
from torchseq.npyfile import (
    load_npy,
    load_npz_member,
    npy_header,
    npz_member_header,
    npz_members,
)
from torchseq.sources import TraverseError, natural_key

DESCRIPTOR_KEY = "descriptors"
KAPTURE_HEADER = "global_features.txt"
KAPTURE_SUFFIX = ".gfeat"
EVENTS_KEY = "events"  # an event file's array: never taken as the only descriptor array
H5_ERRORS = (OSError, KeyError, RuntimeError, ValueError, TypeError)  # links, heaps, filters
LAYOUTS = ("a (T, D) .npy; an .npz or HDF5 file with a 'descriptors' array; or a folder of "
           "VPR-methods-evaluation .gfeat files under a global_features.txt")


class DescriptorError(TraverseError):
    """Descriptors could not be read or do not fit; the message says why in one line."""


def as_descriptors(array, name: str = "descriptors") -> torch.Tensor:
    """Check a ``(T, D)`` array of finite numbers and return it as a float tensor.

    float64 stays float64; every other numeric type becomes float32.
    """
    if not isinstance(array, torch.Tensor):
        array = torch_numbers(np.asarray(array), name, DescriptorError)
    x = torch.as_tensor(array)
    if x.dim() != 2:
        raise DescriptorError(f"{name} must be (T, D), got {tuple(x.shape)}")
    if x.shape[0] == 0 or x.shape[1] == 0:
        raise DescriptorError(f"{name} is empty: {tuple(x.shape)}")
    if x.dtype == torch.bool or x.is_complex():
        raise DescriptorError(f"{name} has unsupported dtype {x.dtype}")
    x = x if x.dtype == torch.float64 else x.to(torch.float32)
    if not bool(torch.isfinite(x).all()):
        raise DescriptorError(f"{name} holds NaN or infinite values")
    return x


def _h5py():
    try:
        import h5py
    except ImportError:  # pragma: no cover - h5py is a declared extra
        raise DescriptorError("reading HDF5 needs h5py (pip install torchseq[hdf5])") from None
    return h5py


def _h5_dataset(f, h5py, path: Path):
    """The ``descriptors`` dataset of an open HDF5 file (or its only 2-D one), or None.

    ``descriptors`` must be stored in the file (a hard link): a soft or external link is
    refused. Other datasets are found through hard links only.
    """
    link = f.get(DESCRIPTOR_KEY, getlink=True)
    if link is not None:
        if not isinstance(link, h5py.HardLink):
            raise DescriptorError(f"{path}: '{DESCRIPTOR_KEY}' is a {type(link).__name__}, "
                                  f"not a dataset stored in the file")
        if isinstance(f[DESCRIPTOR_KEY], h5py.Dataset):
            return f[DESCRIPTOR_KEY]
    found = []
    f.visititems(lambda n, o: found.append(o) if isinstance(o, h5py.Dataset) else None)
    if (len(found) == 1 and found[0].ndim == 2 and found[0].dtype.names is None
            and found[0].name != "/" + EVENTS_KEY):
        return found[0]
    return None


def _h5_descriptors(path: Path) -> np.ndarray | None:
    """The ``descriptors`` dataset (or the only dataset, when 2-D) of an HDF5 file, or None.

    The dataset's declared size is checked against the bytes the file stores before it is
    read (``events.hdf5.check_storage``).
    """
    from torchseq.events.hdf5 import check_storage

    h5py = _h5py()
    try:
        with h5py.File(path, "r") as f:
            d = _h5_dataset(f, h5py, path)
            if d is None:
                return None
            check_storage(d, str(path), DescriptorError)
            return np.asarray(d[()])
    except DescriptorError:
        raise
    except H5_ERRORS as err:
        raise DescriptorError(f"{path}: cannot read HDF5 ({str(err).splitlines()[0][:200]})"
                              ) from None


def _kapture_folder(folder: Path) -> tuple[list[Path], np.dtype, int] | None:
    """The ``.gfeat`` files of a folder and the dtype and size its kapture header gives."""
    files = sorted((p for p in folder.iterdir() if p.name.endswith(KAPTURE_SUFFIX)),
                   key=lambda p: natural_key(p.name))
    if not files:
        return None
    for parent in (folder, *folder.parents):
        header = parent / KAPTURE_HEADER
        if header.is_file():
            break
    else:
        raise DescriptorError(f"{folder}: .gfeat descriptors without a {KAPTURE_HEADER} in "
                              f"the folder or above it (VPR-methods-evaluation writes one "
                              f"beside them)")
    rows = [ln.strip() for ln in header.read_text(errors="replace").splitlines()
            if ln.strip() and not ln.startswith("#")]
    parts = [p.strip() for p in rows[0].split(",")] if rows else []
    if len(parts) < 3:
        raise DescriptorError(f"{header}: expected a line 'name, dtype, dsize, metric_type'")
    try:
        dtype, dsize = np.dtype(parts[1]), int(parts[2])
    except (TypeError, ValueError):
        raise DescriptorError(f"{header}: unreadable dtype or size in {rows[0]!r}") from None
    if dtype.kind not in "iuf" or dsize < 1:
        raise DescriptorError(f"{header}: dtype {dtype} and size {dsize} are not descriptors")
    return files, dtype, dsize


def descriptor_kind(path: str | Path) -> str | None:
    """``"npy"``, ``"npz"``, ``"hdf5"`` or ``"kapture"`` where ``path`` holds descriptors.

    None where it holds something else (frames, events, images). Only headers are read
    (HDF5: the dataset names).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if path.is_dir():
        has = any(p.name.endswith(KAPTURE_SUFFIX) for p in path.iterdir())
        return "kapture" if has else None
    if suffix == ".npy":
        shape, dtype = npy_header(path, DescriptorError)
        return "npy" if len(shape) == 2 and dtype.names is None else None
    if suffix == ".npz":
        return "npz" if _npz_key(path) is not None else None
    if suffix in (".h5", ".hdf5"):
        h5py = _h5py()
        try:
            with h5py.File(path, "r") as f:
                return "hdf5" if _h5_dataset(f, h5py, path) is not None else None
        except H5_ERRORS:
            return None  # not descriptors: the event readers say what the file is
    return None


def _npz_key(path: Path) -> str | None:
    """The member descriptors are read from: ``descriptors``, or the only one when 2-D."""
    members = npz_members(path, DescriptorError)
    if DESCRIPTOR_KEY in members:
        return DESCRIPTOR_KEY
    if len(members) == 1 and EVENTS_KEY not in members:
        key = next(iter(members))
        header = npz_member_header(path, key, DescriptorError)
        if len(header.shape) == 2 and header.dtype.names is None:
            return key
    return None


def load_descriptors(path: str | Path) -> torch.Tensor:
    """Read a traverse of descriptors, ``(T, D)`` (float64 kept, else float32).

    Args:
        path: a file or folder in one of the layouts of this module's docstring.

    Raises:
        DescriptorError: a missing file, another layout (the message lists the expected
            ones), or values that are not finite numbers.
    """
    path = Path(path)
    if not path.exists():
        raise DescriptorError(f"no such file or folder: {path}")
    suffix = path.suffix.lower()
    if path.is_dir():
        try:
            kapture = _kapture_folder(path)
        except OSError as err:
            raise DescriptorError(f"{path}: cannot read ({err})") from None
        if kapture is None:
            raise DescriptorError(f"{path}: no descriptors; expected {LAYOUTS}")
        files, dtype, dsize = kapture
        rows = []
        for f in files:
            try:
                if f.stat().st_size != dsize * dtype.itemsize:  # checked before it is read
                    raise DescriptorError(f"{f}: {f.stat().st_size} bytes, the header says "
                                          f"{dsize} values of {dtype}")
                rows.append(np.fromfile(f, dtype=dtype))
            except OSError as err:
                raise DescriptorError(f"{f}: cannot read ({err.strerror or err})") from None
        return as_descriptors(np.stack(rows), str(path))
    if suffix == ".npy":
        array = load_npy(path, DescriptorError)
    elif suffix == ".npz":
        key = _npz_key(path)
        if key is None:
            members = npz_members(path, DescriptorError)
            raise DescriptorError(f"{path}: no '{DESCRIPTOR_KEY}' array among "
                                  f"{', '.join(sorted(members))}; expected {LAYOUTS}")
        array = load_npz_member(path, key, DescriptorError)
    elif suffix in (".h5", ".hdf5"):
        array = _h5_descriptors(path)
        if array is None:
            raise DescriptorError(f"{path}: no '{DESCRIPTOR_KEY}' dataset; expected {LAYOUTS}")
    else:
        raise DescriptorError(f"{path}: not a descriptor file; expected {LAYOUTS}")
    if array.dtype.names is not None or array.dtype.kind not in "iuf":
        raise DescriptorError(f"{path}: descriptors must be numbers, got dtype {array.dtype}")
    return as_descriptors(array, str(path))


def save_descriptors(path: str | Path, descriptors) -> None:
    """Write ``(T, D)`` descriptors atomically as ``.npy`` (or ``.npz`` with ``descriptors``)."""
    from torchseq.atomic import atomic_open

    x = as_descriptors(descriptors).cpu().numpy()
    path = Path(path)
    with atomic_open(path) as f:
        if path.suffix.lower() == ".npz":
            np.savez(f, **{DESCRIPTOR_KEY: x})
        else:
            np.save(f, x)


_SPEC = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$")


def load_hook(spec: str) -> Callable[[torch.Tensor], torch.Tensor]:
    """``"module:callable"`` -> the descriptor hook it names.

    The attribute may be a function, an ``nn.Module`` (or any callable object), or a class
    built with no arguments; a module is put in eval mode. The current folder is importable
    (``--descriptor mynet:describe`` finds ``./mynet.py``).

    Raises:
        DescriptorError: a malformed spec, a module that does not import, a missing name.
    """
    if not isinstance(spec, str) or not _SPEC.match(spec):
        raise DescriptorError(f"a descriptor hook is 'module:callable' (e.g. "
                              f"mypkg.nets:describe), got {spec!r}")
    module_name, attr = spec.split(":")
    if "" not in sys.path and "." not in sys.path:
        sys.path.insert(0, "")
    try:
        obj = importlib.import_module(module_name)
    except ImportError as err:
        raise DescriptorError(f"descriptor hook {spec}: cannot import {module_name} ({err})"
                              ) from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise DescriptorError(f"descriptor hook {spec}: {module_name} has no {attr}")
        obj = getattr(obj, part)
    if isinstance(obj, type):
        obj = obj()
    if not callable(obj):
        raise DescriptorError(f"descriptor hook {spec}: {attr} is not callable")
    if isinstance(obj, torch.nn.Module):
        obj.eval()
    return obj


def describe(frames: Iterable, hook: Callable[[torch.Tensor], torch.Tensor],
             device: torch.device | str = "cpu", batch: int = 64,
             on_frame: Callable[[torch.Tensor], None] | None = None) -> torch.Tensor:
    """Run a descriptor hook over streaming frames, ``batch`` frames at a time.

    Args:
        frames: an iterable of ``(H, W)`` grey frames (arrays or tensors), e.g.
            :func:`torchseq.sources.iter_traverse`.
        hook: maps ``(B, H, W)`` float32 on ``device`` to ``(B, D)``.
        device: where the hook runs (an ``nn.Module`` hook is moved there).
        batch: frames per call.
        on_frame: called with each ``(H, W)`` CPU frame as it arrives (thumbnails).

    Returns:
        ``(T, D)`` descriptors on CPU (float64 kept, else float32).
    """
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise DescriptorError(f"descriptor batch must be an integer >= 1, got {batch!r}")
    device = torch.device(device)
    if isinstance(hook, torch.nn.Module):
        hook = hook.to(device)
    out: list[torch.Tensor] = []
    pending: list[torch.Tensor] = []

    def flush() -> None:
        x = torch.stack(pending).to(device)
        with torch.inference_mode():
            y = hook(x)
        if isinstance(y, np.ndarray):
            y = torch.from_numpy(torch_numbers(y, "the descriptor hook's output",
                                               DescriptorError))
        if not isinstance(y, torch.Tensor):
            raise DescriptorError(f"the descriptor hook must return a ({len(pending)}, D) "
                                  f"tensor or array, got {type(y).__name__}")
        if y.dim() != 2 or y.shape[0] != len(pending):
            raise DescriptorError(f"the descriptor hook must map ({len(pending)}, H, W) "
                                  f"frames to ({len(pending)}, D), got {tuple(y.shape)}")
        if out and y.shape[1] != out[0].shape[1]:
            raise DescriptorError(f"the descriptor hook changed its size from "
                                  f"{out[0].shape[1]} to {y.shape[1]}")
        out.append(y.detach().to("cpu"))
        pending.clear()

    for frame in frames:
        f = torch.as_tensor(frame, dtype=torch.float32)
        if on_frame is not None:
            on_frame(f)
        pending.append(f)
        if len(pending) == batch:
            flush()
    if pending:
        flush()
    if not out:
        raise DescriptorError("the traverse has no frames to describe")
    return as_descriptors(torch.cat(out), "hook descriptors")


def neural_input(descriptors: torch.Tensor) -> torch.Tensor:
    """Descriptors as Neural SeqSLAM input: ``(T, D)`` -> ``(T, 1, D)`` z-scored rows.

    Each descriptor is standardised (mean 0, standard deviation 1 over its ``D`` values, as
    the network's ``zscore`` patch normalisation does per block), so the L1 input grid
    (``1 / input_steps``) and the k-WTA see the same scale for any descriptor; the network
    is then configured by :func:`neural_config` (L1 = ``D`` units, no patch normalisation).
    """
    x = as_descriptors(descriptors).to(torch.float64)  # float64: offsets far above the spread
    centred = x - x.mean(1, keepdim=True)
    std = centred.pow(2).mean(1, keepdim=True).sqrt()
    z = centred / torch.where(std > 0, std, torch.ones_like(std))
    return z.to(torch.float32)[:, None, :]


def neural_config(config, dim: int):
    """A :class:`~torchseq.neural.NeuralConfig` for ``dim``-dimensional descriptor input.

    ``input_size = (1, dim)`` (L1 has ``dim`` units, so L1 -> L2 has ``dim x hidden``
    weights at the config's density), ``patch_size = 0`` (:func:`neural_input` has
    standardised each descriptor already); every other setting is kept.
    """
    return dataclasses.replace(config, input_size=(1, int(dim)), patch_size=0)

"""Neural SeqSLAM checkpoints: a versioned, checksummed dict, written atomically.

A checkpoint is ``{"format", "config", "state_dict", "extra", "checksum"}`` saved with
``torch.save`` and read with ``torch.load(weights_only=True)`` (no pickled code runs). The
checksum is a SHA-256 over the format, the config, every tensor (name, dtype, shape, bytes)
and ``extra``. :func:`load_model` checks, in this order, before it builds anything: the
format; every tensor held densely in the file (no stride-0 giants); every config field by
type and range (:meth:`NeuralConfig.validate`); the tensors against the shapes and dtypes
that config implies (so the model it allocates is no larger than the file); finite float
tensors; the checksum; then values only ``fit`` makes (a resealed file: 0/1 masks, a ring
shift whose rows sum to at most 1, contiguous unit spans; :func:`_check_values`). Any
failure is a :class:`NeuralError` naming the file. Version-1 files (no checksum) still load,
with a warning.
"""

from __future__ import annotations

import hashlib
import pickle
import struct
import warnings
import zipfile
from pathlib import Path

import numpy as np
import torch

from torchseq.atomic import atomic_open
from torchseq.neural.config import NeuralConfig, NeuralError

FORMAT = "torchseq.neural/2"
FORMAT_V1 = "torchseq.neural/1"  # no checksum: loads with a warning
CHECKSUM = "sha256"


def _feed(h, obj) -> None:
    """Hash ``obj`` canonically: a type tag, then its content (dicts in key order)."""
    if isinstance(obj, torch.Tensor):
        t = obj.detach().cpu().contiguous()
        h.update(f"T{t.dtype}{tuple(t.shape)}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    elif isinstance(obj, dict):
        h.update(f"D{len(obj)}".encode())
        for key in sorted(obj, key=repr):
            _feed(h, key)
            _feed(h, obj[key])
    elif isinstance(obj, (list, tuple)):
        h.update(f"{type(obj).__name__[0]}{len(obj)}".encode())
        for item in obj:
            _feed(h, item)
    elif isinstance(obj, float):
        h.update(b"F" + struct.pack("<d", obj))
    elif isinstance(obj, str):
        data = obj.encode("utf-8", "surrogatepass")
        h.update(f"S{len(data)}:".encode() + data)
    else:  # None, bool, int and any other plain value weights_only can load
        h.update(f"O{type(obj).__name__}:{obj!r};".encode())


def checksum(fmt: str, config: dict, state_dict: dict, extra: dict) -> str:
    """``"sha256:<hex>"`` of a checkpoint's contents (see the module docstring)."""
    h = hashlib.sha256()
    for part in (fmt, config, state_dict, extra):
        _feed(h, part)
    return f"{CHECKSUM}:{h.hexdigest()}"


def save_checkpoint(path: str | Path, config: dict, state_dict: dict,
                    extra: dict | None = None) -> None:
    """Write ``{"format", "config", "state_dict", "extra", "checksum"}`` atomically.

    Args:
        path: target file (its folder must exist).
        config: ``NeuralConfig.to_dict()``.
        state_dict: the model's tensors (saved on the CPU).
        extra: plain data ``torch.load(weights_only=True)`` can read back.
    """
    path = Path(path)
    blob = {"format": FORMAT, "config": dict(config),
            "state_dict": {k: v.detach().cpu() for k, v in state_dict.items()},
            "extra": dict(extra or {})}
    blob["checksum"] = checksum(FORMAT, blob["config"], blob["state_dict"], blob["extra"])
    with atomic_open(path) as f:
        torch.save(blob, f)


def _load_failure(path: Path, err: Exception) -> str:
    """Why ``torch.load(weights_only=True)`` failed, in one line for the user.

    torch's own text for the safe loader is several lines with terminal escapes, and its
    first advice is to load with ``weights_only=False``, which a checkpoint never needs.
    """
    if not zipfile.is_zipfile(path):
        return "no intact torch.save archive: damaged, cut short or another kind of file"
    text = str(err)
    if isinstance(err, pickle.UnpicklingError):
        why = [ln.strip() for ln in text.splitlines() if "WeightsUnpickler error:" in ln]
        detail = why[0].split("error:", 1)[1].split(". ", 1)[0].strip() if why else ""
        return ("it holds objects the safe loader (weights_only=True) refuses"
                + (f": {detail[:200]}" if detail else ""))
    return f"{type(err).__name__}: {' '.join(text.split())[:200]}"


def load_checkpoint(path: str | Path, map_location=None) -> dict:
    """Read a checkpoint's dict and check its outline (format, the dicts it must hold).

    The contents are checked by :func:`load_model`.

    Raises:
        NeuralError: missing or unreadable file, an unknown format, or a missing part.
    """
    path = Path(path)
    if not path.is_file():
        raise NeuralError(f"no such checkpoint: {path}")
    try:
        blob = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # truncated, corrupt or foreign file
        raise NeuralError(f"{path}: not a readable torchseq checkpoint "
                          f"({_load_failure(path, err)})") from err
    if not isinstance(blob, dict) or blob.get("format") not in (FORMAT, FORMAT_V1):
        got = blob.get("format") if isinstance(blob, dict) else type(blob).__name__
        raise NeuralError(f"{path}: format {got!r} is not {FORMAT!r}")
    for key in ("config", "state_dict"):
        if not isinstance(blob.get(key), dict):
            raise NeuralError(f"{path}: checkpoint has no {key!r} dict")
    if not isinstance(blob.setdefault("extra", {}), dict):
        raise NeuralError(f"{path}: checkpoint 'extra' is not a dict")
    sd = blob["state_dict"]
    bad = [repr(k) for k, v in sd.items() if not isinstance(k, str)
           or not isinstance(v, torch.Tensor)]
    if bad:
        raise NeuralError(f"{path}: state_dict entries that are not named tensors: "
                          f"{', '.join(sorted(bad))[:200]}")
    for name, t in sd.items():  # the file holds every element (no stride-0 giants)
        if t.untyped_storage().nbytes() < t.numel() * t.element_size():
            raise NeuralError(f"{path}: tensor {name} {tuple(t.shape)} is not stored densely "
                              "in the file")
    return blob


def expected_tensors(config: NeuralConfig, n_units: int) -> dict:
    """Name -> ``(shape, dtype)`` of every tensor of a fitted model with ``n_units`` units.

    Computed from the config alone (nothing allocated): the sizes a checkpoint's tensors
    must have before a model of that config is built.
    """
    m, d = config.hidden, config.n_input
    cohorts = max(1, min(config.n_cohorts, n_units))
    f32, i64 = torch.float32, torch.int64
    return {"l1.weight": ((m, d), f32), "l1.mask": ((m, d), f32),
            "l3.weight": ((n_units, m), f32), "l3.mask": ((n_units, m), f32),
            "ring.shift": ((n_units, n_units), f32), "cohorts": ((n_units, cohorts), f32),
            "unit_to_reference": ((n_units, 2), i64), "unit_centre": ((n_units,), i64)}


def _check_tensors(path: Path, config: NeuralConfig, sd: dict) -> None:
    spans = sd.get("unit_to_reference")
    n = int(spans.shape[0]) if spans is not None and spans.dim() == 2 else -1
    if not 1 <= n <= config.n_output:
        raise NeuralError(f"{path}: state_dict does not fit the config (unit_to_reference "
                          f"{None if spans is None else tuple(spans.shape)}, n_output "
                          f"{config.n_output})")
    want = expected_tensors(config, n)
    if set(sd) != set(want):
        raise NeuralError(f"{path}: state_dict does not fit the config (missing "
                          f"{sorted(set(want) - set(sd))}, unexpected "
                          f"{sorted(set(sd) - set(want))[:10]})")
    for name, (shape, dtype) in want.items():
        t = sd[name]
        if tuple(t.shape) != shape or t.dtype != dtype:
            raise NeuralError(f"{path}: state_dict does not fit the config ({name} is "
                              f"{t.dtype} {tuple(t.shape)}, the config needs {dtype} {shape})")
        if t.dtype.is_floating_point and not np.isfinite(t.detach().cpu().numpy()).all():
            raise NeuralError(f"{path}: {name} holds NaN or infinite values")


MAX_WEIGHT = 2.0**8  # |l1.weight|, |l3.weight|: fit makes them at most ~1


def _check_values(path: Path, sd: dict) -> None:
    """Refuse values ``fit`` cannot make, whatever the checksum says (a resealed file).

    Masks and cohorts are 0/1 (one cohort per unit); the ring's shift is non-negative with
    rows summing to at most 1 (``learn_shift_matrix`` normalises them), so activity cannot
    grow without bound; weights are bounded; the units' spans are contiguous stretches of the
    route from frame 0 and each unit's centre is its span's middle, as the unit search and
    the read-out assume.
    """
    def refuse(name: str, what: str) -> None:
        raise NeuralError(f"{path}: {name} {what}: not a fitted model's values")

    for name in ("l1.mask", "l3.mask", "cohorts"):
        if not bool(((sd[name] == 0) | (sd[name] == 1)).all()):
            refuse(name, "holds values other than 0 and 1")
    if not bool((sd["cohorts"].sum(1) == 1).all()):
        refuse("cohorts", "does not put each unit in one cohort")
    shift = sd["ring.shift"]
    if bool((shift < 0).any()) or float(shift.double().sum(1).max()) > 1 + 1e-4:
        refuse("ring.shift", "has negative entries or rows summing to more than 1")
    for name in ("l1.weight", "l3.weight"):
        if float(sd[name].abs().max()) > MAX_WEIGHT:
            refuse(name, f"holds values beyond +-{MAX_WEIGHT:g}")
    spans = sd["unit_to_reference"]
    start, stop = spans[:, 0], spans[:, 1]
    if (int(start[0]) != 0 or bool((stop <= start).any()) or bool((start[1:] != stop[:-1]).any())
            or int(stop[-1]) > 2**40):
        refuse("unit_to_reference", "is not contiguous stretches of the route from frame 0")
    if not torch.equal(sd["unit_centre"], (start + stop - 1) // 2):
        refuse("unit_centre", "is not the middle of each unit's stretch")


def load_model(cls, path: str | Path, map_location=None):
    """Read, check and build a model written by :func:`save_checkpoint` (see the module doc).

    Args:
        cls: :class:`torchseq.neural.NeuralSeqSLAM` (or a subclass).
        path: the checkpoint.
        map_location: as :func:`torch.load`.

    Returns:
        The model, with the checkpoint's ``extra`` dict as ``model.extra``.

    Raises:
        NeuralError: anything wrong with the file, naming it.
    """
    path = Path(path)
    blob = load_checkpoint(path, map_location)
    try:
        config = NeuralConfig.from_dict(blob["config"])
    except NeuralError as err:
        raise NeuralError(f"{path}: bad config: {err}") from None
    sd = blob["state_dict"]
    _check_tensors(path, config, sd)
    stored = blob.get("checksum")
    if blob["format"] == FORMAT or stored is not None:
        if stored != checksum(blob["format"], blob["config"], sd, blob["extra"]):
            raise NeuralError(f"{path}: checksum mismatch: the checkpoint is corrupt")
    else:
        warnings.warn(f"{path}: a {FORMAT_V1} checkpoint has no checksum, so corruption "
                      "cannot be detected; save it again to add one", stacklevel=3)
    _check_values(path, {k: v.detach().cpu() for k, v in sd.items()})
    device = sd["l1.weight"].device if map_location is not None else None
    model = cls(config, device=device)
    try:
        model.load_state_dict(sd)
    except (RuntimeError, KeyError) as err:  # the model disagrees with expected_tensors
        raise NeuralError(f"{path}: state_dict does not fit the config ({err})") from err
    model.extra = blob["extra"]
    return model

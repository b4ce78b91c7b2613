"""Neural SeqSLAM checkpoints: a versioned dict written atomically, read with weights_only."""

from __future__ import annotations

from pathlib import Path

import torch

from torchseq.atomic import atomic_open
from torchseq.neural.config import NeuralError

FORMAT = "torchseq.neural/1"


def save_checkpoint(path: str | Path, config: dict, state_dict: dict,
                    extra: dict | None = None) -> None:
    """Write ``{"format", "config", "state_dict", "extra"}`` to ``path`` atomically.

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
    with atomic_open(path) as f:
        torch.save(blob, f)


def load_checkpoint(path: str | Path, map_location=None) -> dict:
    """Read and check a checkpoint written by :func:`save_checkpoint`.

    Raises:
        NeuralError: missing or unreadable file, or a format other than ``FORMAT``.
    """
    path = Path(path)
    if not path.is_file():
        raise NeuralError(f"no such checkpoint: {path}")
    try:
        blob = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # truncated or foreign file
        raise NeuralError(f"{path}: not a readable torchseq checkpoint ({err})") from err
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        got = blob.get("format") if isinstance(blob, dict) else type(blob).__name__
        raise NeuralError(f"{path}: format {got!r} is not {FORMAT!r}")
    for key in ("config", "state_dict"):
        if not isinstance(blob.get(key), dict):
            raise NeuralError(f"{path}: checkpoint has no {key!r} dict")
    return blob

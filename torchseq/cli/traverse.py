"""A loaded traverse of an eval run: frames at each size its engines read, thumbnails, facts."""

from __future__ import annotations

from dataclasses import dataclass

import torch


def size_key(size) -> str:
    """``(32, 64)`` -> ``"32x64"``."""
    return f"{int(size[0])}x{int(size[1])}"


@dataclass
class Traverse:
    """A loaded traverse: frames at each size an engine needs, thumbnails for plots, facts."""

    frames: dict
    thumbnail: torch.Tensor | None
    info: dict
    descriptors: torch.Tensor | None = None  # (T, D) for a traverse of descriptors
    members: list | None = None  # temporal-window ensemble: one frames dict per member

    def __len__(self) -> int:
        return int(self.info["n_frames"])

    def at(self, size) -> torch.Tensor:
        """``(T, h, w)`` frames at ``size``."""
        return self.frames[size_key(size)]

    def members_at(self, size) -> list[torch.Tensor]:
        """The ensemble members' ``(T, h, w)`` frames at ``size``, in ``--window-ms`` order."""
        return [m[size_key(size)] for m in self.members]

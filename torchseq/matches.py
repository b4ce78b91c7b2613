"""The result every engine returns: one reference index and one score per query frame."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Matches:
    """Place decisions for a query traverse.

    Attributes:
        reference: ``(Q,)`` int64 matched reference index, ``-1`` where a query gets no match
            (e.g. the first and last ``ds/2`` frames in SeqSLAM).
        score: ``(Q,)`` float, the engine's own score (NaN where there is no match).
        lower_is_better: True when a lower score is a more confident match (SeqSLAM's
            uniqueness ratio); False for confidences (Neural SeqSLAM).
    """

    reference: torch.Tensor
    score: torch.Tensor
    lower_is_better: bool

    def __post_init__(self) -> None:
        if self.reference.shape != self.score.shape or self.reference.dim() != 1:
            raise ValueError(
                f"reference and score must both be (Q,), got {tuple(self.reference.shape)} "
                f"and {tuple(self.score.shape)}"
            )

    @property
    def confidence(self) -> torch.Tensor:
        """``(Q,)`` float, higher = more confident; ``-inf`` where there is no match."""
        c = -self.score if self.lower_is_better else self.score
        c = c.to(torch.float64)
        return torch.where(self.reference >= 0, c.nan_to_num(nan=-torch.inf), -torch.inf)

    def __len__(self) -> int:
        return int(self.reference.shape[0])

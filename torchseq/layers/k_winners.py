"""``KWinnersTakeAll``: keep the k largest units per sample, zero the rest."""

from __future__ import annotations

import torch
from torch import nn

from torchseq.layers.functional import kwta, kwta_k


class KWinnersTakeAll(nn.Module):
    """k-winners-take-all over the last axis with deterministic ties (lowest index wins).

    Give either ``k`` (winners per sample) or ``fraction`` (of the input width, resolved at
    call time as ``max(1, round(fraction * N))``).

    Args:
        k: winners per sample.
        fraction: winners as a fraction of the units.
        binary: output 1.0 at winners instead of their values.
        straight_through: identity gradient in the backward pass.
    """

    def __init__(self, k: int | None = None, fraction: float | None = None, binary: bool = False,
                 straight_through: bool = False) -> None:
        super().__init__()
        kwta_k(10**9, k, fraction)  # validates the arguments early
        self.k = k
        self.fraction = fraction
        self.binary = binary
        self.straight_through = straight_through

    def winners(self, n: int) -> int:
        """Winner count for ``n`` units."""
        return kwta_k(n, self.k, self.fraction)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Keep the winners.

        Args:
            x: ``(..., N)``.

        Returns:
            ``(..., N)``, see :func:`torchseq.layers.functional.kwta`.
        """
        return kwta(x, self.winners(x.shape[-1]), self.binary, self.straight_through)

    def extra_repr(self) -> str:
        """Summary for print(module)."""
        size = f"k={self.k}" if self.k is not None else f"fraction={self.fraction}"
        return f"{size}, binary={self.binary}, straight_through={self.straight_through}"

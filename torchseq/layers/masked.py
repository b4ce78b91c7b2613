"""``MaskedLinear``: a linear layer with a fixed random sparse connection mask."""

from __future__ import annotations

import math

import torch
from torch import nn

from torchseq.layers.functional import make_mask, mask_fan_in, masked_linear


class MaskedLinear(nn.Module):
    """Linear layer whose weight only acts through a fixed random binary mask.

    The mask is a buffer (it travels in ``state_dict`` but never trains) with exactly
    ``round(density * in_features)`` ones in every output row, drawn from ``seed``. The
    forward pass is ``F.linear(x, weight * mask, bias)``, so gradients outside the mask are
    zero and an ordinary optimiser never moves a masked-out weight away from its value.

    Args:
        in_features: input size.
        out_features: output size.
        density: fraction of connections kept per row, in ``(0, 1]``.
        bias: learn an additive bias.
        seed: seed for the mask and the initial weights (None: torch's global RNG).
        device: device of parameters and buffers.
        dtype: dtype of parameters and buffers.
    """

    def __init__(self, in_features: int, out_features: int, density: float = 0.2,
                 bias: bool = False, seed: int | None = None, device=None, dtype=None) -> None:
        super().__init__()
        self.in_features = int(in_features)
        self.out_features = int(out_features)
        self.density = float(density)
        self.seed = seed
        kw = {"device": device, "dtype": dtype}
        self.weight = nn.Parameter(torch.empty(out_features, in_features, **kw))
        self.bias = nn.Parameter(torch.empty(out_features, **kw)) if bias else None
        self.register_buffer("mask", torch.empty(out_features, in_features, **kw))
        self.reset_parameters()

    @property
    def fan_in(self) -> int:
        """Connections per output unit."""
        return mask_fan_in(self.in_features, self.density)

    def reset_parameters(self) -> None:
        """Draw the mask and the weights again (same seed: same values).

        Weights are uniform in ``+-sqrt(3 / fan_in)`` (unit output variance for unit-variance
        inputs); the bias uniform in ``+-1 / sqrt(fan_in)``.
        """
        gen = torch.Generator().manual_seed(self.seed) if self.seed is not None else None
        mask = make_mask(self.out_features, self.in_features, self.density, gen)
        bound = math.sqrt(3.0 / self.fan_in)
        w = (torch.rand(self.out_features, self.in_features, generator=gen) * 2 - 1) * bound
        with torch.no_grad():
            self.mask.copy_(mask)
            self.weight.copy_(w)
            if self.bias is not None:
                b = (torch.rand(self.out_features, generator=gen) * 2 - 1) / math.sqrt(self.fan_in)
                self.bias.copy_(b)

    def folded_weight(self) -> torch.Tensor:
        """``(out, in)`` ``weight * mask`` as one dense tensor (for fast inference)."""
        return self.weight * self.mask

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Apply the masked map.

        Args:
            x: ``(..., in_features)``.

        Returns:
            ``(..., out_features)``.
        """
        return masked_linear(x, self.weight, self.mask, self.bias)

    def extra_repr(self) -> str:
        """Summary for print(module)."""
        return (f"in_features={self.in_features}, out_features={self.out_features}, "
                f"density={self.density}, bias={self.bias is not None}, seed={self.seed}")

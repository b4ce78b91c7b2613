"""Network layers of Neural SeqSLAM: masked linear maps, k-WTA, the output ring."""

from torchseq.layers.functional import (
    RingParams,
    RingState,
    cohort_normalise,
    kwta,
    learn_shift_matrix,
    make_mask,
    masked_linear,
    ring_scan,
    ring_step,
)
from torchseq.layers.k_winners import KWinnersTakeAll
from torchseq.layers.masked import MaskedLinear
from torchseq.layers.output_ring import OutputRing

__all__ = [
    "KWinnersTakeAll",
    "MaskedLinear",
    "OutputRing",
    "RingParams",
    "RingState",
    "cohort_normalise",
    "kwta",
    "learn_shift_matrix",
    "make_mask",
    "masked_linear",
    "ring_scan",
    "ring_step",
]

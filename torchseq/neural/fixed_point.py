"""Integer grids of Neural SeqSLAM: quantised L1 input, integer L1 weights, int8 L3 rows.

With the defaults (``input_steps=32``, ``l1_levels=64``, ``l3_levels=127``) the model's
numbers sit on integer grids by definition, not as an approximation of a float model:

- L1 input: patch z-scores rounded to multiples of ``1 / input_steps`` (``|z| <= 3.75`` for
  4x4 patches, so ``32`` gives signed 8-bit values ``-120..120``);
- L1 weights: integers ``-l1_levels..l1_levels`` times a power of two;
- L2 -> L3 weights: each unit's row rounded to integers ``-l3_levels..l3_levels`` times a
  per-unit scale.

Every L1 product is then a small integer times a power of two, and every L1 sum (below
``2**24`` in magnitude) is exact in float32 whatever the summation order: float32 GEMMs,
int8 GEMMs (:mod:`torchseq.layers.kernels`) and the integer export all give the same L2 code.
"""

from __future__ import annotations

# the input stage moved to torchseq.preprocess (one z-score); names kept for callers
from torchseq.preprocess import (  # noqa: F401
    block_order,
    in_order_sum,
    quantise_input,
    zscore_blocks,
    zscore_pixel_major,
)

# the training-time grids live in the one quantiser, beside the export grids
from torchseq.quantise import (  # noqa: F401
    factor_power_of_two,
    factor_rows,
    integer_weights,
    power_of_two_scale,
    round_rows,
)

"""The export grids of the one quantiser (:mod:`torchseq.quantise`), under their export name.

Every integer number the exporter stores comes from :func:`quantise` (weight tensors) or
:func:`fixed_point` (scalar constants), rounded halves away from zero (``HALF_AWAY``); the
training-time grids come from the same module (``HALF_EVEN``).
"""

from torchseq.quantise import (
    HALF_AWAY,
    Quantised,
    dequantise,
    fixed_point,
    fixed_point_array,
    integer_grid,
    quantise,
    round_half_away,
)

__all__ = ["HALF_AWAY", "Quantised", "dequantise", "fixed_point", "fixed_point_array",
           "integer_grid", "quantise", "round_half_away"]

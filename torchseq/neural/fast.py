"""Former home of the fast inference paths, kept so that existing imports keep working.

The kernels now sit behind the functions they compute: :mod:`torchseq.layers.kernels`
(int8 GEMM, NumPy partition k-WTA, embedding-bag), :mod:`torchseq.layers.ring` (the
blocked ring scan beside ``ring_step``); :class:`torchseq.neural.inference.NeuralInference`
chooses them per stage when it is built.
"""

from torchseq.layers.kernels import (  # noqa: F401
    TIE_STEP,
    Int8Linear,
    has_tie,
    kwta_partition,
    sum_rows,
)
from torchseq.layers.kernels import topk_indices as winners  # noqa: F401
from torchseq.layers.ring import (  # noqa: F401
    RING_BLOCK,
    band_diagonals,
    ring_advance,
    ring_power,
    ring_scan,
    ring_steps,
)

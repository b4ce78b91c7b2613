"""Neural SeqSLAM: a rate-coded network of ``nn.Module`` s whose memory is bounded."""

from torchseq._moved import moved_names
from torchseq.neural.config import NeuralConfig, NeuralError
from torchseq.neural.inference import NeuralInference
from torchseq.neural.model import (
    NeuralFitLog,
    NeuralResult,
    NeuralSeqSLAM,
    NeuralStep,
    seqslam_bytes,
)
from torchseq.neural.velocity import VelocityState

__all__ = [
    "NeuralConfig",
    "NeuralError",
    "NeuralFitLog",
    "NeuralInference",
    "NeuralResult",
    "NeuralSeqSLAM",
    "NeuralStep",
    "VelocityState",
    "seqslam_bytes",
]

# the names of the removed re-export module torchseq.neural.fixed_point, at their homes
__getattr__ = moved_names(__name__, {
    **{n: f"torchseq.quantise.{n}" for n in (
        "factor_power_of_two", "factor_rows", "integer_weights", "power_of_two_scale",
        "round_rows")},
    **{n: f"torchseq.preprocess.{n}" for n in (
        "block_order", "in_order_sum", "quantise_input", "zscore_blocks", "zscore_pixel_major")},
})

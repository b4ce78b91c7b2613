"""Neural SeqSLAM: a rate-coded network of ``nn.Module`` s whose memory is bounded."""

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


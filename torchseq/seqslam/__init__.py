"""Classic SeqSLAM, tensorised, with OpenSeqSLAM parity (see docs/seqslam.md)."""

from torchseq.seqslam.config import SeqSLAMConfig
from torchseq.seqslam.difference import difference_matrix
from torchseq.seqslam.engine import SeqSLAM, SeqSLAMResult
from torchseq.seqslam.enhance import enhance_contrast
from torchseq.seqslam.search import search, trajectory_offsets, velocities
from torchseq.seqslam.streaming import StreamingMatch, StreamingSeqSLAM

__all__ = [
    "SeqSLAM",
    "SeqSLAMConfig",
    "SeqSLAMResult",
    "StreamingMatch",
    "StreamingSeqSLAM",
    "difference_matrix",
    "enhance_contrast",
    "search",
    "trajectory_offsets",
    "velocities",
]

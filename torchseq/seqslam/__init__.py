"""Classic SeqSLAM, tensorised, with OpenSeqSLAM parity (see docs/guide/seqslam.md)."""

from torchseq.seqslam.ann_index import CandidateIndex
from torchseq.seqslam.candidates import CandidateSeqSLAM
from torchseq.seqslam.config import SeqSLAMConfig
from torchseq.seqslam.difference import difference_matrix
from torchseq.seqslam.engine import SeqSLAM
from torchseq.seqslam.enhance import enhance_contrast
from torchseq.seqslam.result import SeqSLAMResult
from torchseq.seqslam.search import search, trajectory_offsets, velocities
from torchseq.seqslam.single import SingleFrameResult, single_frame
from torchseq.seqslam.streaming import StreamingMatch, StreamingSeqSLAM, StreamingState

__all__ = [
    "CandidateIndex",
    "CandidateSeqSLAM",
    "SeqSLAM",
    "SeqSLAMConfig",
    "SeqSLAMResult",
    "StreamingMatch",
    "StreamingSeqSLAM",
    "StreamingState",
    "difference_matrix",
    "enhance_contrast",
    "search",
    "trajectory_offsets",
    "velocities",
    "SingleFrameResult",
    "single_frame",
]

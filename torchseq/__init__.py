"""torchseq: sequence-based visual place recognition for ordinary and event cameras."""

from torchseq import metrics, preprocess
from torchseq.datasets import PlaceDataset, open_dataset
from torchseq.demo import DemoRoute, make_demo
from torchseq.descriptors import load_descriptors
from torchseq.events import (
    EventFormatError,
    EventStream,
    accumulate,
    frames_to_events,
    load_event_frames,
    read_events,
    write_aedat2,
    write_npz,
)
from torchseq.ground_truth import alignment_ground_truth, load_ground_truth
from torchseq.matches import Matches
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.preprocess import patch_normalise, resize, to_grey
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig, StreamingSeqSLAM
from torchseq.sources import EventFrameOptions, TraverseError, load_traverse

__version__ = "0.1.0"


__all__ = [
    "DemoRoute",
    "EventFormatError",
    "EventFrameOptions",
    "EventStream",
    "Matches",
    "NeuralConfig",
    "NeuralSeqSLAM",
    "SeqSLAM",
    "SeqSLAMConfig",
    "StreamingSeqSLAM",
    "TraverseError",
    "accumulate",
    "alignment_ground_truth",
    "frames_to_events",
    "load_event_frames",
    "load_ground_truth",
    "load_traverse",
    "make_demo",
    "metrics",
    "patch_normalise",
    "preprocess",
    "read_events",
    "resize",
    "to_grey",
    "write_aedat2",
    "write_npz",
    "PlaceDataset",
    "load_descriptors",
    "open_dataset",
]

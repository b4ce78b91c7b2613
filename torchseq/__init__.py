"""torchseq: sequence-based visual place recognition for ordinary and event cameras."""

from torchseq import metrics
from torchseq.demo import DemoRoute, make_demo
from torchseq.ground_truth import alignment_ground_truth, load_ground_truth
from torchseq.matches import Matches
from torchseq.preprocess import patch_normalise, preprocess, resize, to_grey
from torchseq.sources import EventFrameOptions, TraverseError, load_traverse

__version__ = "0.1.0"

__all__ = [
    "DemoRoute",
    "EventFrameOptions",
    "Matches",
    "TraverseError",
    "alignment_ground_truth",
    "load_ground_truth",
    "load_traverse",
    "make_demo",
    "metrics",
    "patch_normalise",
    "preprocess",
    "resize",
    "to_grey",
]

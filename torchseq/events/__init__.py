"""Event cameras: read and write event files, accumulate frames, simulate events from video.

Events are a structured NumPy array ``(t int64 us, x int16, y int16, p uint8)`` with the
sensor size ``(W, H)``: an :class:`EventStream`. See ``docs/guide/events.md``.
"""

from torchseq.events.aedat2 import iter_aedat2, write_aedat2
from torchseq.events.aedat4 import iter_aedat4, write_aedat4
from torchseq.events.filters import hot_pixel_mask, refractory_mask
from torchseq.events.frames import accumulate, window_origin
from torchseq.events.hdf5 import iter_hdf5, read_hdf5_positions, write_hdf5
from torchseq.events.io import detect_format, iter_events, read_events
from torchseq.events.parquet import iter_parquet, write_parquet
from torchseq.events.plain import read_csv, read_npz, write_npz
from torchseq.events.positions import (
    geodetic_to_ecef,
    ground_truth_within,
    positions_at,
    window_times,
)
from torchseq.events.prophesee import iter_raw, write_evt3
from torchseq.events.runs import EventRun, simulate_run
from torchseq.events.simulator import frames_to_events
from torchseq.events.stream import (
    EVENT_DTYPE,
    EventFormatError,
    EventStream,
    as_event_array,
    make_events,
)
from torchseq.events.traverse import load_event_frames

__all__ = [
    "EventRun",
    "frames_to_events",
    "simulate_run",
    "EVENT_DTYPE",
    "EventFormatError",
    "EventStream",
    "accumulate",
    "as_event_array",
    "detect_format",
    "hot_pixel_mask",
    "iter_aedat2",
    "iter_aedat4",
    "iter_events",
    "iter_raw",
    "load_event_frames",
    "make_events",
    "read_csv",
    "read_events",
    "read_npz",
    "refractory_mask",
    "write_aedat2",
    "write_aedat4",
    "write_evt3",
    "write_npz",
    "iter_hdf5",
    "read_hdf5_positions",
    "write_hdf5",
    "iter_parquet",
    "write_parquet",
    "window_origin",
    "window_times",
    "positions_at",
    "geodetic_to_ecef",
    "ground_truth_within",
]

"""Write tests/data/map_v1 (reference map format version 1) and its expected values.

Run once from the repository root: ``python tests/data/make_map_v1.py``. The files are kept
so that later torchseq versions are tested to still read format version 1.
"""

from pathlib import Path

import numpy as np
import torch

from torchseq.maps import build_map
from torchseq.seqslam import SeqSLAMConfig

HERE = Path(__file__).parent

if __name__ == "__main__":
    rng = np.random.default_rng(2024)
    ref = torch.tensor(127 + np.round(rng.normal(0, 3, (30, 8))), dtype=torch.float32)
    m = build_map(ref, HERE / "map_v1", SeqSLAMConfig(image_size=(8, 16), patch_size=4),
                  shard_size=12, index="flat",
                  record={"source": "synthetic (tests/data/make_map_v1.py)", "n_frames": 30,
                          "frame_size": [8, 16]}, overwrite=True)
    np.savez(HERE / "map_v1_expected.npz", descriptors=ref.numpy(),
             top3=m.index().search(ref[:5], 3).numpy())

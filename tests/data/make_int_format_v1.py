"""Make the released integer-format file ``int_format_v1.tsq`` and its expected outputs.

Run once when format version 1 was released (``python tests/data/make_int_format_v1.py``);
the files are kept, never regenerated, so that a reader change that breaks old files fails
``tests/test_export_released.py``.
"""

from pathlib import Path

import numpy as np
import torch

from torchseq.demo import make_demo
from torchseq.export.int_format import write_integer_model
from torchseq.export.int_model import choose_pool, device_frames, integer_model
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.neural import NeuralConfig, NeuralSeqSLAM

HERE = Path(__file__).resolve().parent

if __name__ == "__main__":
    demo = make_demo(n_reference=40, size=(48, 64), seed=7)
    torch.manual_seed(0)
    model = NeuralSeqSLAM(NeuralConfig(hidden=256, n_output=20))
    model.fit(demo.reference, log=False)
    pool = choose_pool(tuple(demo.query.shape[1:]), model.config.input_size)
    im = integer_model(model, pool)
    write_integer_model(HERE / "int_format_v1.tsq", im)
    frames = device_frames(demo.query[:24], model.config.input_size, pool)
    ref, conf, act = IntegerRuntime(im).run(frames)
    np.savez_compressed(HERE / "int_format_v1_expected.npz", frames=frames, reference=ref,
                        confidence=conf, activity=act)
    print(f"wrote {HERE / 'int_format_v1.tsq'} and the expected outputs of {len(frames)} steps")

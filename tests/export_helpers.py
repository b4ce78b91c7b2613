"""Shared small models for the export tests (cached: fitted once per test session)."""

from functools import lru_cache

import torch
from conftest import coarse_units_expected

from torchseq.demo import make_demo
from torchseq.export.int_model import choose_pool, device_frames, integer_model
from torchseq.neural import NeuralConfig, NeuralSeqSLAM

SMALL = {"hidden": 512, "n_output": 40}


@lru_cache(maxsize=None)
def small_setup(seed: int = 1, hidden: int = 1024, n_output: int = 40, n_reference: int = 60,
                readout: str = "centre"):
    """A small model fitted on a small demo route, its integer model and uint8 device frames."""
    demo = make_demo(n_reference=n_reference, size=(48, 64), seed=seed)
    torch.manual_seed(0)
    model = NeuralSeqSLAM(NeuralConfig(
        unit_search="off", hidden=hidden, n_output=n_output, readout=readout))
    with coarse_units_expected():  # a small model: units of several frames
        model.fit(demo.reference, log=False)
    pool = choose_pool(tuple(demo.query.shape[1:]), model.config.input_size)
    frames = device_frames(demo.query, model.config.input_size, pool)
    return model, demo, pool, frames, integer_model(model, pool)

"""Recognition quality floors (default config), measured with experiments/neural_quality.py.

Over 8 model seeds the corridor gives 0.866 recall@1 on average, 0.811 for the worst seed
(density_out 1.0; with Table 1's 0.2 mask: 0.796, worst 0.676)."""

import numpy as np
import pytest
from conftest import shared_data

from torchseq.demo import make_demo
from torchseq.metrics import evaluate
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.sources import load_traverse


@pytest.mark.slow
def test_demo_recall_default_config():
    d = make_demo()
    model = NeuralSeqSLAM()
    model.fit(d.reference, log=False)
    m = evaluate(model.run(d.query).matches, d.ground_truth)
    assert m["recall_at_1"] >= 0.99  # measured 1.000 (0.996 with the 20% L2->L3 mask)


@pytest.mark.slow
def test_corridor_recall_default_config(corridor):
    ref, query, gt = corridor.ref, corridor.query, corridor.ground_truth
    model = NeuralSeqSLAM()
    model.fit(ref, log=False)
    m = evaluate(model.run(query).matches, gt)
    assert m["recall_at_1"] >= 0.78  # measured 0.811 (20% mask: 0.838; the seed: about 80%)
    assert m["auc"] >= 0.72  # measured 0.777 (20% mask: 0.798)


@pytest.mark.slow
def test_corridor_every_seed_at_least_080(corridor):
    """Issue 15: no model seed below 0.80 on the corridor (the L2 -> L3 mask draws were the
    spread: with density_out 0.2 the worst of these 8 seeds gives 0.676)."""
    ref, query, gt = corridor.ref, corridor.query, corridor.ground_truth
    recalls = []
    for seed in range(8):
        model = NeuralSeqSLAM(NeuralConfig(seed=seed))
        model.fit(ref, log=False)
        recalls.append(evaluate(model.run(query).matches, gt)["recall_at_1"])
    assert min(recalls) >= 0.80, recalls  # measured worst 0.811, mean 0.866


@pytest.mark.slow
def test_lens_within_two_frames():
    root = shared_data("lens-davis128")
    ref = load_traverse(root / "example-reference", progress=False)
    query = load_traverse(root / "example-query", progress=False)
    model = NeuralSeqSLAM()
    model.fit(ref, log=False)
    got = model.run(query).matches.reference.numpy()
    near = np.abs(got - np.arange(len(query))) <= 2  # the file's ground truth is the identity
    assert near.mean() >= 0.78  # measured 0.85 (20% mask: 0.83)

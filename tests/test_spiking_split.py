"""experiments/spiking_split.py: its stage-by-stage split ends at the two models it splits.

The split (docs/results/nir.md, "Where the disagreement comes from") recomputes the pipeline
with each stage as the spiking or as the rate model has it; its claims hold only if the
all-spiking variant is the spiking model and the all-exact variant the rate model, frame for
frame. Checked here on the tiny route of tests/spiking_helpers.py.
"""

import numpy as np
import pytest
from conftest import load_script


@pytest.fixture(scope="module")
def split():
    return load_script("experiments/spiking_split.py")


def test_spiking_end_is_the_spiking_model(split, tiny_runs):
    model, sp, xr, xq, _rate, spiking = tiny_runs
    refs, fired = split.simulate(model, xr, xq, sp.calibration["theta2"], "fixed:fixed:ring:K6")
    np.testing.assert_array_equal(refs, spiking["reference"].numpy())
    np.testing.assert_array_equal(fired, spiking["l2_spikes"].numpy())


def test_exact_end_is_the_rate_model(split, tiny_runs):
    model, sp, xr, xq, rate, _spiking = tiny_runs
    refs, fired = split.simulate(model, xr, xq, sp.calibration["theta2"], split.RATE)
    np.testing.assert_array_equal(refs, rate)
    assert (fired == model.config.k).all()  # the exact k-WTA keeps k units every frame


def test_linear_threshold_folds_into_w1(split, tiny_runs):
    # the linear rule fires where x @ w1.T > b + x @ c: fitted on the reference midpoints, it
    # keeps about k units there (a rule folded wrongly fires none or all)
    model, sp, xr, xq, _rate, _spiking = tiny_runs
    code = split.l2_rule("linear0.001", xr, model.l1.folded_weight().double(), model.config.k,
                         sp.calibration["theta2"])
    fired = code(xr).sum(1).numpy()
    assert abs(float(np.median(fired)) - model.config.k) <= 0.1 * model.config.k

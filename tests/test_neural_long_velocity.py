"""Units of several frames: the learnt shift does not depend on the kernel (docs/results/neural.md,
"Units of several frames" and the adaptive rows of the long-route table).

When every unit holds at least two frames, the default kernel (lags 0/1/2, stay 0.5, spread
decay 0.5) and ``NeuralConfig.adaptive_velocity()``'s narrow kernel (lag 1 only, no stay)
learn the same shift: unit ``u`` of ``n_u`` frames keeps ``(n_u - 1) / n_u`` of its
activity and takes ``1 / n_u`` from unit ``u - 1``. Reference: that formula, by a plain loop
over the units. With units of one frame the kernels differ (the claim's boundary).
"""

import numpy as np
import pytest

from torchseq.layers.functional import learn_shift_matrix
from torchseq.neural import NeuralConfig
from torchseq.neural.learning import recruit_units


def _kernel(cfg: NeuralConfig) -> tuple:
    return cfg.ring_spread, cfg.ring_spread_decay, cfg.ring_stay


def _plain_shift(lengths: list[int]) -> np.ndarray:
    n = len(lengths)
    w = np.zeros((n, n))
    for u, length in enumerate(lengths):
        if u == 0:
            w[0, 0] = 1.0  # no unit before the first: all its input is its own
            continue
        w[u, u] = (length - 1) / length
        w[u, u - 1] = 1.0 / length
    return w


@pytest.mark.parametrize("frames,units", [(3000, 555), (111, 37), (111, 55), (600, 300),
                                          (6000, 2500)])
def test_kernels_learn_the_same_shift_on_units_of_several_frames(frames, units):
    unit_of_frame, spans = recruit_units(frames, units)
    lengths = (spans[:, 1] - spans[:, 0]).tolist()
    assert min(lengths) >= 2
    default = learn_shift_matrix(unit_of_frame, units, *_kernel(NeuralConfig()))
    narrow = learn_shift_matrix(unit_of_frame, units,
                                *_kernel(NeuralConfig.adaptive_velocity()))
    want = _plain_shift(lengths)
    np.testing.assert_allclose(default.numpy(), want, atol=1e-6)
    np.testing.assert_allclose(narrow.numpy(), want, atol=1e-6)


def test_kernels_differ_where_a_unit_holds_one_frame():
    unit_of_frame, spans = recruit_units(100, 55)
    assert int((spans[:, 1] - spans[:, 0]).min()) == 1
    default = learn_shift_matrix(unit_of_frame, 55, *_kernel(NeuralConfig()))
    narrow = learn_shift_matrix(unit_of_frame, 55, *_kernel(NeuralConfig.adaptive_velocity()))
    assert float((default - narrow).abs().max()) > 0.1

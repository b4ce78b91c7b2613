"""The interpolating readout (issue 15, long routes): the place within the winner's stretch.

The oracle is a plain loop written here from docs/guide/neural.md ("Step maths", step 8b), in
Python floats; the floors are on the demo route with units of several frames.
"""

import math
import warnings

import numpy as np
import pytest
import torch

from torchseq.demo import make_demo
from torchseq.export.int_model import integer_model
from torchseq.metrics import evaluate
from torchseq.neural import NeuralConfig, NeuralError, NeuralSeqSLAM
from torchseq.neural.readout import decide


def within_unit_loop(row, spans):
    """Reference frame of one activity row: parabola vertex through the winner's neighbours."""
    n = len(row)
    u = max(range(n), key=lambda i: (row[i], -i))  # largest, first index on ties
    x = 0.0
    if 0 < u < n - 1:
        den = row[u - 1] - 2.0 * row[u] + row[u + 1]
        if den < 0:
            x = (row[u - 1] - row[u + 1]) / (2.0 * den)
    first, last = spans[u]
    pos = math.floor((first + last - 1) / 2.0 + x * (last - first) + 0.5)
    return min(max(pos, first), last - 1)


def random_spans(n_units, seed, longest=7):
    rng = np.random.default_rng(seed)
    lengths = rng.integers(1, longest + 1, n_units)
    first = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    return torch.from_numpy(np.stack([first, first + lengths], 1).astype(np.int64))


@pytest.mark.parametrize("kernel", ["torch", "numpy"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_within_unit_readout_equals_loop(kernel, seed):
    g = torch.Generator().manual_seed(seed)
    n = 23
    a = torch.rand(64, n, generator=g)
    a[0] = 0.0  # flat: no vertex (x = 0)
    a[1, 0] = 5.0  # winner at the first unit
    a[2, -1] = 5.0  # and at the last
    a[3, 4] = a[3, 5] = 5.0  # tie with the right neighbour: x = +1/2
    a[4, 6] = a[4, 5] = 5.0  # tie on the left: the first index wins, x = +1/2
    spans = random_spans(n, seed)
    centre = (spans[:, 0] + spans[:, 1] - 1) // 2
    got, conf = decide(a, centre, 3, kernel, spans=spans)
    want = [within_unit_loop(row, spans.tolist()) for row in a.tolist()]
    assert got.tolist() == want
    assert got.dtype == torch.int64
    _, plain_conf = decide(a, centre, 3, kernel)
    assert torch.equal(conf, plain_conf)  # the confidence does not change
    # the loop is not trivially the centre: positions move inside multi-frame units
    assert sum(w != c for w, c in zip(want, centre[a.argmax(1)].tolist())) > 10


@pytest.mark.parametrize("kernel", ["torch", "numpy"])
def test_units_of_one_frame_report_that_frame(kernel):
    g = torch.Generator().manual_seed(5)
    a = torch.rand(50, 30, generator=g)
    spans = torch.stack([torch.arange(30), torch.arange(1, 31)], 1)
    got, _ = decide(a, spans[:, 0], 2, kernel, spans=spans)
    assert torch.equal(got, a.argmax(1))


def _recall(readout, n_output, seed=0):
    d = make_demo()
    model = NeuralSeqSLAM(NeuralConfig(
        unit_search="off", n_output=n_output, readout=readout, seed=seed))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(d.reference, log=False)
    result = model.run(d.query)
    return model, d, evaluate(result.matches, d.ground_truth)["recall_at_1"], result


@pytest.mark.slow
def test_interpolating_readout_recovers_resolution_of_coarse_units():
    # 200 reference frames on 40 units (5 frames each), seed 0: measured 0.835 with the
    # centre readout, 0.988 within units (8 seeds, 37 units: 0.774 and 0.973)
    _, _, centre, _ = _recall("centre", 40)
    model, d, within, result = _recall("interpolate", 40)
    assert within >= 0.95 and within - centre >= 0.1, (centre, within)
    # one definition: the streaming step (eager and the inference module) makes run's decisions
    state, eager = None, []
    for t in range(40):
        out, state = model.step(d.query[t:t + 1], state)
        eager.append(int(out.reference[0]))
    assert eager == result.matches.reference[:40].tolist()
    inf = model.inference()
    state, fast = None, []
    for t in range(40):
        out, state = inf.step(d.query[t:t + 1], state)
        fast.append(int(out.reference[0]))
    assert fast == eager


def test_readout_setting_is_checked_and_old_checkpoints_read_centre():
    with pytest.raises(NeuralError, match="readout must be one of 'centre', 'interpolate'"):
        NeuralConfig(unit_search="off", readout="middle").validate()
    d = NeuralConfig(unit_search="off").to_dict()
    del d["readout"]  # a checkpoint written before the field existed
    assert NeuralConfig.from_dict(d).readout == "centre"


def test_fit_warns_when_units_hold_several_frames():
    ref = make_demo(n_reference=60, size=(24, 32), step=4.0).reference
    with pytest.warns(UserWarning, match="3.0 frames per unit.*readout='interpolate'"):
        NeuralSeqSLAM(NeuralConfig(unit_search="off", hidden=256, n_output=20)).fit(ref, log=False)
    with pytest.warns(UserWarning, match="12.0 frames per unit.*raise n_output"):
        NeuralSeqSLAM(NeuralConfig(
            unit_search="off", hidden=256, n_output=5, readout="interpolate")).fit(ref)
    with warnings.catch_warnings():  # no coarse-unit warning (the self-check has its tests)
        warnings.simplefilter("error")
        NeuralSeqSLAM(NeuralConfig(
            unit_search="off", hidden=256, n_output=60)).fit(ref, log=False, check=False)
        NeuralSeqSLAM(NeuralConfig(
            unit_search="off", hidden=256, n_output=20, readout="interpolate")).fit(
            ref, check=False)


def test_integer_export_holds_the_interpolating_readout():
    ref = make_demo(n_reference=60, size=(24, 32), step=4.0).reference
    coarse = NeuralSeqSLAM(NeuralConfig(
        unit_search="off", hidden=256, n_output=20, readout="interpolate"))
    coarse.fit(ref, log=False)
    # format version 2 (tests/test_export_int_readout.py checks it against the float rule)
    assert integer_model(coarse).params["readout"] == 1
    fine = NeuralSeqSLAM(NeuralConfig(
        unit_search="off", hidden=256, n_output=60, readout="interpolate"))
    fine.fit(ref, log=False)
    integer_model(fine)  # units of one frame: the same decisions as the centre readout


@pytest.mark.parametrize("batch", [1, 3])
def test_float_onnx_follows_the_interpolating_readout(batch):
    from torchseq.export.onnx_float import build_float_onnx
    from torchseq.export.sessions import session
    from torchseq.preprocess import resize

    d = make_demo(n_reference=60, size=(24, 32), step=4.0)
    model = NeuralSeqSLAM(NeuralConfig(
        unit_search="off", hidden=256, n_output=20, readout="interpolate"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(d.reference, log=False)
    sess = session(build_float_onnx(model))
    small = resize(d.query, model.config.input_size)
    state, state_pt = np.zeros((batch, model.n_units), np.float32), None
    refs, want, units = [], [], []
    for t in range(0, 60, batch):
        act, state, ref, _ = sess.run(None, {"frames": small[t:t + batch].numpy(),
                                             "state": state})
        out, state_pt = model.step(small[t:t + batch], state_pt)  # the eager definition
        refs.append(ref)
        want.append(out.reference.numpy())
        units.append(act.argmax(1))
    refs, want, units = np.concatenate(refs), np.concatenate(want), np.concatenate(units)
    assert np.array_equal(refs, want)
    spans = model.unit_to_reference.numpy()
    assert (refs != (spans[units, 0] + spans[units, 1] - 1) // 2).sum() > 5  # not the centres

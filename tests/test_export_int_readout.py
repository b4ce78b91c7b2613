"""The integer interpolating read-out (format version 2): its exact rule against the float
definition and the plain-Python oracle, and every integer form bit-exact with the others."""

import json
import struct
import zlib
from fractions import Fraction

import numpy as np
import pytest
import torch
from export_helpers import small_setup
from int_oracle import oracle_step, oracle_within_unit

from torchseq.export.int_format import (
    READOUT_INTERPOLATE,
    IntegerFormatError,
    IntegerModel,
    decode,
    encode,
)
from torchseq.export.int_functional import within_unit as within_unit_torch
from torchseq.export.int_kernels import within_unit as within_unit_numpy
from torchseq.export.int_onnx import build_integer_onnx
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.export.int_stream import StreamRuntime
from torchseq.export.sessions import run_integer_onnx, session
from torchseq.neural.readout import _within_unit_numpy as float_within_unit

INT32_MAX = 2**31 - 1


def _cases(rng, b, n, top, span_max):
    """``b`` int32 activity rows over ``n`` units with values in ``-top..top``, their
    first-index winners, and contiguous spans of 1..span_max frames."""
    act = rng.integers(-top, top + 1, size=(b, n), dtype=np.int64).astype(np.int32)
    # neighbours equal to the winner (ties), flat rows and winners at the ring's ends
    act[: b // 8, 1::2] = act[: b // 8, ::2][:, : act[:, 1::2].shape[1]]
    act[b // 8: b // 6] = act[b // 8: b // 6, :1]
    lengths = rng.integers(1, span_max + 1, size=n)
    first = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    spans = np.stack([first, first + lengths], 1).astype(np.int64)
    return act, act.argmax(1), spans


def _exact(act, unit, spans):
    """The oracle's reference, the exact rational value whose floor it is, and whether the
    float read-out's parabola term is 0 (then its float64 value is exact too)."""
    refs, values, flat = [], [], []
    for row, u in zip(act.tolist(), unit.tolist()):
        f, last = (int(v) for v in spans[u])
        refs.append(oracle_within_unit(row, u, f, last))
        x = Fraction(0)
        if 0 < u < len(row) - 1 and row[u - 1] - 2 * row[u] + row[u + 1] < 0:
            x = Fraction(row[u - 1] - row[u + 1], 2 * (row[u - 1] - 2 * row[u] + row[u + 1]))
        values.append(Fraction(f + last - 1, 2) + x * (last - f) + Fraction(1, 2))
        flat.append(x == 0)
    return np.array(refs), values, np.array(flat)


@pytest.mark.parametrize("top,span_max", [(50, 4), (2**16, 40), (INT32_MAX, 3000)])
def test_integer_readout_equals_the_oracle_and_the_float_definition(top, span_max):
    rng = np.random.default_rng(top)
    act, unit, spans = _cases(rng, 3000, 7, top, span_max)
    refs, values, flat = _exact(act, unit, spans)
    got = within_unit_numpy(act, unit, spans)
    assert got.dtype == np.int64
    assert np.array_equal(got, refs)  # exact, boundaries included
    eager = within_unit_torch(torch.from_numpy(act), torch.from_numpy(unit),
                              torch.from_numpy(spans))
    assert np.array_equal(eager.numpy(), refs)
    # the float kernel agrees wherever its float64 value is not within rounding of an
    # integer (where its floor may go either way); with no parabola term it is exact
    flt = float_within_unit(act.astype(np.float64), unit, spans)
    near = np.array([abs(v - round(v)) <= 2**-40 * (abs(v) + 1) for v in values]) & ~flat
    assert np.array_equal(flt[~near], got[~near])
    assert near.mean() < 0.1 and (~flat).mean() > 0.5  # most cases interpolate
    assert (got != spans[unit, 0] + (spans[unit, 1] - spans[unit, 0]) // 2).mean() > 0.2


def test_exact_half_boundaries_and_extremes():
    # am, a0, ap with x = 1/6 on a span of 3: the exact value f + 2 lies on a floor boundary
    # (0.5 as 3 * float(1/6)); the integer rule says f + 2, as the exact fraction does
    rows = [[0, 2, 1], [1, 2, 0], [0, 4, 1], [5, 7, 7], [7, 7, 5], [-INT32_MAX, INT32_MAX, 0],
            [INT32_MAX - 1, INT32_MAX, -INT32_MAX], [3, 3, 3], [9, 1, 0], [0, 1, 9]]
    act = np.array(rows, np.int32)
    unit = act.argmax(1)
    for spans in ([[0, 5], [5, 8], [8, 20]], [[0, 1], [1, 2**31 - 1], [2**31 - 1 - 0, 2**31 - 1]]):
        spans = np.array(spans, np.int64)
        if (spans[:, 1] <= spans[:, 0]).any():  # the last test span is empty: drop the unit
            act_, unit_ = act[unit == 1], unit[unit == 1]
        else:
            act_, unit_ = act, unit
        refs, _, _ = _exact(act_, unit_, spans)
        assert np.array_equal(within_unit_numpy(act_, unit_, spans), refs)
        assert np.array_equal(within_unit_torch(torch.from_numpy(act_), torch.from_numpy(unit_),
                                                torch.from_numpy(spans)).numpy(), refs)
    assert oracle_within_unit([0, 2, 1], 1, 5, 8) == 7


@pytest.fixture(scope="module")
def interp():
    model, demo, pool, frames, im = small_setup(hidden=512, n_output=20, n_reference=60,
                                                readout="interpolate")
    return model, frames, im


def test_the_model_is_written_as_version_2(interp):
    _, _, im = interp
    assert im.format_version == 2 and im.params["readout"] == READOUT_INTERPOLATE
    data = encode(im)
    assert struct.unpack_from("<I", data, 8)[0] == 2
    back = decode(data)
    assert back.params == im.params and encode(back) == data
    d = im.to_dict()
    assert d["format_version"] == 2 and d["params"]["readout"] == 1
    assert IntegerModel.from_dict(d).params == im.params
    # a version-1 header over version-2 params is refused (the params section's length)
    bad = bytearray(data)
    bad[8:12] = struct.pack("<I", 1)
    bad[24:28] = struct.pack("<I", zlib.crc32(bytes(bad[:24])))
    bad[-4:] = struct.pack("<I", zlib.crc32(bytes(bad[:-4])))
    with pytest.raises(IntegerFormatError, match="params section"):
        decode(bytes(bad))
    with pytest.raises(IntegerFormatError, match="readout 2 not in 0..1"):
        IntegerModel.from_params(dict(d["params"], readout=2), d["arrays"])


def test_every_integer_form_agrees_and_follows_the_oracle(interp):
    model, frames, im = interp
    ref, conf, act = IntegerRuntime(im).run(frames)
    for other in (IntegerRuntime(im, kernel="torch").run(frames), StreamRuntime(im).run(frames),
                  run_integer_onnx(session(build_integer_onnx(im)), frames)):
        assert all(np.array_equal(x, y) for x, y in zip((ref, conf, act), other))
    state = [0] * im.params["n_units"]
    for t in range(4):
        state, r, c = oracle_step(im, frames[t].tolist(), state)
        assert (act[t].tolist(), r, c) == (act[t].tolist(), int(ref[t]), int(conf[t]))
        assert state == act[t].tolist()
    # the read-out moves within units: not every reference is its winner's centre
    centre = im.arrays["unit_centre"][act.argmax(1)]
    assert (ref != centre).mean() > 0.2
    # and the float model's decisions on the same uint8 frames agree (its own interpolation)
    ref_float = model.run(torch.from_numpy(frames).float()).matches.reference.numpy()
    assert np.mean(ref == ref_float) >= 0.95  # measured 73 of 74 (one frame off by one)


def test_checkpoint_export_of_an_interpolating_model_passes(interp, tmp_path):
    from torchseq.export import export_checkpoint
    from torchseq.export.int_format import read_integer_model

    model, frames, _ = interp
    model.save(tmp_path / "m.pt")
    out = tmp_path / "export"
    assert export_checkpoint(tmp_path / "m.pt", out, query=frames[:30])
    report = json.loads((out / "validation.json").read_text())
    assert report["integer_onnx_bit_exact"] is True and report["integer_agreement"] >= 0.95
    assert "no spiking (NIR) form" in report["nir"]["skipped"]  # reported, not silently absent
    assert not (out / "model.nir").exists()
    stored = read_integer_model(out / "model_int.tsq")
    assert stored.format_version == 2 and stored.params["readout"] == READOUT_INTERPOLATE

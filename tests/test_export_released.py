"""Released integer files must keep loading and reproducing their stored outputs exactly.

``tests/data/int_format_v1.tsq`` was written by format version 1 (see
``tests/data/make_int_format_v1.py``) together with 24 uint8 input frames and the exact
outputs of the NumPy runtime at that time. A change of the reader or of the integer
arithmetic that breaks old files fails here.
"""

from pathlib import Path

import numpy as np
import pytest

from torchseq.export.int_format import FORMAT_VERSION, read_integer_model
from torchseq.export.int_onnx import build_integer_onnx
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.export.sessions import run_integer_onnx, session

DATA = Path(__file__).resolve().parent / "data"


@pytest.fixture(scope="module")
def released():
    path = DATA / "int_format_v1.tsq"
    expected = np.load(DATA / "int_format_v1_expected.npz")
    return read_integer_model(path), {k: expected[k] for k in expected.files}


def test_v1_file_loads(released):
    model, _ = released
    head = (DATA / "int_format_v1.tsq").read_bytes()[:12]  # magic (8 bytes), version (u32)
    assert int.from_bytes(head[8:12], "little") == 1 <= FORMAT_VERSION  # a v1 file, still read
    assert model.params["n_units"] == 20 and model.params["hidden"] == 256
    assert model.arrays["l1.values"].dtype == np.int16


def test_v1_file_reproduces_the_stored_outputs_numpy(released):
    model, exp = released
    ref, conf, act = IntegerRuntime(model).run(exp["frames"])
    assert np.array_equal(act, exp["activity"])
    assert np.array_equal(ref, exp["reference"])
    assert np.array_equal(conf, exp["confidence"])


def test_v1_file_reproduces_the_stored_outputs_onnx(released):
    model, exp = released
    ref, conf, act = run_integer_onnx(session(build_integer_onnx(model)), exp["frames"])
    assert np.array_equal(act, exp["activity"])
    assert np.array_equal(ref, exp["reference"])
    assert np.array_equal(conf, exp["confidence"])


def test_v1_file_reproduces_the_stored_outputs_stream_runtime(released):
    from torchseq.export.int_stream import StreamRuntime

    model, exp = released
    ref, conf, act = StreamRuntime(model, chunk=7).run(exp["frames"])
    assert np.array_equal(act, exp["activity"])
    assert np.array_equal(ref, exp["reference"])
    assert np.array_equal(conf, exp["confidence"])

"""Public names of torchseq.export (fails when one disappears) and integer-only runtime state."""

import numpy as np
from export_helpers import small_setup

import torchseq.export as export
from torchseq.export.int_runtime import IntegerRuntime

PUBLIC = ["FORMAT_VERSION", "ExportError", "IntegerFormatError", "IntegerInputError",
          "IntegerModel", "IntegerRuntime", "IntegerStep", "Quantised", "StreamRuntime",
          "StreamingStep", "build_float_onnx", "build_integer_onnx", "choose_pool", "dequantise",
          "device_frames", "export_checkpoint", "export_float_onnx", "fixed_point",
          "integer_model", "quantise", "read_integer_model", "write_integer_model"]


def test_public_names():
    for name in PUBLIC:
        assert hasattr(export, name), name
    assert sorted(export.__all__) == sorted(PUBLIC)
    assert issubclass(export.IntegerFormatError, ValueError)
    assert issubclass(export.IntegerInputError, ValueError)
    assert issubclass(export.ExportError, ValueError)


def test_runtime_holds_only_integers():
    *_, frames, im = small_setup()
    rt = IntegerRuntime(im)
    arrays = {k: v for k, v in vars(rt).items() if isinstance(v, np.ndarray)}
    assert arrays and all(np.issubdtype(v.dtype, np.integer) for v in arrays.values())
    out, state = rt.step(frames[:2])
    assert all(np.issubdtype(np.asarray(v).dtype, np.integer) for v in (*out, state))

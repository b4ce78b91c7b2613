"""Deployment export of Neural SeqSLAM: float ONNX, quantised ONNX, integer file and graph.

See ``docs/guide/export.md`` (how to use it; measured agreement and speed in
``docs/results/export.md``), ``docs/reference/integer_format.md`` (the integer file and its
arithmetic) and ``docs/guide/nir.md`` (the spiking model as a NIR graph:
``torchseq.export.nir_export``).
"""

from torchseq.export.checkpoint import export_checkpoint
from torchseq.export.errors import ExportError
from torchseq.export.int_format import (
    FORMAT_VERSION,
    IntegerFormatError,
    IntegerModel,
    read_integer_model,
    write_integer_model,
)
from torchseq.export.int_model import choose_pool, device_frames, integer_model
from torchseq.export.int_onnx import build_integer_onnx
from torchseq.export.int_runtime import IntegerRuntime, IntegerStep
from torchseq.export.int_stages import IntegerInputError
from torchseq.export.int_stream import StreamRuntime
from torchseq.export.onnx_float import StreamingStep, build_float_onnx, export_float_onnx
from torchseq.quantise import Quantised, dequantise, fixed_point, quantise

__all__ = [
    "FORMAT_VERSION", "ExportError", "IntegerFormatError", "IntegerInputError", "IntegerModel",
    "IntegerRuntime", "IntegerStep", "Quantised", "StreamRuntime", "StreamingStep",
    "build_float_onnx", "build_integer_onnx", "choose_pool", "dequantise", "device_frames",
    "export_checkpoint", "export_float_onnx", "fixed_point", "integer_model", "quantise",
    "read_integer_model", "write_integer_model",
]

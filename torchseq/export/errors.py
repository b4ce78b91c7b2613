"""The errors of the export package, in their own module so every part can raise them.

:class:`ExportError` (the exporter's bad input) lives here rather than in
:mod:`torchseq.export.checkpoint`, so the float ONNX writer can raise it without importing the
checkpoint exporter (which imports the writer): no two modules import each other. The integer
format's errors (:class:`~torchseq.export.int_stages.IntegerFormatError`,
:class:`~torchseq.export.int_stages.IntegerInputError`) live with the typed stages that
raise them.
"""

from __future__ import annotations


class ExportError(ValueError):
    """Bad input to the exporter (unreadable checkpoint, query or ground truth)."""

"""The exporter's error (its own module: the export steps and the checkpoint exporter raise it)."""


class ExportError(ValueError):
    """Bad input to the exporter (unreadable checkpoint, query or ground truth)."""

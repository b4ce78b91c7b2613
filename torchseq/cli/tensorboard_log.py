"""TensorBoard logs of a run: torch's ``SummaryWriter``, its records checksummed in C.

An event file is a sequence of TFRecords, each framed as ``length`` (uint64) | masked CRC-32C
of those 8 bytes (uint32) | the serialised ``Event`` | masked CRC-32C of the ``Event`` (uint32),
little-endian (``tensorboard/summary/writer/record_writer.py``). TensorBoard computes the
CRC-32C in pure Python (``tensorboard.compat.tensorflow_stub.pywrap_tensorflow.masked_crc32c``,
a byte loop): about 0.15 s of CPU for the 0.8 MB of PNG figures an eval report logs on a
3,576-place route, a quarter of the report.

:func:`summary_writer` returns torch's writer (the same summaries, tags and protobufs) after
:func:`use_kernel` has set the function the record writer calls, the name
``masked_crc32c`` in ``tensorboard.summary.writer.record_writer``: :func:`masked_crc32c` over
google-crc32c's C extension (kernel ``"c"``), or TensorBoard's own (kernel ``"python"``). Both
return the same value for every input (``tests/test_tensorboard_log.py`` compares them, and
reads the files back with TensorBoard's reader, which checks every record with its own
function), so the files are the same bytes either way. The choice is made for the whole
process (any other TensorBoard writer in it gets the same checksums, faster); the kernel is
``"c"`` where google-crc32c's C extension imports (a torchseq dependency), else ``"python"``,
and :func:`kernel_in_use` says which one the record writer calls.
"""

from __future__ import annotations

from pathlib import Path

KERNELS = ("c", "python")


def crc_kernel() -> str:
    """The kernel :func:`summary_writer` picks: ``"c"`` with google-crc32c's C extension.

    Returns:
        ``"c"`` where ``google_crc32c`` imports with its C implementation, else ``"python"``
        (TensorBoard's own byte loop; google-crc32c's pure-Python fallback is no faster).
    """
    try:
        import google_crc32c
    except ImportError:
        return "python"
    return "c" if google_crc32c.implementation == "c" else "python"


def masked_crc32c(data: bytes) -> int:
    """TFRecord's masked CRC-32C of ``data``, by google-crc32c's C extension.

    The CRC-32C (Castagnoli) of ``data``, rotated right by 15 bits plus ``0xa282ead8``
    (mod 2**32), as TensorFlow masks the checksums it stores.

    Args:
        data: the bytes of a record's length field or of its ``Event``.

    Returns:
        The masked checksum, ``0 <= value < 2**32``.
    """
    from google_crc32c import value

    crc = value(bytes(data))
    return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def use_kernel(kernel: str) -> str:
    """Make TensorBoard's record writer checksum with ``kernel`` (``"c"`` or ``"python"``).

    Args:
        kernel: ``"c"`` (:func:`masked_crc32c`) or ``"python"`` (TensorBoard's own).

    Returns:
        ``kernel``.

    Raises:
        ValueError: an unknown kernel, or ``"c"`` without google-crc32c's C extension.
    """
    if kernel not in KERNELS:
        raise ValueError(f"unknown CRC-32C kernel {kernel!r}; expected one of {KERNELS}")
    if kernel == "c" and crc_kernel() != "c":
        raise ValueError("the 'c' CRC-32C kernel needs google-crc32c's C extension "
                         "(pip install google-crc32c)")
    from tensorboard.compat.tensorflow_stub import pywrap_tensorflow
    from tensorboard.summary.writer import record_writer

    record_writer.masked_crc32c = (masked_crc32c if kernel == "c"
                                   else pywrap_tensorflow.masked_crc32c)
    return kernel


def kernel_in_use() -> str:
    """``"c"`` when TensorBoard's record writer calls :func:`masked_crc32c`, else ``"python"``."""
    from tensorboard.summary.writer import record_writer

    return "c" if getattr(record_writer, "masked_crc32c", None) is masked_crc32c else "python"


def summary_writer(log_dir: Path, kernel: str | None = None):
    """A ``SummaryWriter`` (torch's) over ``log_dir``, records checksummed by ``kernel``.

    Args:
        log_dir: the folder of the event files (``OUT/tensorboard``).
        kernel: ``"c"`` or ``"python"``; None: :func:`crc_kernel`.

    Returns:
        A ``torch.utils.tensorboard.SummaryWriter``.
    """
    from torch.utils.tensorboard import SummaryWriter

    use_kernel(crc_kernel() if kernel is None else kernel)
    return SummaryWriter(log_dir=str(log_dir))

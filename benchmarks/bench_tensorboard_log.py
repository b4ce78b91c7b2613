"""Where an eval report's TensorBoard time goes: the writer's import, and the records' CRC-32C.

    .venv/bin/python benchmarks/bench_tensorboard_log.py              # fastest of 5, one thread
    .venv/bin/python benchmarks/bench_tensorboard_log.py --rounds 9

Two parts, as ``torchseq.cli.report.log_tensorboard`` pays them:

- **import**: ``torch.utils.tensorboard`` (and google-crc32c) in a fresh interpreter that has
  already imported ``torchseq.cli.eval`` and ``torchseq.cli.report`` (what an eval process has
  loaded when its report starts), fastest of ``--rounds``.
- **write**: the records of the 3,576-place nordland route's report (its three PNG figures,
  578,155 + 222,489 + 23,126 bytes, as ``Summary.Image`` records, and 40 scalars) through
  ``torchseq.cli.tensorboard_log.summary_writer`` with each CRC-32C kernel, interleaved, in this
  process after both imports, fastest of ``--rounds``; and the masked CRC-32C of those bytes
  alone. PNG bytes are random: a checksum's time does not depend on the content.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PNG_BYTES = (578_155, 222_489, 23_126)  # the report's figures on the 3,576-place route
IMPORT = """
import time
import torchseq.cli.eval, torchseq.cli.report
w, c = time.perf_counter(), time.process_time()
import torch.utils.tensorboard, google_crc32c
print(time.perf_counter() - w, time.process_time() - c)
"""


def import_seconds(rounds: int) -> tuple[float, float]:
    """Fastest (wall, CPU) seconds of the writer's import in a fresh interpreter."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    best = (float("inf"), float("inf"))
    for _ in range(rounds):
        out = subprocess.run([sys.executable, "-c", IMPORT], env=env, capture_output=True,
                             text=True, check=True).stdout.split()
        best = min(best, (float(out[0]), float(out[1])))
    return best


def write_once(kernel: str, images: list[bytes]) -> tuple[float, float]:
    """(wall, CPU) seconds to write the report's records with ``kernel``, closing the file."""
    from tensorboard.compat.proto.summary_pb2 import Summary

    from torchseq.cli.tensorboard_log import summary_writer

    with tempfile.TemporaryDirectory() as tmp:
        w, c = time.perf_counter(), time.process_time()
        with summary_writer(Path(tmp), kernel=kernel) as tb:
            for i in range(40):
                tb.add_scalar(f"seqslam/value_{i}", float(i))
            for i, data in enumerate(images):
                picture = Summary.Image(height=500, width=600, colorspace=3,
                                        encoded_image_string=data)
                tb._get_file_writer().add_summary(
                    Summary(value=[Summary.Value(tag=f"figure_{i}", image=picture)]))
        return time.perf_counter() - w, time.process_time() - c


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    import torch

    torch.set_num_threads(1)
    from tensorboard.compat.tensorflow_stub.pywrap_tensorflow import masked_crc32c as python

    from torchseq.cli.tensorboard_log import crc_kernel, masked_crc32c, use_kernel

    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, n, dtype=np.uint8).tobytes() for n in PNG_BYTES]
    imp = import_seconds(args.rounds)
    writes = {k: (float("inf"), float("inf")) for k in ("python", "c")}
    crc = {k: float("inf") for k in writes}
    for _ in range(args.rounds):
        for kernel, fn in (("python", python), ("c", masked_crc32c)):
            writes[kernel] = min(writes[kernel], write_once(kernel, images))
            c = time.process_time()
            for data in images:
                fn(data)
            crc[kernel] = min(crc[kernel], time.process_time() - c)
    use_kernel(crc_kernel())
    total = sum(PNG_BYTES)
    print(f"{total:,} bytes of PNG records, torch threads {torch.get_num_threads()}, load "
          f"average {os.getloadavg()[0]:.1f}, fastest of {args.rounds}\n")
    print("| part | wall s | CPU s |\n|---|---:|---:|")
    print(f"| import torch.utils.tensorboard (after torchseq.cli.eval) | {imp[0]:.3f} | "
          f"{imp[1]:.3f} |")
    for kernel, (w, c) in writes.items():
        print(f"| write the records, CRC-32C kernel {kernel!r} | {w:.3f} | {c:.3f} |")
    for kernel, c in crc.items():
        print(f"| the CRC-32C of the PNG bytes alone, {kernel!r} | | {c:.4f} |")


if __name__ == "__main__":
    main()

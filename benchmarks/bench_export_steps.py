"""Wall and CPU seconds of each step of ``export_checkpoint``, the NIR steps against the rest.

One command (from the repository root, one thread):

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_export_steps.py CHECKPOINT OUT

``CHECKPOINT`` is a ``torchseq train`` checkpoint (validated on its own reference, as
``train --export`` does). Each step the exporter reports to its progress
(:class:`torchseq.export.progress.ExportProgress`) is timed, wall (``perf_counter``) and CPU
(``process_time``: steadier on a shared host); prints one line per step, then a JSON line
with the totals of the NIR steps and of the rest.
"""

from __future__ import annotations

import json
import sys
import time
from contextlib import contextmanager

import torch

import torchseq.export.progress as progress_module


def main() -> None:
    torch.set_num_threads(1)
    ckpt, out = sys.argv[1], sys.argv[2]
    times: list[tuple[str, float, float]] = []

    class Timed(progress_module.ExportProgress):
        @contextmanager
        def step(self, desc, total=None, unit="frames"):
            t0, c0 = time.perf_counter(), time.process_time()
            yield lambda done: None
            times.append((desc, round(time.perf_counter() - t0, 2),
                          round(time.process_time() - c0, 2)))
            print(f"{desc}: wall {times[-1][1]} s, cpu {times[-1][2]} s", flush=True)

    progress_module.ExportProgress = Timed  # export_checkpoint builds its progress from it
    from torchseq.export.checkpoint import export_checkpoint

    t0, c0 = time.perf_counter(), time.process_time()
    ok = export_checkpoint(ckpt, out, progress=True)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    nir = [t for t in times if t[0].startswith("NIR")]
    nir_wall, nir_cpu = sum(t[1] for t in nir), sum(t[2] for t in nir)
    print(json.dumps({"passed": ok, "wall": round(wall, 2), "cpu": round(cpu, 2),
                      "nir_wall": round(nir_wall, 2), "nir_cpu": round(nir_cpu, 2),
                      "rest_wall": round(wall - nir_wall, 2),
                      "rest_cpu": round(cpu - nir_cpu, 2)}))


if __name__ == "__main__":
    main()

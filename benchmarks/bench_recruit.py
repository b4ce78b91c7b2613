"""Novelty recruitment (``recruit="novelty"``) on long demo routes: the search and its cost.

    .venv/bin/python benchmarks/bench_recruit.py [--lengths 3000,20000]

One thread. Per route (the long-route table's demo: 48x64 frames, 4 px per frame, default
model, seed 0): seconds to compute the route's L2 codes, seconds of the segmentation
(:func:`torchseq.neural.learning.recruit_by_novelty`), the walks over the route the
bisection made, the threshold it kept, the stretches it gave (the rest of the 555 units
come from the fallback cuts), the longest unit, and ``fit`` with each rule side by side.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchseq.demo import make_demo  # noqa: E402
from torchseq.neural import NeuralConfig, NeuralSeqSLAM  # noqa: E402
from torchseq.neural.learning import novelty_search, recruit_by_novelty  # noqa: E402


def winners_of(model: NeuralSeqSLAM, frames: torch.Tensor, chunk: int = 256) -> torch.Tensor:
    """``(T, k)`` indices of each frame's active L2 units."""
    parts = []
    for lo in range(0, len(frames), chunk):
        code = model.code(model.encode(frames[lo:lo + chunk]))
        parts.append(code.nonzero()[:, 1].reshape(code.shape[0], -1).to(torch.int32))
    return torch.cat(parts)


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--lengths", default="3000,20000")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    for n in [int(v) for v in args.lengths.split(",") if v]:
        d = make_demo(n_reference=n, size=(48, 64), step=4.0, dense_ground_truth=False)
        model = NeuralSeqSLAM(NeuralConfig())
        with torch.no_grad():
            t0 = time.perf_counter()
            w = winners_of(model, d.reference).numpy()
            codes_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        _, spans = recruit_by_novelty(w, 555)
        seg_s = time.perf_counter() - t0
        starts, threshold, walks = novelty_search(w, 555)
        fit = {}
        for rule in ("uniform", "novelty"):
            m = NeuralSeqSLAM(NeuralConfig(recruit=rule))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                t0 = time.perf_counter()
                m.fit(d.reference, log=False)
                fit[rule] = time.perf_counter() - t0
        rows.append({"frames": n, "codes s": f"{codes_s:.1f}", "segmentation s": f"{seg_s:.1f}",
                     "walks": walks, "threshold": f"{threshold:.4f}",
                     "stretches before cuts": int(starts.size),
                     "longest unit": int((spans[:, 1] - spans[:, 0]).max()),
                     "fit s uniform / novelty": f"{fit['uniform']:.1f} / {fit['novelty']:.1f}"})
        print(rows[-1], flush=True)
    cols = list(rows[0])
    print("| " + " | ".join(cols) + " |\n|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(str(r[c]) for c in cols) + " |")
    return rows


if __name__ == "__main__":
    main()

"""SeqSLAM's exact mode on nordland-b with each thermometer product, side by side, one thread.

    python benchmarks/bench_thermometer_product.py [--places 1788]

The thermometer kernel's int8 product runs as ``torch._int_mm`` or as an exact float32
product (``torchseq.seqslam.difference.thermometer_product`` picks by CPU); this forces each
in turn through the CPU capability torch reports, and checks the matches are identical.
"""

import argparse
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from torchseq.seqslam import SeqSLAM, SeqSLAMConfig

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nordland-b"


def load(season: str, n: int) -> torch.Tensor:
    files = sorted((DATA / season).glob("*.png"))[:n]
    return torch.tensor(np.stack([cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]),
                        dtype=torch.float32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--places", type=int, default=1788)
    args = ap.parse_args()
    torch.set_num_threads(1)
    ref, query = load("summer", args.places), load("winter", args.places)
    real = torch.backends.cpu.get_cpu_capability
    print(f"CPU capability: {real()}; {args.places} places, one thread")
    print("| product | difference s | total s |\n|---|---:|---:|")
    matches = []
    for capability in ("AVX2", "AVX512"):  # float32, then int8
        torch.backends.cpu.get_cpu_capability = lambda c=capability: c
        t = time.perf_counter()
        r = SeqSLAM(SeqSLAMConfig()).match(ref, query)
        total = time.perf_counter() - t
        matches.append(r.matches.reference)
        print(f"| {r.kernels['product']} | {r.seconds['difference']:.2f} | {total:.2f} |")
    torch.backends.cpu.get_cpu_capability = real
    print("identical matches:", bool(torch.equal(*matches)))


if __name__ == "__main__":
    main()

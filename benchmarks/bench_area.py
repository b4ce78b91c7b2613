"""Banded preview, one band: the former row pooling vs torchseq.area.reduce_rows, side by side.

    python benchmarks/bench_area.py [--rows 35768] [--columns 64]

One thread; best of 7 per round, two rounds alternated. The former kernel
(``adaptive_avg_pool1d`` of the band, not NaN-aware) is rewritten here for the comparison.
"""

import argparse
import time

import torch
import torch.nn.functional as F

from torchseq.area import reduce_rows


def former(e_t: torch.Tensor) -> torch.Tensor:
    return F.adaptive_avg_pool1d(e_t.float()[:, None, :], 1024)[:, 0]


def current(e_t: torch.Tensor):
    return reduce_rows(e_t, 1024)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", type=int, default=35768)
    ap.add_argument("--columns", type=int, default=64)
    a = ap.parse_args()
    torch.set_num_threads(1)
    band = torch.randn(a.columns, a.rows, dtype=torch.float64)
    best = {}
    for f in (former, current, former, current):
        for _ in range(7):
            t = time.perf_counter()
            f(band)
            best[f.__name__] = min(best.get(f.__name__, 1e9), time.perf_counter() - t)
    for name, s in best.items():
        print(f"{name:8s} {s * 1e3:.2f} ms per band of {a.columns}x{a.rows}")
    print(f"ratio current/former {best['current'] / best['former']:.2f}")


if __name__ == "__main__":
    main()

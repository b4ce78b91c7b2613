"""Coarse-grained parallelism for the SeqSLAM stages: whole blocks per worker, no spin-waits.

PyTorch's intra-op threads split every small op of the enhancement tiles and search blocks
into an OpenMP parallel region; with another busy process on the machine each region waits
for its slowest thread, and the stages ran up to 10x slower than on one thread. Instead each
stage runs its ops single-threaded and hands whole blocks (a band of reference rows, a band
of query columns) to a pool of Python threads (PyTorch releases the GIL inside ops), taken
from a shared queue: a worker on a busy core simply takes fewer blocks.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Callable, Iterable, Iterator

import torch


def resolve_threads(threads: int | None) -> int:
    """``threads``, or PyTorch's intra-op thread count when None (at least 1)."""
    return max(1, int(threads) if threads is not None else torch.get_num_threads())


@contextmanager
def single_threaded_ops() -> Iterator[None]:
    """Run PyTorch ops on one intra-op thread inside the block; restore the count after."""
    old = torch.get_num_threads()
    if old != 1:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        if old != 1:
            torch.set_num_threads(old)


def run_blocks(fn: Callable[[object], None], blocks: Iterable, workers: int,
               device: torch.device | None = None) -> None:
    """Call ``fn(block)`` for every block, ``workers`` blocks at a time (dynamic order).

    ``fn`` must write disjoint outputs. One worker, or a CUDA device (whose kernels are
    asynchronous anyway), runs the blocks in order on the calling thread with one intra-op
    thread on CPU.
    """
    blocks = list(blocks)
    if device is not None and device.type == "cuda":
        for b in blocks:
            fn(b)
        return
    with single_threaded_ops():
        if workers <= 1 or len(blocks) <= 1:
            for b in blocks:
                fn(b)
            return
        with ThreadPoolExecutor(max_workers=min(workers, len(blocks))) as pool:
            for _ in pool.map(fn, blocks):  # re-raises the first failure
                pass

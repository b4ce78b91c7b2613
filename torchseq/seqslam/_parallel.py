"""Coarse-grained parallelism for the SeqSLAM stages: whole blocks per worker, no spin-waits.

PyTorch's intra-op threads split every small op of the enhancement tiles and search blocks
into an OpenMP parallel region; with another busy process on the machine each region waits
for its slowest thread, and the stages ran up to 10x slower than on one thread. Instead each
stage runs its ops single-threaded and hands whole blocks (a band of reference rows, a band
of query columns) to a pool of Python threads (PyTorch releases the GIL inside ops), taken
from a shared queue: a worker on a busy core simply takes fewer blocks.

With the default thread use (``threads=None``) each stage also counts the cores other
processes keep busy right now (the kernel's count of runnable tasks in ``/proc/loadavg``,
sampled a few times, minimum taken) and uses only the idle ones, at least one: on a 2-core
machine beside a busy co-tenant the stages run on one worker instead of fighting for the
busy core (measured: two workers there were slower than one, see docs/results/seqslam.md).
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Callable, Iterable, Iterator

import torch

LOADAVG = "/proc/loadavg"


def _busy_elsewhere(samples: int = 3, pause_s: float = 0.001) -> int | None:
    """Tasks running or runnable now besides this one (min over a few samples).

    None where ``/proc/loadavg`` is not available.
    """
    seen = []
    for i in range(samples):
        try:
            with open(LOADAVG) as f:
                running = int(f.read().split()[3].split("/")[0])
        except (OSError, ValueError, IndexError):
            return None
        seen.append(running - 1)  # the reader itself is running
        if i + 1 < samples:
            time.sleep(pause_s)
    return max(0, min(seen))


def cpu_count() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def resolve_threads(threads: int | None) -> int:
    """Worker threads for a stage.

    An explicit ``threads`` is used as given. None: PyTorch's intra-op thread count, capped
    by the cores not busy with other tasks right now (at least 1).
    """
    if threads is not None:
        return max(1, int(threads))
    want = max(1, _intra_op_threads[-1] if _intra_op_threads else torch.get_num_threads())
    busy = _busy_elsewhere()
    if busy is None:
        return want
    return max(1, min(want, cpu_count() - busy))


_intra_op_threads: list[int] = []  # the counts single_threaded_ops replaced, innermost last


@contextmanager
def single_threaded_ops() -> Iterator[None]:
    """Run PyTorch ops on one intra-op thread inside the block; restore the count after.

    Nested blocks keep the outermost count, which :func:`resolve_threads` reads.
    """
    old = torch.get_num_threads()
    _intra_op_threads.append(_intra_op_threads[-1] if _intra_op_threads else old)
    if old != 1:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        _intra_op_threads.pop()
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


def map_rows(fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor, threads: int | None,
             rows: int = 256) -> torch.Tensor:
    """``fn`` over blocks of ``rows`` leading rows of ``x``, concatenated, by this file's rule.

    For per-row work (frames to descriptors): each block runs on one intra-op thread and the
    blocks go to :func:`resolve_threads` workers (:func:`run_blocks`), so a busy core slows
    the step by at most its share instead of stalling every op's parallel region. On CUDA,
    or with at most one block, ``fn(x)`` runs as it is.

    Args:
        fn: ``(n, ...) -> (n, ...)``, row ``i`` of the output depending on row ``i`` of the
            input only.
        x: ``(T, ...)``.
        threads: worker threads (None: :func:`resolve_threads`' rule).
        rows: rows per block.

    Returns:
        ``fn`` of every block, concatenated along the first axis.
    """
    if x.device.type == "cuda" or x.shape[0] <= rows:
        if x.device.type == "cuda":
            return fn(x)
        with single_threaded_ops():
            return fn(x)
    starts = range(0, x.shape[0], rows)
    out: list[torch.Tensor | None] = [None] * len(starts)

    def block(i: int) -> None:
        out[i] = fn(x[starts[i]:starts[i] + rows])

    run_blocks(block, range(len(starts)), resolve_threads(threads), x.device)
    return torch.cat(out)  # type: ignore[arg-type]

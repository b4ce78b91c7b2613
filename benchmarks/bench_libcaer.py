"""DDD20 original-recording reader (libcaer packets in HDF5): events per second, one thread.

    .venv/bin/python benchmarks/bench_libcaer.py [--packets 2000] [--per-packet 1000]

Writes a recording in ddd20-utils' layout (one APS frame packet, then polarity packets of
``--per-packet`` valid events) to a temporary folder and times ``read_events`` on it (best
of 3, process CPU time, after one warm-up read). DDD20's DAVIS346B packets are
typically a few hundred to a few thousand events; the per-row cost (an HDF5 variable-length
read and a header parse) dominates for small packets.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def write_recording(path: Path, packets: int, per: int, seed: int = 0) -> int:
    """Write the layout with vectorised packet bodies; return the number of events."""
    import h5py

    rng = np.random.default_rng(seed)
    vl = h5py.vlen_dtype(np.uint8)

    def row(head: bytes, body: bytes) -> np.ndarray:
        return np.array([np.frombuffer(b"1", np.uint8), np.frombuffer(head, np.uint8),
                         np.frombuffer(body, np.uint8)], dtype=object)

    with h5py.File(path, "w") as f:
        d = f.create_dataset("dvs/data", (packets + 1, 3), dtype=vl, chunks=(128, 3))
        frame = np.array([1, 0, 0, 0, 0, 346, 260, 0, 0], "<i4").tobytes()
        d[0] = row(np.array([2, 1], "<i2").tobytes()
                   + np.array([36 + 346 * 260 * 2, 12, 0, 1, 1, 1], "<i4").tobytes(),
                   frame + bytes(346 * 260 * 2))
        t = 0
        for k in range(packets):
            ts = t + np.sort(rng.integers(0, 1000, per))
            t = int(ts[-1]) + 1
            data = ((rng.integers(0, 346, per).astype(np.uint32) << 17)
                    | (rng.integers(0, 260, per).astype(np.uint32) << 2)
                    | (rng.integers(0, 2, per).astype(np.uint32) << 1) | 1)
            body = np.stack([data, ts.astype(np.uint32)], 1).astype("<u4").tobytes()
            head = np.array([1, 1], "<i2").tobytes() + np.array([8, 4, 0, per, per, per],
                                                                  "<i4").tobytes()
            d[k + 1] = row(head, body)
    return packets * per


def main() -> None:
    """Print one Markdown row."""
    from torchseq.events import read_events

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--packets", type=int, default=2000)
    ap.add_argument("--per-packet", type=int, default=1000)
    args = ap.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ddd20.hdf5"
        n = write_recording(path, args.packets, args.per_packet)
        read_events(path)
        best = float("inf")
        for _ in range(3):
            t0 = time.process_time()
            s = read_events(path)
            best = min(best, time.process_time() - t0)
        assert len(s) == n and s.sensor_size == (346, 260)
    print("| packets | events/packet | events | CPU s | M events/s |")
    print("|---|---|---|---|---|")
    print(f"| {args.packets} | {args.per_packet} | {n} | {best:.3f} | {n / best / 1e6:.1f} |")


if __name__ == "__main__":
    main()

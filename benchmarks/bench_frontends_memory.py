"""Peak memory of ``eval.py`` on long 720p videos (streaming load vs. whole-traverse load).

Makes two synthetic 1280x720 videos with OpenCV (a textured route scrolled past the camera;
the query relit), then runs ``eval.py`` on them in a child process and reads the
child's peak resident set size (``ru_maxrss``). ``--baseline SRC`` also runs another checkout's
``eval.py`` (e.g. ``/work/main``, which loads whole traverses at full resolution) on the same
videos, side by side.

    python benchmarks/bench_frontends_memory.py --frames 3000
    python benchmarks/bench_frontends_memory.py --frames 300 --baseline /work/main
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def make_video(path: Path, n: int, speed: float, gain: float, seed: int = 0) -> None:
    """``n`` frames of 1280x720 BGR: a random-texture strip scrolled ``speed * 8`` px/frame."""
    h, w, step = 720, 1280, 8.0
    rng = np.random.default_rng(seed)
    length = int(n * speed * step) + w + 16
    coarse = rng.uniform(0, 255, (h // 16, length // 16 + 1)).astype(np.float32)
    strip = cv2.resize(coarse, (length, h), interpolation=cv2.INTER_CUBIC)
    strip = np.clip(strip, 0, 255)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25, (w, h))
    if not writer.isOpened():
        raise RuntimeError("OpenCV cannot write mp4v here")
    noise = np.random.default_rng(seed + 1)
    for i in range(n):
        x = int(i * speed * step)
        grey = strip[:, x:x + w] * gain + noise.normal(0, 3, (h, w))
        frame = np.clip(grey, 0, 255).astype(np.uint8)
        writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    writer.release()


def peak_rss(cmd: list[str], cwd: Path, env: dict) -> tuple[float, float, int, str]:
    """Run ``cmd``; return (peak RSS in MiB, seconds, exit code, last stdout line)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    _, usage = os.wait4(proc.pid, 0)[1:]
    out, err = proc.stdout.read(), proc.stderr.read()
    seconds = time.perf_counter() - t0
    code = proc.returncode if proc.returncode is not None else 0
    last = (out.strip().splitlines() or err.strip().splitlines() or [""])[-1]
    return usage.ru_maxrss / 1024, seconds, code, last


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=3000, help="reference video frames")
    ap.add_argument("--engine", default="both")
    ap.add_argument("--baseline", help="another checkout to compare (its eval.py)")
    ap.add_argument("--keep", help="folder to keep the videos in (default: a temp folder)")
    args = ap.parse_args()
    folder = Path(args.keep or tempfile.mkdtemp(prefix="torchseq-bench-"))
    folder.mkdir(parents=True, exist_ok=True)
    ref, query = folder / f"ref_{args.frames}.mp4", folder / f"query_{args.frames}.mp4"
    t0 = time.perf_counter()
    if not ref.exists():
        make_video(ref, args.frames, 1.0, 1.0, seed=0)
    if not query.exists():
        make_video(query, args.frames, 1.0, 0.8, seed=0)
    made = time.perf_counter() - t0
    rows = []
    for name, src in [("this checkout", ROOT)] + (
            [("baseline " + args.baseline, Path(args.baseline))] if args.baseline else []):
        env = {**os.environ, "PYTHONPATH": str(src)}
        cmd = [sys.executable, str(src / "eval.py"), "--reference", str(ref), "--query",
               str(query), "--tolerance", "2", "--engine", args.engine, "--no-progress",
               "--no-tensorboard", "--out", str(folder / f"out_{len(rows)}_{time.time_ns()}")]
        mib, seconds, code, last = peak_rss(cmd, src, env)
        rows.append({"eval.py": name, "frames": args.frames, "engine": args.engine,
                     "peak_rss_mib": round(mib, 1), "seconds": round(seconds, 1),
                     "exit": code, "last_line": last})
        print(json.dumps(rows[-1]))
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"videos: {ref.stat().st_size / 2**20:.1f} + {query.stat().st_size / 2**20:.1f} MiB "
          f"(made in {made:.0f} s); this script's own peak {own:.0f} MiB")


if __name__ == "__main__":
    main()

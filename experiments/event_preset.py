"""Choose the event preset: simulated event runs of nordland-b, same and across seasons.

The route is ``--places`` consecutive places of nordland-b (64x32 grey, every 10th video
frame of the Nordland line). The reference run drives the summer images at one place per
10 ms window; query runs drive the summer (same season, other simulator seed) or the winter
images (across seasons) at the seed's speed ratios, 66% and 25% of the reference's speed
(1.5x and 4x speed difference). Events come from the project's simulator
(``torchseq.events.runs.simulate_run``: log-intensity threshold crossings between the
linearly interpolated images, threshold spread 0.03, 1 Hz/pixel background noise, as the
speed experiment). Ground truth is exact from the route positions: a query window matches
the reference windows within ``--tolerance`` (2) reference windows of its centre, and one
reference window is one place, so +-2 reference frames = +-2 places of nordland-b.

Every candidate preset is run on every pair with the engine calls ``torchseq eval`` makes on
event files (``SeqSLAM.match`` for one window, ``match_ensemble`` for several; the member
frames of ``accumulate_ensemble``, as ``--window-ms 5,10,20`` loads them), with the known
speed ratio as ``--speed-ratio``; recall@1 counts all queries (an unmatched query is wrong).
The whole route (1,788 places, 7,148 query windows at 4x) is too slow for a few minutes on
one thread, so the default is its first 400 places. One command writes the table (Markdown
and JSON)::

    python experiments/event_preset.py --out experiments/results
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchseq.atomic import write_json, write_text
from torchseq.events.ensemble import accumulate_ensemble, match_ensemble
from torchseq.events.frames import accumulate
from torchseq.events.runs import ground_truth, simulate_run
from torchseq.metrics import evaluate
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
from torchseq.sources import load_traverse

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nordland-b"
WINDOW_US = 10_000  # the reference run: one place per 10 ms window


@dataclass
class Candidate:
    """One event preset: SeqSLAM settings and the event windows (ms)."""

    name: str
    windows_ms: tuple = (10.0,)
    seqslam: dict = field(default_factory=dict)


CANDIDATES = [
    Candidate("events, ds 100, no edges (the preset before)", (10.0,),
              {"ds": 100, "edges": False}),
    Candidate("edges, ds 100", (10.0,), {"ds": 100}),
    Candidate("edges, ds 100, ensemble 5+10+20", (5.0, 10.0, 20.0), {"ds": 100}),
    Candidate("edges, ds 100, ensemble 10+20+40", (10.0, 20.0, 40.0), {"ds": 100}),
    Candidate("edges, ds 100, 16x32 frames", (10.0,), {"ds": 100, "image_size": (16, 32)}),
    Candidate("events (the preset now: edges, ds = 100 / ratio)", (10.0,), {}),
]
PAIRS = [("same", "summer", 0.66), ("same", "summer", 0.25), ("cross", "winter", 0.66),
         ("cross", "winter", 0.25)]


def route(places: int, start: int) -> dict[str, np.ndarray]:
    """``{"summer": (N, 32, 64), "winter": ...}`` grey images of ``places`` places."""
    out = {}
    for season in ("summer", "winter"):
        folder = DATA / season
        if not folder.exists():
            raise SystemExit(f"nordland-b not found at {folder}")
        frames = load_traverse(folder, progress=False).numpy()
        out[season] = frames[start:start + places]
    return out


def members(run, windows_ms, n_windows: int, size) -> torch.Tensor:
    """``(M, T, h, w)`` count frames centred on the 10 ms steps, area-pooled to ``size``."""
    if tuple(windows_ms) == (10.0,):
        f = accumulate(run.stream, window_us=WINDOW_US, mode="signed", anchor="zero")[:n_windows]
        return torch.nn.functional.adaptive_avg_pool2d(f[:, None], tuple(size))[:, 0][None]
    m = accumulate_ensemble(run.stream, [int(round(ms * 1000)) for ms in windows_ms],
                            step_us=WINDOW_US, downsample=tuple(size), anchor="zero")
    return m[:, :n_windows]


def table(rows: list[dict], a) -> str:
    """The Markdown table of recall@1 per candidate and pair."""
    keys = [f"{kind} {1 / v:.1f}x" for kind, _, v in PAIRS]
    head = ("| candidate | " + " | ".join(k.replace("same", "same season").replace(
        "cross", "across seasons") for k in keys) + " | CPU s |")
    lines = [head, "|---" + "|---:" * (len(keys) + 1) + "|"]
    for r in rows:
        lines.append(f"| {r['candidate']} | " + " | ".join(f"{r[k]:.3f}" for k in keys)
                     + f" | {r['cpu_seconds']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default="experiments/results")
    p.add_argument("--places", type=int, default=400)
    p.add_argument("--start", type=int, default=0, help="first place of nordland-b used")
    p.add_argument("--tolerance", type=float, default=2.0,
                   help="ground truth, in reference windows (= places)")
    p.add_argument("--only", default=None, help="semicolon-separated candidate names")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    t0 = time.process_time()
    images = route(a.places, a.start)
    positions = np.arange(a.places, dtype=np.float64)
    units_per_s = 1e6 / WINDOW_US  # one place per reference window
    sim = dict(contrast_threshold=0.2, threshold_noise=0.03, noise_rate_hz=1.0)
    ref_run = simulate_run(images["summer"], positions, 1.0, units_per_s, seed=1, **sim)
    n_ref = a.places - 1
    ref_pos = ref_run.window_positions(n_ref, WINDOW_US)
    pairs = []
    for k, (kind, season, speed) in enumerate(PAIRS):
        run = simulate_run(images[season], positions, speed, units_per_s, seed=2 + k, **sim)
        n_q = int(np.floor(n_ref / speed))
        gt = ground_truth(ref_pos, run.window_positions(n_q, WINDOW_US), a.tolerance)
        pairs.append((f"{kind} {1 / speed:.1f}x", speed, run, n_q, gt))
    sim_s = time.process_time() - t0
    cands = CANDIDATES if a.only is None else [c for c in CANDIDATES
                                               if c.name in a.only.split(";")]
    rows = []
    for c in cands:
        row = {"candidate": c.name, "windows_ms": list(c.windows_ms), "seqslam": c.seqslam}
        t1 = time.process_time()
        for key, speed, run, n_q, gt in pairs:
            sc = SeqSLAMConfig.events(speed_ratio=speed, **c.seqslam)
            rm = members(ref_run, c.windows_ms, n_ref, sc.image_size)
            qm = members(run, c.windows_ms, n_q, sc.image_size)
            if len(rm) == 1:
                res = SeqSLAM(sc).match(rm[0], qm[0])
            else:
                res = match_ensemble(list(rm), list(qm), sc)
            row[key] = evaluate(res.matches, gt)["recall_at_1"]
        row["cpu_seconds"] = time.process_time() - t1
        rows.append(row)
        print(" | ".join(f"{v:.3f}" if isinstance(v, float) else str(v) for k, v in row.items()
                         if k not in ("windows_ms", "seqslam")), flush=True)
    command = "python experiments/event_preset.py " + shlex.join(
        argv if argv is not None else sys.argv[1:])
    md = (f"nordland-b places {a.start}..{a.start + a.places - 1} ({a.places} places; "
          f"{n_ref} reference windows of 10 ms, one place each), recall@1 over all queries, "
          f"ground truth +-{a.tolerance:g} reference windows (= +-{a.tolerance:g} places), "
          f"one thread, simulation {sim_s:.0f} CPU s.\n\n" + table(rows, a)
          + f"\nCommand: `{command.strip()}`\n")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "event_preset.md", md)
    result = {"places": a.places, "start": a.start, "tolerance": a.tolerance,
              "pairs": [k for k, *_ in pairs], "rows": rows, "command": command.strip()}
    write_json(out / "event_preset.json", result)
    print(md)
    print(f"wrote {out / 'event_preset.md'} and {out / 'event_preset.json'} "
          f"({time.process_time() - t0:.0f} CPU s)", file=sys.stderr)
    return result


if __name__ == "__main__":
    main()

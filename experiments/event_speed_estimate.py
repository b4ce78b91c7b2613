"""`torchseq eval --preset events` with the speed ratio from the data, against ratio 1.

The reference run drives nordland-b's first ``--places`` summer images at one place per 10 ms
window; query runs drive the summer (other simulator seed) or winter images at 66% and 25% of
its speed, simulated as ``experiments/event_preset.py`` simulates them. Each pair is written
as event files with an exact ground truth from the route positions (+-2 reference windows)
and run through the command line twice: without ``--speed-ratio`` (the ratio estimated from
the window counts) and with ``--speed-ratio 1`` (what every run used before the estimate).
One command writes the table::

    python experiments/event_speed_estimate.py --out experiments/results
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from event_preset import WINDOW_US, route  # noqa: E402

import torchseq.cli.eval as cli_eval  # noqa: E402
from torchseq.atomic import write_text  # noqa: E402
from torchseq.events.plain import write_npz  # noqa: E402
from torchseq.events.runs import ground_truth, simulate_run  # noqa: E402
from torchseq.sources import load_traverse  # noqa: E402

PAIRS = [("same season 1.5x", "summer", 0.66), ("across seasons 1.5x", "winter", 0.66),
         ("across seasons 4x", "winter", 0.25)]
SIM = dict(contrast_threshold=0.2, threshold_noise=0.03, noise_rate_hz=1.0)


def eval_recall(folder: Path, name: str, *extra: str) -> tuple[float, dict | None]:
    """recall@1 of one ``torchseq eval`` run and the speed ratio it recorded."""
    out = folder / f"run-{name}-{len(extra)}"
    code = cli_eval.main(["--reference", str(folder / "ref.npz"), "--query",
                          str(folder / f"{name}.npz"), "--ground-truth",
                          str(folder / f"{name}_gt.npy"), "--preset", "events", "--engine",
                          "seqslam", "--threads", "1", "--no-tensorboard", "--no-progress",
                          "--out", str(out), *extra])
    if code:
        raise SystemExit(f"torchseq eval failed on {name}")
    m = json.loads((out / "metrics.json").read_text())
    return m["seqslam"]["recall_at_1"], m["inputs"].get("speed_ratio")


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default="experiments/results")
    p.add_argument("--places", type=int, default=300)
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    images = route(a.places, 0)
    positions = np.arange(a.places, dtype=np.float64)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        ref = simulate_run(images["summer"], positions, 1.0, 100.0, seed=1, **SIM)
        write_npz(folder / "ref.npz", ref.stream)
        ref_pos = ref.window_positions(a.places - 1, WINDOW_US)
        for k, (label, season, speed) in enumerate(PAIRS):
            run = simulate_run(images[season], positions, speed, 100.0, seed=2 + k, **SIM)
            name = f"q{k}"
            write_npz(folder / f"{name}.npz", run.stream)
            n_windows = len(load_traverse(folder / f"{name}.npz", progress=False))  # as eval
            np.save(folder / f"{name}_gt.npy",
                    ground_truth(ref_pos, run.window_positions(n_windows, WINDOW_US), 2.0))
            estimated, ratio = eval_recall(folder, name)
            before, _ = eval_recall(folder, name, "--speed-ratio", "1")
            rows.append({"pair": label, "speed": speed, "estimated_ratio": ratio["value"],
                         "from": ratio["from"], "recall_estimated": estimated,
                         "recall_ratio_1": before})
            print(rows[-1], flush=True)
    command = "python experiments/event_speed_estimate.py " + shlex.join(
        argv if argv is not None else sys.argv[1:])
    md = (f"nordland-b places 0..{a.places - 1}, simulated event runs, `torchseq eval --preset "
          f"events --engine seqslam`, recall@1, ground truth +-2 reference windows.\n\n"
          "| pair | speed ratio estimated (window counts) | recall@1 estimated | recall@1 at "
          "ratio 1 |\n|---|---:|---:|---:|\n"
          + "".join(f"| {r['pair']} | {r['estimated_ratio']:.3f} ({r['from']}) | "
                    f"{r['recall_estimated']:.3f} | {r['recall_ratio_1']:.3f} |\n" for r in rows)
          + f"\nCommand: `{command.strip()}`\n")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "event_speed_estimate.md", md)
    print(md)
    return {"rows": rows, "command": command.strip()}


if __name__ == "__main__":
    main()

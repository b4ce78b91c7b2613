"""Where the compiled ``"sad"`` L1 kernel starts to pay, numba's start-up included.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_l1_size_rule.py [--places 1000 1788 3576]
        [--rounds 2]

Each run is a fresh process (so numba's import and the load of its cached compiled loop count,
as they do for a user's ``torchseq eval``) that matches the first ``n`` places of nordland-b
(summer against winter, then each season again backwards: up to 3,576 places; SeqSLAM's
default descriptors: D = 2,048, OpenSeqSLAM's patch normalisation, 16 thresholds) with
``SeqSLAM().match_descriptors`` on one thread, once with the difference kernel forced to the
thermometer product (``SAD_MIN_WORK`` and ``SAD_INT8_MIN_SAVING`` above every size) and once
to ``"sad"`` (both below), interleaved, ``--rounds`` times. Prints the CPU kind (torch's CPU
capability and the thermometer's product), wall and CPU seconds of the match, the ratio, and
the kernel the rule picks unforced. The descriptors are computed once, up front, and saved
to a temporary folder. The compiled loop's cache must exist (run any ``"sad"`` once before;
a first-ever compile costs about 1.5 s more, once per install).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "nordland-b"

CHILD = """
import json, sys, time
import numpy as np, torch
torch.set_num_threads(1)
import torchseq.seqslam.difference as d
from torchseq.seqslam import SeqSLAM
mode, n, folder = sys.argv[1], int(sys.argv[2]), sys.argv[3]
d.SAD_MIN_WORK = d.SAD_INT8_MIN_SAVING = -2**62 if mode == "sad" else 2**62
ref = torch.from_numpy(np.load(folder + "/ref.npy"))[:n]
qry = torch.from_numpy(np.load(folder + "/qry.npy"))[:n]
t, c = time.perf_counter(), time.process_time()
res = SeqSLAM().match_descriptors(ref, qry)
print(json.dumps({"wall": time.perf_counter() - t, "cpu": time.process_time() - c,
                  "kernel": res.kernels.get("difference"), "numba": "numba" in sys.modules}))
"""


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--places", type=int, nargs="+", default=[1000, 1788, 3576])
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args(argv)
    import numpy as np
    import torch

    from torchseq.seqslam import SeqSLAM
    from torchseq.seqslam.difference import l1_kernel, thermometer_levels, thermometer_product
    from torchseq.sources import load_traverse

    with tempfile.TemporaryDirectory() as tmp:
        s = SeqSLAM()
        for name, season in (("ref", "summer"), ("qry", "winter")):
            x = s.descriptors(load_traverse(DATA / season, progress=False)).numpy()
            np.save(Path(tmp) / f"{name}.npy", np.concatenate([x, x[::-1]]))  # up to 3,576
        ref, qry = (torch.from_numpy(np.load(Path(tmp) / f"{n}.npy")) for n in ("ref", "qry"))
        levels = thermometer_levels(ref, qry)
        print(f"CPU: torch capability {torch.backends.cpu.get_cpu_capability()}, thermometer "
              f"product {thermometer_product('cpu')}, {levels[0].numel()} thresholds\n")
        print("| places | R Q D | thermometer wall / CPU s | sad wall / CPU s (numba start-up "
              "included) | sad / thermometer (CPU, best of rounds) | the rule picks |")
        print("|---:|---:|---|---|---:|---|")
        for n in args.places:
            best = {}
            for _ in range(args.rounds):
                for mode in ("thermometer", "sad"):
                    out = subprocess.run([sys.executable, "-c", CHILD, mode, str(n), tmp],
                                         capture_output=True, text=True, check=True,
                                         env={"PYTHONPATH": str(ROOT), "PATH": ""})
                    r = json.loads(out.stdout.strip().splitlines()[-1])
                    assert r["kernel"] == mode and r["numba"] == (mode == "sad"), r
                    if mode not in best or r["cpu"] < best[mode]["cpu"]:
                        best[mode] = r
            t, s_ = best["thermometer"], best["sad"]
            print(f"| {n} | {n * n * 2048:.2e} | {t['wall']:.2f} / {t['cpu']:.2f} | "
                  f"{s_['wall']:.2f} / {s_['cpu']:.2f} | {s_['cpu'] / t['cpu']:.2f} | "
                  f"{l1_kernel(ref[:n], qry[:n], levels)} |", flush=True)


if __name__ == "__main__":
    main()

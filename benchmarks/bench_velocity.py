"""The adaptive-velocity ring's cost beside the fixed ring, one CPU thread, one run.

    .venv/bin/python benchmarks/bench_velocity.py [--repeats 5]

Both models fitted on the same demo route (555 reference frames, 555 units, query at 0.8x):
the online step of ``model.inference()`` (batch 1, one frame in, one decision out) and ``run``
over the whole query. Fixed: the banded ring step and the blocked NumPy ring scan. Adaptive
(``NeuralConfig.adaptive_velocity()``): the speed-mixed ring step, the estimator and, in
``run``, the ``"velocity_loop"`` scan (frame by frame). Times are CPU seconds of this process
(``time.process_time``), best of ``--repeats``; the ratio is adaptive / fixed.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchseq.demo import make_demo  # noqa: E402
from torchseq.neural import NeuralConfig, NeuralSeqSLAM  # noqa: E402
from torchseq.preprocess import resize  # noqa: E402


def best(fn, repeats: int, number: int) -> float:
    """Best mean CPU seconds per call over ``repeats`` rounds of ``number`` calls."""
    fn()
    out = float("inf")
    for _ in range(repeats):
        t0 = time.process_time()
        for _ in range(number):
            fn()
        out = min(out, (time.process_time() - t0) / number)
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    d = make_demo(n_reference=555)
    settings = {"fixed (default)": NeuralConfig(), "adaptive_velocity()":
                NeuralConfig.adaptive_velocity()}
    models = {}
    for label, cfg in settings.items():
        m = NeuralSeqSLAM(cfg)
        m.fit(d.reference, log=False)
        models[label] = m
    frames = resize(d.query.float(), models["fixed (default)"].config.input_size)
    rows = {}
    for label, model in models.items():
        m = model.inference()  # the fast form; its step and run
        state = [None]
        t = [0]

        def one_step(m=m, state=state, t=t):
            with torch.inference_mode():
                _, state[0] = m.step(frames[t[0] % len(frames)][None], state[0])
            t[0] += 1

        step_s = best(one_step, args.repeats, 500)
        run_s = best(lambda m=m: m.run(frames), args.repeats, 1)
        rows[label] = (step_s, run_s, m.kernels)
    print(f"| model | online step (us) | run, {len(frames)} frames (ms) | kernels |")
    print("|---|---|---|---|")
    for label, (step_s, run_s, kernels) in rows.items():
        print(f"| {label} | {step_s * 1e6:.0f} | {run_s * 1e3:.1f} | ring {kernels['ring']}, "
              f"scan {kernels['scan']} |")
    (fs, fr, _), (as_, ar, _) = rows.values()
    print(f"\nadaptive / fixed: online step {as_ / fs:.2f}x, run {ar / fr:.2f}x")


if __name__ == "__main__":
    main()

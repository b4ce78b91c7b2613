"""Whole ``torchseq eval --engine seqslam`` process on nordland-b, split into its phases.

    .venv/bin/python benchmarks/bench_eval_process.py                     # this code, 3,576 places
    .venv/bin/python benchmarks/bench_eval_process.py --baseline ../main  # side by side with main
    .venv/bin/python benchmarks/bench_eval_process.py --busy 1            # one core held busy
    .venv/bin/python benchmarks/bench_eval_process.py --places 1788 --rounds 1   # a quick look
    .venv/bin/python benchmarks/bench_eval_process.py --stages --rounds 3   # engine stages

The route is ``../shared/data/nordland-b`` (1,788 places, 64x32, summer and winter). With
``--places 3576`` (the default, the issue's size) the reference is summer followed by summer
in reverse order and the query is winter followed by winter in reverse (symlinks under
``--cache``): the same frames twice, the second time driven backwards, so every place has one
admissible stretch on each pass and index alignment (``--tolerance 2``) stays the ground truth.

Each run is the real console command (``torchseq.cli.main``) in its own process, with the
library functions of each phase wrapped by timers before it starts. Phases are exclusive
(a phase inside another is subtracted from the outer one): imports (``import torchseq.cli`` and
``torchseq.cli.eval``), decode (``load_traverse_for``), descriptors (``SeqSLAM.descriptors``:
grey, resize, patch normalisation), engine (``run_engines`` less descriptors), the single-frame
baseline (``single_frame_baseline`` less descriptors), and the report (``report``: metrics,
``matches.csv``, ``metrics.json``, plots, TensorBoard), with its plots and TensorBoard parts
also shown on their own; "exit" is the wall time from the command's return to the process's
end (Python's finalisation), "start" the rest (interpreter start). The child runs the command
as the console script does (``sys.argv``, ``torchseq.cli.main()``). Wall and CPU seconds
(``time.process_time``: all threads) per phase, and the process's peak RSS (``wait4``); codes
run interleaved ``--rounds`` times and the fastest whole process of each is shown, with the
median ratio of the rounds' whole-process wall times when there are two codes. ``--busy N``
runs N busy-loop processes beside the runs (a co-tenant holding cores).

``--descriptor-step`` times only the descriptor step on the route's frames (both traverses),
in this process: one whole ``preprocess`` call on PyTorch's default intra-op threads (what the
engine did before) against ``SeqSLAM.descriptors`` (blocks of frames on the stages' worker
threads, ``seqslam/_parallel.py``), interleaved, fastest of ``--rounds``, with ``--busy``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "nordland-b"
PHASES = ("imports", "decode", "descriptors", "engine", "single frame", "report")
REPORT_PARTS = ("plots", "tensorboard")


def write_route(places: int, cache: Path) -> Path:
    """Reference and query folders of ``places`` frames (symlinks to nordland-b)."""
    summer = sorted((DATA / "summer").glob("*.png"))
    winter = sorted((DATA / "winter").glob("*.png"))
    if not summer or len(summer) != len(winter):
        raise SystemExit(f"nordland-b not found under {DATA} (see ../shared/data/README.md)")
    n = len(summer)
    if places not in (n, 2 * n):
        raise SystemExit(f"--places must be {n} or {2 * n}")
    order = list(range(n)) + (list(range(n - 1, -1, -1)) if places == 2 * n else [])
    folder = cache / f"nordland-{places}"
    for name, files in (("reference", summer), ("query", winter)):
        (folder / name).mkdir(parents=True, exist_ok=True)
        for i, j in enumerate(order):
            link = folder / name / f"{i:05d}.png"
            if not link.exists():
                link.symlink_to(files[j])
    return folder


class _Timers:
    """Exclusive wall and CPU seconds per phase (time in a nested phase leaves the outer one)."""

    def __init__(self):
        self.wall = dict.fromkeys(PHASES + REPORT_PARTS, 0.0)
        self.cpu = dict.fromkeys(PHASES + REPORT_PARTS, 0.0)
        self.stack: list[str] = []

    def wrap(self, phase: str, fn):
        def timed(*args, **kwargs):
            if phase in self.stack:  # a recursive or repeated call inside the same phase
                return fn(*args, **kwargs)
            self.stack.append(phase)
            w, c = time.perf_counter(), time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                dw, dc = time.perf_counter() - w, time.process_time() - c
                self.stack.pop()
                self.wall[phase] += dw
                self.cpu[phase] += dc
                if self.stack and self.stack[-1] not in REPORT_PARTS and \
                        phase not in REPORT_PARTS:
                    self.wall[self.stack[-1]] -= dw
                    self.cpu[self.stack[-1]] -= dc
        return timed


def run_child(argv: list[str], result: Path) -> None:
    """Inside the child: import, wrap each phase's functions, run ``torchseq eval``."""
    w, c = time.perf_counter(), time.process_time()
    import torchseq.cli
    try:  # the front end as a package (torchseq/cli/), else a baseline's cli_eval.py
        import torchseq.cli.eval as cli_eval
        import torchseq.cli.inputs as inputs
        import torchseq.cli.report as report_module
    except ImportError:
        import torchseq.cli_eval as cli_eval
        inputs = report_module = cli_eval
    imports = (time.perf_counter() - w, time.process_time() - c)
    modules_before_report = set()
    from torchseq.seqslam import SeqSLAM

    timers = _Timers()
    timers.wall["imports"], timers.cpu["imports"] = imports

    def note_modules(fn):
        def noted(*args, **kwargs):
            modules_before_report.update(sys.modules)
            return fn(*args, **kwargs)
        return noted

    wrap = [("decode", inputs, "load_traverse_for"),
            ("descriptors", SeqSLAM, "descriptors"),
            ("engine", cli_eval, "run_engines"),
            ("single frame", cli_eval, "single_frame_baseline"),
            ("tensorboard", report_module, "log_tensorboard")]
    for name in ("plots", "report_images", "cli.plots", "cli.report_images"):  # each layout
        try:
            module = __import__(f"torchseq.{name}", fromlist=["_"])
        except ImportError:
            continue
        wrap += [("plots", module, n) for n in dir(module)
                 if n.startswith(("plot_", "save_", "figure_", "draw_", "encode_"))
                 and callable(getattr(module, n))]
    for phase, owner, name in wrap:
        if hasattr(owner, name):
            setattr(owner, name, timers.wrap(phase, getattr(owner, name)))
    cli_eval.report = note_modules(timers.wrap("report", cli_eval.report))
    sys.argv = ["torchseq", "eval", *argv]
    code = torchseq.cli.main()  # as the console script: the process's own command line
    end, end_cpu = time.monotonic(), time.process_time()
    heavy = sorted(m for m in ("matplotlib", "torch.utils.tensorboard", "tensorboard", "onnx",
                               "onnxruntime", "lz4", "faiss", "ray", "h5py", "pyarrow")
                   if m in modules_before_report)
    result.write_text(json.dumps({"wall": timers.wall, "cpu": timers.cpu, "code": code,
                                  "heavy_before_report": heavy, "end": end,
                                  "end_cpu": end_cpu}))
    sys.exit(code)


def run_once(root: Path, route: Path, out: Path) -> dict:
    """One whole eval process (this file's child) on ``route`` with the code at ``root``.

    Wall and CPU seconds, the phases, the exit's wall seconds, peak RSS (MB), recall@1, AUC.
    """
    with tempfile.TemporaryDirectory() as tmp:
        result, log = Path(tmp) / "phases.json", Path(tmp) / "stderr.txt"
        argv = ["--engine", "seqslam", "--reference", str(route / "reference"),
                "--query", str(route / "query"), "--tolerance", "2", "--out", str(out),
                "--overwrite"]
        env = dict(os.environ, PYTHONPATH=str(root))
        with open(log, "w") as err:
            t = time.monotonic()
            proc = subprocess.Popen([sys.executable, __file__, "--child", str(result), "--",
                                     *argv], cwd=root, env=env, stdout=subprocess.DEVNULL,
                                    stderr=err)
            _, status, usage = os.wait4(proc.pid, 0)  # this child's own rusage
            wall = time.monotonic() - t
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode:
            raise SystemExit(f"{root}: eval failed:\n{log.read_text()[-3000:]}")
        phases = json.loads(result.read_text())
    metrics = json.loads((out / "metrics.json").read_text())["seqslam"]
    return {"wall": wall, "cpu": usage.ru_utime + usage.ru_stime,
            "rss_mb": usage.ru_maxrss / 1024, "exit": t + wall - phases["end"],
            "exit_cpu": usage.ru_utime + usage.ru_stime - phases["end_cpu"],
            "phases": phases, "recall_at_1": metrics["recall_at_1"], "auc": metrics["auc"],
            "matches": (out / "matches.csv").read_bytes(), "kernel": metrics.get("kernels"),
            "single": json.dumps(json.loads((out / "metrics.json").read_text())
                                 .get("single_frame"), sort_keys=True)}


def table(best: dict) -> str:
    """Markdown table: one row per phase, wall and CPU seconds of each code side by side."""
    labels = list(best)
    lines = ["| phase | " + " | ".join(f"{k} wall s | {k} CPU s" for k in labels) + " |",
             "|---|" + "---:|" * (2 * len(labels))]

    def row(name, values):
        lines.append(f"| {name} | " + " | ".join(f"{w:.2f} | {c:.2f}" for w, c in values) + " |")

    for phase in PHASES:
        row(phase, [(r["phases"]["wall"][phase], r["phases"]["cpu"][phase])
                    for r in best.values()])
        if phase == "report":
            for part in REPORT_PARTS:
                row(f"&nbsp;&nbsp;of which {part}", [(r["phases"]["wall"][part],
                                                     r["phases"]["cpu"][part])
                                                    for r in best.values()])
    row("exit (from the command's return)", [(r["exit"], r["exit_cpu"]) for r in best.values()])
    row("start (interpreter) and the rest",
        [(r["wall"] - r["exit"] - sum(r["phases"]["wall"][p] for p in PHASES),
          r["cpu"] - r["exit_cpu"] - sum(r["phases"]["cpu"][p] for p in PHASES))
         for r in best.values()])
    row("**whole process**", [(r["wall"], r["cpu"]) for r in best.values()])
    lines.append("| peak RSS MB | " + " | ".join(f"{r['rss_mb']:.0f} | " for r in best.values())
                 + " |")
    return "\n".join(lines)


def descriptor_step(route: Path, rounds: int) -> str:
    """The descriptor step alone: default threads vs the stages' rule; a markdown table."""
    sys.path.insert(0, str(ROOT))
    import torch

    from torchseq import load_traverse
    from torchseq.preprocess import preprocess
    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig

    frames = torch.cat([load_traverse(route / n, progress=False) for n in ("reference",
                                                                            "query")])
    c = SeqSLAMConfig()
    ways = {"one call, PyTorch's default threads":
            lambda: preprocess(frames, c.image_size, c.patch_size, mode="seqslam"),
            "SeqSLAM.descriptors (the stages' rule)": lambda: SeqSLAM(c).descriptors(frames)}
    best = {k: (float("inf"), 0.0) for k in ways}
    outputs = {}
    for _ in range(rounds):
        for k, fn in ways.items():
            w, cpu = time.perf_counter(), time.process_time()
            outputs[k] = fn()
            w, cpu = time.perf_counter() - w, time.process_time() - cpu
            best[k] = min(best[k], (w, cpu))
    a, b = outputs.values()
    same = torch.equal(a, b)
    lines = [f"descriptor step, {len(frames)} frames, torch threads "
             f"{torch.get_num_threads()}, identical descriptors: {same}\n",
             "| way | wall s | CPU s |", "|---|---:|---:|"]
    lines += [f"| {k} | {w:.3f} | {c_:.3f} |" for k, (w, c_) in best.items()]
    return "\n".join(lines)


def stages(route: Path, rounds: int) -> str:
    """The engine's stages at one thread with each L1 kernel, and the one the rule picks here.

    One process; descriptors computed once; ``SeqSLAM(threads=1).match_descriptors`` with
    the difference kernel forced to the thermometer product and to ``"sad"`` in turn,
    interleaved, fastest of ``rounds`` (numba's start-up is outside: it is loaded before the
    first round). A markdown table: seconds per stage and each row's ratio to the rule's pick.
    """
    sys.path.insert(0, str(ROOT))
    import torch

    from torchseq import load_traverse
    from torchseq.seqslam import SeqSLAM, SeqSLAMConfig
    from torchseq.seqslam import difference as diff

    torch.set_num_threads(1)
    engine = SeqSLAM(SeqSLAMConfig(threads=1))
    ref, query = (engine.descriptors(load_traverse(route / n, progress=False))
                  for n in ("reference", "query"))
    levels = diff.thermometer_levels(ref, query)
    rule = diff.l1_kernel(ref, query, levels)
    diff.difference_with_kernel(ref[:8], query[:8], kernel="sad")  # numba loaded up front
    saved = diff.SAD_MIN_WORK, diff.SAD_INT8_MIN_SAVING
    best: dict = {}
    for _ in range(rounds):
        for name, size in (("thermometer", 2**62), ("sad", -2**62)):
            diff.SAD_MIN_WORK = diff.SAD_INT8_MIN_SAVING = size
            try:
                r = engine.match_descriptors(ref, query)
            finally:
                diff.SAD_MIN_WORK, diff.SAD_INT8_MIN_SAVING = saved
            assert r.kernels["difference"] == name
            row = {k: r.seconds[k] for k in ("difference", "enhance", "search", "total")}
            if name not in best or row["total"] < best[name]["total"]:
                best[name] = row
    lines = [f"{len(ref)} x {len(query)} places, one thread, CPU capability "
             f"{torch.backends.cpu.get_cpu_capability()}, thermometer product "
             f"{diff.thermometer_product('cpu')}, {levels[0].numel()} thresholds; fastest of "
             f"{rounds}, wall seconds\n",
             "| difference kernel | difference s | enhance s | search s | total s | "
             "difference / the rule's pick |", "|---|---:|---:|---:|---:|---:|"]
    for name, r in best.items():
        pick = " (the rule's pick here)" if name == rule else ""
        lines.append(f"| {name}{pick} | {r['difference']:.2f} | {r['enhance']:.2f} | "
                     f"{r['search']:.2f} | {r['total']:.2f} | "
                     f"{r['difference'] / best[rule]['difference']:.2f} |")
    return "\n".join(lines)


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        run_child(sys.argv[4:], Path(sys.argv[2]))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--places", type=int, default=3576, help="1788 or 3576")
    parser.add_argument("--baseline", type=Path, default=None,
                        help="another checkout (e.g. ../main) run side by side")
    parser.add_argument("--rounds", type=int, default=2, help="runs of each code, interleaved")
    parser.add_argument("--busy", type=int, default=0,
                        help="busy-loop processes held beside the runs")
    parser.add_argument("--descriptor-step", action="store_true",
                        help="time only the descriptor step (default threads vs the rule)")
    parser.add_argument("--stages", action="store_true",
                        help="the engine's stages at one thread, the rule's kernel and each "
                             "L1 kernel forced")
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir())
                        / "torchseq-bench-eval-process")
    args = parser.parse_args()
    route = write_route(args.places, args.cache)
    roots = ([("baseline", args.baseline.resolve())] if args.baseline else []) + [("this", ROOT)]
    best: dict = {}
    walls: dict = {}
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(args.busy)]
    try:
        if args.stages:
            print(stages(route, args.rounds))
            return
        if args.descriptor_step:
            print(descriptor_step(route, args.rounds))
            print(f"\n{args.busy} busy-loop process(es) beside, load average "
                  f"{os.getloadavg()[0]:.1f}")
            return
        with tempfile.TemporaryDirectory() as tmp:
            for i in range(args.rounds):
                for label, root in roots:
                    r = run_once(root, route, Path(tmp) / f"{label}-{i}")
                    print(f"round {i}: {label}: {r['wall']:.2f} s wall, {r['cpu']:.2f} s CPU, "
                          f"load {os.getloadavg()[0]:.1f}, heavy modules before the report: "
                          f"{r['phases']['heavy_before_report']}", file=sys.stderr, flush=True)
                    walls.setdefault(label, []).append(r["wall"])
                    if label not in best or r["wall"] < best[label]["wall"]:
                        best[label] = r
    finally:
        for p in busy:
            p.kill()
            p.wait()
    print(f"nordland-b, {args.places} x {args.places} places (64x32 PNGs), "
          f"{os.cpu_count()} CPUs, {args.busy} busy-loop process(es) beside, load average "
          f"{os.getloadavg()[0]:.1f} at the end (CPU seconds are the process's own work, wall "
          f"seconds include waiting for a core)\n")
    print(table(best))
    for label, r in best.items():
        print(f"\n- {label}: recall@1 {r['recall_at_1']:.4f}, AUC {r['auc']:.4f}, kernels "
              f"{r['kernel']}")
    if len(walls) == 2:
        print(f"- matches.csv identical: {len({r['matches'] for r in best.values()}) == 1}, "
              f"single-frame metrics identical: {len({r['single'] for r in best.values()}) == 1}")
        ratios = sorted(b / a for a, b in zip(*walls.values()))
        print(f"- whole-process wall this / baseline, median of {len(ratios)} round(s): "
              f"{ratios[len(ratios) // 2]:.2f}x (each: "
              f"{', '.join(f'{x:.2f}' for x in ratios)})")


if __name__ == "__main__":
    main()
